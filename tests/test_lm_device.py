"""The device LM (:func:`tawarp.fit.lm.levenberg_marquardt`, kernels of
:mod:`tawarp.kernels.lm_step`) takes the same decisions as the host NumPy LM it replaced
(:mod:`lm_host_oracle`): same accepted steps, reasons, converged flags and iteration counts,
values equal to rounding, on a family of nonlinear problems with active bounds, invalid
evaluations, stalls and iteration caps."""

import numpy as np
import pytest
import warp as wp

from test_estimate import FIT, GEOM, noisy
from tawarp.fit.estimate import Problems
from tawarp.measure.synthetic import paper_frequencies
from tawarp.model.core import load_core

from lm_host_oracle import chol_solve, levenberg_marquardt as host_lm
from tawarp.fit.lm import levenberg_marquardt, normal_equations
from tawarp.kernels import lm_step


class CurveProblems:
    """N problems y(t) = exp(z0) exp(-z1 t) + sum_{j>=2} z_j t^j on m points, exact Jacobian.
    Problems with ``fail`` set return an invalid (NaN) cost where z1 > 1.5 (a model that
    fails), some start there; random box bounds, tight for a third of the problems."""

    def __init__(self, N, p, seed=0, m=12):
        rng = np.random.default_rng(seed)
        self.t = np.linspace(0.0, 1.0, m)
        self.p = p
        ztrue = rng.normal(0.0, 0.7, (N, p))
        self.y = np.stack([self.model(ztrue[i]) for i in range(N)]) + 0.05 * rng.standard_normal((N, m))
        self.w = rng.uniform(0.5, 2.0, (N, m))
        half = rng.uniform(0.2, 3.0, (N, p))
        half[rng.random(N) < 0.33] *= 0.1  # tight boxes: bounds active at the solution
        centre = rng.normal(0.0, 0.3, (N, p))
        away = rng.random(N) < 0.1  # boxes away from the solution: "bound"
        half[away] = 0.05
        centre[away] = ztrue[away] + 1.0 * np.sign(rng.standard_normal((away.sum(), p)))
        self.zlo, self.zhi = centre - half, centre + half
        # open ends, but not below the log amplitude: exp(z0) -> 0 leaves a flat valley whose
        # stall is decided by rounding (NumPy's vectorised pow is not libm's)
        self.zlo[:, 1:][rng.random((N, p - 1)) < 0.1] = -np.inf
        self.fail = rng.random(N) < 0.1
        kind = np.array([lm_step.CHANGE_LOG, lm_step.CHANGE_LINEAR, lm_step.CHANGE_ABSOLUTE] * p)[:p]
        self.rule = (kind.astype(np.int32), rng.uniform(0.1, 2.0, (N, p)), rng.normal(0.0, 1.0, (N, p)))

    def model(self, z):
        z = np.atleast_2d(z)
        f = np.exp(z[:, :1]) * (np.exp(-z[:, 1:2] * self.t) if self.p > 1 else 1.0)
        for j in range(2, self.p):
            f = f + z[:, j : j + 1] * self.t**j
        return f[0] if f.shape[0] == 1 else f

    def jacobian(self, z):
        n, m = z.shape[0], self.t.size
        J = np.empty((n, m, self.p))
        e = np.exp(z[:, :1]) * (np.exp(-z[:, 1:2] * self.t) if self.p > 1 else np.ones(m))
        J[:, :, 0] = e
        if self.p > 1:
            J[:, :, 1] = -self.t * e
        for j in range(2, self.p):
            J[:, :, j] = self.t**j
        return J

    def change_rule(self):
        return self.rule

    def evaluate(self, pid, z, max_sets=0):
        w = self.w[pid]
        r = w * (self.model(z).reshape(len(pid), -1) - self.y[pid])
        J = w[:, :, None] * self.jacobian(z)
        cost = np.einsum("ni,ni->n", r, r)
        raw = np.einsum("ni,ni->n", r / w, r / w)
        if self.p > 1:
            cost[self.fail[pid] & (z[:, 1] > 1.5)] = np.nan
        bad = ~np.isfinite(cost)
        cost[bad] = np.inf
        return cost, raw, np.einsum("nij,ni->nj", J, r), np.einsum("nij,nik->njk", J, J)


SETTINGS = [
    dict(),
    dict(damping="paper"),
    dict(xtol=1e-14, gtol=1e-15, max_iter=200),
    dict(max_iter=3),
    dict(xtol=1e-6, gtol=1e-10, damping="paper", max_iter=50),
    # no gradient test: with every component held at a bound the gradient cosine is 0,
    # so "gtol" otherwise always comes before "bound"
    dict(gtol=-1.0, max_iter=30),
]


@pytest.mark.parametrize("p", [1, 3, 5])
@pytest.mark.parametrize("kw", SETTINGS)
def test_device_lm_equals_host_lm(p, kw):
    N = 300
    prob = CurveProblems(N, p, seed=p)
    rng = np.random.default_rng(10 + p)
    z0 = rng.normal(0.0, 0.8, (N, p))
    pid = np.arange(N)
    ref = host_lm(prob, pid, z0, **kw)
    got = levenberg_marquardt(prob, pid, z0, **kw)
    assert got.reason.tolist() == ref.reason.tolist()
    assert np.array_equal(got.iterations, ref.iterations)
    assert np.array_equal(got.converged, ref.converged)
    # values: the same accepted steps, so equal to rounding (the kernels' sums run in
    # index order as NumPy's; expm1 and the einsums may differ in the last bits)
    for name in ("z", "cost", "raw", "g", "H"):
        a, b = getattr(got, name), getattr(ref, name)
        fin = np.isfinite(b)
        assert np.array_equal(np.isfinite(a), fin), name
        assert np.allclose(a[fin], b[fin], rtol=1e-12, atol=1e-12 * max(1.0, np.abs(b[fin]).max(initial=0))), name


@pytest.mark.parametrize("heat", [0.0, 40.0])
@pytest.mark.parametrize("jacobian", ["difference", "tangent"])
def test_device_lm_equals_host_lm_on_tmatrix_problems(heat, jacobian):
    """The T-matrix problems (:class:`Problems`: log and linear parameters, Warp arrays from
    evaluate) from starts spread around the truth, some at the porosity bound. Both loops
    see the same evaluations, but a step can come out one ulp apart (LAPACK's solve against
    the device's Cholesky: iteration 7 of problem 3 at 40 W with the tangent Jacobians,
    iteration 6 of problem 3 at 0 W with differences), and the later iterations along a flat
    valley spread that, to 2e-10 in the scaled variables z by the xtol stop (1e-6; z is near
    0 at the truth, so its relative difference reads 4e-8): the same iterations, reasons and
    results to 1e-9 (z absolute, in its scaled units; the gradients to 1e-9 of
    sqrt(F H_aa), the gradient test's scale; H to 1e-8 of sqrt(H_aa H_bb): the difference
    quotients' Gauss-Newton matrix at those z moved by 1.4e-9 of it)."""
    core = load_core("mesh")
    freqs = paper_frequencies("mesh", 12)
    Y, sd = noisy(core, freqs, heat, 12, seed=5)
    prob = Problems(core, freqs, Y, GEOM, heat_input=heat, weights=1 / sd, settings=FIT, jacobian=jacobian)
    rng = np.random.default_rng(6)
    v0 = np.array([core.get(k) for k in GEOM]) * rng.uniform(0.6, 1.5, (12, 3))
    v0[:3, 0] = 1.0  # porosity at its upper bound
    pid = np.arange(12)
    z0 = prob.to_z(v0, pid)
    ref = host_lm(prob, pid, z0, xtol=1e-6, gtol=1e-10)
    got = levenberg_marquardt(prob, pid, z0, xtol=1e-6, gtol=1e-10)
    assert got.reason.tolist() == ref.reason.tolist()
    assert np.array_equal(got.iterations, ref.iterations) and np.array_equal(got.converged, ref.converged)
    rtol = 1e-9
    for name in ("z", "cost", "raw", "g", "H"):
        a, b = getattr(got, name), getattr(ref, name)
        # g -> 0 at the solution: compared on the scale of the gradient test, sqrt(F H_aa);
        # z on its own scale, the scaled variables' unit
        atol = {"g": rtol * np.sqrt(ref.cost.max() * np.einsum("nii->ni", ref.H).max()), "z": rtol}.get(name, 0)
        if name == "H":
            diag = np.einsum("nii->ni", b)
            assert np.all(np.abs(a - b) <= 10 * rtol * np.sqrt(diag[:, :, None] * diag[:, None, :])), name
            continue
        assert np.allclose(a, b, rtol=rtol, atol=atol), name


def test_reasons_exercised():
    """The family above reaches every reason (else the comparison proves less)."""
    seen = set()
    for p in (1, 3, 5):
        prob = CurveProblems(300, p, seed=p)
        z0 = np.random.default_rng(10 + p).normal(0.0, 0.8, (300, p))
        for kw in SETTINGS:
            seen |= set(levenberg_marquardt(prob, np.arange(300), z0, **kw).reason.tolist())
    assert seen == {"xtol", "gtol", "bound", "stalled", "max_iterations", "invalid"}


def test_propose_is_the_cholesky_step():
    """With mu = 0 and no bounds the proposed step solves H d = -g (the host's vectorised
    Cholesky and NumPy agree); an indefinite H gives no step and chol_ok = 0."""
    rng = np.random.default_rng(1)
    n, p = 50, 5
    A = rng.standard_normal((n, p, p))
    A = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(p)
    b = rng.standard_normal((n, p))
    dev = "cpu"
    propose = lm_step.step_kernels(p)[1]
    for H, ok_expected in ((A, 1), (-A, 0)):
        arr = lambda x, dt=wp.float64: wp.array(np.ascontiguousarray(x), dtype=dt, device=dev)  # noqa: E731
        setup = lm_step.Setup()
        setup.pid = arr(np.arange(n, dtype=np.int32), wp.int32)
        setup.zlo, setup.zhi = arr(np.full((n, p), -np.inf)), arr(np.full((n, p), np.inf))
        state = lm_step.Iterate()
        state.z = arr(np.zeros((n, p)))
        state.at_z = normal_equations((np.zeros(n), np.zeros(n), -b, H), dev)
        state.mu = arr(np.zeros(n))
        trial = lm_step.Trial()
        trial.act = setup.pid
        trial.zt, trial.dz = wp.empty((n, p), dtype=wp.float64), wp.empty((n, p), dtype=wp.float64)
        trial.pred, trial.chol_ok = wp.empty(n, dtype=wp.float64), wp.empty(n, dtype=wp.int32)
        wp.launch(propose, dim=n, device=dev, inputs=[setup, state, trial])
        zt, ok = trial.zt, trial.chol_ok
        assert np.all(ok.numpy() == ok_expected)
        if ok_expected:
            # 1e-10: well-conditioned SPD systems, double precision
            assert np.allclose(zt.numpy(), np.linalg.solve(A, b[..., None])[..., 0], rtol=1e-10, atol=1e-12)
            assert np.array_equal(zt.numpy(), chol_solve(A, b)[0])
        else:
            assert np.all(zt.numpy() == 0)


def test_device_lm_equals_host_lm_on_kind_problems():
    """:class:`KindProblems` (host evaluate, NumPy arrays, |dz| rule, padded z): several fits
    of a linear kind with different parameter counts, bounds on some."""
    from test_fit_lm import LinearKind, linear_case
    from tawarp.fit.problems import KindProblems
    from tawarp.model.effects import Param

    A, sigma, y, _, _ = linear_case(4)
    kind = LinearKind(A, sigma, y)
    params = [Param(f"v{j}", (f"v{j}",), 0.5, 1.0) for j in range(3)]
    bounded = [Param("v0", ("v0",), 0.5, 1.0, lower=0.0, upper=0.6)] + params[1:]
    specs = [
        (params, None, np.zeros(3)),
        (params[:2], None, np.ones(2)),
        (bounded, None, np.zeros(3)),
        (params[1:], None, np.full(2, 0.3)),
    ]
    lm = KindProblems(kind, specs)
    pid = np.arange(len(specs))
    ref = host_lm(lm, pid, lm.start(), xtol=1e-10, gtol=1e-6)
    got = levenberg_marquardt(lm, pid, lm.start(), xtol=1e-10, gtol=1e-6)
    assert got.reason.tolist() == ref.reason.tolist()
    assert np.array_equal(got.iterations, ref.iterations) and np.array_equal(got.converged, ref.converged)
    for name in ("z", "cost", "raw", "g", "H"):
        assert np.allclose(getattr(got, name), getattr(ref, name), rtol=1e-12, atol=1e-14), name
