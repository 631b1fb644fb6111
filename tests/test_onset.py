"""Complex eigenfrequencies and onset of engines (tawarp.model.onset, kernels/onset.py).

Oracles: mpmath (pore functions at complex argument), the closed-form duct wavenumber
k(omega) L = n pi solved by a scalar SciPy root find, the independent NumPy reference
(tawarp.reference, complex omega) driven by SciPy, and a dense bisection on Q.
"""

import math

import mpmath
import numpy as np
import pytest
import scipy.optimize as so
import scipy.special as sp
import warp as wp

from tawarp import reference as ref
from tawarp.kernels.onset import HeatedCore, core_vector
from tawarp.kernels.pore import PORE_CIRCULAR, PORE_PLATES, pore_functions_complex
from tawarp.model.core import CoreError, core_from_dict, load_core
from tawarp.model.forward import Engine, ForwardSettings, transfer_matrices
from tawarp.model.onset import eigenfrequencies, heated_core, onset
from tawarp.model.resonator import EndCondition, ResonatorDuct, ThermoacousticEngine, engine_from_dict, load_engine

from imposed_cores import imposed_ceramic

DEVICE = "cpu"


@wp.kernel
def _pore_c(model: int, s: wp.array(dtype=wp.vec2d), f: wp.array(dtype=wp.vec2d), g: wp.array(dtype=wp.vec2d)):
    i = wp.tid()
    fi, gi = pore_functions_complex(model, s[i])
    f[i] = fi
    g[i] = gi


def _mp_pore(model, s):
    with mpmath.workdps(40):
        s = mpmath.mpc(s.real, s.imag)
        if model == PORE_CIRCULAR:
            z = (1 + 1j) * s
            f = 2 * mpmath.besselj(1, z) / (z * mpmath.besselj(0, z))
            g = -mpmath.besselj(2, z) / mpmath.besselj(0, z)
        else:
            w = (1 - 1j) * s
            f = mpmath.tanh(w) / w
            g = 1 - f
        return complex(f), complex(g)


@pytest.mark.parametrize("model", [PORE_CIRCULAR, PORE_PLATES])
def test_pore_functions_complex_argument(model):
    """f and g = 1 - f at complex s = r/delta (|arg s| <= 0.35, i.e. |Im omega| up to
    ~0.7 Re omega), on both sides of each method's threshold: relative error < 1e-13
    against mpmath at 40 digits, each of f and g relative to itself."""
    rng = np.random.default_rng(3)
    mag = np.concatenate([np.geomspace(1e-3, 1e3, 40), [0.99, 1.01, 19.5, 20.5, 25.0]])
    s = mag * np.exp(1j * rng.uniform(-0.35, 0.35, mag.size))
    ws = wp.array(s.view(np.float64).reshape(-1, 2), dtype=wp.vec2d, device=DEVICE)
    f = wp.empty(s.size, dtype=wp.vec2d, device=DEVICE)
    g = wp.empty(s.size, dtype=wp.vec2d, device=DEVICE)
    wp.launch(_pore_c, dim=s.size, inputs=[model, ws, f, g], device=DEVICE)
    f = f.numpy().view(np.complex128).ravel()
    g = g.numpy().view(np.complex128).ravel()
    exact = np.array([_mp_pore(model, x) for x in s])
    assert np.max(np.abs(f - exact[:, 0]) / np.abs(exact[:, 0])) < 1e-13
    assert np.max(np.abs(g - exact[:, 1]) / np.abs(exact[:, 1])) < 1e-13


@wp.kernel
def _core_columns(core: HeatedCore, omega: wp.array(dtype=wp.vec2d), out: wp.array2d(dtype=wp.vec2d)):
    j = wp.tid()
    one = wp.vec2d(wp.float64(1.0), wp.float64(0.0))
    zero = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    w = omega[j]
    p, u = core_vector(core, 0, w, w[0], one, zero)
    out[j, 0] = p
    out[j, 2] = u
    p, u = core_vector(core, 0, w, w[0], zero, one)
    out[j, 1] = p
    out[j, 3] = u


def _core_matrix(core, Q, omega):
    fe = Engine(core, [1.0], (), ForwardSettings(device=DEVICE, cells=16))
    params, theta = fe.heat(np.array([[Q]]))
    w = np.ascontiguousarray(np.asarray(omega, dtype=complex))
    out = wp.empty((w.size, 4), dtype=wp.vec2d, device=DEVICE)
    wp.launch(
        _core_columns,
        dim=w.size,
        device=DEVICE,
        inputs=[
            heated_core(fe, params, theta),
            wp.array(w.view(np.float64).reshape(-1, 2), dtype=wp.vec2d, device=DEVICE),
            out,
        ],
    )
    return out.numpy().view(np.complex128).reshape(-1, 2, 2)


def test_core_cascade_complex_omega():
    """Heated ceramic core (Q = 30 W, 16 cells): the complex-omega cascade at real omega is
    transfer_matrices' T to 1e-13 (same scheme, other code path); at omega (1 + 0.02 i) it
    is the reference's DOP853 T-matrix at complex omega to 1e-6 (each entry, relative)."""
    core = load_core("ceramic")
    f = np.array([60.0, 150.0])
    K = _core_matrix(core, 30.0, 2 * np.pi * f)
    T = transfer_matrices(core, f, 30.0, cells=16, device=DEVICE).T[0]
    assert np.max(np.abs(K - T) / np.abs(T)) < 1e-13
    w = 2 * np.pi * f * (1 + 0.02j)
    K = _core_matrix(core, 30.0, w)
    R = ref.transfer_matrix_omega(core, w, 30.0, rtol=1e-11)
    assert np.max(np.abs(K - R) / np.abs(R)) < 1e-6


@pytest.mark.parametrize(
    "core, Q",
    [
        # every effect of A at once: limp frame, shape factor, separate thermal radius, a
        # bypass gap
        (
            load_core("rvc_foam").replace(
                **{
                    "stack.frame_mobility": 0.03,
                    "stack.viscous_shape_factor": 1.4,
                    "stack.thermal_radius_ratio": 1.8,
                    "stack.bypass_gap": 3e-4,
                }
            ),
            20.0,
        ),
        # imposed temperatures: a graded stack and buffer tube, a uniform hot exchanger
        (imposed_ceramic(), 0.0),
    ],
    ids=["effects", "imposed"],
)
def test_complex_walk_equals_the_cascade_at_real_omega(core, Q):
    """The onset's segment matrices (A at complex omega) at real omega are transfer_matrices'
    T (A at real omega, the tabulated pore functions) to 1e-13: both evaluate the one
    propagation_entries, so every effect is in both."""
    f = np.array([45.0, 320.0])
    K = _core_matrix(core, Q, 2 * np.pi * f)
    T = transfer_matrices(core, f, Q, cells=16, device=DEVICE).T[0]
    assert np.max(np.abs(K - T) / np.abs(T)) < 1e-13


def _tube(length=0.3, radius=0.0167):
    return core_from_dict(
        {
            "gas": {"name": "air"},
            "tube": {"radius": radius},
            "segment": [{"name": "d", "kind": "duct", "length": length}],
        },
        "<tube>",
    )


def _k(omega, radius, T=293.15, p_mean=101325.0):
    """Closed-form complex wavenumber of the duct (docs/physics.md), SciPy Bessel functions."""
    g = ref.gas_properties("air", T, p_mean)

    def f(delta):
        z = (1 + 1j) * radius / delta
        return 2 * sp.jv(1, z) / (z * sp.jv(0, z))

    f_nu = f(np.sqrt(2 * g.mu / (g.rho * omega)))
    f_k = f(np.sqrt(2 * g.k / (g.rho * g.cp * omega)))
    return omega / g.c * np.sqrt((1 + (g.gamma - 1) * f_k) / (1 - f_nu))


@pytest.mark.parametrize(
    "left, right, shift", [("closed", "closed", 0.0), ("closed", "open", 0.5), ("open", "open", 0.0)]
)
def test_uniform_tube_modes(left, right, shift):
    """Unheated uniform tube (a duct core between resonator ducts of the same tube, L = 1 m):
    k(omega) L = (n - shift) pi, shift 0 between like ends, 1/2 closed-open; modes 1-3:
    frequency Re omega and damping rate Im omega each within 1e-8 relative of the scalar
    oracle (scipy.optimize.newton on complex omega)."""
    R, L = 0.0167, 1.0
    eng = ThermoacousticEngine(
        _tube(0.3, R), EndCondition(left), EndCondition(right), ResonatorDuct(0.45), ResonatorDuct(0.25)
    )
    for n in (1, 2, 3):
        res = eigenfrequencies(eng, 0.0, mode=n, device=DEVICE)
        w0 = (n - shift) * math.pi * 343.2 / L
        exact = so.newton(lambda w: _k(w, R) * L - (n - shift) * math.pi, w0 + 0j, tol=1e-10, maxiter=100)
        w = res.omega[0]
        assert res.iterations[0] > 0
        assert abs(w.real - exact.real) < 1e-8 * abs(exact.real)
        assert abs(w.imag - exact.imag) < 1e-8 * abs(exact.imag)
        assert exact.imag < 0  # an unheated tube is damped


def test_impedance_end_against_reference():
    """Closed left end, right end a constant impedance Z: the root of Tpp - Z Tup = 0 for the reference's closed-form duct matrices
    (scipy.optimize.newton) within 1e-9 relative; a table linear in frequency gives the
    root of the same condition with Z(omega) continued linearly to complex omega."""
    R = 0.0167
    core = _tube(0.3, R)
    Z = (2.0 + 1.5j) * ref.gas_properties("air", 293.15, 101325.0).rho * 343.2 / (math.pi * R**2)
    slope = 0.004 * Z  # per Hz
    za, zb = Z + slope * 50, Z + slope * 400
    table = np.array([[50.0, za.real, za.imag], [400.0, zb.real, zb.imag]])
    for zfun, end in (
        (lambda w: Z, EndCondition("impedance", np.array([[1.0, Z.real, Z.imag]]))),
        (lambda w: Z + slope * w / (2 * math.pi), EndCondition("impedance", table)),
    ):
        eng = ThermoacousticEngine(core, EndCondition("closed"), end, ResonatorDuct(0.45), ResonatorDuct(0.25))
        res = eigenfrequencies(eng, 0.0, device=DEVICE)

        def resid(w):
            M = ref.duct_matrix_omega("air", 101325.0, 293.15, R, 1.0, w)[0]
            return M[0, 0] - zfun(w) * M[1, 0]

        exact = so.newton(resid, res.omega[0] * (1 + 1e-3), tol=1e-10, maxiter=100)
        assert abs(res.omega[0] - exact) < 1e-9 * abs(exact)


def _engine_matrix_ref(eng, w, Q):
    core = eng.core
    res = eng.resonator_row()
    Ml = ref.duct_matrix_omega("air", core.gas.p_mean, res[2], res[1], res[0], w)[0]
    Mr = ref.duct_matrix_omega("air", core.gas.p_mean, res[5], res[4], res[3], w)[0]
    return Mr @ ref.transfer_matrix_omega(core, w, Q, rtol=1e-11)[0] @ Ml


def test_heated_engine_against_reference():
    """Bundled standing-wave engine at Q = 40 W: the kernel's eigenfrequency (16 Magnus
    cells per thermal segment) equals the root of Tup = 0 of the reference (closed-form
    ducts, DOP853 at complex omega with the exact heat profile) found by SciPy's secant
    from an independent start, within 1e-6 |omega|; T_hot equals the exact heat profile's
    largest temperature (HeatSolution.theta_max) within 1e-9 relative."""
    eng = load_engine("standing_wave")
    Q = 40.0
    res = eigenfrequencies(eng, Q, cells=16, device=DEVICE)
    exact = so.newton(lambda w: _engine_matrix_ref(eng, w, Q)[1, 0], 2 * math.pi * 170.0 - 3.0j, tol=1e-12, maxiter=50)
    assert abs(res.omega[0] - exact) < 1e-6 * abs(exact)
    assert exact.imag > 0  # 40 W is above onset for this engine (growth)
    T_max = eng.core.gas.T_cold + ref.heat_profile_exact(eng.core, Q).theta_max()[1]
    assert abs(res.T_hot[0] - T_max) < 1e-9 * T_max


def test_onset_against_bisection():
    """Bundled engine: Im omega changes sign exactly once on Q = 0..100 W (11 points);
    the secant onset is within 1e-6 relative of a 50-step bisection on Q, Im omega there is
    below 1e-9 |omega|, f_onset and T_hot equal eigenfrequencies() at Q_onset (1e-9)."""
    eng = load_engine("standing_wave")
    grid = eigenfrequencies(eng, np.linspace(0, 100, 11), device=DEVICE)
    assert np.count_nonzero(np.diff(np.sign(grid.growth_rate))) == 1
    res = onset(eng, Q_max=100.0, device=DEVICE)
    lo, hi = 0.0, 100.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if eigenfrequencies(eng, mid, device=DEVICE).growth_rate[0] < 0:
            lo = mid
        else:
            hi = mid
    q = res.Q_onset[0]
    assert abs(q - 0.5 * (lo + hi)) < 1e-6 * q
    at = eigenfrequencies(eng, q, device=DEVICE)
    assert abs(res.omega_onset[0].imag) < 1e-9 * abs(res.omega_onset[0])
    assert abs(res.f_onset[0] - at.frequency[0]) < 1e-9 * at.frequency[0]
    assert abs(res.T_hot[0] - at.T_hot[0]) < 1e-9 * at.T_hot[0]


def test_onset_batch_equals_single_runs():
    """A batch over the resonator length and the stack's h gives, set by set, the onset of
    single runs (threads are independent: 1e-12 relative); a set stable up to Q_max is NaN."""
    eng = load_engine("standing_wave")
    L = np.array([0.6, 0.7, 0.8, 0.0])
    h = np.array([150.0, 120.0, 180.0, 150.0])
    batch = onset(eng, Q_max=80.0, params={"engine.left_duct": L, "stack.h": h}, device=DEVICE)
    for k in range(3):
        one = onset(eng, Q_max=80.0, params={"engine.left_duct": L[k], "stack.h": h[k]}, device=DEVICE)
        assert abs(batch.Q_onset[k] - one.Q_onset[0]) <= 1e-12 * one.Q_onset[0]
    assert np.isnan(batch.Q_onset[3])


def _random_designs(seed, n):
    """The bench's design ranges (bench/onset.py): left duct, stack length, porosity, h_s."""
    rng = np.random.default_rng(seed)
    return {
        "engine.left_duct": rng.uniform(0.5, 0.9, n),
        "stack.length": rng.uniform(0.03, 0.07, n),
        "stack.porosity": rng.uniform(0.85, 0.93, n),
        "stack.h": rng.uniform(100, 200, n),
    }


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_newton_onset_against_brentq(seed):
    """Random designs (2 per seed, fixed 16 Magnus cells so that both sides evaluate the same
    residual): the Newton refinement on (Re omega, Q) gives Q_onset within 1e-8 relative of
    scipy.optimize.brentq on Im omega(Q) from eigenfrequencies() (Muller to 1e-13 per Q,
    bracket [0, Q_max], xtol 1e-12 W), with no set falling back to the secant; at Q_onset
    eigenfrequencies() gives |Im omega| and |Re omega - omega_onset| below 1e-12 |omega|
    (the Newton point is converged to about the Muller tolerance in omega as well)."""
    eng = load_engine("standing_wave")
    designs = _random_designs(seed, 2)
    res = onset(eng, Q_max=100.0, params=designs, cells=16, device=DEVICE)
    assert res.fallback.size == 0
    for k in range(2):
        one = {name: v[k] for name, v in designs.items()}

        def growth(Q):
            return eigenfrequencies(eng, Q, params=one, cells=16, device=DEVICE).growth_rate[0]

        exact = so.brentq(growth, 0.0, 100.0, xtol=1e-12, rtol=1e-14)
        assert abs(res.Q_onset[k] - exact) < 1e-8 * exact
        w = eigenfrequencies(eng, res.Q_onset[k], params=one, cells=16, device=DEVICE).omega[0]
        assert abs(w.imag) < 1e-12 * abs(w)
        assert abs(w.real - res.omega_onset[k].real) < 1e-12 * abs(w)


@pytest.mark.parametrize("newton_steps", [0, 1])
def test_onset_secant_fallback(newton_steps):
    """The fallback path: with no Newton step allowed (0), or one (not enough to converge
    from the bracket's interpolation, so every set falls back after it), every set is
    refined by the Illinois secant, and Q_onset agrees with the Newton refinement within
    1e-8 relative over random designs (seeds 4, 5, 6); Newton costs fewer residual
    evaluations per onset than the secant on the same sets."""
    eng = load_engine("standing_wave")
    for seed in (4, 5, 6):
        designs = _random_designs(seed, 3)
        newton = onset(eng, Q_max=100.0, params=designs, device=DEVICE)
        fb = onset(eng, Q_max=100.0, params=designs, newton_steps=newton_steps, device=DEVICE)
        assert newton.fallback.size == 0 and np.array_equal(fb.fallback, np.arange(3))
        assert np.all(np.abs(fb.Q_onset - newton.Q_onset) < 1e-8 * newton.Q_onset)
        assert newton.mean_evaluations < fb.mean_evaluations


def _engine_dict(**engine):
    core = {"gas": {"name": "air"}, "segment": [{"name": "d", "kind": "duct", "length": 0.1}]}
    return dict(core, engine=engine)


@pytest.mark.parametrize(
    "engine, match",
    [
        ({"left": "shut"}, "left = 'shut'"),
        ({"right": "impedance"}, "right_impedance"),
        ({"left": "closed", "left_impedance": [1.0, 0.0]}, "left_impedance given"),
        ({"left_duct": -1.0}, "left_duct"),
        ({"right_duct_T": 0.0}, "right_duct_T"),
        ({"middle": 1}, "unknown key"),
    ],
)
def test_engine_file_errors(engine, match):
    """Bad [engine] tables are refused with the file and key named."""
    with pytest.raises(CoreError, match=match):
        engine_from_dict(_engine_dict(**engine), "eng.toml")


def test_impedance_csv(tmp_path):
    """An impedance CSV is read relative to the engine file; a bad line is named."""
    (tmp_path / "z.csv").write_text("freq_Hz,Z_re,Z_im\n100,1.0,2.0\n200,3.0,4.0\n")
    eng = engine_from_dict(_engine_dict(right="impedance", right_impedance_csv="z.csv"), "e.toml", tmp_path)
    assert np.array_equal(eng.right.table(), [[100, 1, 2], [200, 3, 4]])
    (tmp_path / "bad.csv").write_text("freq_Hz,Z_re,Z_im\n100,1.0\n")
    with pytest.raises(CoreError, match="bad.csv:2"):
        engine_from_dict(_engine_dict(right="impedance", right_impedance_csv="bad.csv"), "e.toml", tmp_path)


def test_cli_onset(tmp_path, capsys):
    """``tawarp onset`` writes JSON whose Q_onset, f_onset, T_hot are the API's (exact
    float round trip) for each --var value, and the growth-rate figure; a bad --var name
    exits 2 naming it."""
    import json

    from tawarp.cli import main

    out = tmp_path / "o"
    assert (
        main(
            [
                "onset",
                "standing_wave",
                "--Q-max",
                "80",
                "--bracket",
                "9",
                "--var",
                "engine.left_duct=0.6,0.8",
                "-o",
                str(out),
                "--device",
                "cpu",
                "--quiet",
            ]
        )
        == 0
    )
    js = json.loads((out / "onset.json").read_text())
    api = onset(
        load_engine("standing_wave"), Q_max=80.0, n_bracket=9, params={"engine.left_duct": [0.6, 0.8]}, device=DEVICE
    )
    for k, s in enumerate(js["sets"]):
        assert s["params"] == {"engine.left_duct": [0.6, 0.8][k]}
        assert (s["Q_onset_W"], s["f_onset_Hz"], s["T_hot_K"]) == (api.Q_onset[k], api.f_onset[k], api.T_hot[k])
    assert (out / "growth_rate.png").stat().st_size > 0 and (out / "root_locus.png").stat().st_size > 0
    assert (
        main(["onset", "standing_wave", "--var", "engine.middle=1", "-o", str(out), "--device", "cpu", "--quiet"]) == 2
    )
    assert "engine.middle" in capsys.readouterr().err


def test_demo_onset(tmp_path, capsys):
    """The demo's onset step writes the onset of the bundled engine (as onset() gives it,
    exact round trip) and prints it in one line."""
    import json

    from tawarp.cli.demo import demo_onset

    demo_onset(tmp_path / "onset.json", device=DEVICE)
    js = json.loads((tmp_path / "onset.json").read_text())
    api = onset(load_engine("standing_wave"), Q_max=100.0, n_bracket=9, device=DEVICE)
    assert (js["Q_onset_W"], js["f_onset_Hz"], js["T_hot_K"]) == (api.Q_onset[0], api.f_onset[0], api.T_hot[0])
    assert f"Q_onset {api.Q_onset[0]:.2f} W" in capsys.readouterr().out
