"""Segments with imposed temperatures (T_start, T_end or T; docs/formats.md): the forward
cascade, the complex-frequency walk and the onset in the hot temperature.

Oracles: the closed-form duct matrix at the imposed temperature (tawarp.reference), DOP853 on
Rott's ODE with the same linear profile (the reference's segment integrator, no code shared
with the kernels), SciPy's secant on the reference's boundary residual, and the eigenvalue
search run at the onset the search reports.
"""

import json
import math

import numpy as np
import pytest
import scipy.optimize as so

from tawarp import reference as ref
from tawarp.model.coefficients import duct_impedance, normalize
from tawarp.model.core import CoreError, core_from_dict, dump_core, load_core
from tawarp.model.forward import ForwardSettings, transfer_matrices
from tawarp.model.onset import eigenfrequencies, onset
from tawarp.model.resonator import engine_from_dict

DEVICE = "cpu"
T_COLD = 293.15
T_HOT = 600.0


def _segments(hot: float = T_HOT) -> list[dict]:
    """The bundled standing-wave engine's core with its temperatures imposed: the stack
    linear from T_cold to T_hot, the hot exchanger at T_hot, the buffer tube back to T_cold."""
    stack = dict(kind="porous", pore_model="circular", porosity=0.9, pore_radius=0.47e-3, solid_conductivity=3.0)
    return [
        dict(name="duct_left", kind="duct", length=0.03),
        dict(name="stack", length=0.048, T_start=T_COLD, T_end=hot, **stack),
        dict(name="hot_hx", length=0.01, T=hot, **stack),
        dict(name="tbt", kind="duct", length=0.10, T_start=hot, T_end=T_COLD),
        dict(name="duct_right", kind="duct", length=0.03),
    ]


def _engine_dict(segments=None) -> dict:
    return {
        "engine": {"left": "closed", "right": "closed", "left_duct": 0.7, "right_duct": 0.2},
        "gas": {"name": "air", "p_mean": 101325.0, "T_cold": T_COLD},
        "tube": {"radius": 0.0167},
        "segment": _segments() if segments is None else segments,
    }


def _core(segments) -> dict:
    return {k: v for k, v in _engine_dict(segments).items() if k != "engine"}


def _segment_matrix_ref(core, s, w):
    """The reference's matrix of segment s at angular frequency w [rad/s] (real or complex):
    closed form at a uniform imposed temperature, DOP853 along the linear profile else."""
    seg = core.segments[s]
    if not seg.imposed:
        return ref.duct_matrix_omega(core.gas.name, core.gas.p_mean, core.gas.T_cold, core.radius, seg.length, w)[0]
    if seg.T_start == seg.T_end and not seg.is_porous:
        return ref.duct_matrix_omega(core.gas.name, core.gas.p_mean, seg.T_start, core.radius, seg.length, w)[0]
    x0 = core.positions()[s]
    slope = (seg.T_end - seg.T_start) / seg.length

    def profile(x):
        return seg.T_start + slope * (x - x0), slope

    return ref._ode_matrix(core, seg, x0, w, profile, 1e-12)


def _core_matrix_ref(core, w):
    M = np.eye(2, dtype=complex)
    for s in range(len(core.segments)):
        M = _segment_matrix_ref(core, s, w) @ M
    return M


def test_uniform_imposed_temperature_is_the_closed_form():
    """A duct at an imposed uniform 500 K is exp(A L) at 500 K: the closed form
    [[cos kL, i Zc sin kL], [i sin kL / Zc, cos kL]] to 1e-12 of each row's largest entry."""
    core = core_from_dict(_core([dict(name="d", kind="duct", length=0.4, T=500.0)]), "t.toml")
    freqs = np.array([40.0, 150.0, 480.0])
    got = transfer_matrices(core, freqs, device=DEVICE).T[0]
    want = ref.duct_matrix_omega("air", 101325.0, 500.0, 0.0167, 0.4, 2 * np.pi * freqs)
    Y, Yw = normalize(got, duct_impedance(core)), normalize(want, duct_impedance(core))
    assert np.abs(Y - Yw).max() < 1e-12 * np.abs(Yw).max()


@pytest.mark.parametrize("cells", [None, 24])
def test_linear_profile_against_the_reference_ode(cells):
    """The standing-wave core with imposed temperatures against DOP853 (rtol 1e-12) on the
    same linear profiles, dimensionless coefficients, row-relative: the adaptive cells meet
    their 1e-6 target; 24 fixed sixth-order cells per segment reach 1e-9."""
    core = core_from_dict(_core(_segments()), "t.toml")
    freqs = np.array([30.0, 170.0, 500.0])
    got = transfer_matrices(core, freqs, settings=ForwardSettings(cells=cells, device=DEVICE)).T[0]
    want = np.stack([_core_matrix_ref(core, 2 * np.pi * f) for f in freqs])
    Y, Yw = normalize(got, duct_impedance(core)), normalize(want, duct_impedance(core))
    err = np.abs(Y - Yw).max(axis=-1) / np.abs(Yw).max(axis=-1)
    assert err.max() < (1e-6 if cells is None else 1e-9), err


def test_temperature_profile_is_the_imposed_one():
    """ForwardResult.temperature: T_cold outside the imposed segments, the linear profiles
    (and their slopes) inside, exactly."""
    core = core_from_dict(_core(_segments()), "t.toml")
    res = transfer_matrices(core, [100.0], device=DEVICE)
    x0 = core.positions()
    x = np.array([0.01, x0[1] + 0.012, x0[2] + 0.005, x0[3] + 0.05, x0[-1] - 0.01])
    T, dT = res.temperature(x)
    slope = (T_HOT - T_COLD) / 0.048
    want = [T_COLD, T_COLD + slope * 0.012, T_HOT, T_HOT + (T_COLD - T_HOT) * 0.5, T_COLD]
    np.testing.assert_allclose(T[0], want, rtol=1e-14)
    np.testing.assert_allclose(dT[0], [0.0, slope, 0.0, (T_COLD - T_HOT) / 0.1, 0.0], rtol=1e-12, atol=1e-12)


def test_eigenfrequency_against_the_reference():
    """The engine at its file's temperatures (T_hot = 600 K, no heater): the kernel's complex
    eigenfrequency (24 Magnus cells per graded segment) is the root of Tup = 0 of the
    reference (closed-form ducts, DOP853 at complex omega) found by SciPy's secant from an
    independent start, within 1e-8 |omega|; T_hot is the largest imposed temperature."""
    eng = engine_from_dict(_engine_dict(), "e.toml")
    res = eigenfrequencies(eng, 0.0, cells=24, device=DEVICE)
    row = eng.resonator_row()

    def tup(w):
        left = ref.duct_matrix_omega("air", 101325.0, row[2], row[1], row[0], w)[0]
        right = ref.duct_matrix_omega("air", 101325.0, row[5], row[4], row[3], w)[0]
        return (right @ _core_matrix_ref(eng.core, w) @ left)[1, 0]

    exact = so.newton(tup, 2 * math.pi * 160.0 + 1.0j, tol=1e-12, maxiter=50)
    assert abs(res.omega[0] - exact) < 1e-8 * abs(exact)
    assert res.T_hot[0] == T_HOT


def test_onset_in_the_hot_temperature():
    """Onset searched in T_hot / T_cold on [1, 4]: the eigenfrequency at the reported ratio
    (every imposed excess scaled, the file's profile kept) has |Im omega| < 1e-8 |omega| and
    Re omega / 2 pi = f_onset to 1e-9; the mode decays at ratio 1 and grows at 4; T_hot =
    ratio T_cold; Q_onset is NaN (no heater). The same engine with T_hot = 450 K in its file
    gives the same onset ratio (the search scales the profile, not the file's values) to 1e-8."""
    eng = engine_from_dict(_engine_dict(), "e.toml")
    res = onset(eng, T_ratio_max=4.0, n_bracket=7, curve=True, device=DEVICE)
    ratio = res.ratio_onset[0]
    assert 1.0 < ratio < 4.0 and np.isnan(res.Q_onset[0]) and res.searched == "T_ratio"
    assert abs(res.T_hot[0] - ratio * T_COLD) < 1e-12 * res.T_hot[0]
    assert res.omega_grid[0, 0].imag < 0 < res.omega_grid[0, -1].imag
    hot = T_COLD * ratio
    at = engine_from_dict(_engine_dict(_segments(hot)), "e.toml")
    eig = eigenfrequencies(at, 0.0, device=DEVICE)
    assert abs(eig.omega[0].imag) < 1e-8 * abs(eig.omega[0])
    assert abs(eig.frequency[0] - res.f_onset[0]) < 1e-9 * res.f_onset[0]
    other = onset(engine_from_dict(_engine_dict(_segments(450.0)), "e.toml"), T_ratio_max=4.0, device=DEVICE)
    assert abs(other.ratio_onset[0] - ratio) < 1e-8 * ratio


def test_onset_in_the_hot_temperature_needs_imposed_temperatures():
    """The bundled engine (a heater, no imposed temperature) refuses a search in T_hot,
    naming what is missing; both bounds or none is refused too."""
    from tawarp.model.resonator import load_engine

    with pytest.raises(CoreError, match="needs imposed temperatures"):
        onset(load_engine("standing_wave"), T_ratio_max=3.0, device=DEVICE)
    with pytest.raises(ValueError, match="one"):
        onset(load_engine("standing_wave"), Q_max=50.0, T_ratio_max=3.0, device=DEVICE)
    eng = engine_from_dict(_engine_dict(), "e.toml")
    with pytest.raises(CoreError, match="stack.T_end cannot vary"):
        onset(eng, T_ratio_max=3.0, params={"stack.T_end": [500.0, 550.0]}, device=DEVICE)


def test_files_with_imposed_temperatures():
    """T gives T_start = T_end; thermal = true beside imposed temperatures is dropped (the
    profile replaces the heat model), so such a core needs no heater; the temperatures are
    parameters (SEGMENT.T_start, SEGMENT.T_end) and survive a dump/load round trip."""
    segs = _segments()
    segs[1]["thermal"] = True
    core = core_from_dict(_core(segs), "t.toml")
    hx = core.segment("hot_hx")
    assert (hx.T_start, hx.T_end, hx.thermal, core.thermal_indices) == (T_HOT, T_HOT, False, [])
    assert {"stack.T_start", "stack.T_end", "hot_hx.T_start"} <= set(core.parameter_names())
    assert "duct_left.T_start" not in core.parameter_names()
    assert core.replace(**{"stack.T_end": 700.0}).segment("stack").T_end == 700.0


def test_round_trip(tmp_path):
    core = core_from_dict(_core(_segments()), "t.toml")
    path = tmp_path / "c.toml"
    path.write_text(dump_core(core))
    again = load_core(path)
    assert [(s.T_start, s.T_end) for s in again.segments if s.imposed] == [
        (s.T_start, s.T_end) for s in core.segments if s.imposed
    ]


@pytest.mark.parametrize(
    "change, match",
    [
        ({"T": 500.0, "T_start": 400.0}, "T .uniform. and T_start both given"),
        ({"T_start": 400.0}, "T_start given without T_end"),
        ({"T_end": -5.0, "T_start": 400.0}, r"T_end \[K\]: must lie in"),
        ({"T_start": float("nan"), "T_end": 400.0}, r"T_start \[K\]: expected a finite number"),
        ({"T_start": "hot", "T_end": 400.0}, r"T_start \[K\]: expected a number"),
        ({"T": 500.0, "thermal": True, "heater": True}, "heater = true with imposed temperatures"),
        ({"T": {"value": 500.0, "sd": 5.0}}, "T takes a plain value"),
    ],
)
def test_bad_imposed_temperatures(change, match):
    """Bad imposed temperatures are refused in one line naming the file, the segment and the key."""
    segs = [dict(name="d", kind="duct", length=0.1, **change)]
    with pytest.raises(CoreError, match=match) as err:
        core_from_dict(_core(segs), "bad.toml")
    msg = str(err.value)
    assert msg.startswith("bad.toml") and "'d'" in msg and "\n" not in msg


def test_thermal_segment_without_heater_says_what_is_missing():
    """A thermal segment with neither imposed temperatures nor a heater in the heat model:
    the error names it and both ways out (heater = true, or T_start/T_end)."""
    segs = _segments()
    segs[3] = dict(name="tbt", kind="duct", length=0.1, thermal=True, h=0.2)
    with pytest.raises(CoreError, match="'tbt'.*heater = true.*T_start and T_end"):
        core_from_dict(_core(segs), "bad.toml")


def test_cli_onset_in_the_hot_temperature(tmp_path):
    """``tawarp onset --in T_hot`` writes the API's onset ratio, frequency and T_hot (exact
    float round trip) and the T_hot/T_cold grid."""
    from tawarp.cli import main

    lines = ["[engine]", 'left = "closed"', 'right = "closed"', "left_duct = 0.7", "right_duct = 0.2", ""]
    text = "\n".join(lines) + dump_core(core_from_dict(_core(_segments()), "t.toml"))
    path = tmp_path / "hot.toml"
    path.write_text(text)
    out = tmp_path / "o"
    args = ["onset", str(path), "--in", "T_hot", "--T-ratio-max", "3", "--bracket", "5"]
    assert main(args + ["-o", str(out), "--device", DEVICE, "--quiet", "--no-plots"]) == 0
    js = json.loads((out / "onset.json").read_text())
    api = onset(engine_from_dict(_engine_dict(), "e.toml"), T_ratio_max=3.0, n_bracket=5, curve=True, device=DEVICE)
    s = js["sets"][0]
    assert (s["T_ratio_onset"], s["f_onset_Hz"], s["T_hot_K"]) == (api.ratio_onset[0], api.f_onset[0], api.T_hot[0])
    assert js["searched"] == "T_ratio" and js["T_ratio_grid"] == list(api.grid) and s["Q_onset_W"] is None
