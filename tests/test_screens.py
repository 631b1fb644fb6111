"""Stacked wire screens (pore_model = "screens"): Swift & Ward's correlations in A(x)
(docs/physics.md, "Stacked wire screens"), checked against the correlations' own
definitions, the NumPy reference (tawarp/reference.py, DOP853), open-thermoacoustics'
STKSCREEN (DeltaEC's equations, code-to-code), central differences of the cascade (the
fits' Jacobian) and the reference at complex frequency (the onset's path)."""

import dataclasses
import math

import numpy as np
import pytest
import scipy.linalg as sla

from tawarp import reference
from tawarp.fit.estimate import is_log
from tawarp.model.core import CoreError, core_from_dict, load_core, screen_geometry
from tawarp.model.forward import Engine, ForwardSettings, transfer_matrices

DEVICE = "cpu"
#: A helium regenerator: 3 bar, porosity 0.69, hydraulic radius 40 um (a 120-mesh screen
#: of 70 um wire has 0.70 and 41 um).
POROSITY, R_H = 0.69, 4.0e-5


def screens_core(porosity: float = POROSITY, r_h: float = R_H, **gas):
    """The bundled nicr_foam core in helium at 3 bar with its stack as wire screens."""
    d = load_core("nicr_foam").to_dict()
    d["gas"].update(name="helium", p_mean=3e5, **gas)
    d["segment"][1].update(pore_model="screens", porosity=porosity, pore_radius=r_h, tortuosity=1.0)
    return core_from_dict(d, "<screens>")


def uniform_segment(core, length: float = 1e-3):
    """``core`` cut to its stack, ``length`` [m] long, at T_cold."""
    stack = dataclasses.replace(core.segment("stack"), length=length, thermal=False, heater=False, h=0.0)
    return type(core)((stack,), core.gas, core.radius, "<one screen segment>")


def propagation_matrix(core, f: float) -> np.ndarray:
    """A of a uniform one-segment core from the kernels: log(T)/L (T = exp(A L))."""
    T = transfer_matrices(core, [f], device=DEVICE, cells=4).T[0, 0]
    return sla.logm(T) / core.segments[0].length


def test_screen_geometry_and_core_keys():
    """phi = 1 - pi m d_w/4 and r_h = d_w phi/(4 (1 - phi)) (Swift, sec. 7.3): a 120-mesh
    (4724 wires per m) screen of 70 um wire; the core file's keys and errors."""
    mesh, d_w = 120 / 0.0254, 70e-6
    phi, r_h = screen_geometry(d_w, mesh)
    assert phi == pytest.approx(1 - math.pi * mesh * d_w / 4, rel=1e-15)
    assert phi == pytest.approx(0.7403, abs=1e-4)
    assert r_h == pytest.approx(d_w * phi / (4 * (1 - phi)), rel=1e-15)
    d = load_core("nicr_foam").to_dict()
    d["segment"][1].update(pore_model="screens", wire_diameter=d_w, mesh=mesh)
    d["segment"][1].pop("pore_radius")
    d["segment"][1].pop("porosity")
    core = core_from_dict(d, "scr.toml")
    assert core.segment("stack").porosity == phi and core.segment("stack").pore_radius == r_h
    assert core_from_dict(core.to_dict(), "again.toml").segments == core.segments
    bad = dict(d["segment"][1], porosity=0.7)
    with pytest.raises(CoreError, match="scr.toml: segment #2 .*give mesh or porosity"):
        core_from_dict(dict(d, segment=[d["segment"][0], bad, *d["segment"][2:]]), "scr.toml")
    low = core.to_dict()
    low["segment"][1]["porosity"] = 0.45
    with pytest.raises(CoreError, match="scr.toml: segment 'stack': porosity = 0.45 .*0.5 < porosity < 1"):
        core_from_dict(low, "scr.toml")
    ratio = core.to_dict()
    ratio["segment"][1]["thermal_radius_ratio"] = 1.5
    with pytest.raises(CoreError, match="thermal_radius_ratio applies to Rott's pore functions"):
        core_from_dict(ratio, "scr.toml")
    wire = load_core("nicr_foam").to_dict()
    wire["segment"][1]["wire_diameter"] = d_w
    with pytest.raises(CoreError, match="wire_diameter and mesh apply only to pore_model = 'screens'"):
        core_from_dict(wire, "scr.toml")


@pytest.mark.parametrize("porosity", [0.62, 0.69, 0.76])
def test_friction_and_heat_transfer_are_the_correlations(porosity):
    """A of a uniform screen segment from the kernels (log of its T-matrix): its viscous
    resistance is the steady friction f = c1/Re of Swift & Ward's correlation,
    dp/dx = -(f/r_h) rho u^2/2 with Re = 4 r_h rho u/mu (so -Re a12 phi S = mu c1/(8 r_h^2)),
    its inertance K rho/(phi S); its compressibility the gas relaxing to the wires with the
    low-Reynolds Nusselt number Nu = 4 h r_h/k = b Pr^(1/3); to 1e-9 (the heat transfer to
    1e-6: the reference's helium conductivity is the kernels' to 3e-7)."""
    core = uniform_segment(screens_core(porosity))
    g = reference.gas_properties("helium", core.gas.T_cold, core.gas.p_mean)
    c1, _, b, K = reference.screen_correlations(porosity)
    flow_area = porosity * core.area
    for f in (0.5, 40.0, 300.0):
        w = 2 * math.pi * f
        A = propagation_matrix(core, f)
        assert -A[0, 1].real * flow_area == pytest.approx(g.mu * c1 / (8 * R_H**2), rel=1e-9)
        assert A[0, 1].imag * flow_area == pytest.approx(w * g.rho * K, rel=1e-9)
        # gas heat capacity per volume rho cp against the wires' h/r_h: f_k = 1/(1 - i w rho cp r_h/h)
        f_k = (A[1, 0] / (1j * w * flow_area / (g.rho * g.c**2)) - 1) / (g.gamma - 1)
        h = b * g.Pr ** (1 / 3) * g.k / (4 * R_H)
        assert f_k == pytest.approx(1 / (1 - 1j * w * g.rho * g.cp * R_H / h), rel=1e-6)
        assert abs(A[1, 1]) < 1e-12 * abs(A[1, 0]) * g.rho * g.c**2 / flow_area


def test_low_frequency_limit_is_the_steady_regenerator():
    """As f -> 0 a screen stack is a steady Darcy resistance and isothermal: its T-matrix
    over length L tends to [[1, -R L], [i w phi S L/p, 1]] with R = mu c1/(8 r_h^2 phi S)."""
    core = uniform_segment(screens_core(), length=5e-3)
    g = reference.gas_properties("helium", core.gas.T_cold, core.gas.p_mean)
    c1, *_ = reference.screen_correlations(POROSITY)
    R = g.mu * c1 / (8 * R_H**2 * POROSITY * core.area)
    L, p = 5e-3, core.gas.p_mean
    for f in (0.01, 0.001):
        w = 2 * math.pi * f
        T = transfer_matrices(core, [f], device=DEVICE, cells=4).T[0, 0]
        assert T[0, 1] == pytest.approx(-R * L, rel=20 * f)
        assert T[1, 0] == pytest.approx(1j * w * POROSITY * core.area * L / p, rel=20 * f)


def test_kernels_match_reference():
    """A heated core (helium at 3 bar, 30 W) with a screen stack: the kernels' T-matrices
    against the independent NumPy reference (its own form of the correlations, DOP853) to
    1e-7 (measured 1.7e-8 at 48 cells)."""
    core = screens_core()
    freqs = np.array([30.0, 120.0, 260.0, 500.0])
    Y = transfer_matrices(core, freqs, 30.0, device=DEVICE, cells=48).dimensionless()[0]
    Yref = reference.dimensionless_transfer(core, freqs, 30.0)
    assert float((np.abs(Y - Yref).max(-1) / np.abs(Yref).max(-1)).max()) < 1e-7


def test_against_open_thermoacoustics_stkscreen():
    """open-thermoacoustics' StackScreen (DeltaEC's STKSCREEN equations, exp(+iwt), RK45)
    at vanishing amplitude (its Reynolds number -> 0: g_c = 1, g_v = 0) and a solid of
    unbounded heat capacity (eps_s = 0), given tawarp's helium: p1, U1 at the end of a
    2 cm regenerator agree with tawarp's to 1e-6. (At uniform temperature: its gradient
    term carries a stray 1/T_m.)"""
    ota = pytest.importorskip("openthermoacoustics.segments")
    core = uniform_segment(screens_core(), length=0.02)
    T0, p_mean = core.gas.T_cold, core.gas.p_mean

    class Helium:  # tawarp's helium (tawarp/reference.py) behind open-thermoacoustics' gas interface
        mean_pressure = p_mean

        def _g(self, T):
            return reference.gas_properties("helium", T, p_mean)

        def density(self, T):
            return float(self._g(T).rho)

        def sound_speed(self, T):
            return float(self._g(T).c)

        def gamma(self, T):
            return float(self._g(T).gamma)

        def viscosity(self, T):
            return float(self._g(T).mu)

        def thermal_conductivity(self, T):
            return float(self._g(T).k)

        def specific_heat_cp(self, T):
            return float(self._g(T).cp)

        def prandtl(self, T):
            return float(self._g(T).Pr)

    seg = ota.StackScreen(length=0.02, porosity=POROSITY, hydraulic_radius=R_H, area=core.area,
                          solid_heat_capacity=1e300)  # fmt: skip
    f = 80.0
    p1, U1 = 1e-6 * np.exp(0.3j), 2e-12 * np.exp(-0.9j)  # |u1| ~ 1e-9 m/s: Re ~ 1e-14
    p_end, U_end, _ = seg.propagate(p1, U1, T0, 2 * math.pi * f, Helium())
    T = transfer_matrices(core, [f], device=DEVICE, cells=8).T[0, 0]
    ours = np.conj(T @ np.conj([p1, U1]))  # tawarp's phasors are exp(-iwt)'s: conjugates
    assert abs(ours[0] / p_end - 1) < 1e-6 and abs(ours[1] / U_end - 1) < 1e-6


def test_cascade_tangents():
    """dT/dz of the tangent cascade (the fit's Jacobian, every coefficient of the screens
    moving with the porosity) against central differences of the plain cascade at steps
    2k and k (k = 1e-3), extrapolated, to 1e-8 of max |dT/dz|."""
    core = screens_core()
    names = ["stack.porosity", "stack.pore_radius", "stack.tortuosity", "stack.h", "gas.T_cold"]
    v0 = np.array([core.get(k) for k in names]) * np.array([1.03, 1.2, 1.1, 0.8, 1.02])
    log = np.array([is_log(k) for k in names])
    P, heat = len(names), 30.0
    eng = Engine(core, np.array([35.0, 160.0, 450.0]), names, ForwardSettings(cells=6, device=DEVICE, cpu_threads=1))

    def table(zs):
        return np.stack([np.r_[heat, np.where(log, v0 * np.exp(z), v0 + 0.02 * z)] for z in zs], axis=1)

    step = eng.tangent_step
    zs = [np.zeros(P)] + [s * step * e for e in np.eye(P) for s in (1, -1)]
    out, tangent = (a.numpy() for a in eng.evaluate_tangents(table(zs), np.full((1, P), step), P))
    k = 1e-3
    ref = [np.zeros(P)] + [s * c * k * e for e in np.eye(P) for c in (2, 1) for s in (1, -1)]
    T = eng.evaluate(table(ref))[0].numpy()
    np.testing.assert_allclose(out[0], T[0], rtol=0, atol=1e-13 * np.abs(T[0]).max())
    for a in range(P):
        want = (4 * (T[3 + 4 * a] - T[4 + 4 * a]) / (2 * k) - (T[1 + 4 * a] - T[2 + 4 * a]) / (4 * k)) / 3
        err = np.abs(tangent[0, a] - want).max()
        assert err < 1e-8 * np.abs(want).max() + 1e-11 * np.abs(T[0]).max(), (names[a], err)


def test_complex_frequency_path_against_reference():
    """The onset's complex-frequency cascade of a heated screen core: at real omega it is
    transfer_matrices' T to 1e-13; at omega (1 + 0.02 i) the reference's DOP853 T-matrix at
    complex omega to 1e-6."""
    from test_onset import _core_matrix

    core = screens_core()
    f = np.array([60.0, 150.0])
    K = _core_matrix(core, 30.0, 2 * np.pi * f)
    T = transfer_matrices(core, f, 30.0, cells=16, device=DEVICE).T[0]
    assert np.max(np.abs(K - T) / np.abs(T)) < 1e-13
    w = 2 * np.pi * f * (1 + 0.02j)
    K = _core_matrix(core, 30.0, w)
    R = reference.transfer_matrix_omega(core, w, 30.0, rtol=1e-11)
    assert np.max(np.abs(K - R) / np.abs(R)) < 1e-6


def test_loop_library_leaves_out_the_thermal_radius_of_screens():
    """A screen stack has no thermal radius of its own (A takes its Prandtl number from the
    two radii): the loop's library offers no thermal_radius_ratio for it, heated or passive,
    and keeps it for the other porous segments of a passive core."""
    from tawarp.model.effects import tmatrix_library

    heated = screens_core()
    assert "thermal_radius_ratio" not in {e.name for e in tmatrix_library(heated)}
    passive = type(heated)(
        tuple(dataclasses.replace(s, thermal=False, heater=False, h=0.0) for s in heated.segments),
        heated.gas,
        heated.radius,
        "<passive screens>",
    )
    lib = {e.name: e for e in tmatrix_library(passive)}
    assert lib["thermal_radius_ratio"].params[0].targets == ("hot_hx.thermal_radius_ratio",)
    assert lib["viscous_shape_factor"].params[0].targets == (
        "stack.viscous_shape_factor",
        "hot_hx.viscous_shape_factor",
    )


def test_thermal_radius_ratio_does_not_act_on_screens():
    """The kernels read a screen stack's thermal radius as its hydraulic radius whatever
    thermal_radius_ratio a fit hands them (the core file refuses one): its T-matrices at
    ratio 1.8 and 1 are equal bit for bit, heated."""
    core = screens_core()
    eng = Engine(core, np.array([60.0, 300.0]), ["stack.thermal_radius_ratio"], ForwardSettings(cells=6, device=DEVICE))
    T = eng.evaluate(np.array([[30.0, 30.0], [1.0, 1.8]]))[0].numpy()
    assert np.array_equal(T[0], T[1])
