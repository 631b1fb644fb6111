"""Adaptive Magnus cells chosen by a step-doubling error estimate (ForwardSettings.tolerance)
against the independent NumPy reference (DOP853, rtol 1e-12) on random cores drawn over
the documented ranges of the parameter table (``fields.Field.prior``)."""

import warnings

import numpy as np
import pytest

from tawarp import reference
from tawarp.model.core import load_core
from tawarp.fit.estimate import spread_starts
from tawarp.model.forward import transfer_matrices
from tawarp.model.validity import ValidityWarning

FREQS = np.array([30.0, 120.0, 260.0, 500.0])
POROUS = ("porosity", "pore_radius", "tortuosity", "solid_conductivity")


def relative_error(Y, Yref):
    """Max over rows of max_c |Y - Yref| / max_c |Yref| (as tests/test_forward.py)."""
    return float((np.abs(Y - Yref).max(-1) / np.abs(Yref).max(-1)).max())


def random_sets(core, n, seed):
    """n (heat input, values) pairs: every field of every thermal segment drawn over its
    documented range (``spread_starts``: Sobol, log-uniform for log fields), Q uniform in
    0-80 W; sets the model warns about (T_max above its limit) are left out."""
    names = [f"{s.name}.{f}" for s in core.segments if s.thermal for f in ("h",) + (POROUS if s.is_porous else ())]
    X = spread_starts(core, names, 32, seed)
    Q = np.random.default_rng(seed).uniform(0.0, 80.0, len(X))
    out = []
    for q, x in zip(Q, X):
        values = dict(zip(names, x.tolist()))
        with warnings.catch_warnings():
            warnings.simplefilter("error", ValidityWarning)
            try:
                transfer_matrices(core, [FREQS[-1]], q, params={k: [v] for k, v in values.items()}, device="cpu")
            except ValidityWarning:
                continue
        out.append((float(q), values))
        if len(out) == n:
            return out
    raise AssertionError("too few valid sets")


def errors(core, sets, **settings):
    """Error of each set against the reference, for each of the given forward settings."""
    out = []
    for Q, vals in sets:
        Yref = reference.dimensionless_transfer(core.replace(**vals), FREQS, Q)
        out.append([relative_error(transfer_matrices(core, FREQS, Q, params={k: [v] for k, v in vals.items()},
                                                     device="cpu", **s).dimensionless()[0], Yref)
                    for s in settings.values()])
    return np.array(out)


def test_estimated_cells_meet_tolerance_on_random_cores():
    # Default settings (tolerance 1e-6) on random cores, four seeds: every set within 1e-6
    # of the converged reference (itself ~1e-11). On the same sets the bare rule of thumb
    # (tolerance=None) errs by more than 1e-6 (up to 1e-3 on such draws: narrow pores,
    # where the wave's scale is the viscous wavenumber, not w/c), so the estimate is what
    # meets the budget and this test fails without it.
    err = np.concatenate([errors(load_core(name), random_sets(load_core(name), 3, seed), estimate={},
                                 rule={"tolerance": None})
                          for name, seed in [("ceramic", 0), ("mesh", 1), ("ceramic", 2), ("mesh", 3)]])
    assert err[:, 0].max() < 1e-6, err[:, 0]
    assert err[:, 1].max() > 1e-6, err[:, 1]


def test_tighter_tolerance_gives_tighter_error():
    # The estimate follows the tolerance: 1e-9 is met too (sixth order, measured estimate).
    core = load_core("ceramic")
    sets = random_sets(core, 2, 2)
    assert errors(core, sets, tight={"tolerance": 1e-9}).max() < 1e-9


def test_estimate_only_raises_cells():
    # A set whose estimate is already below target keeps the rule's cells: bit for bit.
    core = load_core("ceramic")
    a = transfer_matrices(core, FREQS, [0.0, 40.0], device="cpu", tolerance=1e-2).T
    b = transfer_matrices(core, FREQS, [0.0, 40.0], device="cpu", tolerance=None).T
    assert np.array_equal(a, b)


def test_estimate_that_cannot_be_met_warns(monkeypatch):
    # A tolerance below rounding is never met: after the last round the sets are named in a
    # ValidityWarning instead of a silent miss (two rounds here, to keep the cells few).
    import tawarp.model.forward as fwd

    monkeypatch.setattr(fwd, "MAX_ESTIMATE_ROUNDS", 2)
    with pytest.warns(ValidityWarning, match=r"error estimate of 1 of 1 sets is still"):
        transfer_matrices(load_core("ceramic"), FREQS, 40.0, device="cpu", tolerance=1e-20)
