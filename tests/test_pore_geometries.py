"""Rectangular channels (Stinson 1991) and pin arrays (Swift's pin-array stack) of
kernels/pore.py: the kernels' functions against independent series and mpmath, their limits
(Shah & London's Poiseuille numbers, the parallel plates, the boundary layer, Poiseuille flow in
a pin's cell), their derivative and complex argument, and such stacks through the parser, the
forward model, the tangent cascade, the onset and the design evaluator."""

import dataclasses

import mpmath
import numpy as np
import pytest
import warp as wp

from tawarp.design.evaluate import Evaluator
from tawarp.design.space import DesignSpace
from tawarp.kernels.pore import (
    ASPECT_MAX,
    RECT_ASYMPTOTIC_S,
    SHAPE_HEADER,
    SHAPE_SLOTS,
    PoreTable,
    bessel_ik_scaled,
    pore_functions_complex,
    pore_functions_log,
    pore_log_derivative,
    pore_model_code,
)
from tawarp.kernels.pore_table import circular_table
from tawarp.model.core import CoreError, core_from_dict, load_core
from tawarp.model.forward import Engine, ForwardSettings, transfer_matrices
from tawarp.model.onset import onset
from tawarp.model.resonator import load_engine

from cascade_differences import assert_tangents_match_differences

DEVICE = "cpu"


@wp.kernel
def _pore(
    model: int,
    s: wp.array(dtype=wp.vec2d),
    table: PoreTable,
    f: wp.array(dtype=wp.vec2d),
    g: wp.array(dtype=wp.vec2d),
    df: wp.array(dtype=wp.vec2d),
    fc: wp.array(dtype=wp.vec2d),
    gc: wp.array(dtype=wp.vec2d),
):
    i = wp.tid()
    log_s = wp.log(s[i][0])
    fi, gi = pore_functions_log(model, log_s, table)
    f[i] = fi
    g[i] = gi
    df[i] = pore_log_derivative(model, log_s, fi, gi)
    a, b = pore_functions_complex(model, s[i])
    fc[i] = a
    gc[i] = b


def kernel_pore(alpha: float, s, model: str = "rectangular"):
    """f, g, df/d ln s at real s (the cascade's path: tabulated for s in [1e-3, 1e4]) and
    f, g by the complex path at s (computed; complex allowed, the real path then uses |s|);
    ``alpha``: the shape number (aspect ratio, or a pin array's outer radius ratio)."""
    s = np.asarray(s, dtype=complex)
    sw = wp.array(np.stack([s.real, s.imag], 1), dtype=wp.vec2d, device=DEVICE)
    out = [wp.zeros(len(s), dtype=wp.vec2d, device=DEVICE) for _ in range(5)]
    model = pore_model_code(model, alpha)
    wp.launch(_pore, dim=len(s), inputs=[model, sw, circular_table(DEVICE, [model]), *out], device=DEVICE)
    return [o.numpy().view(np.complex128).ravel() for o in out]


def g_double_series(s, alpha, M=801, N=None):
    """g = 1 - f of a rectangular channel from Stinson's double series over odd m, n:
    g = (64/pi^4) sum 1/(m^2 n^2) / (1 + i pi^2 (m^2 + n^2/alpha^2) / (8 s^2)), s = a/delta."""
    N = N or int(M * alpha) | 1
    m = np.arange(1, M + 1, 2, dtype=float)[:, None]
    out = 0j
    for n0 in range(1, N + 1, 2 * 2000):
        n = np.arange(n0, min(n0 + 4000, N + 1), 2, dtype=float)[None, :]
        lam = m**2 + n**2 / alpha**2
        out += np.sum(64 / (np.pi**4 * m**2 * n**2) / (1 + 1j * np.pi**2 * lam / (8 * s * s)))
    return out


def cosine_series(s, alpha, M=200000):
    """(f, g) from the cosine series across the narrow side, the wide side solved exactly
    (the decomposition kernels/pore.py sums, here to M terms, without its closed-form tail or
    its large-s form), q = (m pi/2)^2, z^2 = alpha^2 (q - 2 i s^2), E = 2 s^2/(2 s^2 + i q)::

        g = sum_m 8/(m pi)^2 (1 - tanh(z)/z) E,    f = f_plates(s) + sum_m 8/(m pi)^2 tanh(z)/z E

    each summed as written, so neither is 1 minus the other (g -> 0 for small s, f -> 0 for
    large s). The terms fall as m^-5 once m > |s|: M = 2e5 leaves < 1e-19."""
    m = np.arange(1, 2 * M, 2, dtype=float)
    q = (m * np.pi / 2) ** 2
    z = alpha * np.sqrt(q - 2j * s * s)
    t = np.tanh(z) / z
    w = 8 / (m * np.pi) ** 2 * (2 * s * s) / (2 * s * s + 1j * q)
    return f_plates(s) + (w * t)[::-1].sum(), (w * (1 - t))[::-1].sum()


def g_cosine_series(s, alpha):
    return cosine_series(s, alpha)[1]


def f_plates(s):
    w = (1 - 1j) * s
    return np.tanh(w) / w


@pytest.mark.parametrize("alpha", [1.0, 2.5])
@pytest.mark.parametrize("s", [0.3, 1.0, 3.0])
def test_cosine_series_equals_stinson_double_series(alpha, s):
    """The one-dimensional series the kernels sum is Stinson's double series (JASA 89:550,
    1991, the rectangular duct) summed exactly over one index: equal to the double series'
    truncation (odd m, n up to 801 and 801 alpha: 1e-7 of g)."""
    assert g_cosine_series(s, alpha) == pytest.approx(g_double_series(s, alpha), rel=1e-7)


@pytest.mark.parametrize("alpha", [1.0, 3.0, 50.0])
def test_rectangular_against_converged_series(alpha):
    """f and g, each to 1e-13 of itself, against the converged cosine series over s in
    [1e-3, 200] (both sides of the switch to the large-s form at s = 20), real and complex
    paths."""
    s = np.concatenate(
        [np.geomspace(1e-3, 200, 40), [float(RECT_ASYMPTOTIC_S) * (1 - 1e-9), float(RECT_ASYMPTOTIC_S) * (1 + 1e-9)]]
    )
    f_ref, g_ref = np.array([cosine_series(x, alpha) for x in s]).T
    f, g, _, fc, gc = kernel_pore(alpha, s)
    for got, ref in ((f, f_ref), (g, g_ref), (fc, f_ref), (gc, g_ref)):
        assert np.max(np.abs(got / ref - 1)) < 1e-13


def test_rectangular_at_complex_s_against_converged_series():
    """The complex-frequency path (onset) at s with |arg s| up to 0.3 rad against the
    converged series evaluated at the same complex s (1e-13)."""
    s = np.array([0.2 * np.exp(0.3j), 1.5 * np.exp(-0.2j), 7.0 * np.exp(0.1j), 35.0 * np.exp(-0.25j)])
    for alpha in (1.0, 4.0):
        _, _, _, fc, gc = kernel_pore(alpha, s)
        f_ref, g_ref = np.array([cosine_series(x, alpha) for x in s]).T
        assert np.max(np.abs(gc / g_ref - 1)) < 1e-13
        assert np.max(np.abs(fc / f_ref - 1)) < 1e-13


@pytest.mark.parametrize("alpha, fRe", [(1.0, 14.227), (2.0, 15.548), (4.0, 18.233), (8.0, 20.585)])
def test_poiseuille_limit_against_shah_london(alpha, fRe):
    """Low frequency (s -> 0): g -> -i k^2 D_h^2/(2 fRe) with the Fanning friction factor
    times Reynolds number of fully developed laminar flow, fRe = 14.227, 15.548, 18.233,
    20.585 for aspect ratios 1, 2, 4, 8 (Shah & London, *Laminar Flow Forced Convection in
    Ducts*, 1978; five digits): g / (-i s^2) = 16 alpha^2 / ((1 + alpha)^2 fRe)."""
    _, g, _, _, _ = kernel_pore(alpha, [1e-3])
    assert (g[0] / (-1j * 1e-6)).real == pytest.approx(16 * alpha**2 / ((1 + alpha) ** 2 * fRe), rel=5e-5)


def test_wide_aspect_tends_to_parallel_plates():
    """alpha -> infinity: the channel is the plates of half-spacing a; the difference is the
    narrow walls' share, O(1/alpha) (falls 1000-fold from alpha = 1e3 to 1e6)."""
    s = np.array([0.05, 0.7, 4.0, 60.0])
    diff = {a: np.abs(kernel_pore(a, s)[0] / f_plates(s) - 1) for a in (1e3, ASPECT_MAX)}
    assert np.all(diff[ASPECT_MAX] < 2e-6)
    np.testing.assert_allclose(diff[1e3] / diff[ASPECT_MAX], 1e3, rtol=0.01)


def test_boundary_layer_limit():
    """s -> infinity: f -> (1 + i) delta / (2 r_h) (Rott, boundary layer on the perimeter),
    r_h = a alpha / (1 + alpha) the hydraulic radius: s f -> (1 + i)(1 + 1/alpha)/2,
    approached as 1/s (the corners)."""
    for alpha in (1.0, 3.0):
        s = np.array([1e3, 1e4])
        f = kernel_pore(alpha, s)[0]
        limit = (1 + 1j) * (1 + 1 / alpha) / 2
        err = np.abs(s * f - limit) / abs(limit)
        assert err[1] < 1e-3 and err[0] / err[1] == pytest.approx(10, rel=0.01)


@pytest.mark.parametrize("model, shape", [("rectangular", 1.0), ("rectangular", 7.0), ("pins", 1.2), ("pins", 3.0)])
def test_table_against_the_computed_functions(model, shape):
    """The kernels' table (real s, the cascades' path) against the computed functions at 400
    random log-spaced s in [1e-3, 1e4]: f to 1e-13 of itself, g to 1e-13 of itself plus the
    computed pins' few eps absolute; an Engine on such a core tabulates its stack."""
    s = np.exp(np.random.default_rng(1).uniform(np.log(1e-3), np.log(1e4), 400))
    f, g, _, fc, gc = kernel_pore(shape, s, model)
    assert np.max(np.abs(f / fc - 1)) < 1e-13
    assert np.all(np.abs(g - gc) < 1e-13 * np.abs(gc) + (2e-14 if model == "pins" else 0.0))
    core = with_pores(load_core("ceramic"), model, shape + 0.25)
    table = Engine(core, [100.0], [], ForwardSettings(cells=4, device=DEVICE)).pore_table.numpy()
    assert pore_model_code(model, shape + 0.25) in table[:SHAPE_SLOTS, SHAPE_HEADER]


@pytest.mark.parametrize("alpha", [1.0, 6.0])
def test_log_derivative_against_central_differences(alpha):
    """df/d ln s against Richardson-extrapolated central differences of -g (g = 1 - f keeps
    its digits where f -> 1; steps 2e-4 and 1e-4 in ln s: 1e-10 of |df|) on both sides of
    the large-s switch."""
    s = np.array([1e-3, 0.05, 0.8, 5.0, 19.0, 21.0, 400.0])
    df = kernel_pore(alpha, s)[2]

    def central(h):
        return -(kernel_pore(alpha, s * np.exp(h))[1] - kernel_pore(alpha, s * np.exp(-h))[1]) / (2 * h)

    want = (4 * central(1e-4) - central(2e-4)) / 3
    assert np.max(np.abs(df - want) / np.abs(want)) < 1e-10


# -- pin arrays ---------------------------------------------------------------------------------


@wp.kernel
def _bessel(y: wp.array(dtype=wp.vec2d), out: wp.array2d(dtype=wp.vec2d)):
    i = wp.tid()
    a, b, c, d = bessel_ik_scaled(y[i])
    out[i, 0] = a
    out[i, 1] = b
    out[i, 2] = c
    out[i, 3] = d


def mp_pins(s, R, derivative=False):
    """f (or df/d ln s) of a pin array at 30 digits: f = 2/(x (R^2 - 1)) [I1(Rx) K1(x) -
    K1(Rx) I1(x)] / [I1(Rx) K0(x) + K1(Rx) I0(x)], x = (1 - i) s."""
    with mpmath.workdps(30):

        def f(t):
            x = (1 - 1j) * t
            i, k = mpmath.besseli, mpmath.besselk
            return (
                2
                / (x * (R * R - 1))
                * (i(1, R * x) * k(1, x) - k(1, R * x) * i(1, x))
                / (i(1, R * x) * k(0, x) + k(1, R * x) * i(0, x))
            )

        t = mpmath.mpc(s.real, s.imag)
        return complex(t * mpmath.diff(f, t)) if derivative else complex(f(t))


def test_scaled_bessel_functions_against_mpmath():
    """exp(-y) I0, I1 and exp(y) K0, K1 at complex y over |y| in [1e-3, 300] and arg y in
    -pi/4 +- 0.3 (real and complex frequencies' x = (1 - i) s), each to 5e-15 of itself:
    through the power series, Steed's continued fraction and Hankel's expansions."""
    y = np.array(
        [np.sqrt(2) * r * np.exp(1j * a) for r in np.geomspace(1e-3, 200, 50) for a in (-0.485, -0.785, -1.085)]
    )
    out = wp.zeros((len(y), 4), dtype=wp.vec2d, device=DEVICE)
    wp.launch(_bessel, dim=len(y), inputs=[wp.array(np.stack([y.real, y.imag], 1), dtype=wp.vec2d, device=DEVICE), out])
    got = out.numpy().view(np.complex128)[..., 0]
    with mpmath.workdps(30):
        for k, v in enumerate(y):
            z = mpmath.mpc(v.real, v.imag)
            want = [mpmath.besseli(0, z) * mpmath.exp(-z), mpmath.besseli(1, z) * mpmath.exp(-z),
                    mpmath.besselk(0, z) * mpmath.exp(z), mpmath.besselk(1, z) * mpmath.exp(z)]  # fmt: skip
            assert np.max(np.abs(got[k] / np.array([complex(w) for w in want]) - 1)) < 5e-15, v


@pytest.mark.parametrize("R", [1.05, 2.0, 5.0])
def test_pins_against_mpmath(R):
    """f of the kernels (real and complex paths) to 2e-14 of itself against the closed form
    at 30 digits over s in [1e-3, 300]; g = 1 - f to 2e-14 absolute (it is 1 - f: a few eps
    over |g| relative, 1e-11 at |g| ~ 1e-3); at complex s the same."""
    s = np.geomspace(1e-3, 300, 12)
    f, g, _, fc, gc = kernel_pore(R, s, "pins")
    want = np.array([mp_pins(x, R) for x in s])
    for got in (f, fc):
        assert np.max(np.abs(got / want - 1)) < 2e-14
    for got in (g, gc):
        assert np.max(np.abs(got - (1 - want))) < 2e-14
    sc = np.array([0.3 * np.exp(0.25j), 2.0 * np.exp(-0.2j), 40.0 * np.exp(0.1j)])
    fc = kernel_pore(R, sc, "pins")[3]
    assert np.max(np.abs(fc / np.array([mp_pins(x, R) for x in sc]) - 1)) < 2e-14


def test_pins_log_derivative_against_mpmath():
    """df/d ln s (the tangent cascade's) against mpmath's derivative of the closed form:
    2e-14 of |df| + 2e-14 (the few eps of g's small-s end)."""
    s = np.array([1e-2, 0.7, 60.0])
    for R in (1.5, 3.0):
        df = kernel_pore(R, s, "pins")[2]
        want = np.array([mp_pins(x, R, derivative=True) for x in s])
        assert np.all(np.abs(df - want) < 2e-14 * np.abs(want) + 2e-14)


def test_pins_limits():
    """Pins' limiting cases: (1) a thin cell, R -> 1, is the plates of half-spacing (R - 1) r_i
    (no slip on the pin, no shear at the cell's edge), to O(R - 1); (2) small s is Poiseuille
    flow in the cell, g -> 2 i s^2 P(R), P(R) = (R^2 - 1)/8 + R^2/4 - R^4 ln R / (2 (R^2 - 1))
    (the mean of u = G/4 (r^2 - r_i^2) - G r_o^2/2 ln(r/r_i)); (3) large s is the boundary layer
    on the pin: s f -> (1 + i)/(R^2 - 1), perimeter over gas area, approached as 1/s."""
    s = np.array([0.05, 0.5, 3.0])
    err = {}
    for eps in (1e-2, 1e-3):
        err[eps] = np.abs(kernel_pore(1 + eps, s / eps, "pins")[0] / f_plates(s) - 1)
    assert np.all(err[1e-3] < 2e-3) and np.all(err[1e-2] / err[1e-3] > 8)
    for R in (1.5, 3.0):
        P = (R * R - 1) / 8 + R * R / 4 - R**4 * np.log(R) / (2 * (R * R - 1))
        g = kernel_pore(R, [1e-3, 2e-3], "pins")[1]
        ratio = g / (2j * np.array([1e-3, 2e-3]) ** 2 * P)
        assert abs(ratio[0] - 1) < 1e-5 and abs(ratio[1] - 1) / abs(ratio[0] - 1) == pytest.approx(4, rel=0.05)
        big = np.array([1e3, 1e4])
        lim = (1 + 1j) / (R * R - 1)
        e = np.abs(big * kernel_pore(R, big, "pins")[0] / lim - 1)
        assert e[1] < 1e-4 and e[0] / e[1] == pytest.approx(10, rel=0.01)


# -- a rectangular stack in the model ------------------------------------------------------------


def with_pores(core, model: str, shape: float, segment: str = "stack"):
    """``core`` with ``segment``'s pores of ``model`` (rectangular: aspect ratio ``shape``;
    pins: outer radius ratio ``shape``)."""
    key = {"rectangular": "aspect_ratio", "pins": "outer_radius_ratio"}[model]
    segs = tuple(
        dataclasses.replace(s, pore_model=model, **{key: shape}) if s.name == segment else s for s in core.segments
    )
    return type(core)(segs, core.gas, core.radius, core.source)


def rectangular(core, aspect_ratio: float):
    return with_pores(core, "rectangular", aspect_ratio)


def plates(core, segment: str = "stack"):
    segs = tuple(dataclasses.replace(s, pore_model="plates") if s.name == segment else s for s in core.segments)
    return type(core)(segs, core.gas, core.radius, core.source)


def test_core_file_keys_and_errors():
    data = load_core("ceramic").to_dict()
    data["segment"][1].update(pore_model="rectangular", aspect_ratio=2.5)
    core = core_from_dict(data, "rect.toml")
    assert core.segment("stack").aspect_ratio == 2.5
    assert core_from_dict(core.to_dict(), "again.toml").segments == core.segments
    for value, match in ((0.5, r"must lie in \[1, "), ("2", "finite number"), (2e6, r"must lie in \[1, ")):
        data["segment"][1]["aspect_ratio"] = value
        with pytest.raises(CoreError, match=f"rect.toml: segment 'stack': aspect_ratio.*{match}"):
            core_from_dict(data, "rect.toml")
    data["segment"][1].update(pore_model="plates", aspect_ratio=2.0)
    with pytest.raises(CoreError, match="aspect_ratio applies only to pore_model = 'rectangular'"):
        core_from_dict(data, "rect.toml")
    data["segment"][1].pop("aspect_ratio")
    data["segment"][1].update(pore_model="pins", outer_radius_ratio=2.2)
    pins = core_from_dict(data, "pins.toml")
    assert core_from_dict(pins.to_dict(), "again.toml").segments == pins.segments
    for value in (1.0, float("nan")):
        data["segment"][1]["outer_radius_ratio"] = value
        with pytest.raises(CoreError, match="pins.toml: segment 'stack': outer_radius_ratio"):
            core_from_dict(data, "pins.toml")
    data["segment"][1].pop("outer_radius_ratio")
    with pytest.raises(CoreError, match="outer_radius_ratio must be a finite number"):
        core_from_dict(data, "pins.toml")


def test_reference_functions_against_series_and_mpmath():
    """The NumPy reference's rectangular channels (its own truncated series) against the
    converged series (1e-11), and its pins (SciPy's Bessel functions) against mpmath (1e-12)."""
    from tawarp import reference

    s = np.array([0.02, 0.4, 3.0, 40.0])
    f, g = reference.thermoviscous_function("rectangular", s, np.ones_like(s), 2.5)
    f_ref, g_ref = np.array([cosine_series(x, 2.5) for x in s]).T
    assert np.max(np.abs(f / f_ref - 1)) < 1e-11 and np.max(np.abs(g / g_ref - 1)) < 1e-11
    f, _ = reference.thermoviscous_function("pins", s, np.ones_like(s), 2.5)
    assert np.max(np.abs(f / np.array([mp_pins(x, 2.5) for x in s]) - 1)) < 1e-12


@pytest.mark.parametrize("model, shape", [("rectangular", 2.5), ("pins", 2.5)])
def test_kernels_match_reference(model, shape):
    """A heated core (helium at 3 bar, 30 W) whose stack has the new pores: the kernels'
    T-matrices against the independent NumPy reference (adaptive ODE, its own series and
    SciPy's Bessel functions) to 1e-8, as tests/test_forward.py holds the other pores."""
    from tawarp import reference

    d = load_core("nicr_foam").to_dict()
    d["gas"].update(name="helium", p_mean=3e5)
    d["segment"][1]["pore_model"] = model
    d["segment"][1]["aspect_ratio" if model == "rectangular" else "outer_radius_ratio"] = shape
    core = core_from_dict(d, f"<{model}>")
    freqs = np.array([30.0, 120.0, 260.0, 500.0])
    Y = transfer_matrices(core, freqs, 30.0, device=DEVICE, cells=48).dimensionless()[0]
    Yref = reference.dimensionless_transfer(core, freqs, 30.0)
    assert float((np.abs(Y - Yref).max(-1) / np.abs(Yref).max(-1)).max()) < 1e-8


def test_forward_model_of_a_wide_channel_is_the_plates_one():
    """A stack of rectangular channels of aspect ratio 1e6 has the T-matrix of the plates
    (heated: the gradient term too) to the O(1/alpha) of its pore functions."""
    core = load_core("ceramic")
    freqs = np.array([60.0, 180.0])
    T_rect = transfer_matrices(rectangular(core, ASPECT_MAX), freqs, 40.0, device=DEVICE).T
    T_plates = transfer_matrices(plates(core), freqs, 40.0, device=DEVICE).T
    np.testing.assert_allclose(T_rect, T_plates, rtol=0, atol=1e-5 * np.abs(T_plates).max())
    T_square = transfer_matrices(rectangular(core, 1.0), freqs, 40.0, device=DEVICE).T
    assert np.abs(T_square - T_plates).max() > 1e-3 * np.abs(T_plates).max()  # the shape shows


@pytest.mark.parametrize("model, shape", [("rectangular", 2.0), ("pins", 2.5)])
def test_cascade_tangents_of_new_pores(model, shape):
    """dT/dz of the tangent cascade (the fit's Jacobian) against extrapolated central
    differences of the plain cascade (tests/cascade_differences.py), as tests/test_tangents.py
    checks the circular and plate pores."""
    core = with_pores(load_core("ceramic"), model, shape)
    names = ["stack.porosity", "stack.pore_radius", "stack.tortuosity", "stack.h", "gas.T_cold"]
    v0 = np.array([core.get(k) for k in names]) * np.array([0.97, 1.2, 1.1, 0.8, 1.02])
    assert_tangents_match_differences(core, names, v0, 40.0)


@pytest.mark.parametrize("model, shape", [("rectangular", 1.0), ("pins", 2.5)])
def test_fit_round_trip_on_a_new_pore_stack(model, shape):
    """Data made by the model of a stack of square channels (or of pins) at heat input 40 W,
    0.5 % noise: the batched Levenberg-Marquardt fit (tangent Jacobian) from 15 % off brings
    porosity, pore radius and h back to within 3 of its reported standard deviations."""
    from tawarp.fit.estimate import fit
    from tawarp.measure.synthetic import paper_frequencies

    core = with_pores(load_core("ceramic"), model, shape)
    names = ["stack.porosity", "stack.pore_radius", "stack.h"]
    freqs = paper_frequencies("ceramic", 16)
    Y0 = transfer_matrices(core, freqs, 40.0, cells=12, device=DEVICE).dimensionless()[0]
    sd = 0.005 * np.abs(Y0) / np.sqrt(2)
    rng = np.random.default_rng(5)
    Y = Y0 + sd * (rng.standard_normal(Y0.shape) + 1j * rng.standard_normal(Y0.shape))
    truth = np.array([core.get(k) for k in names])
    settings = ForwardSettings(cells=8, device=DEVICE)
    r = fit(core, freqs, Y[None], names, truth * [0.9, 1.15, 0.85], heat_input=40.0, weights=1 / sd,
            settings=settings, jacobian="tangent", warn=False)  # fmt: skip
    assert r.converged.all()
    assert np.all(np.abs(r.values[0] - truth) < 3 * r.std[0])


def test_onset_of_a_pin_stack_against_its_growth_rate():
    """The bundled engine with a pin-array stack (outer radius ratio 3, porosity 1 - 1/9):
    Im omega changes sign once over Q = 0..200 W and the onset found (complex-frequency
    path of the pin functions) is where eigenfrequencies() says the growth rate is 0."""
    from tawarp.model.onset import eigenfrequencies

    eng = load_engine("standing_wave")
    pins = dataclasses.replace(eng, core=with_pores(eng.core, "pins", 3.0).replace(**{"stack.porosity": 1 - 1 / 9}))
    grid = eigenfrequencies(pins, np.linspace(0, 200, 9), device=DEVICE)
    assert np.count_nonzero(np.diff(np.sign(grid.growth_rate))) == 1
    res = onset(pins, Q_max=200.0, device=DEVICE)
    at = eigenfrequencies(pins, res.Q_onset[0], device=DEVICE)
    assert abs(at.growth_rate[0]) < 1e-8 * 2 * np.pi * at.frequency[0]


def test_onset_of_a_wide_channel_stack_is_the_plates_one():
    """The onset heat input (complex-frequency path) of the bundled engine with its stack
    as rectangular channels of aspect ratio 1e6 equals the plates' to 1e-5."""
    eng = load_engine("standing_wave")
    rect = dataclasses.replace(eng, core=rectangular(eng.core, ASPECT_MAX))
    plate = dataclasses.replace(eng, core=plates(eng.core))
    q_rect = onset(rect, Q_max=200.0, device=DEVICE).Q_onset[0]
    q_plates = onset(plate, Q_max=200.0, device=DEVICE).Q_onset[0]
    assert np.isfinite(q_plates) and q_rect == pytest.approx(q_plates, rel=1e-5)


def test_design_evaluator_on_a_rectangular_stack():
    """The design evaluator (sweeps, searches) on a rectangular stack: every objective of a
    design batch, the acoustic loss included, equals the plates' at aspect ratio 1e6 (1e-5);
    square channels change the acoustic loss."""
    core = load_core("ceramic")
    points = {"stack.pore_radius": np.array([0.3e-3, 0.5e-3]), "heat_input": np.array([20.0, 40.0])}
    variables = ["stack.pore_radius=0.2e-3:0.8e-3", "heat_input=0:60"]

    def objectives(c):
        ev = Evaluator(DesignSpace(c, variables), extra=("acoustic_loss",), settings=ForwardSettings(device=DEVICE))
        return ev.evaluate(points)

    rect, plate, square = (
        objectives(rectangular(core, ASPECT_MAX)),
        objectives(plates(core)),
        objectives(rectangular(core, 1.0)),
    )
    assert set(rect) == set(plate)
    for name in plate:
        np.testing.assert_allclose(rect[name], plate[name], rtol=1e-5, atol=1e-12)
    assert np.all(np.abs(square["acoustic_loss"] / plate["acoustic_loss"] - 1) > 1e-3)
