"""The reference's lab effects (:mod:`tawarp.reference_effects`): each one's "off" limit,
and a closed form or an independent solution where it is on."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from tawarp import reference as ref
from tawarp.model.core import Segment, load_core
from tawarp.reference_effects import (
    LabEffects,
    LabHeatSolution,
    lab_segment_matrices,
    lab_transfer_matrix,
    microphone_error,
    parallel,
    side_branch_impedance,
)

Q = 40.0
FREQS = np.array([40.0, 150.0, 400.0])


@pytest.fixture(scope="module")
def mesh():
    return load_core("mesh")


def _thermal_x(core, n=401):
    pos = core.positions()
    return np.linspace(pos[1], pos[4], n)


def test_no_lab_effect_is_the_exact_heat_solution(mesh):
    # the BVP of the lab model with every effect off (and a wall coupling but no wall) solves
    # the paper's model: it equals the exact piecewise solution to the BVP's tolerance
    exact = ref.heat_profile_exact(mesh, Q)
    lab = LabHeatSolution(mesh, LabEffects(wall_coupling_porous=500.0), Q)
    x = _thermal_x(mesh)
    th = exact.theta(x)
    assert np.max(np.abs(lab.theta(x) - th)) < 1e-7 * th.max()
    assert abs(lab.lost() / Q - 1) < 1e-9


def test_off_effects_give_the_reference_bit_for_bit(mesh):
    base = ref.transfer_matrix(mesh, FREQS, Q)
    for lab in (
        LabEffects(),
        LabEffects(
            contact_resistance=0.0,
            bypass_gap=0.0,
            leak_diameter=0.0,
            porosity_gradient=0.0,
            wall_conductance=0.0,
            mic_gain=1.0,
            mic_phase=0.0,
        ),
    ):
        np.testing.assert_array_equal(lab_transfer_matrix(mesh, lab, FREQS, Q), base)


def test_contact_resistance_is_a_thin_resistive_layer(mesh):
    # A contact resistance R_c is the limit of a layer of thickness d and conductivity d/R_c
    # (no lateral loss) as d -> 0. The layer is solved by the exact piecewise solution
    # (another algorithm); with d = 1e-7 m the two agree to O(d/L) ~ 1e-5 of theta.
    Rc, d = 5e-4, 1e-7
    lab = LabHeatSolution(mesh, LabEffects(contact_resistance=Rc), Q)
    segs = list(mesh.segments)
    layer = Segment(
        "contact", "porous", d, porosity=1e-9, pore_radius=1e-4, solid_conductivity=d / Rc, h=0.0, thermal=True
    )
    hot = segs[2]
    layered = dataclasses.replace(
        mesh, segments=segs[:2] + [layer, dataclasses.replace(hot, length=hot.length - d)] + segs[3:]
    )
    exact = ref.heat_profile_exact(layered, Q)
    pos = mesh.positions()
    xs = np.linspace(pos[1], pos[2], 101)
    xh = np.linspace(pos[2], pos[3], 101)
    scale = exact.theta_max()[1]
    assert np.max(np.abs(lab.theta_in(1, xs) - exact.theta_in(1, xs))) < 1e-4 * scale
    assert np.max(np.abs(lab.theta_in(2, xh[1:]) - exact.theta_in(3, xh[1:]))) < 1e-4 * scale
    jump = float(lab.theta_in(2, pos[2]) - lab.theta_in(1, pos[2]))
    assert jump > 1.0 and abs(lab.lost() / Q - 1) < 1e-9  # the hot side hotter, energy conserved


def test_wall_field_tends_to_the_added_conductivity(mesh):
    # The wall as a second temperature field coupled by h_w: as h_w -> infinity theta_w ->
    # theta and the two fields' sum is the library's added conductivity lam + wall_conductance
    # (the reference's exact solution with that field). The gap closes as h_w^(-1/2) (the
    # coupling length sqrt(lam R/(2 h_w)) of the layers at the interfaces): 10x the coupling,
    # sqrt(10) x closer (+-15 %).
    lam_w = 0.5
    added = ref.heat_profile_exact(
        mesh.replace(**{f"{mesh.segments[i].name}.wall_conductance": lam_w for i in mesh.thermal_indices}), Q
    )
    x = _thermal_x(mesh)
    gaps = []
    for hw in (3e3, 3e4):
        lab = LabHeatSolution(
            mesh, LabEffects(wall_conductance=lam_w, wall_coupling_porous=hw, wall_coupling_duct=hw), Q, tol=1e-6
        )
        gaps.append(np.max(np.abs(lab.theta(x) - added.theta(x))))
        assert abs(lab.lost() / Q - 1) < 1e-6
    assert abs(gaps[0] / gaps[1] / math.sqrt(10) - 1) < 0.15, gaps
    assert gaps[1] < 0.01 * added.theta_max()[1]
    # at a physical coupling (laminar gas in the buffer tube, h_w = 3) the wall runs apart
    # from the gas: that is what the added conductivity leaves out
    lab = LabHeatSolution(mesh, LabEffects(wall_conductance=lam_w), Q)
    pos = mesh.positions()
    xt = np.linspace(pos[3], pos[4], 51)
    assert np.max(np.abs(lab.wall_theta_in(3, xt) - lab.theta_in(3, xt))) > 1.0
    # converged: a 10x looser residual tolerance moves theta by < 1e-8 of its maximum
    loose = LabHeatSolution(mesh, LabEffects(wall_conductance=lam_w), Q, tol=1e-6)
    assert np.max(np.abs(loose.theta(x) - lab.theta(x))) < 1e-8 * added.theta_max()[1]


def test_convection_is_the_reference_law(mesh):
    # buffer-tube convection h + h_c theta^(1/4) is the reference's own nonlinear law; the lab
    # heat model keeps it: with no lab effect on, the two BVPs agree to their tolerance
    core = mesh.replace(**{"tbt.h_convection": 2.0})
    nonlinear = ref.NonlinearHeatSolution(core, Q)
    lab = LabHeatSolution(core, LabEffects(), Q)
    x = _thermal_x(core)
    assert np.max(np.abs(lab.theta(x) - nonlinear.theta(x))) < 1e-6 * nonlinear.theta(x).max()


def test_bypass_gap_limits(mesh):
    base = ref.transfer_matrix(mesh, FREQS, Q)
    # a vanishing gap: the stack loses the share 2g/R of its section, the slit adds an
    # admittance ~ g^3: the change is linear in g, of the size of the lost share
    change = [
        np.max(np.abs(lab_transfer_matrix(mesh, LabEffects(bypass_gap=g), FREQS, Q) - base) / np.abs(base))
        for g in (1e-5, 2e-5)
    ]
    share = 2 * 1e-5 / mesh.radius
    assert abs(change[1] / change[0] - 2) < 0.1 and 0.5 < change[0] / share < 2, (change, share)
    # the gap alone (stack porosity -> 0): a parallel-plate slit of spacing g and the
    # annulus' area, closed form at uniform temperature (docs/physics.md, f = tanh(w)/w)
    g = 3e-4
    core = mesh.replace(**{"stack.porosity": 1e-10})
    M = lab_segment_matrices(core, LabEffects(bypass_gap=g), FREQS, 0.0)[1]
    gas = ref.gas_properties("air", core.gas.T_cold, core.gas.p_mean)
    w = 2 * np.pi * FREQS
    area = math.pi * (core.radius**2 - (core.radius - g) ** 2)

    def f(delta):
        z = (1 - 1j) * (g / 2) / delta
        return np.tanh(z) / z

    f_nu, f_k = f(np.sqrt(2 * gas.mu / (gas.rho * w))), f(np.sqrt(2 * gas.k / (gas.rho * gas.cp * w)))
    bulk = 1 + (gas.gamma - 1) * f_k
    k = w / gas.c * np.sqrt(bulk / (1 - f_nu))
    Zc = gas.rho * gas.c / area / np.sqrt((1 - f_nu) * bulk)
    L = core.segment("stack").length
    slit = np.array([[np.cos(k * L), 1j * Zc * np.sin(k * L)], [1j * np.sin(k * L) / Zc, np.cos(k * L)]])
    slit = np.moveaxis(slit, -1, 0)
    assert np.max(np.abs(M - slit) / np.abs(slit)) < 1e-6


def test_parallel_two_ports_add_their_areas(mesh):
    # two equal ducts side by side are one duct of twice the flow area: at uniform temperature
    # the closed form with twice the porosity (half the characteristic impedance, same k)
    w = 2 * np.pi * FREQS
    half = mesh.segment("stack")
    double = dataclasses.replace(half, porosity=2 * half.porosity * 0.7)
    single = dataclasses.replace(half, porosity=half.porosity * 0.7)
    T1 = ref._uniform_matrix(mesh, single, w)
    np.testing.assert_allclose(parallel(T1, T1), ref._uniform_matrix(mesh, double, w), rtol=1e-12)


def test_leak_limits(mesh):
    base = ref.transfer_matrix(mesh, FREQS, Q)
    np.testing.assert_array_equal(lab_transfer_matrix(mesh, LabEffects(leak_diameter=0.0), FREQS, Q), base)
    # a hole of 0.5 mm at 1 Hz (a/delta_nu = 0.1): Poiseuille flow, Re Z = 8 mu l/(pi a^4);
    # corrections O((a/delta)^4) and the radiation resistance (~1e-9 of it)
    d, l = 0.5e-3, 1.5e-3
    gas = ref.gas_properties("air", 293.15, 101325.0)
    Z = side_branch_impedance("air", 101325.0, 293.15, d, l, 2 * np.pi * np.array([1.0]))
    poiseuille = 8 * gas.mu * l / (math.pi * (d / 2) ** 4)
    assert abs(Z[0].real / poiseuille - 1) < 1e-3
    # with a cavity: a Helmholtz resonator, Im Z = 0 at f0 = c/(2 pi) sqrt(A/(V l_eff)),
    # l_eff = l + 2 (8 a/(3 pi)); the viscous layer adds l delta_nu/a to the neck's mass
    d, l, V = 20e-3, 20e-3, 1e-3
    a = d / 2
    l_eff = l + 2 * 8 * a / (3 * math.pi)
    f0 = gas.c / (2 * math.pi) * math.sqrt(math.pi * a * a / (V * l_eff))
    f = np.linspace(0.8 * f0, 1.2 * f0, 40001)
    im = side_branch_impedance("air", 101325.0, 293.15, d, l, 2 * np.pi * f, volume=V).imag
    f_res = f[np.argmin(np.abs(im))]
    delta = math.sqrt(2 * gas.mu / (gas.rho * 2 * math.pi * f0))
    assert f_res < f0 and abs(f_res / f0 - 1) < l * delta / (a * l_eff), (f_res, f0)


def test_leak_draws_flow_out_of_the_duct(mesh):
    # sign of the shunt: the duct's volume velocity downstream of the hole is the upstream
    # one minus the flow into the hole, Y p (exp(-iwt), U positive towards +x)
    lab = LabEffects(leak_diameter=1e-3, leak_position=0.015)
    M = lab_segment_matrices(mesh, lab, FREQS, 0.0)[0]
    half = dataclasses.replace(mesh.segments[0], length=0.015)
    H = ref._uniform_matrix(mesh, half, 2 * np.pi * FREQS)
    Y = 1 / side_branch_impedance("air", mesh.gas.p_mean, mesh.gas.T_cold, 1e-3, lab.leak_length, 2 * np.pi * FREQS)
    state = H @ np.array([1.0, 0.0])  # unit pressure, no flow, at x1
    after = M @ np.array([1.0, 0.0])
    expect = H @ (state - np.stack([np.zeros_like(Y), Y * state[:, 0]], -1))[..., None]
    np.testing.assert_allclose(after, expect[..., 0], rtol=1e-12)


@pytest.mark.parametrize("pair", ["downstream", "upstream"])
def test_microphone_mismatch_is_the_two_load_method(mesh, pair):
    # An explicit two-load measurement: two independent states at x1, the true T, the four
    # microphone pressures of plane waves p = A e^{ikx} + B e^{-ikx} (one microphone times
    # G), each pair's wave amplitudes solved from its two pressures, the face states
    # (p, U) = (A + B, (A - B)/Zc), and T = X6 X1^-1. It equals E_down T E_up^-1 whatever
    # the loads; G = 1 gives T.
    w = 2 * np.pi * FREQS
    T = ref.transfer_matrix(mesh, FREQS, Q)
    lab = LabEffects(mic_gain=1.04, mic_phase=math.radians(2.0), mic_pair=pair)
    k, Zc = ref.duct_waves("air", mesh.gas.p_mean, mesh.gas.T_cold, mesh.radius, w)
    rng = np.random.default_rng(0)
    X1 = rng.standard_normal((2, 2)) + 1j * rng.standard_normal((2, 2))
    X1 = X1 * np.array([[1.0], [1.0 / Zc[0].real]])  # pressures [Pa], volume velocities [m^3/s]
    side = {"downstream": 1.0, "upstream": -1.0}
    G = lab.mic_gain * np.exp(1j * lab.mic_phase)

    def measured(states, which):
        x = side[which] * np.array([lab.mic_distance, lab.mic_distance + lab.mic_spacing])
        A = (states[:, 0] + Zc[:, None] * states[:, 1]) / 2  # (m, loads)
        B = (states[:, 0] - Zc[:, None] * states[:, 1]) / 2
        p = A[:, None, :] * np.exp(1j * k[:, None, None] * x[None, :, None]) + B[:, None, :] * np.exp(
            -1j * k[:, None, None] * x[None, :, None]
        )  # (m, mic, loads)
        if which == pair:
            p[:, 1] *= G
        W = np.stack([np.exp(1j * k[:, None] * x), np.exp(-1j * k[:, None] * x)], -1)  # (m, mic, 2)
        AB = np.linalg.solve(W, p)
        return np.stack([AB[:, 0] + AB[:, 1], (AB[:, 0] - AB[:, 1]) / Zc[:, None]], 1)

    states1 = np.broadcast_to(X1, (len(FREQS), 2, 2))
    states6 = T @ states1
    T_two_load = measured(states6, "downstream") @ np.linalg.inv(measured(states1, "upstream"))
    got = lab_transfer_matrix(mesh, lab, FREQS, Q)
    np.testing.assert_allclose(got, T_two_load, rtol=1e-9, atol=0)
    assert np.max(np.abs(got - T) / np.abs(T)) > 1e-2
    E = microphone_error(mesh, dataclasses.replace(lab, mic_gain=1.0, mic_phase=0.0), w)
    np.testing.assert_allclose(E @ T, T, rtol=1e-11)


def test_porosity_gradient_limits(mesh):
    # a = 0: the paper's model; at Q = 0 reciprocity (det T = 1) holds for any a; at a low
    # frequency the graded stack's T_pU is its a12 integrated, a12 ~ 1/phi(x):
    # (1/a) ln((1 + a/2)/(1 - a/2)) times the uniform stack's, T_Up its a21 integrated,
    # a21 ~ phi: the uniform one's (the mean porosity is phi0), to O((kL)^2)
    np.testing.assert_array_equal(
        lab_transfer_matrix(mesh, LabEffects(porosity_gradient=0.0), FREQS, Q), ref.transfer_matrix(mesh, FREQS, Q)
    )
    a = 0.3
    lab = LabEffects(porosity_gradient=a)
    T = lab_transfer_matrix(mesh, lab, FREQS, 0.0)
    np.testing.assert_allclose(np.linalg.det(T), 1.0, atol=1e-9)
    f = np.array([0.1])
    graded = lab_segment_matrices(mesh, lab, f, 0.0)[1][0]
    uniform = ref.segment_transfer_matrices(mesh, f, 0.0)[1][0]
    kL2 = abs(uniform[0, 1] * uniform[1, 0])  # (kL)^2 of the uniform stack
    assert abs(graded[0, 1] / uniform[0, 1] / (math.log((1 + a / 2) / (1 - a / 2)) / a) - 1) < kL2
    assert abs(graded[1, 0] / uniform[1, 0] - 1) < kL2
    heat = LabHeatSolution(mesh, lab, Q)
    assert abs(heat.lost() / Q - 1) < 1e-9


def test_lab_effects_reject_bad_input(mesh):
    with pytest.raises(ValueError, match="contact_resistance"):
        LabEffects(contact_resistance=-1.0)
    with pytest.raises(ValueError, match="porous segment"):
        lab_transfer_matrix(mesh, LabEffects(leak_diameter=1e-3, leak_position=0.05), FREQS)
    with pytest.raises(ValueError, match="outside"):
        lab_transfer_matrix(mesh.replace(**{"stack.porosity": 0.95}), LabEffects(porosity_gradient=0.3), FREQS)
