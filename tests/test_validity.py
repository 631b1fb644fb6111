"""Numeric guards of the engine: every set outside the model raises or
warns with its index and parameters; none comes back as a silent NaN."""

import re
import warnings

import numpy as np
import pytest

from tawarp.model.core import CoreError, load_core
from tawarp.model.forward import steady_temperature, transfer_matrices
from tawarp.model.validity import MAX_CELLS, ModelValidityError, NonFiniteError, T_LIMIT, ValidityWarning

CORE = load_core("ceramic")
KW = dict(device="cpu")


@pytest.mark.parametrize(
    "params, freq",
    [
        ({"stack.pore_radius": 1e-7}, 1000.0),  # the fit's own lower bound
        ({"stack.porosity": 1e-12, "stack.pore_radius": 1e-7}, 1000.0),
        ({"stack.length": 100.0, "stack.pore_radius": 1e-5}, 100.0),
    ],
)
def test_overflow_names_the_set_instead_of_nan(params, freq):
    name, value = next(iter(params.items()))
    batch = {k: [CORE.get(k), v] for k, v in params.items()}  # set 0 is fine, set 1 overflows
    with pytest.raises(NonFiniteError, match=re.escape(f"set 1 (heat_input = 0 W, {name} = {value:.6g}")):
        transfer_matrices(CORE, [freq], 0.0, params=batch, **KW)


@pytest.mark.parametrize(
    "name, value", [("stack.tortuosity", 1e6), ("stack.length", 1e3), ("stack.h", 1e100), ("gas.p_mean", 0.5)]
)
def test_values_beyond_the_trusted_range_are_refused_before_solving(name, value):
    """Outside docs/trusted_ranges.md a value is refused naming the parameter and the range
    (``stack.h = 1e100`` crashed the cascade with SIGSEGV: an int32 cell count overflowed)."""
    with pytest.raises(CoreError, match=rf"parameter {re.escape(name)} .*outside the trusted range \["):
        transfer_matrices(CORE, [100.0], 10.0, params={name: value}, **KW)


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
    """A 100 m stack at 1 MHz would need ~2e6 adaptive cells per thread (it hung before)."""
    with pytest.raises(ModelValidityError, match=f"more than {MAX_CELLS} cells"):
        transfer_matrices(CORE, [1e6], 0.0, params={"stack.length": 100.0}, **KW)


def test_hot_and_high_frequency_sets_warn():
    with pytest.warns(
        ValidityWarning, match=rf"set 1 \(heat_input = 10000 W\): T_max = \d+ K is above .* {T_LIMIT:g} K"
    ):
        transfer_matrices(CORE, [100.0], [40.0, 1e4], **KW)
    # plane-wave cut-on of a 16.7 mm tube at 293 K: 1.8412 c / (2 pi R) = 6023 Hz
    with pytest.warns(ValidityWarning, match="cut-on 6023 Hz"):
        transfer_matrices(CORE, [8000.0], 0.0, **KW)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the paper's range warns about nothing
        transfer_matrices(CORE, [30.0, 500.0], [0.0, 80.0], **KW)


def _cli(*argv, cwd):
    """``tawarp ARGV`` in a child process: a crash of the kernels is an exit code there
    (-11 for SIGSEGV), not the end of the test run."""
    import subprocess
    import sys

    return subprocess.run(
        [sys.executable, "-c", "import sys; from tawarp.cli import main; sys.exit(main())", *map(str, argv)],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_an_extreme_h_in_a_core_file_is_an_error_line_not_a_signal(tmp_path):
    """``h = 1e300`` in a core file ended ``tawarp forward`` with SIGSEGV (rc 139)."""
    text = open(CORE.source).read().replace("h = 150.0", "h = 1e300", 1)
    (tmp_path / "hot.toml").write_text(text)
    run = _cli("forward", "hot.toml", "--Q", "10", "--freqs", "100", "--device", "cpu", "--no-plots", cwd=tmp_path)
    assert run.returncode == 2, run.stderr
    assert re.search(
        r"hot\.toml: segment 'stack': h \[W/\(m\^2 K\)\]: 1e\+300 lies outside the trusted range", run.stderr
    )
    assert not (tmp_path / "T.csv").exists()


def test_a_data_file_with_an_extreme_frequency_names_the_file(tmp_path):
    """One frequency of 1e300 Hz in a T-matrix file ended ``tawarp fit`` with SIGSEGV."""
    from tawarp.measure.files import read_tmatrix_csv, write_tmatrix_csv

    from importlib import resources

    data = read_tmatrix_csv(resources.files("tawarp") / "data" / "measured" / "ceramic_hidden_effect.csv")
    data.freq = data.freq.copy()
    data.freq[len(data.freq) // 2] = 1e300
    write_tmatrix_csv(tmp_path / "far.csv", data)
    run = _cli("fit", "far.csv", "--device", "cpu", "--quiet", "--no-plots", cwd=tmp_path)
    assert run.returncode == 2, run.stderr
    assert "far.csv: frequency 1e+300 Hz lies outside the trusted range" in run.stderr
    assert not (tmp_path / "fit.json").exists()


def test_a_cascade_beyond_the_cell_limit_is_refused_inside_the_trusted_ranges():
    """h and the length at the top of their trusted ranges: the heat-decay length is 1e-5
    of the stack, more cells than the cascade allows. The kernel caps its count (an int32
    of 1e50 was undefined and crashed the point buffers) and the host names the set."""
    with pytest.raises(
        ModelValidityError,
        match=rf"set 1 \(heat_input = 10 W, stack.h = 1e\+07, stack.length = 100\): "
        rf"stack would need more than {MAX_CELLS} Magnus cells",
    ):
        transfer_matrices(CORE, [100.0], 10.0, params={"stack.h": [150.0, 1e7], "stack.length": [0.048, 100.0]}, **KW)


def test_fits_stay_inside_the_trusted_ranges():
    """A fit is projected onto its field's fit bounds: they must lie inside the trusted
    range, or a fit would step onto values the engine refuses."""
    from tawarp.model.fields import GLOBAL_FIELD_TABLE, SEGMENT_FIELD_TABLE, TRUSTED_RANGE

    for f in (*GLOBAL_FIELD_TABLE.values(), *SEGMENT_FIELD_TABLE):
        lo, hi = TRUSTED_RANGE[f.name]
        assert lo <= f.fit_range[0] and f.fit_range[1] <= hi, f.name
        assert f.check(lo) and f.check(hi), f.name  # inside the physical range
