"""The effects library (tawarp.model.effects): the one scaling scheme of fitted parameters,
base parameters read from the fields table, nested effects."""

import math

import numpy as np
import pytest

from tawarp.model.core import load_core
from tawarp.model.effects import (AMBIENT_HX, Param, ambient_presence, base_params, impedance_library,
                                  tmatrix_library, with_ambient_exchangers)
from tawarp.model.fields import field
from tawarp.model.forward import transfer_matrices

CORE = load_core("ceramic")


@pytest.mark.parametrize("log", [True, False])
def test_param_scaling_round_trip_and_bounds(log):
    par = Param("x", ("a.x",), 2.0, 0.5, 0.5, 8.0, log=log)
    v = np.array([0.5, 1.0, 2.0, 7.5])
    assert np.allclose(par.value(par.x_of(v)), v, rtol=1e-15)
    lo, hi = par.bounds_x()
    assert math.isclose(par.value(lo), 0.5, rel_tol=1e-15) and math.isclose(par.value(hi), 8.0, rel_tol=1e-15)
    # a unit step: a factor e (log) or one scale (linear)
    assert math.isclose(par.value(1.0), 2.0 * math.e if log else 2.5, rel_tol=1e-15)
    out = {}
    Param("w", ("a.w", "b.w"), 0.0).assign(3.0, out)
    assert out == {"a.w": 3.0, "b.w": 3.0}


def test_base_params_read_the_fields_table():
    names = ["stack.porosity", "stack.pore_radius", "stack.h"]
    pars = base_params(CORE, names)
    for par, name in zip(pars, names):
        f = field(name)
        assert par.start == CORE.get(name) and par.log == f.log
        lo, hi = f.fit_range
        if f.log:
            assert par.lower == max(lo, 1e-3 * par.start) and par.upper == min(hi, 1e3 * par.start)
        else:
            assert (par.lower, par.upper, par.scale) == (lo, hi, f.scale)


def test_ambient_exchangers_are_nested():
    # presence 0: porosity 1, pore radius = tube radius: the two segments are empty duct,
    # so the T-matrix is the base core's (to the forward model's accuracy, ~1e-10 here: two
    # extra exponentials of the same duct)
    aug = with_ambient_exchangers(CORE, AMBIENT_HX["length"], 1.0, CORE.radius)
    assert math.isclose(sum(s.length for s in aug.segments), sum(s.length for s in CORE.segments), rel_tol=1e-15)
    vals = ambient_presence(CORE, 0.0)
    assert all(v == 1.0 for k, v in vals.items() if k.endswith("porosity"))
    assert all(math.isclose(v, CORE.radius, rel_tol=1e-15) for k, v in vals.items() if k.endswith("pore_radius"))
    f = np.array([80.0, 300.0])
    T0 = transfer_matrices(CORE, f, 0.0, device="cpu").T[0]
    T1 = transfer_matrices(aug, f, 0.0, params={k: np.array([float(v)]) for k, v in vals.items()}, device="cpu").T[0]
    assert np.max(np.abs(T1 - T0) / np.abs(T0).max()) < 1e-9


def test_every_library_effect_is_off_at_its_start():
    # an effect at its start value is the base model: neutral field values of the table
    for e in tmatrix_library(CORE) + impedance_library(CORE):
        for par in e.params:
            for t in par.targets:
                if t == "layer.length_offset":   # the impedance kind's thickness offset [m]: off at 0
                    assert par.start == 0.0
                    continue
                f = field(t)
                if f.is_effect:
                    assert par.start == f.neutral, (e.name, t)
                elif e.transform is None:
                    assert t.startswith("gas.") or par.start == CORE.get(t), (e.name, t)
