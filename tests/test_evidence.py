"""The loop's Bayesian pieces against closed forms: the Laplace evidence is exact for a
linear model with Gaussian noise and prior (the marginal likelihood is then the Gaussian
N(y; A mu, I + A S A^T)); the linearized evidence equals it at the optimum; the truncated
prior's normalisation equals scipy's truncnorm; the model prior sums to one over the
models; inclusion and group claims follow from the model probabilities."""

import functools
import math

import numpy as np
import pytest
from scipy import integrate, special, stats

from tawarp.fit.lockstep import Together
from tawarp.fit.problem_model import ProblemModel, determined_inverse
from tawarp.fit.result import FitResult
from tawarp.loop.evidence import (
    CLAIM,
    NOISE_LOG_SCALES,
    NOISE_SCALE_RANGE,
    ON_BOUND,
    Model,
    XPrior,
    _logdet_and_quadratic,
    any_of,
    claims,
    inclusion,
    laplace_log_evidence,
    laplace_log_evidences,
    linearized_evidence,
    log_model_prior,
    log_sum_exp,
    posterior,
    prior_arrays,
    subsets,
)


def x_model(priors: list[XPrior]) -> ProblemModel:
    """The problem model of parameters that are their own fit variables (v = x), with
    ``priors`` (their ranges the fit ranges): a linear model known only in x."""
    mu, sd, lo, hi = prior_arrays(priors)
    k = mu.size
    return ProblemModel([f"x{j}" for j in range(k)], np.zeros(k, dtype=bool), np.zeros(k), np.ones(k), lo, hi, mu, sd)


def linear_gaussian(seed, n=40, p=3):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((n, p))
    mu = rng.standard_normal(p)
    sd = rng.uniform(0.3, 2.0, p)
    y = A @ (mu + sd * rng.standard_normal(p)) + rng.standard_normal(n)
    return A, y, mu, sd


def exact_log_evidence(A, y, mu, sd):
    """ln N(y; A mu, I + A diag(sd^2) A^T) plus (n/2) ln 2 pi (the evidence leaves out the
    noise's normalisation, the same for every model)."""
    cov = np.eye(len(y)) + A @ np.diag(sd**2) @ A.T
    return stats.multivariate_normal(A @ mu, cov).logpdf(y) + 0.5 * len(y) * math.log(2 * math.pi)


def map_estimate(A, y, mu, sd):
    H = A.T @ A + np.diag(sd**-2)
    return np.linalg.solve(H, A.T @ y + mu / sd**2)


@pytest.mark.parametrize("seed", range(5))
def test_laplace_evidence_is_exact_for_a_linear_gaussian_model(seed):
    A, y, mu, sd = linear_gaussian(seed)
    x = map_estimate(A, y, mu, sd)
    priors = [XPrior(m, s) for m, s in zip(mu, sd)]
    got = laplace_log_evidence(x_model(priors), A @ x - y, A, x)
    assert got == pytest.approx(exact_log_evidence(A, y, mu, sd), abs=1e-9)


@pytest.mark.parametrize("noise_scale", [False, True])
def test_laplace_evidence_is_exact_on_rotated_columns(noise_scale):
    # the same linear Gaussian model given as Q^T J, Q^T r (Q of the thin QR of [J, r], as
    # linearized_evidence rotates its columns) with the number of residuals beside them: the
    # closed-form evidence, with the noise known and with it estimated
    A, y, mu, sd = linear_gaussian(7)
    x = map_estimate(A, y, mu, sd)
    priors = [XPrior(m, s) for m, s in zip(mu, sd)]
    r = A @ x - y
    Q, _ = np.linalg.qr(np.column_stack([A, r]))
    got = laplace_log_evidence(x_model(priors), Q.T @ r, Q.T @ A, x, noise_scale, len(r))
    want = laplace_log_evidence(x_model(priors), r, A, x, noise_scale)
    assert got == pytest.approx(want, abs=1e-9)
    if not noise_scale:
        assert got == pytest.approx(exact_log_evidence(A, y, mu, sd), abs=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_evidence_with_an_unknown_noise_scale_is_the_exact_marginal(seed):
    # noise 3x its estimate: ln Z marginalized over the scale s (flat in ln s) equals the
    # quadrature of the exact Gaussian marginal N(y; A mu, s^2 I + A S A^T), whatever the
    # point x the quadratic model is taken at (it is exact for a linear model)
    A, y, mu, sd = linear_gaussian(seed)
    y = A @ mu + 3.0 * (y - A @ mu)
    priors = [XPrior(m, s) for m, s in zip(mu, sd)]
    R = NOISE_SCALE_RANGE
    u = np.linspace(-math.log(R), math.log(R), 4001)
    logpdf = [
        stats.multivariate_normal(A @ mu, math.exp(2 * v) * np.eye(len(y)) + A @ np.diag(sd**2) @ A.T).logpdf(y)
        for v in u
    ]
    exact = special.logsumexp(logpdf) + math.log(u[1] - u[0]) - math.log(2 * math.log(R))
    exact += 0.5 * len(y) * math.log(2 * math.pi)
    for x in (map_estimate(A, y, mu, sd), mu + sd):
        got = laplace_log_evidence(x_model(priors), A @ x - y, A, x, noise_scale=True)
        assert got == pytest.approx(exact, abs=2e-3)
    # against the estimate taken as exact, the marginal prefers the scale the data show
    assert laplace_log_evidence(x_model(priors), A @ x - y, A, x, noise_scale=True) > laplace_log_evidence(
        x_model(priors), A @ x - y, A, x
    )


def stacked_noise_scale_evidence(r, J, x, priors):
    """The noise-scale marginal of laplace_log_evidence (without the range cut), written
    independently: at each s the quadratic model's minimum by least squares on the stacked
    system [J/s; diag(1/sd)], its log det from that system's QR."""
    mu = np.array([p.mu for p in priors])
    sd = np.array([p.sd for p in priors])
    u = np.linspace(-math.log(NOISE_SCALE_RANGE), math.log(NOISE_SCALE_RANGE), 401)
    terms = []
    for v in u:
        s = math.exp(v)
        M = np.vstack([J / s, np.diag(1 / sd)])
        b = -np.concatenate([r / s, (x - mu) / sd])
        d, *_ = np.linalg.lstsq(M, b, rcond=None)
        logdet = 2 * np.sum(np.log(np.abs(np.diag(np.linalg.qr(M * sd[None, :], mode="r")))))
        terms.append(-0.5 * float(np.sum((M @ d - b) ** 2)) - len(r) * v - 0.5 * logdet)
    norm = sum(p.log_norm() for p in priors) + 0.5 * len(x) * math.log(2 * math.pi) + float(np.sum(np.log(sd)))
    return norm + special.logsumexp(terms) + math.log(u[1] - u[0]) - math.log(2 * u[-1])


@pytest.mark.parametrize("seed", range(3))
def test_noise_scale_evidence_at_a_bound_with_a_large_gradient(seed):
    # a fit stopped with one parameter at its bound (a variable in small units: its column
    # 3.6e8, its data gradient 4.5e8) beside two the data do not see: every term is a
    # square, so the marginal stays the stacked least squares' (an eigenvector form of the
    # same algebra returned ln Z of order +1e12 here, through cancellation)
    rng = np.random.default_rng(seed)
    n = 2000
    J = rng.standard_normal((n, 8))
    J[:, 5] *= 3.6e8 / math.sqrt(n)
    J[:, 6:] = 0.0
    r = 20 * rng.standard_normal(n) + 4.5e8 * J[:, 5] / np.sum(J[:, 5] ** 2)
    sd = np.array([0.2, 0.4, 0.22, 8.0, 6.7, 200.0, 2.2, 1.1])
    x = rng.uniform(-1, 1, 8) * sd
    x[5] = 0.0
    priors = [XPrior(0.0, s) for s in sd]
    got = laplace_log_evidence(x_model(priors), r, J, x, noise_scale=True)
    assert got == pytest.approx(stacked_noise_scale_evidence(r, J, x, priors), abs=1e-6)


class _Effect:
    def __init__(self, name):
        self.name, self.params = name, (None,)


def _base_fit(A, y, mu, sd):
    """The MAP fit of the linear model of ``A``'s columns as a FitResult (x = values)."""
    p = A.shape[1]
    xb = map_estimate(A, y, mu, sd)
    return FitResult(
        names=[f"b{j}" for j in range(p)],
        values=xb[None],
        std=np.zeros((1, p)),
        covariance=np.zeros((1, p, p)),
        correlation=np.zeros((1, p, p)),
        condition=np.ones(1),
        iterations=np.zeros(1, int),
        converged=np.ones(1, bool),
        reason=np.array(["xtol"]),
        cost=np.ones(1),
        rms_error=np.ones(1),
        s2=np.ones(1),
        dof=1,
        start=np.zeros((1, p)),
        x=xb[None],
        residuals=(A @ xb - y)[None],
        jacobian=A[None],
    )


@pytest.mark.parametrize("seed", range(3))
def test_linearized_evidence_of_added_columns_equals_the_exact_one(seed):
    # the base model holds the first two columns (at its MAP); the "effect" adds the third,
    # off at 0: the quadratic model is exact for a linear model, so the linearized evidence of
    # base + effect equals the exact evidence of the three-column model
    A, y, mu, sd = linear_gaussian(seed)
    mu[2] = 0.0
    base_priors = [XPrior(m, s) for m, s in zip(mu[:2], sd[:2])]
    at = Model((), fit=_base_fit(A[:, :2], y, mu[:2], sd[:2]), priors=base_priors)
    effect = _Effect("e")
    ((logz, x),) = linearized_evidence(at, {"e": A[:, 2:]}, [((effect,), base_priors + [XPrior(0.0, sd[2])])])
    assert logz == pytest.approx(exact_log_evidence(A, y, mu, sd), abs=1e-9)
    assert np.allclose(x, map_estimate(A, y, mu, sd), atol=1e-12)
    # and with no effect it is the base model's own evidence
    ((logz0, _),) = linearized_evidence(at, {}, [((), base_priors)])
    assert logz0 == pytest.approx(exact_log_evidence(A[:, :2], y, mu[:2], sd[:2]), abs=1e-9)


def _reduced_active_set(C, r0, x0, mu, sd, lo, hi, n_base):
    """The linearized optimum one model at a time on the reduced system (the free
    parameters' rows and columns only), the furthest parameter out of its range held on
    its bound and the rest solved again."""
    G = C.T @ C + np.diag(sd**-2)
    b = C.T @ r0 + (x0 - mu) / sd**2
    free = np.ones(len(x0), dtype=bool)
    while True:
        d = np.zeros(len(x0))
        d[free] = np.linalg.solve(G[np.ix_(free, free)], -b[free])
        x = x0 + d
        bad = free & ((x < lo) | (x > hi))
        bad[:n_base] = False
        if not bad.any():
            return np.clip(x, lo, hi)
        free[int(np.argmax(np.where(bad, np.maximum(lo - x, x - hi), -np.inf)))] = False


@pytest.mark.parametrize("seed", range(4))
def test_linearized_evidence_of_many_models_is_each_models_own(seed):
    # every subset of five one-sided effects (off at their lower bound 0) beside a base of
    # two columns, the data pulling some effects below "off": the batched solve holds the
    # same parameters on their bounds as the model-by-model reduced solve, and each model's
    # ln Z is the Laplace evidence of its own quadratic model at that point
    import itertools

    rng = np.random.default_rng(seed)
    A = rng.standard_normal((60, 7))
    truth = np.concatenate([rng.standard_normal(2), rng.choice([-1.0, 0.0, 1.0], 5) * 0.3])
    y = A @ truth + 0.3 * rng.standard_normal(60)
    mu, sd = np.concatenate([rng.standard_normal(2), np.zeros(5)]), np.full(7, 1.0)
    base_priors = [XPrior(m, s) for m, s in zip(mu[:2], sd[:2])]
    at = Model((), fit=_base_fit(A[:, :2], y, mu[:2], sd[:2]), priors=base_priors)
    effects = [_Effect(f"e{j}") for j in range(5)]
    columns = {e.name: A[:, 2 + j : 3 + j] for j, e in enumerate(effects)}
    models = [
        (c, base_priors + [XPrior(0.0, 1.0, 0.0, math.inf)] * len(c))
        for k in range(4)
        for c in itertools.combinations(effects, k)
    ]
    got = linearized_evidence(at, columns, models)
    held = 0
    xb, rb = at.fit.x[0], at.fit.residuals[0]
    for (c, priors), (logz, x) in zip(models, got):
        C = np.hstack([A[:, :2]] + [columns[e.name] for e in c])
        x0 = np.concatenate([xb, np.zeros(len(c))])
        lo, hi = np.array([p.lo for p in priors]), np.array([p.hi for p in priors])
        pm, ps = np.array([p.mu for p in priors]), np.array([p.sd for p in priors])
        want = _reduced_active_set(C, rb, x0, pm, ps, lo, hi, 2)
        assert np.allclose(x, want, rtol=1e-10, atol=1e-12)
        held += int(np.sum(want[2:] == 0.0))
        own = laplace_log_evidence(x_model(priors), rb + C @ (want - x0), C, want)
        assert logz == pytest.approx(own, rel=1e-12, abs=1e-9)
    assert held > 0  # some effect was held on its bound


@pytest.mark.parametrize("noise_scale", [False, True])
def test_laplace_log_evidences_of_a_ragged_batch_are_each_models_own(noise_scale):
    # models of different sizes, rows and parameters on their bounds (lower and upper) in one
    # call: each ln Z is the one the model gets alone
    rng = np.random.default_rng(7)
    models = []
    for _ in range(60):
        n, p = int(rng.choice([8, 30])), int(rng.integers(1, 5))
        J = rng.standard_normal((n, p))
        mu, sd = rng.standard_normal(p), rng.uniform(0.5, 2.0, p)
        lo, hi = np.full(p, -math.inf), np.full(p, math.inf)
        x = mu + sd * rng.standard_normal(p)
        for j in range(p):
            where = rng.integers(0, 3)
            if where == 1:
                lo[j] = x[j]
            elif where == 2:
                hi[j] = x[j]
        models.append((mu, sd, lo, hi, rng.standard_normal(n), J, x))
    got = laplace_log_evidences(models, noise_scale)
    for g, (mu, sd, lo, hi, r, J, x) in zip(got, models):
        priors = [XPrior(*a) for a in zip(mu, sd, lo, hi)]
        assert g == pytest.approx(laplace_log_evidence(x_model(priors), r, J, x, noise_scale), rel=1e-12, abs=1e-9)


def ragged_models(seed: int, count: int) -> list[tuple]:
    """``count`` random (mu, sd, lo, hi, r, J, x) of 8 or 30 residuals, 1-4 parameters,
    some on a lower or an upper bound."""
    rng = np.random.default_rng(seed)
    models = []
    for _ in range(count):
        n, p = int(rng.choice([8, 30])), int(rng.integers(1, 5))
        mu, sd = rng.standard_normal(p), rng.uniform(0.5, 2.0, p)
        x = mu + sd * rng.standard_normal(p)
        side = rng.integers(0, 3, p)
        lo, hi = np.where(side == 1, x, -math.inf), np.where(side == 2, x, math.inf)
        models.append((mu, sd, lo, hi, rng.standard_normal(n), rng.standard_normal((n, p)), x))
    return models


def test_evidences_of_loops_run_together_are_stacked_and_each_models_own():
    # threads of run_together (loops run together) asking for evidences at the same step get
    # them from one stacked call per noise treatment, each the number its caller gets alone
    requests = [(ragged_models(seed, 5 + 3 * seed), seed % 2 == 1) for seed in range(6)]
    together = Together()
    got = together.run([functools.partial(laplace_log_evidences, m, scale) for m, scale in requests])
    assert together.batches == 1 and together.calls == len(requests)
    for g, (models, scale) in zip(got, requests):
        np.testing.assert_allclose(g, laplace_log_evidences(models, scale), rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_log_sum_exp_is_scipys_bit_for_bit(seed):
    # a noise marginal's terms: spread over tens to thousands, some tied at the largest
    rng = np.random.default_rng(seed)
    a = rng.normal(-1e3, 10.0 ** (seed + 1), 401)
    a[rng.integers(0, 401, 3)] = a.max()
    assert log_sum_exp(a) == float(special.logsumexp(a))
    assert log_sum_exp(np.array([2.5])) == 2.5
    rows = np.stack([a, a[::-1] * 0.5, np.full(401, -3.0)])
    assert np.array_equal(log_sum_exp(rows), special.logsumexp(rows, axis=1))


@pytest.mark.parametrize("lo, hi", [(0.0, math.inf), (-1.0, 2.5), (-math.inf, 0.3)])
def test_truncated_prior_normalisation(lo, hi):
    p = XPrior(0.2, 0.7, lo, hi)
    x = 0.25
    expected = stats.truncnorm((lo - 0.2) / 0.7, (hi - 0.2) / 0.7, loc=0.2, scale=0.7).logpdf(x)
    assert p.log_norm() - 0.5 * ((x - 0.2) / 0.7) ** 2 == pytest.approx(expected, abs=1e-12)


def test_model_prior_sums_to_one_and_is_uniform_over_sizes():
    class E:
        def __init__(self, name, structural=False, mechanism=None):
            self.name, self.transform = name, (lambda c: c) if structural else None
            self.mechanism = mechanism

    # two frame models of one mechanism never share a model (a layer has one frame)
    lib = [E("a"), E("b"), E("c"), E("s1", True), E("s2", True), E("limp", mechanism="f"), E("elastic", mechanism="f")]
    sets = subsets(lib, 3)
    assert all(sum(e.transform is not None for e in s) <= 1 for s in sets)
    assert not any({"s1", "s2"} <= {e.name for e in s} for s in sets)
    assert not any({"limp", "elastic"} <= {e.name for e in s} for s in sets)
    assert ("limp",) in [tuple(e.name for e in s) for s in sets]
    sizes = {}
    for s in sets:
        sizes[len(s)] = sizes.get(len(s), 0) + 1
    total = sum(math.exp(log_model_prior(sizes, len(s))) for s in sets)
    assert total == pytest.approx(1.0, abs=1e-12)
    for k in sizes:  # each size carries 1/(number of sizes)
        assert sum(math.exp(log_model_prior(sizes, k)) for s in sets if len(s) == k) == pytest.approx(1 / len(sizes))


def _models(table):
    out = []
    for effects, logz in table:
        m = Model(tuple(effects), log_evidence=logz)
        out.append(m)
    posterior(out)
    return out


def test_inclusion_and_claims():
    # "a" is in every probable model: claimed alone; "b" and "c" substitute for each other
    # (either explains the data, rarely both): a group of joint probability >= 0.95; "d" is
    # in no probable model
    ms = _models(
        [((), -50.0), (("a",), -20.0), (("a", "b"), 0.0), (("a", "c"), 0.1), (("a", "b", "c"), -4.0), (("d",), -30.0)]
    )
    inc = inclusion(ms, ["a", "b", "c", "d"])
    assert inc["a"] > 0.999 and 0.3 < inc["b"] < 0.7 and 0.3 < inc["c"] < 0.7 and inc["d"] < 1e-6
    alone, groups = claims(ms, ["a", "b", "c", "d"])
    assert alone == ["a"] and groups == [["b", "c"]]
    # no claim when the data do not favour the effects
    ms = _models([((), 0.0), (("a",), -1.0), (("b",), -1.0)])
    assert claims(ms, ["a", "b"]) == ([], [])
    assert CLAIM == 0.95


def test_probabilities_summed_over_models_stay_at_most_one():
    # nine equally probable models all holding "a": their normalized probabilities (1/9 each,
    # not exact in binary) sum to 1 + 2.2e-16 in float64, which a probability must not report
    ms = [Model(("a", f"b{k}"), probability=1.0 / 9.0) for k in range(9)]
    assert sum(m.probability for m in ms) > 1.0
    assert inclusion(ms, ["a"]) == {"a": 1.0}
    assert any_of(ms, ["a", "b0"]) == 1.0


def test_an_effect_the_data_do_not_see_changes_nothing():
    # a one-sided effect (half-normal prior on its bound "off") whose column is zero, fitted
    # at "off": the posterior is half the Laplace Gaussian, and the evidence is the base
    # model's exactly (its Occam factor is 1), whatever the prior's width
    A, y, mu, sd = linear_gaussian(0)
    x = map_estimate(A, y, mu, sd)
    base = [XPrior(m, s) for m, s in zip(mu, sd)]
    want = laplace_log_evidence(x_model(base), A @ x - y, A, x)
    for width in (0.1, 1.0, 30.0):
        Ja = np.hstack([A, np.zeros((len(y), 1))])
        got = laplace_log_evidence(
            x_model(base + [XPrior(0.0, width, 0.0, math.inf)]), A @ x - y, Ja, np.append(x, 0.0)
        )
        assert got == pytest.approx(want, abs=1e-10)


def one_sided_exact(A, a, y, mu, sd, width, scale=1.0):
    """ln Z of the linear model y = A theta + a b + noise (sd ``scale``), theta ~ N(mu, sd^2),
    b >= 0 half-normal of ``width``: the theta-marginal N(y - a b; A mu, scale^2 I + A S A^T)
    integrated over b by quadrature (plus (n/2) ln 2 pi, as the evidence leaves out
    the noise's normalisation)."""
    # the marginal's covariance scale^2 I + A S A^T in the eigenvectors of A S A^T
    lam, V = np.linalg.eigh(A @ np.diag(sd**2) @ A.T)
    w = 1.0 / (scale**2 + lam)
    d, av = V.T @ (y - A @ mu), V.T @ a
    ref = -0.5 * (float(np.sum(np.log(scale**2 + lam))) + float(d @ (w * d)))
    # ln N(y - a b) - ln N(y) = c1 b - c2 b^2 / 2
    c1, c2 = float(av @ (w * d)), float(av @ (w * av))

    def f(b):
        # times the half-normal prior's density
        return math.exp(c1 * b - 0.5 * (c2 + width**-2) * b * b) * 2 / (math.sqrt(2 * math.pi) * width)

    # the integrand falls off over about 1/(|c1| + sqrt(c2)) of its logarithm at 0
    decay = 1.0 / (abs(c1) + math.sqrt(c2) + 1.0 / width)
    val, _ = integrate.quad(f, 0.0, 60 * decay, limit=200, epsabs=0.0, epsrel=1e-11)
    return ref + math.log(val)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("pull", [-3.0, 0.0, 3.0])
def test_a_parameter_on_its_bound_is_integrated_over_its_side(seed, pull):
    # a one-sided effect b >= 0 fitted on its bound "off" beside three free parameters, the
    # data pulling b out of its range (pull < 0: the unconstrained optimum at b < 0), not at
    # all, or in (then the MAP is inside and b is free): the evidence equals the exact
    # integral over b >= 0; with the pull outward it stays below the model without b (an
    # effect at "off" earns no evidence from the data's wish to go beyond it)
    A, y, mu, sd = linear_gaussian(seed)
    rng = np.random.default_rng(100 + seed)
    a = rng.standard_normal(len(y))
    width = 0.5
    y = y + pull * a / math.sqrt(len(y))
    M = np.hstack([A, a[:, None]])
    priors = [XPrior(m, s) for m, s in zip(mu, sd)] + [XPrior(0.0, width, 0.0, math.inf)]
    full = map_estimate(M, y, np.append(mu, 0.0), np.append(sd, width))
    x = full if full[-1] > 0 else np.append(map_estimate(A, y, mu, sd), 0.0)
    got = laplace_log_evidence(x_model(priors), M @ x - y, M, x)
    exact = one_sided_exact(A, a, y, mu, sd, width)
    if full[-1] <= 0:
        assert got == pytest.approx(exact, abs=1e-8)
        without = laplace_log_evidence(x_model(priors[:-1]), A @ x[:-1] - y, A, x[:-1])
        assert got < without
    else:  # inside: the Laplace Gaussian cut at the bound, exact up to the cut's shape
        assert got == pytest.approx(exact, abs=0.05)


@pytest.mark.parametrize("seed", range(3))
def test_a_parameter_on_its_bound_with_an_unknown_noise_scale(seed):
    # the same with the noise 3x its estimate and the data pulling b out of its range: the
    # marginal over the noise scale of the one-sided integrals equals the quadrature of the
    # exact ones
    A, y, mu, sd = linear_gaussian(seed)
    rng = np.random.default_rng(200 + seed)
    a = rng.standard_normal(len(y))
    width = 0.5
    y = A @ mu + 3.0 * (y - A @ mu) - 4.0 * a / math.sqrt(len(y))
    M = np.hstack([A, a[:, None]])
    priors = [XPrior(m, s) for m, s in zip(mu, sd)] + [XPrior(0.0, width, 0.0, math.inf)]
    x = np.append(map_estimate(A, y, mu, sd), 0.0)
    R = NOISE_SCALE_RANGE
    u = np.linspace(-math.log(R), math.log(R), 801)
    terms = [one_sided_exact(A, a, y, mu, sd, width, math.exp(v)) for v in u]
    exact = special.logsumexp(terms) + math.log(u[1] - u[0]) - math.log(2 * math.log(R))
    got = laplace_log_evidence(x_model(priors), M @ x - y, M, x, noise_scale=True)
    assert got == pytest.approx(exact, abs=2e-3)


@pytest.mark.parametrize("seed", range(3))
def test_correlated_parameters_on_their_bounds_away_from_the_optimum(seed):
    # a fit stopped with two one-sided effects at "off" whose columns are nearly the same,
    # the data pulling both far into their range: the posterior lies deep inside the orthant,
    # so the evidence is the whole space's (the Gaussian marginal, each half-normal's density
    # twice the normal's); one-dimensional integrals taken one by one would each credit the
    # whole misfit (ln Z hundreds above it here)
    A, y, mu, sd = linear_gaussian(seed)
    rng = np.random.default_rng(300 + seed)
    a1 = rng.standard_normal(len(y))
    a2 = a1 + 0.05 * rng.standard_normal(len(y))
    width = 0.5
    y = y + 5.0 * (a1 + a2)
    M = np.column_stack([A, a1, a2])
    priors = [XPrior(m, s) for m, s in zip(mu, sd)] + [XPrior(0.0, width, 0.0, math.inf)] * 2
    x = np.append(map_estimate(A, y, mu, sd), [0.0, 0.0])
    got = laplace_log_evidence(x_model(priors), M @ x - y, M, x)
    whole = exact_log_evidence(M, y, np.append(mu, [0.0, 0.0]), np.append(sd, [width, width])) + 2 * math.log(2)
    assert got == pytest.approx(whole, abs=1e-6)


def test_the_evidence_gaussian_is_the_fits_posterior_covariance():
    # one covariance: the Laplace Gaussian's, s2 times the determined inverse of J^T J + s2
    # diag(1/sd^2) (for a stack of models at once), is (J^T J / s2 + diag(1/sd^2))^-1 in x,
    # and the covariance a fit reports (ProblemModel.covariance, sigma known: s2 = 1, from J
    # or from J^T J alike) is that one taken to values by the delta method (v for a log
    # parameter, its step for a linear one)
    from tawarp.fit.problem_model import determined_inverse

    A, y, mu, sd = linear_gaussian(3)
    model = ProblemModel(
        ["a", "b", "c"],
        np.array([True, False, True]),
        np.array([2.0, 0.5, 30.0]),
        np.array([1.0, 0.1, 1.0]),
        np.array([0.0, -np.inf, 0.0]),
        np.full(3, np.inf),
        mu,
        sd,
    )
    x = map_estimate(A, y, mu, sd)
    s2 = np.array([1.0, 2.5])
    stacked = s2[:, None, None] * determined_inverse(A.T @ A + s2[:, None, None] * np.diag(sd**-2))[0]
    for got_s2, want_s2 in zip(stacked, s2):
        want = np.linalg.inv(A.T @ A / want_s2 + np.diag(sd**-2))
        assert np.allclose(got_s2, want, rtol=1e-10, atol=1e-15)
    cost = float(np.sum((A @ x - y) ** 2))
    from_h = model.covariance(x, cost=cost, dof=len(y) - 3, H=A.T @ A)
    D = np.array([2.0 * math.exp(x[0]), 0.1, 30.0 * math.exp(x[2])])
    got = model.covariance(x, cost=cost, dof=len(y) - 3, J=A)
    assert np.allclose(
        got.cov, D[:, None] * np.linalg.inv(A.T @ A + np.diag(sd**-2)) * D[None, :], rtol=1e-10, atol=1e-15
    )
    assert np.allclose(from_h.cov, got.cov, rtol=1e-10, atol=1e-15)


def test_covariances_of_a_batch_are_each_problems_own():
    # the loop's fits take their covariances in batches: every problem's must be the one it
    # gets alone, bit for bit (the reports and evidences of loops run together are then those
    # of each loop run alone), and the posterior covariance D (J^T J / s^2 + Lambda)^-1 D
    from tawarp.fit.problem_model import covariances

    rng = np.random.default_rng(7)
    models, xs, costs, dofs, Js = [], [], [], [], []
    for i in range(60):
        p, n = int(rng.integers(0, 6)), int(rng.choice([2, 40]))
        prior = i % 3 != 0
        sd = np.where(rng.random(p) < 0.3, np.inf, np.exp(rng.normal(size=p))) if prior else None
        models.append(
            ProblemModel(
                [f"v{j}" for j in range(p)],
                rng.random(p) < 0.5,
                np.exp(rng.normal(size=p)),
                np.exp(rng.normal(size=p)),
                np.full(p, -np.inf),
                np.full(p, np.inf),
                rng.normal(size=p) if prior else None,
                sd,
                i % 2 == 0,
            )
        )
        J = rng.normal(size=(n, p)) * np.exp(2 * rng.normal(size=p))
        if p > 2 and i % 5 == 0:
            J[:, 1] = 2 * J[:, 0]  # an undetermined direction
        Js.append(J)
        xs.append(0.1 * rng.normal(size=p))
        costs.append(float(40 * rng.random()))
        dofs.append(max(n - p, 1))
    batch = covariances(models, xs, costs, dofs, Js)
    for m, x, cost, dof, J, got in zip(models, xs, costs, dofs, Js, batch):
        alone = m.covariance(x, cost, dof, J=J)
        for name in ("cov", "std", "corr", "undetermined"):
            assert np.array_equal(getattr(got, name), getattr(alone, name), equal_nan=True), name
        assert (got.cond, got.s2) == (alone.cond, alone.s2)
        A = J.T @ J / got.s2 + np.diag(m.precision())
        if m.p and np.linalg.cond(A) < 1e8:
            D = m.dv_dx(x)
            want = D[:, None] * np.linalg.inv(A) * D[None, :]
            assert np.allclose(got.cov, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())


@pytest.mark.parametrize("noise_scale", [False, True])
def test_evidences_in_blocks_are_the_stacked_ones(noise_scale, monkeypatch):
    # laplace_log_evidences stacks at most EVIDENCE_BLOCK models a call: the same ln Z as
    # one call of every model, to rounding
    from tawarp.loop import evidence

    models = ragged_models(11, 50)
    whole = laplace_log_evidences(models, noise_scale)
    monkeypatch.setattr(evidence, "EVIDENCE_BLOCK", 3)
    np.testing.assert_allclose(laplace_log_evidences(models, noise_scale), whole, rtol=1e-12, atol=1e-9)


def dense_log_evidence(mu, sd, lo, hi, r, J, x, noise_scale):
    """ln Z of :func:`laplace_log_evidence` written out for one model the plain way: at each
    noise scale the quadratic model's Hessian and gradient in the prior-whitened variables
    (those on a bound turned into their range), the minimum over the free parameters by a
    solve, the parameters on a bound by the Schur complement, ln det and C^-1 G by LAPACK,
    the inside mass by determined_inverse. Returns (ln Z, whether the cap (the whole space's
    integral) is below the product of the one-sided ones at some noise scale)."""
    side = np.where(x <= lo + ON_BOUND, 1.0, np.where(x >= hi - ON_BOUND, -1.0, 0.0))
    f, b = side == 0, side != 0
    c = np.where(f, 1.0, side)
    Jw, g = J * sd * c, (x - mu) / sd
    k, m = int(f.sum()), int(b.sum())
    u = NOISE_LOG_SCALES if noise_scale else np.zeros(1)
    terms, capped = [], False
    for ui in u:
        s2 = math.exp(2 * ui)
        H = Jw.T @ Jw / s2 + np.eye(k + m)
        grad = Jw.T @ r / s2 + c * g
        Hff, Hfb = H[np.ix_(f, f)], H[np.ix_(f, b)]
        sol = np.linalg.solve(Hff, grad[f])
        phi = r @ r / s2 + g @ g - grad[f] @ sol
        term = -0.5 * phi - len(r) * ui - 0.5 * np.linalg.slogdet(Hff)[1]
        if m:
            C = H[np.ix_(b, b)] - Hfb.T @ np.linalg.solve(Hff, Hfb)
            G = grad[b] - Hfb.T @ sol
            Cjj = np.diag(C)
            one = np.sum(0.5 * np.log(math.pi / (2 * Cjj)) + np.log(special.erfcx(G / np.sqrt(2 * Cjj))))
            whole = 0.5 * m * math.log(2 * math.pi) - 0.5 * np.linalg.slogdet(C)[1] + 0.5 * G @ np.linalg.solve(C, G)
            capped |= whole < one
            term += min(one, whole)
        terms.append(term)
    norm = (
        sum(XPrior(*a).log_norm() for a in zip(mu, sd, lo, hi)) + 0.5 * k * math.log(2 * math.pi) + np.sum(np.log(sd))
    )
    s2 = math.exp(2 * u[int(np.argmax(terms))])
    A = (Jw[:, f].T @ Jw[:, f] + s2 * np.eye(k)) / np.outer(sd[f], sd[f])
    s = np.sqrt(s2 * np.diag(determined_inverse(A)[0]))
    inside = np.sum(np.log(special.ndtr((hi[f] - x[f]) / s) - special.ndtr((lo[f] - x[f]) / s)))
    if not noise_scale:
        return norm + terms[0] + inside, capped
    return norm + special.logsumexp(terms) + math.log(u[1] - u[0]) - math.log(2 * u[-1]) + inside, capped


@pytest.mark.parametrize("noise_scale", [False, True])
def test_stacked_evidence_is_the_plain_dense_one(noise_scale):
    # the stacked evidence (QR and SVD of whitened columns, ln det and C^-1 G of the
    # parameters on their bounds unrolled over their count) against the plain dense
    # formula, for models with 1, 2 and 3 parameters on a bound (lower or upper), some with
    # those on their bounds nearly collinear and pulled into their range so that the whole
    # space's integral caps the one-sided ones: the same to 1e-12 relative (seen: 7e-14)
    rng = np.random.default_rng(21)
    models, capped = [], 0
    for i in range(36):
        m, k, n = 1 + i % 3, int(rng.integers(2, 5)), 30
        A = rng.standard_normal((n, k + m))
        if i % 2 and m > 1:
            A[:, k + 1 :] = A[:, [k]] + 0.05 * rng.standard_normal((n, m - 1))
        mu, sd = rng.standard_normal(k + m), rng.uniform(0.3, 2.0, k + m)
        x = mu + sd * rng.standard_normal(k + m)
        up = rng.random(m) < 0.5
        lo = np.concatenate([np.full(k, -math.inf), np.where(up, -math.inf, x[k:])])
        hi = np.concatenate([np.full(k, math.inf), np.where(up, x[k:], math.inf)])
        pull = (3.0 if i % 2 else rng.normal(0, 3)) * np.where(up, -1.0, 1.0)
        r = rng.standard_normal(n) * rng.uniform(0.5, 3.0) - A[:, k:] @ pull
        models.append((mu, sd, lo, hi, r, A, x))
    got = laplace_log_evidences(models, noise_scale)
    for g, model in zip(got, models):
        want, cap = dense_log_evidence(*model, noise_scale)
        capped += cap
        assert g == pytest.approx(want, rel=1e-12, abs=1e-9)
    assert capped >= 6


@pytest.mark.parametrize("m", [1, 2, 3, 4, 5])
def test_unrolled_logdet_and_quadratic_are_lapacks(m):
    # ln det C and G^T C^-1 G of C = P + I (P positive semi-definite, eigenvalues from 0 to
    # 1e6, as the parameters on their bounds make it) from the unrolled LDL^T: LAPACK's
    # slogdet and solve to rounding amplified by C's condition, 10 eps cond(C) (absolute for
    # ln det, relative for the quadratic form; seen: at most 2.5 eps cond(C))
    rng = np.random.default_rng(m)
    V = rng.standard_normal((50, m, m))
    P = np.swapaxes(V, 1, 2) * 10.0 ** rng.uniform(-3, 6, (50, 1, m)) @ V
    C = P + np.eye(m)
    G = rng.standard_normal((50, m)) * 10.0 ** rng.uniform(-2, 3, (50, 1))
    pairs = [(j, l) for j in range(m) for l in range(j, m)]
    entries = np.stack([C[:, j, l] for j, l in pairs], axis=1)
    logdet, quad = _logdet_and_quadratic(entries[:, :, None], G[:, :, None], pairs)
    tol = 10 * np.finfo(float).eps * np.linalg.cond(C)
    want = np.einsum("mj,mj->m", G, np.linalg.solve(C, G[..., None])[..., 0])
    assert np.all(np.abs(logdet[:, 0] - np.linalg.slogdet(C)[1]) <= tol)
    assert np.all(np.abs(quad[:, 0] - want) <= tol * want)
