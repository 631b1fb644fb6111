"""The annular bypass gap (``SEGMENT.bypass_gap``, tawarp.kernels.acoustics.bypass_entries and
the library's ``bypass_gap``): off bit for bit, the limit of the independent reference's own
parallel 2-ports taken cell by cell, against the reference's lab gap, its heat model, a
passive reciprocal 2-port, its Jacobian columns, and its validation."""

import dataclasses

import numpy as np
import pytest

from tawarp import reference
from tawarp.fit.problems import FD_STEP
from tawarp.measure.files import TMatrixData
from tawarp.measure.tmatrix import TMatrixKind
from tawarp.model.coefficients import duct_impedance, normalize
from tawarp.model.core import CoreError, Segment, load_core
from tawarp.model.effects import TYPICAL_BYPASS_GAP, tmatrix_library
from tawarp.model.forward import ForwardSettings, steady_temperature, transfer_matrices
from tawarp.model.validity import ModelValidityError
from tawarp.reference import _ode_matrix
from tawarp.reference_effects import (
    LabEffects,
    gap_area_fraction,
    lab_heat_profile,
    lab_segment_matrices,
    lab_transfer_matrix,
    parallel,
)

CORE = load_core("ceramic")
FREQS = np.array([30.0, 120.0, 300.0, 500.0])


def _kind(core, freqs, Qs):
    """A T-matrix kind on ``core`` with the fits' fixed cells (its data are placeholders)."""
    nq, m = len(Qs), len(freqs)
    data = TMatrixData(np.repeat(Qs, m), np.tile(freqs, nq), np.tile(np.eye(2, dtype=complex), (nq * m, 1, 1)))
    return TMatrixKind(data, core, ForwardSettings(device="cpu", cells={s.name: 8 for s in core.segments if s.thermal}))


def _base(kind):
    return {k: np.array([kind.core.get(k)]) for k in kind.default_names()}


def _gap(core, freqs, Q, g, **kw):
    """Dimensionless T (m, 2, 2) of the kernels with ``stack.bypass_gap`` g."""
    params = {"stack.bypass_gap": np.array([g])} if g is not None else None
    return normalize(transfer_matrices(core, freqs, Q, params=params, device="cpu", **kw).T[0], duct_impedance(core))


def test_library_bypass_gap_is_a_field_of_the_stack_off_at_zero():
    e = next(x for x in tmatrix_library(CORE) if x.name == "bypass_gap")
    (par,) = e.params
    assert par.targets == ("stack.bypass_gap",) and par.start == 0.0 and par.lower == 0.0
    assert par.upper <= 0.5 * CORE.radius
    assert e.model_values() == {"stack.bypass_gap": TYPICAL_BYPASS_GAP}


@pytest.mark.parametrize("Q", [0.0, 40.0])
def test_bypass_gap_off_is_the_base_model_bit_for_bit(Q):
    """g = 0 is the model without the field: the same T-matrices (the loop's predict and the
    forward model), the same temperatures."""
    kind = _kind(CORE, FREQS, (Q,))
    base = _base(kind)
    off = dict(base, **{"stack.bypass_gap": np.array([0.0])})
    np.testing.assert_array_equal(kind.predict(off, 1), kind.predict(base, 1))
    np.testing.assert_array_equal(_gap(CORE, FREQS, Q, 0.0), _gap(CORE, FREQS, Q, None))
    x = np.linspace(0.031, 0.087, 7)
    np.testing.assert_array_equal(
        steady_temperature(CORE, x, Q, params={"stack.bypass_gap": np.array([0.0])}, device="cpu")[0],
        steady_temperature(CORE, x, Q, device="cpu")[0],
    )


def _parallel_cells(core, g, Q, freqs, parts):
    """The core's T-matrix (m, 2, 2) with the stack as ``parts`` cells, each the reference's
    stack of radius R - g and its slit of spacing g in parallel (:func:`parallel` of their
    DOP853 2-ports, the reference's own machinery), under the reference's heat profile with
    the gap; the other segments the reference's."""
    lab = LabEffects(bypass_gap=g)
    w = 2 * np.pi * freqs
    mats = lab_segment_matrices(core, lab, freqs, Q)
    i, seg = 1, core.segments[1]
    profile = lab_heat_profile(core, lab, Q).segment_profile(i)
    share = gap_area_fraction(core, g)
    pores = dataclasses.replace(seg, porosity=seg.porosity * (1 - share), length=seg.length / parts)
    slit = Segment(
        "slit", "porous", seg.length / parts, pore_model="plates", porosity=share, pore_radius=g / 2, tortuosity=1.0
    )
    M = np.broadcast_to(np.eye(2, dtype=complex), (w.size, 2, 2))
    x0 = core.positions()[i]
    for k in range(parts):
        x = x0 + k * seg.length / parts
        a = np.stack([_ode_matrix(core, pores, x, wk, profile, 1e-11) for wk in w])
        b = np.stack([_ode_matrix(core, slit, x, wk, profile, 1e-11) for wk in w])
        M = parallel(a, b) @ M
    mats[i] = M
    T = mats[0]
    for m in mats[1:]:
        T = m @ T
    return normalize(T, duct_impedance(core))


def test_bypass_gap_is_the_limit_of_the_references_parallel_slits_cell_by_cell():
    """The kernels' gap (two pore families under one pressure, per unit length) is the limit
    of the reference's two 2-ports in parallel taken over ever shorter cells of the stack
    (its own ODE, heat BVP and admittance sum): at 40 W and g = 0.4 mm the difference falls
    at least 3x when the cells halve (second order) and is below 1.5 % of the gap's effect
    with 16 cells."""
    g, Q = 4e-4, 40.0
    f = np.array([30.0, 120.0, 500.0])
    T = _gap(CORE, f, Q, g, cells=32)
    size = np.abs(T - _gap(CORE, f, Q, None, cells=32)).max()
    err = [np.abs(_parallel_cells(CORE, g, Q, f, n) - T).max() / size for n in (8, 16)]
    assert err[1] < 0.015 and err[1] < err[0] / 3, err


@pytest.mark.parametrize(
    "Q, g, tol",
    [
        (0.0, 2e-4, 0.05),
        (0.0, 4e-4, 0.01),
        # the reference's channels meet only at the stack's ends: along the temperature
        # gradient each carries its own gas expansion (a22), and the flow's split drifts
        # from the one lateral equilibrium keeps (the previous test: the kernels' form is
        # the cell-by-cell limit of the same 2-ports)
        (40.0, 4e-4, 0.2),
    ],
)
def test_bypass_gap_agrees_with_the_references_lab_gap(Q, g, tol):
    """The change the gap makes to the dimensionless T-matrix (30-500 Hz) against the
    independent reference's lab gap (tawarp.reference_effects: the stack of radius R - g
    and a slit of spacing g, their admittance matrices added at the stack's ends), within
    ``tol`` of the reference's change (measured: 3 %, 0.3 %, 13 %)."""
    ref = normalize(lab_transfer_matrix(CORE, LabEffects(bypass_gap=g), FREQS, Q), duct_impedance(CORE))
    ref0 = normalize(reference.transfer_matrix(CORE, FREQS, Q), duct_impedance(CORE))
    change = _gap(CORE, FREQS, Q, g) - _gap(CORE, FREQS, Q, None)
    size = np.abs(ref - ref0).max()
    assert size > 1e-3  # the gap is visible at 0.3-1 % noise
    assert np.abs(change - (ref - ref0)).max() < tol * size


@pytest.mark.parametrize("g", [1e-4, 5e-4])
def test_bypass_gap_heat_model_is_the_references(g):
    """In the heat model the gap's gas replaces its share g (2R - g)/R^2 of the stack: the
    kernels' steady temperature equals the reference's BVP with the lab gap to 1e-7 of its
    peak (the BVP's tolerance), and the hot end warms (gas conducts less than the ceramic)."""
    Q = 40.0
    pos = CORE.positions()
    x = np.concatenate([np.linspace(pos[1], pos[2], 6), np.linspace(pos[2], pos[4], 5)[1:]])
    T = steady_temperature(CORE, x, Q, params={"stack.bypass_gap": np.array([g])}, device="cpu")[0][0]
    hs = lab_heat_profile(CORE, LabEffects(bypass_gap=g), Q)
    idx = np.clip(np.searchsorted(pos, x, side="right") - 1, 1, 3)  # the thermal segments'
    theta = np.array([hs.theta_in(int(i), xi) for i, xi in zip(idx, x)])
    peak = theta.max()
    assert np.abs(T - CORE.gas.T_cold - theta).max() < 1e-7 * peak
    T0 = steady_temperature(CORE, x, Q, device="cpu")[0][0]
    assert T.max() > T0.max()


def test_bypass_gap_energy_balance_with_a_nonlinear_conductivity():
    """Q = int (2 h / R) theta S dx over the thermal segments (adiabatic ends) to 1e-9 of Q
    with a gap of 0.5 mm and the Kirchhoff cells (conductivity exponent on): the gap's gas
    changes where the heat goes, not how much."""
    Q, cells = 40.0, 32
    params = {"stack.bypass_gap": 5e-4, "stack.conductivity_exponent": 0.5}
    pos = CORE.positions()
    nodes, weights = np.polynomial.legendre.leggauss(12)
    lost = 0.0
    for i in CORE.thermal_indices:
        edges = np.linspace(pos[i], pos[i + 1], cells + 1)
        x = (0.5 * np.diff(edges)[:, None] * nodes + 0.5 * (edges[1:] + edges[:-1])[:, None]).ravel()
        w = (0.5 * np.diff(edges)[:, None] * weights).ravel()
        theta = steady_temperature(CORE, x, Q, params=params, device="cpu")[0][0] - CORE.gas.T_cold
        lost += np.sum(w * theta * 2 * CORE.segments[i].h / CORE.radius * CORE.area)
    assert abs(lost - Q) < 1e-9 * Q


@pytest.mark.parametrize("g", [1e-9, 1e-4, 1e-3, 0.99 * CORE.radius])
def test_bypass_gap_unheated_stack_is_reciprocal_and_passive(g):
    """At Q = 0 a stack with its gap is a reciprocal passive 2-port, from a gap of 1 nm to
    one that leaves 2e-4 of the section to the pores: det T = 1 to 1e-12 and the power
    entering, Re(p1 conj U1) for p2 = 0 (a pressure release downstream), is > 0 at every
    frequency; at 10 W every entry is finite."""
    f = np.array([20.0, 100.0, 700.0, 2000.0])
    T = transfer_matrices(CORE, f, 0.0, params={"stack.bypass_gap": np.array([g])}, device="cpu").T[0]
    assert np.all(np.isfinite(T))
    assert np.abs(np.linalg.det(T) - 1).max() < 1e-12
    hot = transfer_matrices(CORE, f, 10.0, params={"stack.bypass_gap": np.array([g])}, device="cpu").T[0]
    assert np.all(np.isfinite(hot))
    # p2 = 0: (p1, U1) = T^-1 (0, U2) with U2 = 1
    Ti = np.linalg.inv(T)
    p1, U1 = Ti[:, 0, 1], Ti[:, 1, 1]
    assert np.all(np.real(p1 * np.conj(U1)) > 0)


@pytest.mark.parametrize("g0", [0.0, 2e-4])
def test_bypass_gap_jacobian_against_extrapolated_differences(g0):
    """The loop's fits take the gap's Jacobian column by a forward difference of ``predict``
    at FD_STEP in the scaled variable: against Richardson-extrapolated differences (central
    inside, one-sided from g = 0, where a negative gap has no meaning) at steps k and 2k,
    to 1e-5 of the column's largest entry, at 0 and 40 W. The slit's flow admittance grows as
    g^3 (a term of scale ~0.1 mm): one-sided differences need k = 0.1 um to leave 1e-6."""
    kind = _kind(CORE, np.array([50.0, 120.0, 300.0]), (0.0, 40.0))
    e = next(x for x in tmatrix_library(CORE) if x.name == "bypass_gap")
    (par,) = e.params
    base = _base(kind)

    def Y(gs):
        return kind.predict(dict(base, **{par.label: np.asarray(gs, dtype=float)}), len(gs))

    h = FD_STEP * par.scale
    fwd = np.diff(Y([g0, g0 + h]), axis=0)[0] / h
    k = 1e-7 if g0 == 0.0 else 2e-6
    if g0 == 0.0:
        c = Y([g0, g0 + k, g0 + 2 * k])
        want = 2 * (c[1] - c[0]) / k - (c[2] - c[0]) / (2 * k)
    else:
        c = Y([g0 + 2 * k, g0 - 2 * k, g0 + k, g0 - k])
        want = (4 * (c[2] - c[3]) / (2 * k) - (c[0] - c[1]) / (4 * k)) / 3
    assert np.abs(fwd - want).max() < 1e-5 * np.abs(want).max()


def test_bypass_gap_is_validated_naming_the_key():
    with pytest.raises(CoreError, match=r"segment 'stack': bypass_gap \[m\]: must lie in"):
        CORE.replace(**{"stack.bypass_gap": -1e-4})
    with pytest.raises(CoreError, match="segment 'stack': bypass_gap 0.02 m must be narrower than the tube radius"):
        CORE.replace(**{"stack.bypass_gap": 0.02})
    with pytest.raises(CoreError, match="bypass_gap.*applies only to porous segments"):
        CORE.replace(**{"tbt.bypass_gap": 1e-4})
    with pytest.raises(CoreError, match="parameter stack.bypass_gap"):
        transfer_matrices(CORE, FREQS, 0.0, params={"stack.bypass_gap": np.array([-1e-4])}, device="cpu")
    with pytest.raises(ModelValidityError, match="stack.bypass_gap = 0.02 m is not narrower than the tube"):
        transfer_matrices(CORE, FREQS, 0.0, params={"stack.bypass_gap": np.array([1e-4, 0.02])}, device="cpu")
