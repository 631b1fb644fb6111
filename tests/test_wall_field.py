"""The tube wall as a temperature field of its own (``SEGMENT.wall_resistance`` = 1/h_w with a
``wall_conductance``; kernels/heat.py, ``solve_heat_wall``): its gas and wall profiles against
the independent reference's lab wall field (tawarp.reference_effects, scipy solve_bvp), the
limit of a strong coupling, its heat balance, its T-matrix, and the fit's Jacobian columns of
the library effect's new parameters."""

import numpy as np
import pytest

from tawarp.fit.problems import FD_STEP
from tawarp.measure.files import TMatrixData
from tawarp.measure.tmatrix import TMatrixKind
from tawarp.model.coefficients import duct_impedance, normalize
from tawarp.model.core import load_core
from tawarp.model.effects import tmatrix_library
from tawarp.model.forward import Engine, ForwardSettings, batch_table, steady_temperature, transfer_matrices
from tawarp.model.priors import effect_priors
from tawarp.reference_effects import LabEffects, lab_heat_profile, lab_transfer_matrix

CORE = load_core("nicr_foam")
THERMAL = [CORE.segments[i] for i in CORE.thermal_indices]
Q = 40.0
#: A lab wall: lam_w A_w/S [W/(m K)], h_w of the porous parts and of the buffer tube [W/(m^2 K)]
LAM_W, H_POROUS, H_DUCT = 0.6, 300.0, 3.1


def wall_values(lam_w=LAM_W, h_porous=H_POROUS, h_duct=H_DUCT) -> dict:
    """Kernel parameters of a wall field on every thermal segment (h = inf: perfect contact)."""
    out = {}
    for s in THERMAL:
        h = h_porous if s.is_porous else h_duct
        out[f"{s.name}.wall_conductance"] = lam_w
        out[f"{s.name}.wall_resistance"] = 0.0 if np.isinf(h) else 1.0 / h
    return out


def nodal(core, heat_input, values, heat_cells):
    """(nodes, gas theta, wall theta) [m, K, K] of the heat grid of one set."""
    names, varying = batch_table(core, heat_input, values)
    eng = Engine(core, [1.0], names, ForwardSettings(device="cpu", heat_cells=heat_cells))
    theta = eng.heat(varying)[1].numpy()[0]
    pos = core.positions()
    x = np.concatenate(
        [np.linspace(pos[i], pos[i + 1], heat_cells + 1)[:-1] for i in core.thermal_indices]
        + [[pos[core.thermal_indices[-1] + 1]]]
    )
    n = eng.nodes
    assert theta.shape == (2 * n,) and x.size == n
    return x, theta[:n], theta[n:]


def segment_of(core, x):
    """Index of the thermal segment holding each x (an interface: the one it starts)."""
    pos = np.array(core.positions())
    idx = np.array(core.thermal_indices)
    return idx[np.clip(np.searchsorted(pos[idx], x, side="right") - 1, 0, idx.size - 1)]


@pytest.fixture(scope="module")
def reference_solution():
    lab = LabEffects(
        wall_conductance=LAM_W,
        wall_coupling_porous=H_POROUS,
        wall_coupling_duct=H_DUCT,
        contact_resistance=3e-4,
        contact_left="stack",
    )
    return lab_heat_profile(CORE, lab, Q)


def test_profile_matches_the_lab_reference(reference_solution):
    # The exact two-field cells are exact at any cell count for piecewise-constant coefficients:
    # gas theta and dtheta/dx between the nodes (one cell per segment) and the wall's nodal
    # theta_w (4 cells) within 1e-9 of the peak rise of the reference's BVP, converged to ~1e-10
    # of its maximum (tawarp.reference_effects.HEAT_TOL); measured 2e-11. A contact resistance
    # between stack and hot exchanger sits on a two-field cell's left end.
    ref = reference_solution
    values = {**wall_values(), "hot_hx.contact_resistance": 3e-4}
    pos = CORE.positions()
    x = np.linspace(pos[1], pos[4], 801)
    x = x[np.all(np.abs(x[:, None] - np.array(pos)[None, 1:5]) > 1e-9, axis=1)]  # theta jumps at the contact
    T, dT = steady_temperature(CORE, x, Q, params=values, device="cpu")
    peak = ref.theta(x).max()
    assert np.abs(T[0] - CORE.gas.T_cold - ref.theta(x)).max() < 1e-9 * peak
    assert np.abs(dT[0] - ref.dtheta(x)).max() < 1e-9 * np.abs(ref.dtheta(x)).max()
    xn, gas, wall = nodal(CORE, Q, values, 4)
    want = np.array([ref.wall_theta_in(int(i), xx) for i, xx in zip(segment_of(CORE, xn), xn)])
    assert np.abs(wall - want).max() < 1e-9 * peak
    assert wall.max() > 0.1 * peak  # a wall that does carry heat


def test_strong_coupling_is_the_added_conductivity():
    # h_w -> inf: the wall at the gas temperature, its conductance added to the segment's
    # (wall_resistance 0: in every segment the single-field model; in the porous parts alone,
    # their nodes tied beside the buffer tube's two-field cells). Where the two fields share
    # the heat flux differently on either side of an interface they readjust over the coupling
    # length sqrt(lam_w R/(2 h_w)), so theta approaches the limit as h_w^(-1/2): 100x closer
    # from 1e9 to 1e13 W/(m^2 K) (to 1 %), within 1e-7 of the peak rise at 1e13.
    pos = CORE.positions()
    x = np.linspace(pos[1], pos[4], 301)
    for h_duct in (H_DUCT, np.inf):
        tied = steady_temperature(CORE, x, Q, params=wall_values(h_porous=np.inf, h_duct=h_duct), device="cpu")[0]
        rise = (tied - CORE.gas.T_cold).max()
        gap = []
        for h in (1e9, 1e13):
            strong = steady_temperature(
                CORE, x, Q, params=wall_values(h_porous=h, h_duct=min(h, h_duct)), device="cpu"
            )[0]
            gap.append(np.abs(strong - tied).max() / rise)
        assert gap[1] < 1e-7 and gap[0] / gap[1] == pytest.approx(100.0, rel=0.01), (h_duct, gap)
    # the other end of the trusted range, R_w = 1e6 m^2 K/W: a wall all but decoupled, the
    # bare gas/solid's profile within 1e-5 of the peak rise (its exchange 2/(R R_w) is 5e-6
    # of the buffer tube's h sink)
    bare = steady_temperature(CORE, x, Q, device="cpu")[0]
    loose = steady_temperature(CORE, x, Q, params=wall_values(h_porous=1e-6, h_duct=1e-6), device="cpu")[0]
    assert np.abs(loose - bare).max() < 1e-5 * (bare - CORE.gas.T_cold).max()
    xn, gas, wall = nodal(CORE, Q, wall_values(h_porous=np.inf), 2)
    porous = segment_of(CORE, xn) != CORE.thermal_indices[-1]
    np.testing.assert_allclose(wall[porous], gas[porous], rtol=1e-12)  # the tied nodes: theta_w = theta


def test_without_the_wall_field_the_model_is_unchanged_bit_for_bit():
    # A wall_resistance without a wall conductance, or a wall in perfect contact, takes the
    # single-field path: the same numbers as before the field existed.
    pos = CORE.positions()
    x = np.linspace(pos[1], pos[4], 51)
    added = {f"{s.name}.wall_conductance": LAM_W for s in THERMAL}
    a = steady_temperature(CORE, x, Q, params=added, device="cpu")
    b = steady_temperature(
        CORE, x, Q, params={**added, **{f"{s.name}.wall_resistance": 0.0 for s in THERMAL}}, device="cpu"
    )
    np.testing.assert_array_equal(a[0], b[0])
    off = steady_temperature(CORE, x, Q, device="cpu")[0]
    np.testing.assert_array_equal(
        off, steady_temperature(CORE, x, Q, params={"tbt.wall_resistance": 0.3}, device="cpu")[0]
    )


def test_heat_balance():
    # The heater's Q leaves through the gas/solid's h to the room and the end exchangers
    # (end_conductance), none through the adiabatic wall: int (2 h/R) theta S dx + H theta S
    # at the ends = Q to 1e-9, the profile integrated by 20-point Gauss-Legendre on 16 parts
    # per segment (its fastest mode decays over ~1.5 mm of a 4 cm stack). A contact resistance
    # and end exchangers on both ends exercise every row of the block system.
    H_end = 500.0
    values = {
        **wall_values(),
        "hot_hx.contact_resistance": 3e-4,
        "stack.end_conductance": H_end,
        "tbt.end_conductance": H_end,
    }
    pos = CORE.positions()
    g, w = np.polynomial.legendre.leggauss(20)
    S, R = CORE.area, CORE.radius
    xs, weights, hs = [], [], []
    for i in CORE.thermal_indices:
        edges = np.linspace(pos[i], pos[i + 1], 17)
        for a, b in zip(edges[:-1], edges[1:]):
            xs.append((a + b) / 2 + (b - a) / 2 * g)
            weights.append((b - a) / 2 * w)
            hs.append(np.full(g.size, CORE.segments[i].h))
    x, wts, h = (np.concatenate(v) for v in (xs, weights, hs))
    ends = np.array([pos[CORE.thermal_indices[0]], pos[CORE.thermal_indices[-1] + 1]])
    T = steady_temperature(CORE, np.r_[x, ends], Q, params=values, device="cpu")[0][0] - CORE.gas.T_cold
    lost = np.sum(wts * 2.0 * h / R * T[: x.size]) * S + H_end * S * T[x.size :].sum()
    assert abs(lost - Q) < 1e-9 * Q


def test_transfer_matrix_matches_the_lab_reference():
    # The T-matrix with the wall field at 40 W against the reference's (its own heat BVP and
    # acoustic ODE, DOP853 at rtol 1e-10) to 1e-6 of the coefficients (the forward model's
    # default Magnus tolerance, tests/test_nonlinear_heat.py).
    f = np.array([30.0, 140.0, 500.0])
    lab = LabEffects(wall_conductance=LAM_W, wall_coupling_porous=H_POROUS, wall_coupling_duct=H_DUCT)
    Zc = duct_impedance(CORE)
    ref = normalize(lab_transfer_matrix(CORE, lab, f, Q, rtol=1e-10), Zc)
    got = normalize(transfer_matrices(CORE, f, Q, params=wall_values(), device="cpu").T[0], Zc)
    plain = normalize(transfer_matrices(CORE, f, Q, device="cpu").T[0], Zc)
    scale = np.abs(ref).max(axis=-1)
    assert (np.abs(got - ref).max(axis=-1) / scale).max() < 1e-6
    assert (np.abs(plain - ref).max(axis=-1) / scale).max() > 1e-2  # a wall the data see


def test_library_effect_and_its_priors():
    e = next(x for x in tmatrix_library(CORE) if x.name == "wall_conduction")
    labels = [p.label for p in e.params]
    assert labels == ["wall_conductance", "stack.wall_resistance", "tbt.wall_resistance"]
    assert e.params[1].targets == ("stack.wall_resistance", "hot_hx.wall_resistance")
    # laminar Nu = 4 over D = 33.4 mm in air at 293 K (k = 0.0257 W/(m K)): h_w = 3.08 W/(m^2 K)
    assert 1.0 / e.params[2].start == pytest.approx(4.0 * 0.0257 / (2 * CORE.radius), rel=0.01)
    # a gas film of 0.1 mm: h_w = 257 W/(m^2 K), inside the lab's 100-500
    assert 1.0 / e.params[1].start == pytest.approx(0.0257 / 1e-4, rel=0.01)
    pri = effect_priors(e, CORE)
    for lab in labels[1:]:
        p = pri[lab]
        assert p.log and p.sd == pytest.approx(np.log(2.0))
    # the lab's couplings lie within 1.6 prior sd (porous 100-500, buffer tube 2.9-3.4)
    for lab, h in (("stack.wall_resistance", 100.0), ("stack.wall_resistance", 500.0), ("tbt.wall_resistance", 2.9)):
        assert abs(pri[lab].z(1.0 / h)) < 1.6


def _kind(core, freqs, Qs):
    """A T-matrix kind on ``core`` with the fits' fixed cells (its data are placeholders)."""
    nq, m = len(Qs), len(freqs)
    data = TMatrixData(np.repeat(Qs, m), np.tile(freqs, nq), np.tile(np.eye(2, dtype=complex), (nq * m, 1, 1)))
    return TMatrixKind(data, core, ForwardSettings(device="cpu", cells={s.name: 8 for s in core.segments if s.thermal}))


@pytest.mark.parametrize(
    "label, lam_w",
    [
        ("tbt.wall_resistance", LAM_W),
        ("stack.wall_resistance", LAM_W),
        ("wall_conductance", LAM_W),
        ("wall_conductance", 0.0),
    ],
)
def test_wall_jacobian_against_extrapolated_differences(label, lam_w):
    """The loop's fits take a Jacobian column by a forward difference of ``predict`` at
    FD_STEP in the scaled variable (ln v for the resistances): at the lab wall against
    Richardson-extrapolated central differences at steps k and 2k (k = 1e-3 in ln v, 1e-4
    W/(m K)) to 1e-5 of the column's largest entry, at 0 and 40 W; at the effect's "off"
    lam_w = 0, where the fits start and the single-field model meets the two-field one, below."""
    kind = _kind(CORE, np.array([50.0, 120.0, 300.0]), (0.0, 40.0))
    e = next(x for x in tmatrix_library(CORE) if x.name == "wall_conduction")
    par = next(p for p in e.params if p.label == label)
    v0 = {"wall_conductance": lam_w, "stack.wall_resistance": 1.0 / H_POROUS, "tbt.wall_resistance": 1.0 / H_DUCT}
    base = {k: np.array([kind.core.get(k)]) for k in kind.default_names()}

    def Y(xs):
        xs = np.asarray(xs, dtype=float)
        values = dict(base)
        for p in e.params:
            p.assign(np.full(xs.shape, v0[p.label]), values)
        par.assign(par.value(par.x_of(v0[label]) + xs), values)
        return kind.predict(values, xs.size)

    h = FD_STEP
    fwd = np.diff(Y([0.0, h]), axis=0)[0] / h
    if lam_w == 0.0:
        # from "off" the model is a lam_w + b lam_w^(3/2) (the fields part over a coupling length
        # ~ sqrt(lam_w)), so a one-sided column carries b sqrt(step): the derivative
        # 2 D(k) - D(4k) of one-sided differences D (k = 1e-6 W/(m K)) is good to O(k), and the
        # fits' column at FD_STEP is within 2e-4 of it (measured 6e-5): fine for a step from "off"
        k = 1e-6 / par.scale
        c = Y([0.0, k, 4 * k])
        want = 2 * (c[1] - c[0]) / k - (c[2] - c[0]) / (4 * k)
        assert np.abs(fwd - want).max() < 2e-4 * np.abs(want).max()
        return
    k = 1e-3 if par.log else 1e-4 / par.scale
    c = Y([2 * k, -2 * k, k, -k])
    want = (4 * (c[2] - c[3]) / (2 * k) - (c[0] - c[1]) / (4 * k)) / 3
    assert np.abs(fwd - want).max() < 1e-5 * np.abs(want).max()


@pytest.mark.parametrize(
    "segment, field, value", [("tbt", "h_convection", 1.0), ("stack", "conductivity_exponent", 0.5)]
)
def test_temperature_laws_with_the_wall_field(segment, field, value):
    # A temperature-dependent effect in a two-field segment: its cells take lam at their mean
    # gas temperature and the sink by its tangent there (the heat solve iterates), second
    # order in the cell size: against the reference's nonlinear BVP with the lab wall, the
    # error falls 4x per halving of the cells (to 10 %) and is below 1.5e-4 of the peak rise
    # at the default 32 cells (measured 1.2e-4 with convection, 2.3e-5 with the exponent).
    core = CORE.replace(**{f"{segment}.{field}": value})
    lab = LabEffects(wall_conductance=LAM_W, wall_coupling_porous=H_POROUS, wall_coupling_duct=H_DUCT)
    ref = lab_heat_profile(core, lab, Q)
    pos = CORE.positions()
    x = np.linspace(pos[1], pos[4], 401)
    peak = ref.theta(x).max()
    err = []
    for cells in (32, 64):
        T = steady_temperature(core, x, Q, params=wall_values(), device="cpu", nonlinear_heat_cells=cells)[0]
        err.append(np.abs(T[0] - CORE.gas.T_cold - ref.theta(x)).max() / peak)
    assert err[0] < 1.5e-4 and err[0] / err[1] == pytest.approx(4.0, rel=0.1), err
