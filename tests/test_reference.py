"""Checks of the independent NumPy/SciPy reference model (tawarp.reference).

docs/physics.md "Checks": uniform closed form, reciprocity, passivity, exact heat solution and
energy balance; plus the special functions against mpmath and the convergence of the
ODE integration. Fast: the whole file runs in a few seconds on one core.
"""

from __future__ import annotations

import dataclasses
import math

import mpmath as mp
import numpy as np
import pytest
from scipy.integrate import quad

from tawarp.model.coefficients import duct_impedance, normalize
from tawarp.model.core import Core, Segment, load_core
from tawarp.reference import (
    _coefficients,
    dimensionless_transfer,
    energy_balance,
    gas_properties,
    heat_profile_exact,
    segment_conductivity,
    segment_transfer_matrices,
    thermoviscous_function,
    transfer_matrix,
)

CORES = ("ceramic", "mesh", "nicr_foam", "rvc_foam")


def _Y(core, T):
    return normalize(T, duct_impedance(core))


def _with(core: Core, index: int, **changes) -> Core:
    segs = list(core.segments)
    segs[index] = dataclasses.replace(segs[index], **changes)
    return Core(tuple(segs), core.gas, core.radius, core.source)


def _stress_cores():
    """Heat-model cores beyond the bundled ones: an insulated (h = 0) buffer tube, a
    stack with m L ~ 900 (cosh would overflow), and five thermal segments with the
    heater in the middle."""
    c = load_core("ceramic")
    yield "ceramic", c
    yield "h0_and_huge_mL", _with(_with(c, 1, h=1e6), 3, h=0.0)
    segs = (
        Segment("d0", "duct", 0.02),
        Segment("a", "porous", 0.03, porosity=0.8, pore_radius=2e-4, solid_conductivity=10.0, h=40.0, thermal=True),
        Segment("b", "duct", 0.015, h=0.0, thermal=True),
        Segment(
            "heat",
            "porous",
            0.012,
            porosity=0.9,
            pore_radius=4.7e-4,
            solid_conductivity=3.0,
            h=100.0,
            thermal=True,
            heater=True,
        ),
        Segment(
            "c",
            "porous",
            0.02,
            pore_model="plates",
            porosity=0.7,
            pore_radius=1e-4,
            solid_conductivity=1.0,
            h=5.0,
            thermal=True,
        ),
        Segment("tbt", "duct", 0.08, h=0.3, thermal=True),
        Segment("d1", "duct", 0.02),
    )
    yield "five_thermal", Core(segs)


# -- special functions and gas ---------------------------------------------------------
@pytest.mark.parametrize("model", ["circular", "plates"])
def test_thermoviscous_function_matches_mpmath(model):
    mp.mp.dps = 40
    for x in [1e-4, 0.05, 0.4, 1.0, 1.5, 3.0, 40.0, 1e3, 2e4]:
        f, omf = thermoviscous_function(model, x, 1.0)
        if model == "circular":
            z = mp.mpc(1, 1) * x
            fe = 2 * mp.besselj(1, z) / (z * mp.besselj(0, z))
        else:
            w = mp.mpc(1, -1) * x
            fe = mp.tanh(w) / w
        fe, ome = complex(fe), complex(1 - fe)
        assert abs(complex(f) - fe) <= 1e-14 * abs(fe), (x, f, fe)
        assert abs(complex(omf) - ome) <= 1e-14 * abs(ome), (x, omf, ome)


def test_gas_properties_air_matches_physics_md():
    T = np.array([250.0, 293.15, 600.0, 1000.0])
    g = gas_properties("air", T, 101325.0)
    mu = 1.716e-5 * (T / 273.15) ** 1.5 * 383.55 / (T + 110.4)
    k = 0.0241 * (T / 273.15) ** 1.5 * 467.15 / (T + 194.0)
    np.testing.assert_allclose(g.mu, mu, rtol=1e-14)
    np.testing.assert_allclose(g.k, k, rtol=1e-14)
    np.testing.assert_allclose(g.rho, 101325.0 / (287.05 * T), rtol=1e-15)
    np.testing.assert_allclose(g.c, np.sqrt(1.4 * 287.05 * T), rtol=1e-15)
    np.testing.assert_allclose(g.Pr, mu * 1005.0 / k, rtol=1e-14)
    c = load_core("ceramic")
    k_c = float(gas_properties("air", 293.15, 101325.0).k)
    assert segment_conductivity(c, "tbt") == pytest.approx(k_c, rel=1e-15)
    assert segment_conductivity(c, "stack") == pytest.approx(0.9 * k_c + 0.1 * 3.0, rel=1e-15)


# -- (1) uniform temperature: ODE = closed form ----------------------------------------
@pytest.mark.parametrize("model,r,q", [("circular", 4.7e-4, 1.0), ("circular", 4e-5, 1.06), ("plates", 1.5e-4, 1.2)])
def test_uniform_segment_ode_equals_closed_form(model, r, q):
    seg = Segment("s", "porous", 0.05, pore_model=model, porosity=0.8, pore_radius=r, tortuosity=q)
    core = Core((seg,))
    f = np.array([30.0, 120.0, 500.0])
    Yc = _Y(core, transfer_matrix(core, f))
    Yo = _Y(core, transfer_matrix(core, f, _force_ode=True))
    assert np.max(np.abs(Yo - Yc)) < 1e-10 * np.max(np.abs(Yc))


def test_closed_form_is_lossless_duct_limit():
    # a wide duct at high frequency: k -> w/c, Zc -> rho c/S up to boundary-layer terms
    core = Core((Segment("d", "duct", 0.3),), radius=0.05)
    f = 2000.0
    T = transfer_matrix(core, f)[0]
    g = gas_properties("air", 293.15, 101325.0)
    kL = 2 * np.pi * f / g.c * 0.3
    assert abs(T[0, 0] - np.cos(kL)) < 2e-2
    assert abs(T[0, 1] / (1j * g.rho * g.c / core.area * np.sin(kL)) - 1) < 2e-2


# -- (2) reciprocity --------------------------------------------------------------------
@pytest.mark.parametrize("name", CORES)
def test_det_is_one_at_zero_heat(name):
    core = load_core(name)
    f = np.array([30.0, 200.0, 500.0])
    for force in (False, True):
        d = np.linalg.det(transfer_matrix(core, f, 0.0, _force_ode=force))
        assert np.max(np.abs(d - 1)) < 1e-10


def test_det_with_heat_follows_liouville():
    core = load_core("ceramic")
    f = np.array([50.0, 200.0])
    T = transfer_matrix(core, f, 40.0)
    d = np.linalg.det(T)
    assert np.min(np.abs(d - 1)) > 1e-3
    # Liouville: det T = exp(integral of tr A = a22), an independent check of the ODE solve
    hs = heat_profile_exact(core, 40.0)
    pos = core.positions()
    for fk, dk in zip(f, d):
        w = 2 * np.pi * fk
        log_det = 0.0
        for i in hs.indices:
            prof = hs.segment_profile(i)

            def a22(x, part):
                Tx, dTx = prof(x)
                return getattr(complex(_coefficients(core, core.segments[i], w, float(Tx), float(dTx))[2]), part)

            for part in ("real", "imag"):
                val = quad(a22, pos[i], pos[i + 1], args=(part,), epsabs=0, epsrel=1e-13, limit=200)[0]
                log_det += val if part == "real" else 1j * val
        assert abs(dk - np.exp(log_det)) < 1e-10 * abs(dk)


def test_regenerator_limit_det_is_temperature_ratio():
    # narrow pores (mesh, r/delta ~ 0.1 at 10 Hz): a22 -> (dT/dx)/T, so det T_stack -> T_out/T_in
    # (the volume-flow gain of a regenerator): checks the sign and size of the gradient term
    core = load_core("mesh")
    hs = heat_profile_exact(core, 80.0)
    pos = core.positions()
    i = core.segments.index(core.segment("stack"))
    ratio = (core.gas.T_cold + hs.theta_in(i, pos[i + 1])) / (core.gas.T_cold + hs.theta_in(i, pos[i]))
    d = np.linalg.det(segment_transfer_matrices(core, [10.0], 80.0)[i][0])
    assert ratio > 1.1
    assert abs(d - ratio) < 1e-3 * ratio


# -- (3) exact heat solution ------------------------------------------------------------
@pytest.mark.parametrize("label,core", list(_stress_cores()))
def test_heat_solution_satisfies_model(label, core):
    Q = 40.0
    hs = heat_profile_exact(core, Q)
    R, S = core.radius, core.area
    pos = core.positions()
    scale = hs.theta_max()[1]
    assert scale > 0
    for i in hs.indices:
        seg = core.segments[i]
        lam = segment_conductivity(core, i)
        q = Q / (seg.length * S) if seg.heater else 0.0
        m = math.sqrt(2 * seg.h / (R * lam))
        a, b = pos[i], pos[i + 1]
        # FD step resolving the boundary layers (width 1/m)
        d = 1e-3 * min(b - a, 1 / m if m else math.inf)
        x = np.linspace(a + 2 * d, b - 2 * d, 41)

        def fd(fun):  # 4th-order central first derivative
            return (fun(x - 2 * d) - 8 * fun(x - d) + 8 * fun(x + d) - fun(x + 2 * d)) / (12 * d)

        th = hs.theta_in(i, x)
        dth = hs.dtheta_in(i, x)
        d2_fd = fd(lambda t: hs.dtheta_in(i, t))
        # derivative scales of this segment, for relative errors
        s1 = max(np.max(np.abs(dth)), scale * (m + 1 / (b - a)))
        s2 = s1 * (m + 1 / (b - a))
        assert np.max(np.abs(fd(lambda t: hs.theta_in(i, t)) - dth)) < 1e-8 * s1
        assert np.max(np.abs(d2_fd - hs.d2theta_in(i, x))) < 1e-8 * s2
        # the ODE itself, with the FD second derivative
        resid = lam * d2_fd - (2 * seg.h / R) * th + q
        assert np.max(np.abs(resid)) < 1e-8 * (lam * s2 + abs(q))
        # the global evaluators agree with the segment's formula inside it
        np.testing.assert_allclose(hs.theta(x), th, rtol=0, atol=1e-14 * scale)
        np.testing.assert_allclose(hs.temperature(x), core.gas.T_cold + th, rtol=1e-15)
    # boundary and interface conditions
    first, last = hs.indices[0], hs.indices[-1]
    flux = hs.lam * scale * (hs.m + 1 / hs.length)
    assert abs(hs.dtheta_in(first, pos[first])) * hs.lam[0] < 1e-12 * flux.max()
    assert abs(hs.dtheta_in(last, pos[last + 1])) * hs.lam[-1] < 1e-12 * flux.max()
    for j in range(len(hs.indices) - 1):
        i, k = hs.indices[j], hs.indices[j + 1]
        xi = pos[i + 1]
        assert abs(hs.theta_in(i, xi) - hs.theta_in(k, xi)) < 1e-12 * scale
        assert abs(hs.lam[j] * hs.dtheta_in(i, xi) - hs.lam[j + 1] * hs.dtheta_in(k, xi)) < 1e-12 * flux.max()
    # outside the thermal domain
    assert hs.theta(np.array([0.0, pos[-1]])).tolist() == [0.0, 0.0]
    # energy balance: analytic, and by adaptive quadrature of theta itself
    assert energy_balance(core, Q) == pytest.approx(Q, rel=1e-10)
    total = 0.0
    for j, i in enumerate(hs.indices):
        a, b = pos[i], pos[i + 1]
        # break points graded into the boundary layers (width 1/m) at both ends
        w = [t / hs.m[j] for t in (1, 4, 16, 64) if hs.m[j] and t / hs.m[j] < (b - a) / 2]
        pts = sorted({a, b, (a + b) / 2, *[a + t for t in w], *[b - t for t in w]})
        for lo, hi in zip(pts[:-1], pts[1:]):
            total += (
                (2 * hs.h[j] / core.radius)
                * S
                * quad(
                    lambda t: float(hs.theta_in(i, t)),
                    lo,
                    hi,
                    epsabs=1e-14 * scale * (hi - lo),
                    epsrel=1e-12,
                    limit=200,
                )[0]
            )
    assert total == pytest.approx(Q, rel=1e-10)


def test_heat_solution_limits():
    c = load_core("ceramic")
    hs = heat_profile_exact(c, 0.0)
    assert np.all(hs.temperature(np.linspace(0, c.positions()[-1], 11)) == c.gas.T_cold)
    # linear in Q
    h1, h2 = heat_profile_exact(c, 10.0), heat_profile_exact(c, 30.0)
    x = np.linspace(0, c.positions()[-1], 57)
    np.testing.assert_allclose(h2.theta(x), 3 * h1.theta(x), rtol=1e-13, atol=1e-13)
    # no thermal segment: T = T_cold everywhere, and the core still has a T-matrix
    cold = Core(tuple(dataclasses.replace(s, thermal=False, heater=False) for s in c.segments))
    assert heat_profile_exact(cold, 50.0).theta_max() == (0.0, 0.0)
    np.testing.assert_allclose(transfer_matrix(cold, [100.0], 50.0), transfer_matrix(c, [100.0], 0.0), rtol=1e-13)
    # heat with no way out is rejected
    insulated = Core(tuple(dataclasses.replace(s, h=0.0) for s in c.segments))
    with pytest.raises(ValueError, match="h = 0"):
        heat_profile_exact(insulated, 10.0)


# -- (4) passivity ----------------------------------------------------------------------
@pytest.mark.parametrize("name", CORES)
def test_passive_at_zero_heat(name):
    core = load_core(name)
    f = np.linspace(30.0, 500.0, 8)
    T = transfer_matrix(core, f, 0.0)
    Z0 = duct_impedance(core)
    rng = np.random.default_rng(1)
    for Tk in T:
        p1 = rng.normal(size=200) + 1j * rng.normal(size=200)
        U1 = (rng.normal(size=200) + 1j * rng.normal(size=200)) / Z0
        p6 = Tk[0, 0] * p1 + Tk[0, 1] * U1
        U6 = Tk[1, 0] * p1 + Tk[1, 1] * U1
        absorbed = 0.5 * np.real(p1 * np.conj(U1)) - 0.5 * np.real(p6 * np.conj(U6))
        scale = 0.5 * (np.abs(p1) ** 2 / Z0 + np.abs(U1) ** 2 * Z0)
        assert np.all(absorbed >= -1e-12 * scale)
        # and for every input: K - T^H K T is positive semi-definite, K = [[0, 1/2], [1/2, 0]]
        D = np.diag([1.0, Z0])  # dimensionless (p, Z0 U)
        Td = D @ Tk @ np.linalg.inv(D)
        K = np.array([[0, 0.5], [0.5, 0]])
        assert np.linalg.eigvalsh(K - Td.conj().T @ K @ Td).min() > -1e-12


# -- (5) physical sanity and convergence ------------------------------------------------
def test_ceramic_close_to_lossless_duct_at_100Hz():
    core = load_core("ceramic")
    g = gas_properties("air", core.gas.T_cold, core.gas.p_mean)
    kL = 2 * np.pi * 100.0 / g.c * core.positions()[-1]
    Tpp = dimensionless_transfer(core, [100.0], 0.0)[0, 0]
    assert abs(abs(Tpp) - abs(np.cos(kL))) < 0.1 * abs(np.cos(kL))


def test_ode_converged():
    core = load_core("mesh")
    f = np.array([30.0, 500.0])
    Y12 = _Y(core, transfer_matrix(core, f, 80.0, rtol=1e-12))
    Y13 = _Y(core, transfer_matrix(core, f, 80.0, rtol=1e-13))
    assert np.max(np.abs(Y12 - Y13)) < 1e-11 * np.max(np.abs(Y13))
    # the cascade order: the product of the segment matrices, last on the left
    mats = segment_transfer_matrices(core, f, 80.0)
    prod = mats[-1]
    for M in mats[-2::-1]:
        prod = prod @ M
    np.testing.assert_allclose(_Y(core, prod), Y12, rtol=1e-14, atol=1e-14)


# -- effects the validation study needs (studies/loop_validation.py) ------------------------
@pytest.mark.parametrize("ratio", [0.5, 1.6, 1e4])
def test_thermal_radius_ratio_closed_form(ratio):
    """A uniform circular-pore segment whose thermal function is taken at radius ratio * r:
    k = (w q / c) sqrt((1 + (gamma - 1) f(ratio r)) / (1 - f(r))), Zc = rho c q / (phi S) /
    sqrt((1 - f(r)) (1 + (gamma - 1) f(ratio r))), f(a) = 2 J1(z)/(z J0(z)), z = (1 + i) a/delta,
    written here from scipy's Bessel functions; ratio 1e4 is the adiabatic limit f_k -> 0.
    Both the closed-form path and the ODE path of the reference must agree to 1e-10."""
    import scipy.special as sps

    phi, r, q, L = 0.8, 2e-4, 1.1, 0.04
    core = Core((Segment("s", "porous", L, porosity=phi, pore_radius=r, tortuosity=q, thermal_radius_ratio=ratio),))
    f = np.array([40.0, 150.0, 400.0])
    w = 2 * np.pi * f
    g = gas_properties("air", core.gas.T_cold, core.gas.p_mean)

    def fr(a, delta):
        z = (1 + 1j) * a / delta
        return 2 * sps.jve(1, z) / (z * sps.jve(0, z))  # scaled: no overflow at large z

    f_nu = fr(r, np.sqrt(2 * g.mu / (g.rho * w)))
    f_k = fr(ratio * r, np.sqrt(2 * g.k / (g.rho * g.cp * w)))
    bulk = 1 + (g.gamma - 1) * f_k
    k = w * q / g.c * np.sqrt(bulk / (1 - f_nu))
    Zc = g.rho * g.c * q / (phi * core.area) / np.sqrt((1 - f_nu) * bulk)
    T = np.empty((3, 2, 2), dtype=complex)
    T[:, 0, 0] = T[:, 1, 1] = np.cos(k * L)
    T[:, 0, 1] = 1j * Zc * np.sin(k * L)
    T[:, 1, 0] = 1j * np.sin(k * L) / Zc
    Yx = _Y(core, T)
    for force in (False, True):
        Y = _Y(core, transfer_matrix(core, f, _force_ode=force))
        assert np.max(np.abs(Y - Yx)) < 1e-10 * np.max(np.abs(Yx))
    if ratio == 1e4:
        assert np.max(np.abs(f_k)) < 1e-3  # the adiabatic limit is reached


def test_thermal_radius_ratio_one_is_the_paper_model_bit_for_bit():
    core = load_core("mesh")
    f = np.array([40.0, 400.0])
    a = transfer_matrix(core, f, 20.0)
    b = transfer_matrix(core.replace(**{"stack.thermal_radius_ratio": 1.0}), f, 20.0)
    assert np.array_equal(a, b)
