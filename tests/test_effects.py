"""Optional effects of the forward model: each is a field of the same kernels,
off by default; off it reproduces the base model bit for bit, on it is checked against a
closed form, an equivalent base model, the energy balance and grid convergence."""

import dataclasses

import numpy as np
import pytest

from tawarp import reference
from tawarp.model.coefficients import duct_impedance, normalize
from tawarp.model.fields import EFFECT_OFF
from tawarp.model.core import Core, CoreError, core_from_dict, dump_core, load_core
from tawarp.model.forward import steady_temperature, transfer_matrices

FREQS = np.array([30.0, 120.0, 260.0, 500.0])
NONLINEAR = [
    ("stack.conductivity_exponent", 1.0),
    ("stack.radiative_conductivity", 0.5),
    ("tbt.h_convection", 3.0),
    ("hot_hx.conductivity_exponent", -0.5),
    ("tbt.conductivity_exponent", 0.8),
]


@pytest.mark.parametrize("field", sorted(EFFECT_OFF))
def test_effect_off_is_bit_for_bit_the_base_model(field):
    core = load_core("ceramic")
    seg = "tbt" if field in ("h_convection", "wall_conductance", "conductivity_exponent") else "stack"
    name = f"{seg}.{field}"
    kw = dict(device="cpu", cells=6, heat_cells=32)  # a nonlinear field in the batch raises the heat grid to 32
    base = transfer_matrices(core, FREQS, [0.0, 40.0], **kw)
    off = transfer_matrices(core, FREQS, [0.0, 40.0], params={name: EFFECT_OFF[field]}, **kw)
    np.testing.assert_array_equal(base.T, off.T)
    # a batch that varies wall_resistance keeps room for the wall's nodes after the gas's
    np.testing.assert_array_equal(base.theta, off.theta[:, : base.theta.shape[1]])


def test_effect_fields_in_toml_round_trip_and_validation():
    d = load_core("nicr_foam").to_dict()
    assert not any(k in seg for seg in d["segment"] for k in EFFECT_OFF)  # off: not written
    d["segment"][1].update(thermal_radius_ratio=1.8, conductivity_exponent=0.5, radiative_conductivity=0.1)
    d["segment"][3].update(h_convection=2.0, wall_conductance=0.3)
    core = core_from_dict(d, "<effects>")
    import tomllib

    again = core_from_dict(tomllib.loads(dump_core(core)), "<again>")
    assert again == dataclasses.replace(core, source="<again>")
    assert "stack.thermal_radius_ratio" in core.parameter_names() and "tbt.h_convection" in core.parameter_names()
    assert "tbt.thermal_radius_ratio" not in core.parameter_names()
    bad = load_core("nicr_foam").to_dict()
    bad["segment"][0]["thermal_radius_ratio"] = 2.0
    with pytest.raises(CoreError, match="duct"):
        core_from_dict(bad, "x.toml")
    bad = load_core("nicr_foam").to_dict()
    bad["segment"][4]["h_convection"] = 2.0  # duct_right is not thermal
    with pytest.raises(CoreError, match="thermal"):
        core_from_dict(bad, "x.toml")
    bad = load_core("nicr_foam").to_dict()
    bad["segment"][1]["thermal_radius_ratio"] = -1.0
    with pytest.raises(CoreError, match="thermal_radius_ratio"):
        core_from_dict(bad, "x.toml")


def johnson(x, s):
    """Johnson's alpha(w)/alpha_inf for sigma = 8 mu alpha_inf/(phi r^2), Lambda = r/s, x = r/delta."""
    return 1 + 4j / x**2 * np.sqrt(1 - 1j * s**2 * x**2 / 8)


def _closed_form_two_radii(
    core: Core, freqs, ratios: dict, mobility: dict | None = None, shape: dict | None = None
) -> np.ndarray:
    """T-matrix at uniform T_cold with f_k taken at radius ratio * r (closed form, SciPy);
    ``mobility``: segment -> 1/rho_frame of a limp frame, derived independently here from
    the fluid and frame momentum balances (2x2 solve per frequency)."""
    w = 2 * np.pi * np.asarray(freqs)
    g = reference.gas_properties(core.gas.name, core.gas.T_cold, core.gas.p_mean)
    S = core.area
    M = np.broadcast_to(np.eye(2, dtype=complex), (len(w), 2, 2)).copy()
    for seg in core.segments:
        phi, r, q = (seg.porosity, seg.pore_radius, seg.tortuosity) if seg.is_porous else (1.0, core.radius, 1.0)
        d_nu = np.sqrt(2 * g.mu / (g.rho * w))
        d_k = np.sqrt(2 * g.k / (g.rho * g.cp * w))
        _, omf_nu = reference.thermoviscous_function("circular", r, d_nu)
        sh = (shape or {}).get(seg.name, 1.0)
        if sh != 1.0:
            omf_nu = omf_nu * johnson(r / d_nu, 1.0) / johnson(r / d_nu, sh)
        f_k, _ = reference.thermoviscous_function("circular", r * ratios.get(seg.name, 1.0), d_k)
        k = w * q / g.c * np.sqrt((1 + (g.gamma - 1) * f_k) / omf_nu)
        k = np.where(k.imag < 0, -k, k)
        Zc = q * g.rho * g.c / (phi * S) / np.sqrt(omf_nu * (1 + (g.gamma - 1) * f_k))
        # branch of Zc consistent with k: Zc = a12 / (i k), a12 = i q^2 rho w/(phi S (1 - f_nu))
        Zc = q**2 * g.rho * w / (phi * S * omf_nu) / k
        m = (mobility or {}).get(seg.name, 0.0)
        if m:
            # fluid:  (phi rho0 + A) U - A u = phi p'/w^2;  frame: A U - (rho1 + A) u = -(1 - phi) p'/w^2
            # with A = phi (rho_e - rho0); displacement w_tot = phi U + (1 - phi) u, dp/dx = w^2 rho_w w_tot
            rho_e = q**2 * g.rho / omf_nu
            A = phi * (rho_e - g.rho)
            rho_w = np.empty_like(rho_e)
            for j in range(len(w)):
                B = np.array([[phi * g.rho + A[j], -A[j]], [A[j], -(1 / m + A[j])]])
                U, u = np.linalg.solve(B, [phi, -(1 - phi)])
                rho_w[j] = 1.0 / (phi * U + (1 - phi) * u)
            a12 = 1j * w * rho_w / S
            a21 = 1j * phi * S * w * (1 + (g.gamma - 1) * f_k) / (g.rho * g.c**2)
            k = np.sqrt(-a12 * a21)
            k = np.where(k.imag < 0, -k, k)
            Zc = a12 / (1j * k)
        kL = k * seg.length
        Ts = np.stack(
            [np.stack([np.cos(kL), 1j * Zc * np.sin(kL)], -1), np.stack([1j * np.sin(kL) / Zc, np.cos(kL)], -1)], -2
        )
        M = Ts @ M
    return M


def test_thermal_radius_ratio_matches_closed_form():
    core = load_core("nicr_foam")
    cold = Core(
        tuple(dataclasses.replace(s, thermal=False, heater=False) for s in core.segments),
        core.gas,
        core.radius,
        core.source,
    )
    ratio = 1.9
    T = transfer_matrices(cold, FREQS, 0.0, params={"stack.thermal_radius_ratio": ratio}, device="cpu").T[0]
    Zc = duct_impedance(core)
    Y, Yref = normalize(T, Zc), normalize(_closed_form_two_radii(cold, FREQS, {"stack": ratio}), Zc)
    assert np.abs(Y - Yref).max() < 1e-11 * np.abs(Yref).max()
    Y1 = normalize(transfer_matrices(cold, FREQS, 0.0, device="cpu").T[0], Zc)
    assert np.abs(Y - Y1).max() > 1e-3  # the effect is visible


def test_limp_frame_matches_closed_form_and_rigid_limit():
    core = load_core("rvc_foam")
    cold = Core(
        tuple(dataclasses.replace(s, thermal=False, heater=False) for s in core.segments),
        core.gas,
        core.radius,
        core.source,
    )
    Zc = duct_impedance(core)
    m = 1 / 30.0  # a 30 kg/m^3 frame
    Y = normalize(transfer_matrices(cold, FREQS, 0.0, params={"stack.frame_mobility": m}, device="cpu").T[0], Zc)
    Yref = normalize(_closed_form_two_radii(cold, FREQS, {}, {"stack": m}), Zc)
    assert np.abs(Y - Yref).max() < 1e-10 * np.abs(Yref).max()
    rigid = normalize(transfer_matrices(cold, FREQS, 0.0, device="cpu").T[0], Zc)
    assert np.abs(Y - rigid).max() > 1e-3
    heavy = normalize(transfer_matrices(cold, FREQS, 0.0, params={"stack.frame_mobility": 1e-9}, device="cpu").T[0], Zc)
    assert np.abs(heavy - rigid).max() < 1e-6 * np.abs(rigid).max()  # continuous at m = 0 (rigid)


def test_viscous_shape_factor_matches_closed_form_and_limits():
    core = load_core("nicr_foam")
    cold = Core(
        tuple(dataclasses.replace(s, thermal=False, heater=False) for s in core.segments),
        core.gas,
        core.radius,
        core.source,
    )
    Zc = duct_impedance(core)
    Y = normalize(
        transfer_matrices(cold, FREQS, 0.0, params={"stack.viscous_shape_factor": 1.6}, device="cpu").T[0], Zc
    )
    Yref = normalize(_closed_form_two_radii(cold, FREQS, {}, shape={"stack": 1.6}), Zc)
    assert np.abs(Y - Yref).max() < 1e-11 * np.abs(Yref).max()
    # the correction keeps the flow resistivity (x -> 0) and gives Lambda = r/s at high frequency
    x = np.array([1e-3, 1e3])
    ratio = johnson(x, 1.6) / johnson(x, 1.0)
    assert abs(ratio[0] - 1) < 1e-5
    assert abs((ratio[1] - 1) - (1 + 1j) * 0.6 / x[1]) < 0.05 * 0.6 / x[1] * np.sqrt(2)


def test_wall_conductance_equals_a_raised_solid_conductivity():
    # lam = phi lam_gas + (1 - phi) lam_s + G: the same as lam_s + G / (1 - phi)
    core = load_core("ceramic")
    G = 0.4
    seg = core.segment("stack")
    a = transfer_matrices(core, FREQS, 60.0, params={"stack.wall_conductance": G}, device="cpu", cells=12)
    b = transfer_matrices(
        core,
        FREQS,
        60.0,
        params={"stack.solid_conductivity": seg.solid_conductivity + G / (1 - seg.porosity)},
        device="cpu",
        cells=12,
    )
    np.testing.assert_allclose(a.theta, b.theta, rtol=1e-12)
    np.testing.assert_allclose(a.T, b.T, rtol=1e-10, atol=1e-12 * np.abs(b.T).max())


def _local_h(core, name, value, seg, theta):
    """Exchange coefficient h(theta) of segment ``seg`` at temperature excess theta (as the
    kernels' Kirchhoff cells take it, point by point)."""
    s = core.segments[seg]
    h = np.full_like(theta, s.h)
    if name == f"{s.name}.h_convection":
        h = h + value * np.maximum(theta, 0) ** 0.25
    return h


@pytest.mark.parametrize("name, value", NONLINEAR)
def test_nonlinear_heat_energy_balance(name, value):
    # All of Q leaves through the walls: Q = sum over heat cells of int (2 h(theta) / R) theta S dx,
    # integrated on the kernel's own profile (Gauss-Legendre per cell), to the Picard tolerance.
    core = load_core("ceramic")
    Q, cells = 60.0, 32
    res = transfer_matrices(core, [100.0], Q, params={name: value}, device="cpu", cells=4)
    assert res.theta.shape[1] == 3 * cells + 1  # the heat grid was raised for the nonlinear solve
    nodes, weights = np.polynomial.legendre.leggauss(12)
    pos = core.positions()
    lost = 0.0
    for i in core.thermal_indices:
        edges = np.linspace(pos[i], pos[i + 1], cells + 1)
        x = (0.5 * (edges[1:] - edges[:-1])[:, None] * nodes + 0.5 * (edges[1:] + edges[:-1])[:, None]).ravel()
        w = (0.5 * (edges[1:] - edges[:-1])[:, None] * weights).ravel()
        # evaluate inside cells only (a node is shared by two cells)
        theta = steady_temperature(core, x, Q, params={name: value}, device="cpu")[0][0] - core.gas.T_cold
        lost += np.sum(w * theta * 2 * _local_h(core, name, value, i, theta) / core.radius * core.area)
    assert abs(lost - Q) < 1e-9 * Q
    base = transfer_matrices(core, [100.0], Q, device="cpu", cells=4)
    assert abs(res.theta.max() - base.theta.max()) > 1.0  # the effect changes the profile


@pytest.mark.parametrize("name, value", NONLINEAR[:3])
def test_nonlinear_heat_converges_with_heat_cells(name, value):
    # the per-cell coefficients (at the cell's mean temperature) make the scheme second order
    core = load_core("ceramic")
    x = np.array(core.positions()[1:5])  # planes x2..x5 are nodes on every grid
    T = {
        c: steady_temperature(core, x, 80.0, params={name: value}, device="cpu", nonlinear_heat_cells=c)[0][0]
        for c in (32, 64, 128, 1024)
    }
    e = [np.abs(T[c] - T[1024]).max() for c in (32, 64, 128)]
    orders = np.log2(np.array(e[:-1]) / np.array(e[1:]))
    assert np.all(orders > 1.7), (e, orders)
    assert e[0] < 2e-3 * (T[1024].max() - core.gas.T_cold)


def test_effects_on_cuda_match_cpu():
    import warp as wp

    wp.init()
    if not wp.is_cuda_available():
        pytest.skip("no CUDA device: GPU comparison of the effects skipped")
    core = load_core("ceramic")
    params = {
        "stack.thermal_radius_ratio": [1.0, 1.7, 1.3],
        "stack.conductivity_exponent": [0.0, 0.8, 0.0],
        "tbt.h_convection": [0.0, 2.0, 5.0],
        "stack.radiative_conductivity": [0.0, 0.0, 0.2],
        "hot_hx.wall_conductance": [0.0, 0.1, 0.3],
        "stack.viscous_shape_factor": [1.0, 1.4, 0.8],
        "stack.frame_mobility": [0.0, 0.0, 0.02],
    }
    cpu = transfer_matrices(core, FREQS, [0.0, 40.0, 80.0], params=params, device="cpu")
    gpu = transfer_matrices(core, FREQS, [0.0, 40.0, 80.0], params=params, device="cuda")
    Y, Yg = cpu.dimensionless(), gpu.dimensionless()
    assert np.abs(Yg - Y).max() / np.abs(Y).max() < 1e-11
    np.testing.assert_allclose(gpu.theta, cpu.theta, rtol=1e-10, atol=1e-9)
