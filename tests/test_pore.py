"""Pore functions f, g of tawarp.kernels.pore and of the circular-pore table
(tawarp.kernels.pore_table, the kernels' path at real s) against mpmath (40 digits)."""

import mpmath
import numpy as np
import pytest
import warp as wp

from tawarp.kernels.pore import (
    CIRCULAR_ASYMPTOTIC_S,
    PLATES_EXPONENTIAL_S,
    PORE_CIRCULAR,
    PORE_PLATES,
    PIECES,
    PIECES_PER_OCTAVE,
    S_MAX,
    S_MIN,
    PoreTable,
    circular_inverse_g,
    pore_circular,
    pore_functions_log,
    pore_plates,
)
from tawarp.kernels.pore_table import circular_table

DEVICE = "cpu"
TOL = 1e-13

# 300 log-spaced points over the working range plus spot values beyond it.
S_GRID = np.concatenate([np.geomspace(1e-3, 1e3, 300), [1e-4, 3e-4, 3e3, 1e4]])


@wp.kernel
def _eval_model(
    model: int,
    s: wp.array(dtype=wp.float64),
    table: PoreTable,
    f: wp.array(dtype=wp.vec2d),
    g: wp.array(dtype=wp.vec2d),
):
    i = wp.tid()
    fi, gi = pore_functions_log(model, wp.log(s[i]), table)
    f[i] = fi
    g[i] = gi


@wp.kernel
def _eval_inverse(s: wp.array(dtype=wp.float64), table: PoreTable, inv_g: wp.array(dtype=wp.vec2d)):
    i = wp.tid()
    inv_g[i] = circular_inverse_g(table, wp.log(s[i]))


@wp.kernel
def _eval_direct(
    s: wp.array(dtype=wp.float64),
    fc: wp.array(dtype=wp.vec2d),
    gc: wp.array(dtype=wp.vec2d),
    fp: wp.array(dtype=wp.vec2d),
):
    i = wp.tid()
    fi, gi = pore_circular(s[i])
    fc[i] = fi
    gc[i] = gi
    fi, gi = pore_plates(s[i])
    fp[i] = fi


def _to_complex(a):
    v = a.numpy()
    return v[:, 0] + 1j * v[:, 1]


def evaluate(model, s):
    """f, g of ``model`` at the values ``s`` as the kernels compute them (circular pores
    from the table), as complex numpy arrays."""
    s_wp = wp.array(np.asarray(s, dtype=np.float64), dtype=wp.float64, device=DEVICE)
    f = wp.zeros(len(s), dtype=wp.vec2d, device=DEVICE)
    g = wp.zeros(len(s), dtype=wp.vec2d, device=DEVICE)
    wp.launch(_eval_model, dim=len(s), inputs=[model, s_wp, circular_table(DEVICE), f, g], device=DEVICE)
    return _to_complex(f), _to_complex(g)


def evaluate_direct(s):
    """f, g of :func:`pore_circular` (recurrence and Hankel series) and f of
    :func:`pore_plates` at ``s``."""
    s_wp = wp.array(np.asarray(s, dtype=np.float64), dtype=wp.float64, device=DEVICE)
    fc, gc, fp = (wp.zeros(len(s), dtype=wp.vec2d, device=DEVICE) for _ in range(3))
    wp.launch(_eval_direct, dim=len(s), inputs=[s_wp, fc, gc, fp], device=DEVICE)
    return _to_complex(fc), _to_complex(gc), _to_complex(fp)


def max_rel_err(model, s, f, g):
    """Largest relative error of f and of g against mpmath at the points s."""
    err_f = err_g = 0.0
    for si, fi, gi in zip(s, f, g):
        rf, rg = reference(model, si)
        err_f = max(err_f, rel_err(fi, rf))
        err_g = max(err_g, rel_err(gi, rg))
    return err_f, err_g


def reference(model, s):
    """f, g at 40 digits, exp(-i w t) convention, as mpmath numbers."""
    with mpmath.workdps(40):
        s = mpmath.mpf(float(s))
        if model == PORE_CIRCULAR:
            z = mpmath.mpc(1, 1) * s
            j0 = mpmath.besselj(0, z)
            return 2 * mpmath.besselj(1, z) / (z * j0), -mpmath.besselj(2, z) / j0
        w = mpmath.mpc(1, -1) * s
        f = mpmath.tanh(w) / w
        return f, 1 - f


def rel_err(x, ref):
    return float(abs(mpmath.mpc(x) - ref) / abs(ref))


@pytest.fixture(scope="module", params=[PORE_CIRCULAR, PORE_PLATES], ids=["circular", "plates"])
def model(request):
    return request.param


def test_accuracy_against_mpmath(model):
    f, g = evaluate(model, S_GRID)
    err_f, err_g = max_rel_err(model, S_GRID, f, g)
    print(f"model {model}: max relative error f {err_f:.2e}, g {err_g:.2e}")
    assert err_f <= TOL
    assert err_g <= TOL


def test_circular_recurrence_and_hankel_against_mpmath():
    # the functions the table is built from, and used outside it
    fc, gc, _ = evaluate_direct(S_GRID)
    err_f, err_g = max_rel_err(PORE_CIRCULAR, S_GRID, fc, gc)
    assert err_f <= TOL
    assert err_g <= TOL


def test_table_at_piece_boundaries_and_random_points():
    # both sides of every piece boundary (where a Chebyshev series is least accurate)
    # and 1500 random log-spaced points, 5 seeds' worth of the range
    edges = S_MIN * 2.0 ** (np.arange(PIECES + 1) / PIECES_PER_OCTAVE)
    edges = edges[(edges > S_MIN) & (edges < S_MAX)]
    rng = np.random.default_rng(11)
    s = np.concatenate(
        [
            np.nextafter(edges, 0.0),
            edges,
            np.nextafter(edges, np.inf),
            [S_MIN, np.nextafter(S_MAX, 0.0)],
            np.exp(rng.uniform(np.log(S_MIN), np.log(S_MAX), 1500)),
        ]
    )
    f, g = evaluate(PORE_CIRCULAR, s)
    err_f, err_g = max_rel_err(PORE_CIRCULAR, s, f, g)
    print(f"table: max relative error f {err_f:.2e}, g {err_g:.2e} at {len(s)} points")
    assert err_f <= TOL
    assert err_g <= TOL


@pytest.mark.parametrize("edge", [S_MIN, S_MAX], ids=["s_min", "s_max"])
def test_table_continuous_at_its_ends(edge):
    s = [np.nextafter(edge, 0.0), edge]
    f, g = evaluate(PORE_CIRCULAR, s)
    assert abs(f[1] - f[0]) <= TOL * abs(f[1])
    assert abs(g[1] - g[0]) <= TOL * abs(g[1])


def test_table_matches_direct_functions_and_plates_dispatch():
    fc, gc, fp = evaluate_direct(S_GRID)
    ft, gt = evaluate(PORE_CIRCULAR, S_GRID)
    np.testing.assert_allclose(ft, fc, rtol=TOL, atol=0)
    np.testing.assert_allclose(gt, gc, rtol=TOL, atol=0)
    # the kernels' plates path takes ln s (exp(ln s) is s to a few ulps)
    np.testing.assert_allclose(evaluate(PORE_PLATES, S_GRID)[0], fp, rtol=TOL, atol=0)


def test_circular_outside_the_table_against_mpmath():
    # the series' leading terms the kernels take below S_MIN and from S_MAX on: exact to
    # 1e-17, the rest is the rounding of s = exp(ln s) (a few ulps of s at |ln s| < 20)
    s = [1e-8, 1e-6, 1e-4, 3e-4, 6e-4, np.nextafter(S_MIN, 0.0), S_MAX, 3e4, 1e6]
    f, g = evaluate(PORE_CIRCULAR, s)
    err_f, err_g = max_rel_err(PORE_CIRCULAR, s, f, g)
    assert err_f <= 5e-15
    assert err_g <= 5e-15


def test_nan_argument_does_not_index_the_table():
    f, g = evaluate(PORE_CIRCULAR, [np.nan])
    assert np.isnan(f[0]) or np.isnan(g[0])


@pytest.mark.parametrize(
    "model_id, threshold",
    [(PORE_CIRCULAR, CIRCULAR_ASYMPTOTIC_S), (PORE_PLATES, PLATES_EXPONENTIAL_S)],
    ids=["circular", "plates"],
)
def test_continuous_across_threshold(model_id, threshold):
    t = float(threshold)
    below, at = np.nextafter(t, 0.0), t
    f, g = evaluate(model_id, [below, at])
    assert abs(f[1] - f[0]) <= TOL * abs(f[1])
    assert abs(g[1] - g[0]) <= TOL * abs(g[1])


def test_sign_convention_exp_minus_iwt(model):
    # exp(-i w t): f is the mpmath value at (1 + i) s (plates (1 - i) s), not its
    # conjugate, which is Swift's exp(+i w t) function; Im f > 0 throughout.
    f, g = evaluate(model, S_GRID)
    assert np.all(f.imag > 0)
    assert np.all(g.imag < 0)
    s = 1.0
    rf, _ = reference(model, s)
    fi = evaluate(model, [s])[0][0]
    assert rel_err(fi, rf) <= TOL
    assert rel_err(fi, mpmath.conj(rf)) > 0.1


def test_large_s_limit_circular():
    # f = 2i/z (1 + 4v + O(1/s^2)) with 4v = -(1 + i) / (4 s): the 1/s trend.
    s = np.array([1e2, 1e3, 1e4])
    f, _ = evaluate(PORE_CIRCULAR, s)
    z = (1 + 1j) * s
    correction = s * (f * z / 2j - 1)
    assert np.all(np.abs(correction + (1 + 1j) / 4) <= 1.0 / s)


def test_large_s_limit_plates():
    # tanh(w) = 1 up to exp(-2s), so f = 1/w to rounding.
    s = np.array([30.0, 1e2, 1e4])
    f, _ = evaluate(PORE_PLATES, s)
    np.testing.assert_allclose(f * (1 - 1j) * s, 1.0, rtol=TOL, atol=0)


def test_circular_and_plates_agree_for_equal_hydraulic_radius():
    # r_h = r/2 for the tube, y0 for the plates: with y0 = r/2 both tend to
    # (1 + i) delta / (2 r_h) = (1 + i) / s_r, the tube with a 1/s correction.
    s_r = np.array([50.0, 1e2, 1e3, 1e4])
    fc, _ = evaluate(PORE_CIRCULAR, s_r)
    fp, _ = evaluate(PORE_PLATES, s_r / 2)
    limit = (1 + 1j) / s_r
    assert np.all(np.abs(fc - fp) <= np.abs(limit) / s_r)
    np.testing.assert_allclose(fp, limit, rtol=TOL, atol=0)


def test_circular_inverse_g_against_mpmath():
    """1/g = 1/(1 - f) of a circular pore as the plain cascade reads it (the table's own
    pieces of 1/g inside [S_MIN, S_MAX], the tails' g inverted outside) within TOL of
    mpmath's, over the grid and at the table's ends, where |1/g| spans 4/s^2 ~ 4e8 to 1."""
    s = np.concatenate([S_GRID, [S_MIN, S_MIN * (1 + 1e-12), S_MAX * (1 - 1e-12), S_MAX]])
    s_wp = wp.array(s, dtype=wp.float64, device=DEVICE)
    inv_g = wp.zeros(len(s), dtype=wp.vec2d, device=DEVICE)
    wp.launch(_eval_inverse, dim=len(s), inputs=[s_wp, circular_table(DEVICE), inv_g], device=DEVICE)
    err = max(rel_err(v, 1 / reference(PORE_CIRCULAR, si)[1]) for si, v in zip(s, _to_complex(inv_g)))
    print(f"1/g: max relative error {err:.2e}")
    assert err < TOL
