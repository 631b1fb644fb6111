"""Numeric guards of the engine: every set outside the model raises or
warns with its index and parameters; none comes back as a silent NaN."""

import re
import warnings

import numpy as np
import pytest

from tawarp.model.core import load_core
from tawarp.model.forward import steady_temperature, transfer_matrices
from tawarp.model.validity import MAX_CELLS, ModelValidityError, NonFiniteError, T_LIMIT, ValidityWarning

CORE = load_core("ceramic")
KW = dict(device="cpu")


@pytest.mark.parametrize("params, freq", [({"stack.pore_radius": 1e-7}, 1000.0),   # the fit's own lower bound
                                          ({"stack.tortuosity": 1e6}, 100.0),
                                          ({"stack.length": 1e3}, 100.0)])
def test_overflow_names_the_set_instead_of_nan(params, freq):
    name, value = next(iter(params.items()))
    batch = {name: [CORE.get(name), value]}       # set 0 is fine, set 1 overflows
    with pytest.raises(NonFiniteError, match=re.escape(f"set 1 (heat_input = 0 W, {name} = {value:.6g})")):
        transfer_matrices(CORE, [freq], 0.0, params=batch, **KW)


def test_no_heat_sink_is_refused():
    zero_h = {"stack.h": 0.0, "hot_hx.h": 0.0, "tbt.h": 0.0}
    with pytest.raises(ModelValidityError, match=r"set 1 .*no steady temperature"):
        transfer_matrices(CORE, [100.0], [0.0, 40.0], params=zero_h, **KW)
    with pytest.raises(ModelValidityError, match="h = 0"):
        steady_temperature(CORE, [0.05], 40.0, params=zero_h, **KW)
    # unheated, h = 0 is a valid passive core: finite, exactly the cold result
    T0 = transfer_matrices(CORE, [100.0], 0.0, params=zero_h, **KW).T
    assert np.all(np.isfinite(T0))


def test_pore_radius_wider_than_the_tube_is_refused():
    with pytest.raises(ModelValidityError, match=r"set 1 .*wider than the tube"):
        transfer_matrices(CORE, [100.0], 0.0, params={"stack.pore_radius": [1e-4, 0.05]}, **KW)


def test_a_segment_too_long_for_the_cascade_is_refused_not_run():
    """A 1e6 m stack would need ~1e6 adaptive cells per thread (it hung before)."""
    with pytest.raises(ModelValidityError, match=f"more than {MAX_CELLS} cells"):
        transfer_matrices(CORE, [100.0], 0.0, params={"stack.length": 1e6}, **KW)


def test_hot_and_high_frequency_sets_warn():
    with pytest.warns(ValidityWarning, match=rf"set 1 \(heat_input = 10000 W\): T_max = \d+ K is above .* {T_LIMIT:g} K"):
        transfer_matrices(CORE, [100.0], [40.0, 1e4], **KW)
    # plane-wave cut-on of a 16.7 mm tube at 293 K: 1.8412 c / (2 pi R) = 6023 Hz
    with pytest.warns(ValidityWarning, match="cut-on 6023 Hz"):
        transfer_matrices(CORE, [8000.0], 0.0, **KW)
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # the paper's range warns about nothing
        transfer_matrices(CORE, [30.0, 500.0], [0.0, 80.0], **KW)
