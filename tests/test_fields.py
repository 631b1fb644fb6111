"""The one table of model parameters (tawarp.model.fields) against the kernels' layout
and the model: rows, neutral values, fit scaling and ranges."""

import math

import numpy as np
import pytest

from tawarp.kernels import layout
from tawarp.model.core import Segment, load_core
from tawarp.model.fields import EFFECT_OFF, GLOBAL_FIELD_TABLE, NONLINEAR_FIELDS, SEGMENT_FIELD_TABLE, field
from tawarp.model.forward import base_table, parameter_row

ALL = list(SEGMENT_FIELD_TABLE) + list(GLOBAL_FIELD_TABLE.values())


def test_rows_cover_the_kernel_layout_once():
    assert sorted(f.row for f in SEGMENT_FIELD_TABLE) == list(range(layout.N_FIELDS))
    assert sorted(f.row for f in GLOBAL_FIELD_TABLE.values()) == [layout.T_COLD, layout.P_MEAN, layout.RADIUS]


def test_parameter_rows_put_each_core_value_where_the_kernels_read_it():
    core = load_core("ceramic")
    base = base_table(core)
    for name in core.parameter_names():
        v = core.get(name)
        assert base[parameter_row(core, name)] == (v if math.isfinite(v) else 0.0), name


def test_neutral_values_are_the_segment_defaults():
    """An effect is off at its neutral value, which is what a segment gets when the core
    file does not mention it (the kernels then compute the base model bit for bit:
    tests/test_effects.py)."""
    s = Segment("s", "porous", 0.04, porosity=0.8, pore_radius=1e-4, thermal=True)
    assert EFFECT_OFF and all(getattr(s, k) == v for k, v in EFFECT_OFF.items())
    base = {f.name for f in SEGMENT_FIELD_TABLE if not f.is_effect}
    assert base == {"length", "porosity", "pore_radius", "tortuosity", "solid_conductivity", "h", "T_start", "T_end"}
    assert math.isnan(s.T_start) and math.isnan(s.T_end) and not s.imposed
    assert set(NONLINEAR_FIELDS) == {"conductivity_exponent", "radiative_conductivity", "h_convection"}


@pytest.mark.parametrize("f", ALL, ids=lambda f: f.name)
def test_fit_ranges_lie_inside_the_physical_range(f):
    lo, hi = f.fit_range
    assert lo < hi
    assert f.check(lo)
    assert f.check(hi)
    if f.log:  # a log-scaled parameter must stay positive
        assert lo > 0 and f.lower >= 0
    else:
        assert f.scale > 0
    if f.prior is not None:
        assert lo <= f.prior[0] < f.prior[1] <= hi
    if f.is_effect:
        assert lo <= f.neutral <= hi  # a fit can start from "off"


def test_field_lookup_by_any_name():
    assert field("stack.porosity") is field("porosity")
    assert field("gas.T_cold").unit == "K" and field("tube.radius").row == layout.RADIUS
    with pytest.raises(KeyError, match="porsity"):
        field("stack.porsity")
    assert np.isfinite(field("h").fit_range).all()
