"""The tangent cascade (Engine.evaluate_tangents) and its building blocks, against
derivatives computed another way: scipy's Frechet derivative of expm, Richardson-extrapolated
central differences of the Warp functions and of the whole forward model."""

import numpy as np
import pytest
import scipy.linalg
import warp as wp

from tawarp.kernels.acoustics import CMat2, cmat2, expm2_tangent, expm2_traceless, magnus6_exponent, magnus6_tangent
from tawarp.kernels.acoustics import cosh_sinhc, sinhc_derivative, traceless_parts
from tawarp.kernels.pore import PORE_CIRCULAR, PORE_PLATES, pore_circular, pore_log_derivative, pore_plates
from tawarp.model.core import load_core
from tawarp.model.forward import Engine, ForwardSettings

from cascade_differences import assert_tangents_match_differences
from imposed_cores import imposed_ceramic

wp.config.quiet = True
wp.set_module_options({"enable_backward": False})


@wp.func
def _mat(a: wp.array2d(dtype=wp.vec2d), i: int):
    return cmat2(a[i, 0], a[i, 1], a[i, 2], a[i, 3])


@wp.func
def _put(out: wp.array2d(dtype=wp.vec2d), i: int, m: CMat2):
    out[i, 0] = m.a
    out[i, 1] = m.b
    out[i, 2] = m.c
    out[i, 3] = m.d


@wp.kernel
def _exp_and_tangent(
    m: wp.array2d(dtype=wp.vec2d),
    dm: wp.array2d(dtype=wp.vec2d),
    e: wp.array2d(dtype=wp.vec2d),
    de: wp.array2d(dtype=wp.vec2d),
    tau: wp.array(dtype=wp.vec2d),
    dtau: wp.array(dtype=wp.vec2d),
):
    i = wp.tid()
    x = _mat(m, i)
    t, na, delta = traceless_parts(x)
    ch, sh = cosh_sinhc(delta)
    ei, ti = expm2_traceless(x)
    dei, dti = expm2_tangent(x, na, ch, sh, sinhc_derivative(delta, ch, sh), _mat(dm, i))
    _put(e, i, ei)
    _put(de, i, dei)
    tau[i] = ti
    dtau[i] = dti


def _complex(a):
    return a.numpy().reshape(a.shape[0], -1).view(np.complex128)


def _vec2(z):
    return wp.array(np.ascontiguousarray(z).view(np.float64).reshape(z.shape + (2,)), dtype=wp.vec2d, device="cpu")


@pytest.mark.parametrize("scale", [1e-5, 1e-2, 0.2, 0.6, 0.95, 3.0])
def test_exponential_tangent_against_frechet(scale):
    """d exp(m)[dm] = e^tau (dtau E + dE) against scipy.linalg.expm_frechet on random
    complex 2x2 matrices of each size (the series branch up to |delta| = 1, the closed form
    beyond), to 1e-13 of the largest entry."""
    rng = np.random.default_rng(int(scale * 1e5) + 1)
    n = 100
    a = scale * (rng.normal(size=(n, 2, 2)) + 1j * rng.normal(size=(n, 2, 2)))
    d = rng.normal(size=(n, 2, 2)) + 1j * rng.normal(size=(n, 2, 2))
    e, de = wp.empty((n, 4), dtype=wp.vec2d, device="cpu"), wp.empty((n, 4), dtype=wp.vec2d, device="cpu")
    tau, dtau = wp.empty(n, dtype=wp.vec2d, device="cpu"), wp.empty(n, dtype=wp.vec2d, device="cpu")
    wp.launch(
        _exp_and_tangent, dim=n, inputs=[_vec2(a.reshape(n, 4)), _vec2(d.reshape(n, 4)), e, de, tau, dtau], device="cpu"
    )
    E, dE = _complex(e).reshape(n, 2, 2), _complex(de).reshape(n, 2, 2)
    t, dt = _complex(tau)[:, 0], _complex(dtau)[:, 0]
    got = np.exp(t)[:, None, None] * (dt[:, None, None] * E + dE)
    want = np.array([scipy.linalg.expm_frechet(x, y, compute_expm=False) for x, y in zip(a, d)])
    err = np.abs(got - want).max(axis=(1, 2)) / np.abs(want).max(axis=(1, 2))
    assert err.max() < 1e-13, err.max()


@wp.kernel
def _magnus(
    a: wp.array2d(dtype=wp.vec2d),
    d: wp.array2d(dtype=wp.vec2d),
    h: wp.array(dtype=wp.float64),
    dh: wp.array(dtype=wp.float64),
    om: wp.array2d(dtype=wp.vec2d),
    dom: wp.array2d(dtype=wp.vec2d),
):
    i = wp.tid()
    a1 = cmat2(a[i, 0], a[i, 1], a[i, 2], a[i, 3])
    a2 = cmat2(a[i, 4], a[i, 5], a[i, 6], a[i, 7])
    a3 = cmat2(a[i, 8], a[i, 9], a[i, 10], a[i, 11])
    d1 = cmat2(d[i, 0], d[i, 1], d[i, 2], d[i, 3])
    d2 = cmat2(d[i, 4], d[i, 5], d[i, 6], d[i, 7])
    d3 = cmat2(d[i, 8], d[i, 9], d[i, 10], d[i, 11])
    _put(om, i, magnus6_exponent(a1, a2, a3, h[i]))
    _put(dom, i, magnus6_tangent(a1, a2, a3, h[i], d1, d2, d3, dh[i]))


def test_magnus_tangent_against_central_differences():
    """Omega is a polynomial of degree 5 in (A1, A2, A3, h) jointly along a line, so
    central differences at steps 2k and k extrapolated (the k^2 terms cancel) leave only
    the k^4 term: magnus6_tangent agrees to 1e-10 of |dOmega| on random cells whose |h A|
    ranges over 1e-2 ... 1."""
    rng = np.random.default_rng(11)
    n = 60
    A = (rng.normal(size=(n, 12)) + 1j * rng.normal(size=(n, 12))) * np.geomspace(1e-2, 1.0, n)[:, None]
    D = rng.normal(size=(n, 12)) + 1j * rng.normal(size=(n, 12))
    h = rng.uniform(0.5, 2.0, n)
    dh = rng.normal(size=n)

    def run(k):
        om, dom = wp.empty((n, 4), dtype=wp.vec2d, device="cpu"), wp.empty((n, 4), dtype=wp.vec2d, device="cpu")
        wp.launch(
            _magnus,
            dim=n,
            inputs=[
                _vec2(A + k * D),
                _vec2(D),
                wp.array(h + k * dh, dtype=wp.float64),
                wp.array(dh, dtype=wp.float64),
                om,
                dom,
            ],
            device="cpu",
        )
        return _complex(om), _complex(dom)

    k = 1e-3
    cd = lambda s: (run(s)[0] - run(-s)[0]) / (2 * s)  # noqa: E731
    want = (4 * cd(k) - cd(2 * k)) / 3
    got = run(0.0)[1]
    err = np.abs(got - want).max(axis=1) / np.abs(want).max(axis=1)
    assert err.max() < 1e-10, err.max()


@wp.kernel
def _pore(
    model: int,
    log_s: wp.array(dtype=wp.float64),
    f: wp.array(dtype=wp.vec2d),
    g: wp.array(dtype=wp.vec2d),
    df: wp.array(dtype=wp.vec2d),
):
    i = wp.tid()
    s = wp.exp(log_s[i])
    fi = wp.vec2d()
    gi = wp.vec2d()
    if model == PORE_PLATES:
        fi, gi = pore_plates(s)
    else:
        fi, gi = pore_circular(s)
    f[i] = fi
    g[i] = gi
    df[i] = pore_log_derivative(model, log_s[i], fi, gi)


@pytest.mark.parametrize("model", [PORE_CIRCULAR, PORE_PLATES])
def test_pore_log_derivative_against_central_differences(model):
    """df/d ln s from f, g alone (pore_log_derivative) against extrapolated central
    differences in ln s of the smaller of f and -g (both accurate to ~1e-15 relative: g at
    small s, where f -> 1), s = 1e-3 ... 1e4, to 1e-9 of |df|: the differences' own error
    (rounding / step 1e-3, the step^4 term), and the formula's cancellation at large s
    (about s ulps)."""
    log_s = np.linspace(np.log(1e-3), np.log(1e4), 400)
    n = log_s.size

    def run(k):
        f, g, df = (wp.empty(n, dtype=wp.vec2d, device="cpu") for _ in range(3))
        wp.launch(_pore, dim=n, inputs=[int(model), wp.array(log_s + k, dtype=wp.float64), f, g, df], device="cpu")
        return _complex(f)[:, 0], _complex(g)[:, 0], _complex(df)[:, 0]

    f0, g0, got = run(0.0)
    small_g = np.abs(g0) < np.abs(f0)  # which one each s differentiates, fixed for all steps
    k = 1e-3

    def cd(s):
        (fp, gp, _), (fm, gm, _) = run(s), run(-s)
        return np.where(small_g, gm - gp, fp - fm) / (2 * s)

    want = (4 * cd(k) - cd(2 * k)) / 3
    err = np.abs(got - want) / np.abs(want)
    assert err.max() < 1e-9, err.max()


# -- the whole cascade -------------------------------------------------------------------------
CASES = [
    (
        "mesh",
        40.0,
        [
            "stack.porosity",
            "stack.pore_radius",
            "stack.h",
            "stack.length",
            "hot_hx.tortuosity",
            "gas.T_cold",
            "tube.radius",
            "tbt.h",
        ],
    ),
    ("ceramic", 0.0, ["stack.porosity", "stack.pore_radius", "stack.tortuosity", "stack.length", "gas.p_mean"]),
    (
        "rvc_foam",
        25.0,
        [
            "stack.thermal_radius_ratio",
            "stack.solid_conductivity",
            "hot_hx.h",
            "stack.h_convection",
            "stack.wall_conductance",
        ],
    ),
    # a temperature-dependent effect: the heat solve iterates (Picard)
    ("nicr_foam", 40.0, ["stack.conductivity_exponent", "stack.h", "stack.porosity", "tbt.length"]),
    # a contact resistance between stack and hot exchanger: the temperature jump it makes,
    # with the linear heat model and with the Kirchhoff cells (conductivity exponent on)
    ("ceramic:contact", 40.0, ["hot_hx.contact_resistance", "stack.h", "hot_hx.h", "stack.porosity", "tbt.h"]),
    ("nicr_foam:contact", 40.0, ["hot_hx.contact_resistance", "stack.conductivity_exponent", "stack.h"]),
    # the effects of A beyond the rigid circular pore: a limp frame (1/rho_1 of a 30 kg/m^3
    # foam) and a viscous shape factor, each with the geometry they enter with
    (
        "rvc_foam:limp",
        25.0,
        [
            "stack.frame_mobility",
            "stack.viscous_shape_factor",
            "stack.porosity",
            "stack.tortuosity",
            "stack.pore_radius",
            "tube.radius",
        ],
    ),
    # an annular bypass gap beside the stack's pores: a slit joined to them at the stack's
    # ends (both channels' tangents combined on dual numbers) and the gap's gas in the heat model
    (
        "ceramic:gap",
        40.0,
        ["stack.bypass_gap", "stack.porosity", "stack.pore_radius", "stack.h", "tube.radius"],
    ),
    # imposed temperatures (no heat model): the profile's ends and the geometry it acts on
    (
        "ceramic:imposed",
        0.0,
        ["stack.T_end", "hot_hx.T_start", "tbt.T_start", "stack.porosity", "gas.T_cold", "gas.p_mean"],
    ),
]
#: Cores of CASES beyond the bundled ones: the bundled core and the values that turn effects on.
EFFECTS = {
    "nicr_foam": {"stack.conductivity_exponent": 0.5},
    "ceramic:contact": {"hot_hx.contact_resistance": 3e-4},
    "nicr_foam:contact": {"stack.conductivity_exponent": 0.5, "hot_hx.contact_resistance": 3e-4},
    "rvc_foam:limp": {"stack.frame_mobility": 0.03, "stack.viscous_shape_factor": 1.4},
    "ceramic:gap": {"stack.bypass_gap": 3e-4},
}


@pytest.mark.parametrize("name, heat, names", CASES)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cascade_tangents_against_extrapolated_differences(name, heat, names, seed):
    """dT/dz from the tangent cascade against extrapolated central differences of the plain
    cascade (tolerances: tests/cascade_differences.py) at a point 10-30 % off the core's
    values in every parameter (random signs). Forward differences with step 1e-6, the
    estimator's other Jacobian, reach ~1e-6."""
    core = imposed_ceramic() if name == "ceramic:imposed" else load_core(name.split(":")[0])
    core = core.replace(**EFFECTS.get(name, {}))
    rng = np.random.default_rng(seed)
    v0 = np.array([core.get(k) for k in names])
    v0 = v0 * (1 + rng.uniform(0.1, 0.3, v0.size) * rng.choice([-1, 1], v0.size))
    for a, k in enumerate(names):
        if k.endswith(("porosity", "thermal_radius_ratio")):
            v0[a] = min(v0[a], 0.97)
        if k.endswith("tortuosity"):
            v0[a] = max(v0[a], 1.05)
    assert_tangents_match_differences(core, names, v0, heat, SCALES)


#: Steps of the differences [m] for parameters that act on a scale below 0.05: the bypass
#: gap's slit admits flow as g^3, on the scale of its 0.3 mm.
SCALES = {"stack.bypass_gap": 1e-5}


def test_tangents_need_fixed_cells():
    """The tangent cascade walks the same cells at z and its neighbours: an engine whose cell
    count adapts per set refuses it."""
    freqs = np.array([50.0, 200.0])
    with pytest.raises(ValueError, match="cell count must be fixed"):
        Engine(load_core("mesh"), freqs, ["stack.porosity"], ForwardSettings(device="cpu")).evaluate_tangents(
            np.zeros((2, 3)), np.ones((1, 1)), 1
        )


def test_fits_with_tangents_on_reference_data():
    """Fits with the tangent Jacobians of data the kernels did not make: the independent
    reference (tawarp.reference, DOP853 on the heated segments) at 40 W, 24 noise draws,
    starts 10-30 % off on each of 5 parameters (random signs). All converge; the normalized
    errors (fitted - true)/std have rms within [0.8, 1.25] (1 if the std are honest; 120
    values); forward-difference fits of the same problems agree to 1e-4 std."""
    from tawarp import reference
    from tawarp.fit.estimate import fit
    from tawarp.measure.synthetic import paper_frequencies

    core = load_core("mesh")
    freqs = paper_frequencies("mesh", 24)
    names = ["stack.porosity", "stack.pore_radius", "stack.h", "hot_hx.h", "tbt.h"]
    truth = np.array([core.get(k) for k in names])
    Y0 = reference.dimensionless_transfer(core, freqs, 40.0)
    n = 24
    rng = np.random.default_rng(2026)
    sd = 0.005 * np.abs(Y0) / np.sqrt(2)
    Y = Y0 + sd * (rng.standard_normal((n,) + Y0.shape) + 1j * rng.standard_normal((n,) + Y0.shape))
    start = truth * (1 + rng.uniform(0.1, 0.3, (n, len(names))) * rng.choice([-1, 1], (n, len(names))))
    start[:, 0] = np.minimum(start[:, 0], 0.98)
    kw = dict(heat_input=40.0, weights=1 / sd, device="cpu", warn=False)
    r = fit(core, freqs, Y, names, start, jacobian="tangent", **kw)
    assert r.converged.all()
    z = (r.values - truth) / r.std
    assert 0.8 < np.sqrt(np.mean(z**2)) < 1.25
    d = fit(core, freqs, Y, names, start, jacobian="difference", **kw)
    assert np.max(np.abs(d.values - r.values) / r.std) < 1e-4
