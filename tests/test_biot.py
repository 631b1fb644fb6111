"""Biot-Allard elastic-frame layer (tawarp.model.biot) against independent closed forms.

The oracles are written here from Allard & Atalla (2nd ed.) in their exp(+jwt) convention
and conjugated to exp(-iwt) at the end, so they also check the module's convention
conversion; the gas properties come from the independent reference.
"""

import numpy as np
import pytest

from tawarp.model import biot
from tawarp.reference import gas_properties

T_AIR, P_AIR = 293.15, 101325.0
FREQ = np.linspace(100.0, 4000.0, 40)
# foam2-like fluid parameters (Atalla & Panneton 2005 README), two parameter sets per call
FLUID = dict(
    phi=np.array([0.95, 0.97]),
    sigma=np.array([8197.0, 25000.0]),
    alpha_inf=np.array([1.42, 1.05]),
    Lambda=np.array([133.1e-6, 60e-6]),
    Lambda_prime=np.array([212.65e-6, 150e-6]),
)
FRAME = dict(eta=0.1, nu=0.3, rho_1=30.0)
THICKNESS = np.array([0.03435, 0.06877])


def _jca_oracle(freq, phi, sigma, alpha_inf, Lambda, Lambda_prime):
    """(rho_eq, K_eq, rho0, c0) of the JCA equivalent fluid, exp(-iwt): Allard & Atalla
    Eqs. 5.50/5.52 (rho_eq = rho0 alpha(w)/phi, K_eq = K(w)/phi) written with j = exp(+jwt)
    and conjugated."""
    g = gas_properties("air", T_AIR, P_AIR)
    w = 2 * np.pi * np.asarray(freq)[None, :]
    phi, sigma, alpha_inf, L, Lp = (np.asarray(x)[:, None] for x in (phi, sigma, alpha_inf, Lambda, Lambda_prime))
    j = 1j
    alpha = alpha_inf * (
        1
        + sigma
        * phi
        / (j * w * g.rho * alpha_inf)
        * np.sqrt(1 + 4 * j * alpha_inf**2 * g.mu * g.rho * w / (sigma**2 * L**2 * phi**2))
    )
    K = (
        g.gamma
        * P_AIR
        / (
            g.gamma
            - (g.gamma - 1)
            / (1 + 8 * g.mu / (j * Lp**2 * g.Pr * w * g.rho) * np.sqrt(1 + j * g.rho * w * g.Pr * Lp**2 / (16 * g.mu)))
        )
    )
    return np.conj(g.rho * alpha / phi), np.conj(K / phi), g.rho, g.c


def _fluid_layer(rho, K, freq, d):
    """(k, Zc, T) of an equivalent-fluid layer (exp(-iwt)); T the specific (p, v) 2-port."""
    w = 2 * np.pi * np.asarray(freq)
    k = w * np.sqrt(rho / K)
    Zc = np.sqrt(rho * K)
    kd = k * np.asarray(d)[:, None]
    T = np.stack(
        [np.stack([np.cos(kd), 1j * Zc * np.sin(kd)], -1), np.stack([1j * np.sin(kd) / Zc, np.cos(kd)], -1)], -2
    )
    return k, Zc, T


def _rigid_backed(k, Zc, d, z0):
    """Normalized Zs = i Zc cot(k d) / (rho0 c0) (exp(-iwt); Allard's -j Zc cot(kd) conjugated)."""
    return 1j * Zc / np.tan(k * np.asarray(d)[:, None]) / z0


def _limp_density(rho_eq, rho_1, phi, rho0):
    """Panneton (JASA 122, 2007) limp-frame density (rho_t rho_eq - rho0^2)/(rho_t + rho_eq - 2 rho0),
    rho_t = rho_1 + phi rho0."""
    phi = np.asarray(phi)[:, None]
    rho_t = rho_1 + phi * rho0
    return (rho_t * rho_eq - rho0**2) / (rho_t + rho_eq - 2 * rho0)


def _mobile_rigid_frame(rho_eq, K_eq, rho_1, phi, rho0, freq, d):
    """Specific 2-port of a layer whose frame is rigid but free to move as a body (velocity V):
    fluid pressure p and relative flux q = phi (v^f - V) obey (exp(-iwt))
    dp/dx = i w (rho0 V + rho_eq q), dq/dx = i w p / K_eq; frame balance
    -(1-phi)(p_d - p_0) = -i w (rho_1 V d + rho12/phi int q dx), rho12 = phi rho0 - phi^2 rho_eq;
    air velocity v = V + q. q = q_h - rho0 V / rho_eq with (p, q_h) an equivalent fluid."""
    w = 2 * np.pi * np.asarray(freq)[None, :]
    phi = np.asarray(phi)[:, None]
    dd = np.asarray(d)[:, None]
    _, _, Te = _fluid_layer(rho_eq, K_eq, freq, d)
    rho12 = phi * rho0 - phi**2 * rho_eq
    c = rho12 / (phi * rho_eq) - (1 - phi)
    m = -1j * w * dd * (rho_1 - rho0 * rho12 / (phi * rho_eq))
    T = np.empty(Te.shape, dtype=complex)
    for col, (p0, v0) in enumerate(((1.0, 0.0), (0.0, 1.0))):
        # p_d and q_hd for V = 0 and per unit V; q_h0 = v0 - V (1 - rho0/rho_eq)
        g = 1 - rho0 / rho_eq
        pd0 = Te[..., 0, 0] * p0 + Te[..., 0, 1] * v0
        qd0 = Te[..., 1, 0] * p0 + Te[..., 1, 1] * v0
        pdV, qdV = -Te[..., 0, 1] * g, -Te[..., 1, 1] * g
        V = c * (pd0 - p0) / (m - c * pdV)
        T[..., 0, col] = pd0 + pdV * V
        T[..., 1, col] = qd0 + qdV * V - rho0 * V / rho_eq + V
    return T


def _specific(T, area):
    """(p, U) 2-port -> (p, v) 2-port (U = area v)."""
    out = T.copy()
    out[..., 0, 1] *= area
    out[..., 1, 0] /= area
    return out


def _relmax(a, b):
    return np.max(np.abs(a - b)) / np.max(np.abs(b))


def test_jca_fluid_matches_allard_conjugated():
    """The module's JCA fluid equals Allard's exp(+jwt) formulas conjugated, to 1e-12."""
    fl = biot.jca_fluid(FREQ, **FLUID, T=T_AIR, P0=P_AIR)
    rho, K, _, _ = _jca_oracle(FREQ, **FLUID)
    assert _relmax(fl.rho_eq, rho) < 1e-12
    assert _relmax(fl.K_eq, K) < 1e-12


def test_stiff_frame_rigid_backed_is_rigid_jca():
    """E = 1e12 Pa, frame bonded to the backing: Zs = i Zc cot(kd)/(rho0 c0) of the JCA
    equivalent fluid to 1e-6 relative (frame compliance ~ K_f / E ~ 1e-7)."""
    rho, K, rho0, c0 = _jca_oracle(FREQ, **FLUID)
    k, Zc, _ = _fluid_layer(rho, K, FREQ, THICKNESS)
    Z_ref = _rigid_backed(k, Zc, THICKNESS, rho0 * c0)
    Z = biot.surface_impedance(FREQ, thickness=THICKNESS, E=1e12, **FLUID, **FRAME)
    assert np.max(np.abs(Z - Z_ref) / np.abs(Z_ref)) < 1e-6
    Zr = biot.rigid_surface_impedance(FREQ, thickness=THICKNESS, **FLUID)
    assert np.max(np.abs(Zr - Z_ref) / np.abs(Z_ref)) < 1e-12


def test_stiff_heavy_frame_two_port_is_equivalent_fluid():
    """E = 1e12 Pa and rho_1 = 1e12 kg/m^3 (frame neither strains nor moves): the 2-port
    is the equivalent-fluid cos/sin matrix to 1e-6 relative (in (p, U), area 0.01 m^2)."""
    rho, K, rho0, c0 = _jca_oracle(FREQ, **FLUID)
    _, _, T_ref = _fluid_layer(rho, K, FREQ, THICKNESS)
    area = 0.01
    T = biot.transfer_matrix(FREQ, thickness=THICKNESS, E=1e12, area=area, **FLUID, **{**FRAME, "rho_1": 1e12})
    assert _relmax(_specific(T, area), T_ref) < 1e-6


def test_stiff_frame_two_port_moves_as_a_body():
    """E = 1e12 Pa with a real frame mass (30 kg/m^3) and free edges: the frame moves as a
    rigid body; the 2-port equals the mobile-rigid-frame closed form to 1e-6 and differs
    from the immobile equivalent fluid by far more (> 1e-3)."""
    rho, K, rho0, c0 = _jca_oracle(FREQ, **FLUID)
    T_ref = _mobile_rigid_frame(rho, K, FRAME["rho_1"], FLUID["phi"], rho0, FREQ, THICKNESS)
    _, _, T_fixed = _fluid_layer(rho, K, FREQ, THICKNESS)
    T = biot.transfer_matrix(FREQ, thickness=THICKNESS, E=1e12, **FLUID, **FRAME)
    assert _relmax(T, T_ref) < 1e-6
    assert _relmax(T_ref, T_fixed) > 1e-3


@pytest.mark.parametrize("rho_1", [8.0, 60.0])
def test_soft_frame_is_limp(rho_1):
    """E = 1e-6 Pa: rigid-backed Zs and the 2-port equal the limp-frame equivalent fluid
    (Panneton 2007 density, JCA bulk modulus) to 1e-6 relative."""
    rho, K, rho0, c0 = _jca_oracle(FREQ, **FLUID)
    rho_l = _limp_density(rho, rho_1, FLUID["phi"], rho0)
    k, Zc, T_ref = _fluid_layer(rho_l, K, FREQ, THICKNESS)
    params = dict(thickness=THICKNESS, E=1e-6, **FLUID, **{**FRAME, "rho_1": rho_1})
    Z = biot.surface_impedance(FREQ, **params)
    Z_ref = _rigid_backed(k, Zc, THICKNESS, rho0 * c0)
    assert np.max(np.abs(Z - Z_ref) / np.abs(Z_ref)) < 1e-6
    T = biot.transfer_matrix(FREQ, **params)
    assert _relmax(T, T_ref) < 1e-6


@pytest.mark.parametrize("E", [1e3, 1e5, 1e7, 1e9])
def test_two_port_reciprocal(E):
    """det T = 1 (passive, reciprocal 1-D layer) to 1e-10, across frame stiffness."""
    T = biot.transfer_matrix(FREQ, thickness=THICKNESS, E=E, area=0.00785, **FLUID, **FRAME)
    assert np.max(np.abs(np.linalg.det(T) - 1)) < 1e-10


def test_two_port_passive():
    """Absorbed power >= 0: Re(p conj(U)) at the front face minus that at the back face is
    >= 0 for random inputs (relative to the input power, > -1e-12)."""
    rng = np.random.default_rng(3)
    T = biot.transfer_matrix(FREQ, thickness=THICKNESS, E=2e5, **FLUID, **FRAME)
    x = rng.normal(size=(2, 1, 40, 2)) + 1j * rng.normal(size=(2, 1, 40, 2))
    x = np.broadcast_to(x, (2, 2, 40, 2))
    y = np.einsum("...ij,...j->...i", T, x)
    p_in = np.real(x[..., 0] * np.conj(x[..., 1]))
    p_out = np.real(y[..., 0] * np.conj(y[..., 1]))
    scale = np.abs(x[..., 0]) * np.abs(x[..., 1])
    assert np.min((p_in - p_out) / scale) > -1e-12


def test_frame_resonance_near_quarter_wavelength():
    """A thick (10 cm) layer with a light (10 kg/m^3), soft (E = 2e5 Pa) frame: Re Zs and the
    absorption 1 - |(Zs-1)/(Zs+1)|^2 have a local minimum (the frame-resonance dip), and
    the deviation from the rigid-frame model its maximum, within 15 % of the in-vacuo frame
    quarter-wavelength frequency c_frame / (4 d); the rigid model has no such dip."""
    E, nu, rho_1, d = 2e5, 0.3, 10.0, 0.1
    c_frame = np.sqrt(E * (1 - nu) / ((1 + nu) * (1 - 2 * nu) * rho_1))
    f_r = c_frame / (4 * d)
    f = np.linspace(0.5 * f_r, 2.0 * f_r, 301)
    fluid = dict(phi=0.97, sigma=8000.0, alpha_inf=1.2, Lambda=150e-6, Lambda_prime=300e-6)
    Z = biot.surface_impedance(f, thickness=d, E=E, eta=0.05, nu=nu, rho_1=rho_1, **fluid)
    Zr = biot.rigid_surface_impedance(f, thickness=d, **fluid)

    def dips(y):
        return f[np.flatnonzero((y[1:-1] < y[:-2]) & (y[1:-1] < y[2:])) + 1]

    def absorption(z):
        return 1 - np.abs((z - 1) / (z + 1)) ** 2

    for y in (Z.real, absorption(Z)):
        assert dips(y).size >= 1 and np.min(np.abs(dips(y) / f_r - 1)) < 0.15
    assert dips(absorption(Zr)).size == 0
    assert abs(f[np.argmax(np.abs(Z - Zr))] / f_r - 1) < 0.15


@pytest.mark.parametrize(
    "name, value",
    [("phi", 1.3), ("E", -1e5), ("nu", 0.5), ("nu", 0.7), ("sigma", 0.0), ("thickness", -0.01), ("eta", np.nan)],
)
def test_invalid_parameters_name_the_parameter(name, value):
    """Out-of-range parameters raise ValueError naming the parameter."""
    params = dict(thickness=0.05, E=1e5, **{k: v[0] for k, v in FLUID.items()}, **FRAME)
    params[name] = value
    with pytest.raises(ValueError, match=f"'{name}'"):
        biot.surface_impedance(FREQ, **params)
    with pytest.raises(ValueError, match=f"'{name}'"):
        biot.transfer_matrix(FREQ, **params)


def test_batch_shape_and_waves():
    """Batch (3 stiffnesses x 2 fluids) gives shape (3, 2, m); each row equals its own
    single call to 1e-13; the waves satisfy the Biot dispersion relation to 1e-10."""
    E = np.array([1e4, 1e5, 1e6])[:, None]
    Z = biot.surface_impedance(FREQ, thickness=THICKNESS, E=E, **FLUID, **FRAME)
    assert Z.shape == (3, 2, FREQ.size)
    one = biot.surface_impedance(FREQ, thickness=THICKNESS[1], E=1e5, **{k: v[1] for k, v in FLUID.items()}, **FRAME)
    assert np.max(np.abs(Z[1, 1] - one) / np.abs(one)) < 1e-13
    wv = biot.biot_waves(FREQ, E=E, **FLUID, **FRAME)
    w2 = (2 * np.pi * FREQ) ** 2
    for delta in (wv.delta1, wv.delta2):
        x = delta**2
        a11, a12, a22 = wv.P * x - w2 * wv.rho11, wv.Q * x - w2 * wv.rho12, wv.R * x - w2 * wv.rho22
        scale = np.abs(a11 * a22) + np.abs(a12) ** 2
        assert np.max(np.abs(a11 * a22 - a12 * a12) / scale) < 1e-10
        assert np.all(delta.imag >= 0)


def test_normal_incidence_sees_only_the_p_wave_modulus():
    """(E, nu) = (1e5 Pa, 0.3) and (E', 0.1) with the same P-wave modulus
    E (1-nu)/((1+nu)(1-2nu)) give the same Zs and 2-port to 1e-12 (E, nu not separable)."""

    def p_mod(E, nu):
        return E * (1 - nu) / ((1 + nu) * (1 - 2 * nu))

    E2 = 1e5 * p_mod(1.0, 0.3) / p_mod(1.0, 0.1)
    runs = [dict(E=1e5, nu=0.3), dict(E=E2, nu=0.1)]
    common = dict(thickness=THICKNESS, eta=0.1, rho_1=30.0, **FLUID)
    Z = [biot.surface_impedance(FREQ, **common, **r) for r in runs]
    T = [biot.transfer_matrix(FREQ, **common, **r) for r in runs]
    assert _relmax(Z[1], Z[0]) < 1e-12
    assert _relmax(T[1], T[0]) < 1e-12


def test_flow_resistivity_of_circular_pores():
    """sigma = 8 mu alpha_inf / (phi r^2) with mu of air at T (reference Sutherland law), to 1e-12."""
    r, phi, a = np.array([50e-6, 2e-4]), 0.9, 1.2
    g = gas_properties("air", 300.0, P_AIR)
    assert _relmax(biot.flow_resistivity(r, phi, a, T=300.0), 8 * g.mu * a / (phi * r**2)) < 1e-12
    with pytest.raises(ValueError, match="'pore_radius'"):
        biot.flow_resistivity(-1e-4, phi, a)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_wide_parameter_ranges_stay_passive_and_reciprocal(seed):
    """100 random layers (E 1e-6..1e12 Pa, rho_1 1..300 kg/m^3, d 3 mm..30 cm, sigma 1e3..3e5,
    20 Hz..10 kHz): all finite; Re Zs > 0 (a passive rigid-backed layer absorbs); det T = 1
    relative to |T11 T22| + |T12 T21| to 1e-12 (T of a thick lossy layer reaches 1e20, so an
    absolute det test would only measure the rounding of its products)."""
    rng = np.random.default_rng(seed)
    n = 100
    p = dict(
        phi=rng.uniform(0.7, 1.0, n),
        sigma=10 ** rng.uniform(3, 5.5, n),
        alpha_inf=rng.uniform(1, 3, n),
        Lambda=10 ** rng.uniform(-5, -3, n),
        E=10 ** rng.uniform(-6, 12, n),
        eta=rng.uniform(0, 0.5, n),
        nu=rng.uniform(-0.5, 0.49, n),
        rho_1=10 ** rng.uniform(0, 2.5, n),
        thickness=10 ** rng.uniform(-2.5, -0.5, n),
    )
    p["Lambda_prime"] = p["Lambda"] * rng.uniform(1, 4, n)
    f = np.geomspace(20, 1e4, 30)
    Z = biot.surface_impedance(f, **p)
    T = biot.transfer_matrix(f, **p)  # area 1 m^2: specific, entries O(rho0 c0) apart
    assert np.isfinite(Z).all() and np.isfinite(T).all()
    assert Z.real.min() > 0
    z0 = 413.0  # rho0 c0 scale, only to balance the entries
    a, b, c, d = T[..., 0, 0], T[..., 0, 1] / z0, T[..., 1, 0] * z0, T[..., 1, 1]
    assert np.max(np.abs(a * d - b * c - 1) / (np.abs(a * d) + np.abs(b * c))) < 1e-12


def _four_by_four(rho_eq, K_eq, rho0, c0, freq, d, phi, E, eta, nu, rho_1):
    """(Zs / (rho0 c0), specific 2-port) of one frequency from the 4x4 boundary-value problem
    of Allard & Atalla ch. 11 at normal incidence, written plainly: the textbook Biot
    coefficients, the waves from the 2x2 eigenproblem K u delta^2 = w^2 M u, the stresses from
    the constitutive law sigma = i k (P u^s + Q u^f, Q u^s + R u^f), each wave's amplitude
    referred to the face it decays from, and the air interface's four conditions solved with
    np.linalg.solve."""
    w = 2 * np.pi * freq
    rho22 = phi**2 * rho_eq
    rho12 = phi * rho0 - rho22
    rho11 = rho_1 - rho12
    R, Q = phi**2 * K_eq, (1 - phi) * phi * K_eq
    P = E * (1 - 1j * eta) * (1 - nu) / ((1 + nu) * (1 - 2 * nu)) + Q**2 / R
    x, modes = np.linalg.eig(np.linalg.solve([[P, Q], [Q, R]], [[rho11, rho12], [rho12, rho22]]))
    at0, atd = [], []  # columns (v^s, v^f, sigma^s, sigma^f) at x = 0 and x = d
    for j in range(2):
        delta = w * np.sqrt(x[j])
        delta = -delta if delta.imag < 0 else delta
        us, uf = modes[:, j]
        for k, start in ((delta, 0.0), (-delta, d)):
            state = np.array([-1j * w * us, -1j * w * uf, 1j * k * (P * us + Q * uf), 1j * k * (Q * us + R * uf)])
            at0.append(state * np.exp(1j * k * (0.0 - start)))
            atd.append(state * np.exp(1j * k * (d - start)))
    at0, atd = np.array(at0).T, np.array(atd).T
    split0, splitd = phi * at0[2] - (1 - phi) * at0[3], phi * atd[2] - (1 - phi) * atd[3]
    p0, pd = -at0[3] / phi, -atd[3] / phi
    v0, vd = (1 - phi) * at0[0] + phi * at0[1], (1 - phi) * atd[0] + phi * atd[1]
    a = np.linalg.solve([atd[0], atd[1], split0, p0], [0, 0, 0, 1])
    Zs = 1 / (v0 @ a) / (rho0 * c0)
    a = np.linalg.solve([split0, splitd, p0, v0], [[0, 0], [0, 0], [1, 0], [0, 1]])
    return Zs, np.array([pd @ a, vd @ a])


def test_closed_forms_equal_the_four_by_four_system():
    """The closed forms of the rigid-backed Zs and of the 2-port equal the 4x4 system solved
    frequency by frequency to 1e-10 relative (each entry of T against its own size), across
    frame stiffness (soft to stiff), both fluids and thicknesses, on one fluid given to both."""
    rho, K, rho0, c0 = _jca_oracle(FREQ, **FLUID)
    fluid = biot.JCAFluid(rho, K, rho0, c0)
    E = np.array([1e3, 1e5, 1e7, 1e9])[:, None]
    params = dict(thickness=THICKNESS, phi=FLUID["phi"], E=E, eta=0.1, nu=0.3, rho_1=30.0)
    Z = biot.fluid_surface_impedance(FREQ, fluid, **params)
    T = biot.fluid_transfer_matrix(FREQ, fluid, **params)
    assert Z.shape == (4, 2, FREQ.size) and T.shape == (4, 2, FREQ.size, 2, 2)
    for i, e in enumerate(E[:, 0]):
        for s in range(2):
            for m, f in enumerate(FREQ):
                Z_ref, T_ref = _four_by_four(
                    rho[s, m], K[s, m], rho0, c0, f, THICKNESS[s], FLUID["phi"][s], e, 0.1, 0.3, 30.0
                )
                assert abs(Z[i, s, m] - Z_ref) < 1e-10 * abs(Z_ref)
                assert np.all(np.abs(T[i, s, m] - T_ref) < 1e-10 * np.abs(T_ref))
