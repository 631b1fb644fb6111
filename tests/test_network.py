"""Engine networks: the file format and its graph check, and the NumPy reference's
eigenfrequencies against closed forms of ducts, T-junctions, loops and lumped elements."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import scipy.optimize as so

from tawarp.model.core import CoreError
from tawarp.model.gas import GASES
from tawarp.model.network import bundled_networks, load_network, network_from_dict
from tawarp.model import network_reference as nr
from tawarp.model.resonator import load_engine
from tawarp.reference import duct_waves, gas_properties

AIR = {"name": "air", "p_mean": 101325.0, "T_cold": 293.15}


def duct(name, length, radius, **kw):
    return {"name": name, "kind": "duct", "length": length, "radius": radius, **kw}


def two_ends(*branches, ends=("a", "b")):
    return {"gas": AIR, "branch": list(branches), "end": [{"name": e, "kind": "closed"} for e in ends]}


def tube(L=1.0, R=0.02):
    return two_ends({"name": "tube", "from": "a", "to": "b", "segment": [duct("d", L, R)]})


# -- format ---------------------------------------------------------------------------
def test_bundled_networks_load_and_old_engines_still_do():
    assert {"traveling_wave", "refrigerator"} <= set(bundled_networks())
    for name in bundled_networks():
        net = load_network(name)
        assert net.branches
    assert load_engine("standing_wave").core.segments  # a core-based engine file is unchanged
    with pytest.raises(CoreError, match=r"standing_wave.toml: no \[\[branch\]\] tables"):
        load_network("standing_wave")


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda d: d["branch"][0].pop("to"), r"t.toml: branch #1: missing key 'to'"),
        (lambda d: d["branch"][0]["segment"][0].update(kind="pipe"), r"segment #1 \('d'\): kind = 'pipe'"),
        (lambda d: d["branch"][0]["segment"][0].update(porosity=0.5), r"a duct takes no \['porosity'\]"),
        (lambda d: d["branch"][0]["segment"][0].pop("radius"), r"\('d'\): give its cross-section"),
        (lambda d: d["branch"][0]["segment"][0].update(T="T_warm"), r"\('d'\): T: 'T_warm'"),
        (lambda d: d["branch"][0]["segment"][0].update(T="T_hot"), r"names 'T_hot' but \[network\] T_hot"),
        (lambda d: d["branch"][0]["segment"][0].update(T_start=300.0), r"needs both T_start and T_end"),
        (lambda d: (d["branch"][0].update({"to": "c"}), d["end"].pop()), r"ends at 'c', which nothing else touches"),
        (lambda d: d["end"].append({"name": "c", "kind": "closed"}), r"\[\[end\]\] 'c' is not the from/to"),
        (lambda d: d["end"][0].update(kind="open", flange="baffle"), r"flange = 'baffle'"),
        (lambda d: d["end"][0].update(kind="load", resistance=1.0), r"a load needs resistance"),
        (lambda d: d.update(extra=1), r"unknown top-level key\(s\) \['extra'\]"),
    ],
)
def test_bad_files_name_file_and_key(edit, message):
    d = copy.deepcopy(tube())
    edit(d)
    with pytest.raises(CoreError, match=message):
        network_from_dict(d, "t.toml")


def test_graph_check_ends_touched_once_and_one_piece():
    d = two_ends(
        {"name": "x", "from": "a", "to": "b", "segment": [duct("d1", 1.0, 0.02)]},
        {"name": "y", "from": "b", "to": "j", "segment": [duct("d2", 1.0, 0.02)]},
    )
    with pytest.raises(CoreError, match=r"end 'b' is touched by 2 branch ends"):
        network_from_dict(d, "t.toml")
    d = two_ends(
        {"name": "x", "from": "a", "to": "b", "segment": [duct("d1", 1.0, 0.02)]},
        {"name": "ring", "from": "r", "to": "r", "segment": [duct("d2", 1.0, 0.02)]},
    )
    with pytest.raises(CoreError, match=r"separate pieces; nodes \['r'\]"):
        network_from_dict(d, "t.toml")


# -- eigenfrequencies against closed forms ----------------------------------------------
def _k_zc(radius, w, T=293.15):
    k, Zc = duct_waves("air", 101325.0, T, radius, np.atleast_1d(w))
    return k[0], Zc[0]


def _root(f, w0):
    return complex(so.newton(f, w0, x1=w0 * (1 + 1e-4), tol=1e-12 * abs(w0), maxiter=100))


def test_closed_closed_duct_is_half_wave_of_the_lossy_wavenumber():
    """sin(k(omega) L) = 0: k(omega) L = pi, k from the reference's duct waves (Kirchhoff's
    lossy wavenumber): the network's root agrees to 1e-10."""
    net = network_from_dict(tube(1.0, 0.02), "t")
    c = math.sqrt(1.4 * 287.05 * 293.15)
    w = nr.eigenfrequency(net, math.pi * c)
    exact = _root(lambda w: _k_zc(0.02, w)[0] * 1.0 - math.pi, math.pi * c)
    assert abs(w - exact) < 1e-10 * abs(exact)
    assert w.imag < 0  # a passive duct decays


def test_a_gas_mixture_network_rings_at_the_mixtures_lossy_half_wave():
    """A [gas.mixture] network (helium-argon, a working gas of traveling-wave engines): its
    closed-closed duct has k(omega) L = pi with the mixture's own wavenumber (the reference's
    duct waves of the same mixture), and its frequency is the mixture's, not a pure gas's."""
    data = tube(1.0, 0.02)
    data["gas"] = {"mixture": {"helium": 0.7, "argon": 0.3}, "p_mean": 1e6, "T_cold": 300.0}
    net = network_from_dict(data, "t")
    name = net.gas.name
    g = GASES[name]
    c = math.sqrt(g.gamma * g.R_gas * 300.0)
    w = nr.eigenfrequency(net, math.pi * c)
    k = lambda w: duct_waves(name, 1e6, 300.0, 0.02, np.atleast_1d(w))[0][0]  # noqa: E731
    exact = _root(lambda w: k(w) * 1.0 - math.pi, math.pi * c)
    assert abs(w - exact) < 1e-10 * abs(exact)
    assert abs(w.real / (math.pi * c) - 1) < 0.01
    helium = GASES["helium"]
    assert abs(w.real / (math.pi * math.sqrt(helium.gamma * helium.R_gas * 300.0)) - 1) > 0.2
    data["gas"]["name"] = "helium"
    with pytest.raises(CoreError, match="both name and"):
        network_from_dict(data, "t")


def test_a_plain_junction_changes_nothing():
    """A degree-2 node joining two pieces (in either direction) is the same duct."""
    one = nr.eigenfrequency(network_from_dict(tube(1.0, 0.02), "t"), 1070.0)
    d = two_ends(
        {"name": "x", "from": "a", "to": "j", "segment": [duct("d1", 0.37, 0.02)]},
        {"name": "y", "from": "b", "to": "j", "segment": [duct("d2", 0.63, 0.02)]},
    )
    assert abs(nr.eigenfrequency(network_from_dict(d, "t"), 1070.0) - one) < 1e-10 * abs(one)


def test_t_junction_closed_form():
    """Three closed stubs of lengths L_i and radii R_i meeting at a tee: the admittances
    into them sum to zero, sum_i tan(k_i L_i) / Zc_i = 0 (lossy k_i, Zc_i)."""
    stubs = [(0.5, 0.02), (0.8, 0.02), (0.3, 0.01)]
    d = {
        "gas": AIR,
        "branch": [
            {"name": f"s{i}", "from": "tee", "to": f"e{i}", "segment": [duct(f"d{i}", L, R)]}
            for i, (L, R) in enumerate(stubs)
        ],
        "end": [{"name": f"e{i}", "kind": "closed"} for i in range(3)],
    }
    net = network_from_dict(d, "t")

    def char(w):
        return sum(np.tan(k * L) / Zc for (L, R) in stubs for k, Zc in [_k_zc(R, w)])

    for w0 in (2 * math.pi * 150, 2 * math.pi * 330):
        exact = _root(char, complex(w0))
        assert abs(nr.eigenfrequency(net, exact * (1 + 1e-3)) - exact) < 1e-9 * abs(exact)


def test_loop_with_a_stub_closed_form():
    """A ring of length Lr both of whose ends meet a closed stub of length Ls: the symmetric
    modes satisfy 2 tan(k Lr / 2) / Zc_r + tan(k Ls) / Zc_s = 0."""
    Lr, Rr, Ls, Rs = 1.2, 0.02, 0.7, 0.015
    d = {
        "gas": AIR,
        "branch": [
            {"name": "ring", "from": "j", "to": "j", "segment": [duct("r1", Lr, Rr)]},
            {"name": "stub", "from": "j", "to": "e", "segment": [duct("s1", Ls, Rs)]},
        ],
        "end": [{"name": "e", "kind": "closed"}],
    }
    net = network_from_dict(d, "t")

    def char(w):
        kr, zr = _k_zc(Rr, w)
        ks, zs = _k_zc(Rs, w)
        return 2 * np.tan(kr * Lr / 2) / zr + np.tan(ks * Ls) / zs

    exact = _root(char, complex(2 * math.pi * 200))
    assert exact.real > 2 * math.pi * 100  # the first symmetric mode, not omega = 0
    assert abs(nr.eigenfrequency(net, exact * (1 + 1e-3)) - exact) < 1e-9 * abs(exact)


def test_helmholtz_resonator_of_lumped_elements():
    """Inertance (neck l, S) into a compliance V closed behind, the neck's mouth at p = 0:
    omega^2 = gamma p_m S / (rho l V) within the neck's viscous correction (|f_nu| ~ 2 %)."""
    l, R, V = 0.05, 0.01, 1e-3
    d = {
        "gas": AIR,
        "branch": [
            {
                "name": "h",
                "from": "mouth",
                "to": "back",
                "segment": [
                    {"name": "neck", "kind": "inertance", "length": l, "radius": R},
                    {"name": "cavity", "kind": "compliance", "volume": V},
                ],
            }
        ],
        "end": [{"name": "mouth", "kind": "impedance", "impedance": [0.0, 0.0]}, {"name": "back", "kind": "closed"}],
    }
    g = gas_properties("air", 293.15, 101325.0)
    w_h = math.sqrt(1.4 * 101325.0 * math.pi * R**2 / (g.rho * l * V))
    w = nr.eigenfrequency(network_from_dict(d, "t"), w_h)
    assert abs(w.real / w_h - 1) < 0.02
    assert -0.02 < w.imag / w_h < 0


@pytest.mark.parametrize("flange, correction", [("unflanged", 0.6133), ("flanged", 0.8216)])
def test_open_end_radiates_with_its_end_correction(flange, correction):
    """Closed-open pipe of length L, radius a: the network's root is that of
    -i Zc cot(kL) = Z_rad (the closed form of a lossy duct ending on the radiation
    impedance); Re omega that of k (L + delta a) = pi / 2 (delta: Levine & Schwinger's
    0.6133 unflanged, 0.8216 flanged), and the radiation's share of the decay rate that of
    the energy balance, Im omega_rad = -(c / L) r (ka)^2 (r = 1/4, 1/2), to 5 %."""
    L, R = 1.0, 0.01
    d = tube(L, R)
    d["end"][1] = {"name": "b", "kind": "open", "flange": flange}
    net = network_from_dict(d, "t")
    w = nr.eigenfrequency(net, 500.0)
    res_coef = nr.RADIATION[flange][0]
    g = gas_properties("air", 293.15, 101325.0)
    z0 = g.rho * g.c / (math.pi * R**2)

    def closed_form(w, radiating=True):
        k, Zc = _k_zc(R, w)
        ka = w / g.c * R
        return -1j * Zc / np.tan(k * L) - z0 * (res_coef * ka**2 * radiating - 1j * correction * ka)

    full = _root(closed_form, complex(500.0))
    assert abs(w - full) < 1e-9 * abs(full)
    corrected = _root(lambda w: _k_zc(R, w)[0] * (L + correction * R) - math.pi / 2, complex(500.0))
    assert abs(w.real / corrected.real - 1) < 2e-4
    reactive = _root(lambda w: closed_form(w, radiating=False), complex(500.0))
    ka = w.real / g.c * R
    assert abs((w.imag - reactive.imag) / (-(g.c / L) * res_coef * ka**2) - 1) < 0.05


def test_rc_load_closed_form():
    """A duct closed at one end and loaded at the other by a resistance R into a volume V:
    the root of -i Zc cot(kL) = R + i gamma p_m / (omega V) (lossy k, Zc), to 1e-9; the
    resistance damps the mode (R = 0 leaves only the wall losses and the spring)."""
    L, R0 = 1.0, 0.02
    roots = []
    for R in (0.0, 3e5):
        d = tube(L, R0)
        d["end"][1] = {"name": "b", "kind": "load", "resistance": R, "volume": 1e-4}
        w = nr.eigenfrequency(network_from_dict(d, "t"), 2 * math.pi * 200.0)

        def char(w, R=R):
            k, Zc = _k_zc(R0, w)
            return -1j * Zc / np.tan(k * L) - (R + 1j * 1.4 * 101325.0 / (w * 1e-4))

        exact = _root(char, w * (1 + 1e-3))
        assert abs(w - exact) < 1e-9 * abs(exact)
        roots.append(w)
    assert roots[1].imag < roots[0].imag < 0


# -- mode following and onset -----------------------------------------------------------
def test_follow_reports_a_jump_instead_of_hiding_it():
    """A synthetic root that switches branches at T = 500: the path records one jump between
    the last point before and the first after, refined to the minimum step."""

    def root_at(T, guess):
        return complex(100.0 + 0.01 * T, -1 + 0.004 * T) if T < 500 else complex(150.0 + 0.01 * T, 1.0)

    path = nr.follow(root_at, np.linspace(300, 700, 9), 0j, jump_tol=0.05)
    assert len(path.jumps) == 1
    j = path.jumps[0]
    assert j.T_before < 500 <= j.T_after and j.T_after - j.T_before <= 50 / 64 + 1e-12
    smooth = nr.follow(lambda T, g: complex(100 + 0.01 * T, 0.0), np.linspace(300, 700, 9), 0j)
    assert smooth.jumps == []


@pytest.fixture(scope="module")
def tw_onset():
    net = load_network("traveling_wave")
    (w0,) = [w for w in nr.real_axis_modes(net, 40.0, 130.0, 90, T_hot=net.gas.T_cold)]
    return net, nr.onset(net, w0, T_max=1000.0, n=12)


def test_traveling_wave_onset_is_a_sign_change_of_the_growth_rate(tw_onset):
    net, res = tw_onset
    assert res.path.jumps == []
    assert 1.0 < res.ratio < 3.0 and 70 < res.frequency < 100
    assert abs(res.omega.imag) < 1e-7 * res.omega.real
    below = nr.eigenfrequency(net, res.omega, res.T_onset - 1.0)
    above = nr.eigenfrequency(net, res.omega, res.T_onset + 1.0)
    assert below.imag < 0 < above.imag


# -- power flows ----------------------------------------------------------------------
def test_acoustic_power_is_conserved_at_junctions_and_the_regenerator_produces_it(tw_onset):
    """At onset (real omega) the mode is a steady state: at every junction the acoustic power
    into it sums to zero (1e-9 of the largest flow), it vanishes at the closed end, and the
    regenerator is where Edot grows (the engine's amplifier) while every other segment
    dissipates."""
    net, res = tw_onset
    prof = {p.branch: p for p in nr.profiles(net, res.omega, res.T_onset, amplitude=1e5)}
    scale = max(np.abs(p.Edot).max() for p in prof.values())
    for node, inc in net.nodes().items():
        into = sum(
            prof[net.branches[b].name].Edot[-1 if side == "end" else 0] * (1 if side == "end" else -1)
            for b, side in inc
        )
        if node in net.ends:
            assert abs(into) < 1e-9 * scale
        else:
            assert abs(into) < 1e-9 * scale, node
    core = prof["core"]
    for name in ("main_ahx", "regenerator", "hot_hx", "tbt", "secondary_ahx"):
        at = [k for k, s in enumerate(core.segment) if s == name]
        gain = core.Edot[at[-1]] - core.Edot[at[0]]
        assert (gain > 0) == (name == "regenerator"), (name, gain)


def test_acoustic_power_changes_only_by_dissipation_and_production(tw_onset):
    """Along each distributed segment at onset, Edot(out) - Edot(in) from the mode's p and U
    equals the integral of the local budget (Swift 2002, Ch. 5): viscous and thermal-
    relaxation losses (never positive) plus the thermoacoustic production (zero where the
    temperature is uniform), to 1e-6 of the segment's largest Edot."""
    net, res = tw_onset
    prof = {p.branch: p for p in nr.profiles(net, res.omega, res.T_onset, amplitude=1e5)}
    for br in net.branches:
        pr = prof[br.name]
        for seg in br.segments:
            if seg.lumped:
                continue
            at = [k for k, s in enumerate(pr.segment) if s == seg.name]
            budget = nr.power_budget(net, seg, res.omega.real, res.T_onset, pr.p[at[0]], pr.U[at[0]])
            scale = np.abs(pr.Edot[at]).max()
            assert abs(pr.Edot[at[-1]] - pr.Edot[at[0]] - budget.total) < 1e-6 * scale, seg.name
            assert budget.viscous <= 0 and budget.thermal <= 0
            T0, T1 = seg.temperatures(net.gas.T_cold, res.T_onset)
            if T0 == T1:
                assert budget.production == 0.0


def test_total_power_in_a_tight_regenerator_carries_no_acoustic_power():
    """Swift (2002), Ch. 7: where r << delta (f_nu, f_k -> 1), the p U* term of Htot
    vanishes as (r / delta)^2: an ideal regenerator passes acoustic power without the
    enthalpy flux that would carry it. Checked at r / delta_k = 0.02: that term is below
    1e-3 of Edot."""
    seg = load_network("traveling_wave").branches[1].segments[1]
    assert seg.name == "regenerator"
    net = load_network("traveling_wave")
    T, w = 600.0, 2 * math.pi * 80.0
    g = gas_properties("helium", T, net.gas.p_mean)
    d_k = math.sqrt(2 * g.k / (g.rho * g.cp * w))
    tight = __import__("dataclasses").replace(seg, pore_radius=0.02 * d_k)
    p, U = 1e5 + 0j, 1e-2 * np.exp(0.3j)
    h = nr.total_power(net, tight, w, p, U, T, 0.0, tight.area)
    assert abs(h) < 1e-3 * 0.5 * np.real(p * np.conj(U))


# -- DeltaEC's hofler1 example ----------------------------------------------------------
def _polar(mag, deg):
    return mag * np.exp(1j * np.radians(deg))


#: DeltaEC's hofler1 (Hofler's refrigerator, helium 1 MPa, 500 Hz): each segment's input and
#: output (|p| [Pa], phase [deg], |U| [m^3/s], phase [deg]) in DeltaEC's exp(+i omega t), as
#: open-thermoacoustics copies them (examples/validation/validate_reference_full.py)
HOFLER1 = [
    ("ambient_duct", (30000.0, 0.0, 4.9767e-4, -0.26946), (29739.0, -0.17763, 2.7789e-3, -79.991)),
    ("ambient_hx", (29739.0, -0.17763, 2.7789e-3, -79.991), (29570.0, -0.12971, 3.0568e-3, -81.875)),
    ("stack", (29570.0, -0.12971, 3.0568e-3, -81.875), (26103.0, 1.4277, 6.8004e-3, -87.965)),
    ("cold_hx", (26103.0, 1.4277, 6.8004e-3, -87.965), (25923.0, 1.4848, 6.9051e-3, -88.059)),
    ("cold_duct", (25923.0, 1.4848, 6.9051e-3, -88.059), (1489.2, 1.5242, 8.6235e-3, -88.211)),
    ("cone", (1489.2, 1.5242, 8.6235e-3, -88.211), (4526.5, -178.49, 8.3826e-3, -88.196)),
]


@pytest.mark.parametrize("name, given, expected", HOFLER1)
def test_refrigerator_segments_reproduce_deltaec(name, given, expected):
    """Each segment of the bundled refrigerator, driven by DeltaEC's input state, gives
    DeltaEC's output: |p| and |U| to 0.1 % (the stack 0.5 %: its plates' heat capacity,
    eps_s ~ 0.07 in DeltaEC, is neglected here), phases to 0.1 degree."""
    net = load_network("refrigerator")
    b, s = net.segment(name)
    seg = net.branches[b].segments[s]
    # DeltaEC's exp(+i omega t) -> tawarp's exp(-i omega t): complex conjugates
    state = np.conj([_polar(given[0], given[1]), _polar(given[2], given[3])])
    p, U = np.conj(nr.segment_matrix(net, seg, 2 * math.pi * 500.0, net.T_hot) @ state)
    p_ref, U_ref = _polar(expected[0], expected[1]), _polar(expected[2], expected[3])
    tol = 5e-3 if name == "stack" else 1e-3
    assert abs(abs(p) / abs(p_ref) - 1) < tol
    assert abs(abs(U) / abs(U_ref) - 1) < tol
    assert abs(np.degrees(np.angle(p / p_ref))) < 0.1 and abs(np.degrees(np.angle(U / U_ref))) < 0.1


def test_a_core_engine_with_imposed_temperatures_has_the_same_onset_as_its_network():
    """The bundled standing-wave engine with the ceramic core's temperatures imposed
    (T_cold -> 650 K along the stack, 650 K in the hot exchanger, back along the buffer tube):
    the core-engine onset in T_hot (tawarp.model.onset, the kernels' Magnus walk with adaptive
    cells) and the network reference's (DOP853) are two implementations of one model; they
    agree to 1e-6 in T_hot / T_cold and in frequency."""
    import dataclasses

    from imposed_cores import imposed_ceramic
    from tawarp.model.network import network_from_engine
    from tawarp.model.onset import onset as engine_onset

    eng = dataclasses.replace(load_engine("standing_wave"), core=imposed_ceramic(650.0))
    ours = engine_onset(eng, T_ratio_max=3.0, device="cpu")
    net = network_from_engine(eng)
    assert net.T_hot == 650.0 and [s.name for s in net.branches[0].segments][0] == "left_duct"
    (w0, *_) = nr.real_axis_modes(net, 20.0, 400.0, 200, T_hot=net.gas.T_cold)
    res = nr.onset(net, w0, T_max=3 * net.gas.T_cold, n=12)
    assert abs(res.ratio / ours.ratio_onset[0] - 1) < 1e-6
    assert abs(res.frequency / ours.f_onset[0] - 1) < 1e-6
