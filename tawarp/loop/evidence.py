"""Bayesian comparison of the models the effects library makes: maximum a posteriori fits,
Laplace log-evidence, posterior model and inclusion probabilities, groups the data cannot
separate.

A *model* is the base fit plus a set of effects (at most one that changes the core's
structure, at most one per physical mechanism: one frame model). Every parameter carries a
Gaussian prior in its scaled fit variable x (:class:`tawarp.model.effects.Param`;
log-normal for log fields), truncated to the fit
bounds: the base fields' priors come from the core file or the documented defaults
(:func:`tawarp.model.priors.prior_for`), an effect's parameters sit around "off" with twice
the effect's typical size as one sd (:func:`tawarp.model.priors.effect_priors`).

**Evidence.** The Laplace approximation of the marginal likelihood at the maximum a
posteriori x* (Tierney & Kadane, JASA 81 (1986) 82; Kass & Raftery, JASA 90 (1995) 773,
Eq. 4; MacKay, *Information Theory, Inference and Learning Algorithms* (2003), Ch. 28):

    ln Z = ln L(x*) + ln pi(x*) + (k/2) ln 2 pi - (1/2) ln det H + ln m,
    H = J^T J + diag(1/sd^2),

with ln L = -chi^2/2 (the Gaussian noise's normalisation, the same for every model, is
left out), pi the truncated-Gaussian prior density and H the Gauss-Newton Hessian of
-ln posterior, m the share of that Gaussian inside the parameters' ranges (per parameter:
1/2 for a one-sided effect fitted at its bound). Parameters the data do not determine get
H = 1/sd^2 and m = 1/2 on a half-normal's bound: their Occam factor is then exactly 1, so
an effect that changes nothing is neither rewarded nor punished beyond its model prior
(``tests/test_evidence.py``).

**Model prior.** Uniform over the number of effects (0 ... ``max_effects``), then uniform
among the models of that size: the multiplicity correction of Scott & Berger, Ann. Stat. 38
(2010) 2587, so that the many three-effect models do not outweigh the few small ones by
their count alone.

**Search (Occam's window, Madigan & Raftery, JASA 89 (1994) 1535).** The evidence of every
subset of the library up to ``max_effects`` is first computed from the quadratic model of
the log posterior at the base solution (:func:`linearized_evidence`: one batched launch for
every effect's sensitivity columns, then only linear algebra per model); the base model,
every single effect and the most probable subsets are then refitted (nonlinear MAP fits, one
lockstep batch), and the posterior is taken over the refitted models, those far outside the
window having negligible mass. A second round linearizes at the most probable refitted
model that can take another effect and refits its most probable supersets.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy import special

from ..fit import lockstep
from ..fit.lm import held_fixed
from ..fit.problem_model import RCOND, ProblemModel, determined_inverse, r_factor
from ..fit.problems import FD_STEP, Sets, param_values, predict_sets, residual
from ..fit.result import FitResult
from ..measure.kind import MeasurementKind
from ..model.effects import Effect, Param
from ..model.priors import effect_priors, prior_for

#: An effect (or a group of effects) is claimed when its posterior inclusion probability is
#: at least this.
CLAIM = 0.95
#: A parameter further than this many prior standard deviations from its prior's centre is
#: in tension with it: a model with such a value is never ``adequate``.
TENSION_Z = 3.0
#: The noise estimated from the data is taken as right within this factor either way
#: (:func:`laplace_log_evidence`).
NOISE_SCALE_RANGE = 30.0
#: The ln s of that marginal's quadrature (uniform; made once: every model's ln Z takes it).
NOISE_LOG_SCALES = np.linspace(-math.log(NOISE_SCALE_RANGE), math.log(NOISE_SCALE_RANGE), 401)
#: Models refitted nonlinearly per round besides the base and the single effects (the most
#: probable by the linearized evidence).
REFITS = 8
#: Occam's window: subsets whose linearized posterior is below this fraction of the best are
#: not refitted.
WINDOW = 1e-3


@dataclass(frozen=True)
class XPrior:
    """A Gaussian prior in a parameter's scaled fit variable x, truncated to [lo, hi]."""

    mu: float
    sd: float
    lo: float = -math.inf
    hi: float = math.inf

    def log_norm(self) -> float:
        """ln of the density's normalisation: -ln sd - ln(2 pi)/2 - ln(prior mass inside the bounds)."""
        return float(log_norms(*prior_arrays([self]))[0])


def prior_arrays(priors: list[XPrior]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(mu, sd, lo, hi) of ``priors``, each (k,)."""
    table = np.array([(p.mu, p.sd, p.lo, p.hi) for p in priors], dtype=float).reshape(-1, 4)
    return tuple(np.ascontiguousarray(table.T))


def log_norms(mu, sd, lo, hi) -> np.ndarray:
    """:meth:`XPrior.log_norm` of priors given as arrays (:func:`prior_arrays`)."""
    mass = special.ndtr((hi - mu) / sd) - special.ndtr((lo - mu) / sd)
    return -np.log(sd) - 0.5 * math.log(2 * math.pi) - np.log(np.maximum(mass, 1e-300))


def x_prior(core, par: Param, declared=None) -> XPrior:
    """The prior of ``par`` in its x: ``declared`` (a :class:`tawarp.model.prior.Prior`) or the
    core file's / default prior of the field it fits."""
    pr = declared if declared is not None else prior_for(core, par.label)
    mu, sd = pr.x_moments(par)
    lo, hi = par.bounds_x()
    return XPrior(float(mu), float(sd), lo, hi)


def model_priors(core, params: list[Param], effects: tuple[Effect, ...]) -> list[XPrior]:
    """The priors of a model's ``params`` (base parameters first, then its effects')."""
    declared = {}
    for e in effects:
        declared.update(effect_priors(e, core))
    return [x_prior(core, par, declared.get(par.label)) for par in params]


def log_erfcx(w: np.ndarray) -> np.ndarray:
    """ln erfcx(w) = w^2 + ln erfc(w), without overflow on either side."""
    w = np.asarray(w, dtype=float)
    return np.where(w >= 0, np.log(special.erfcx(np.maximum(w, 0.0))), w**2 + np.log(special.erfc(np.minimum(w, 0.0))))


def log_sum_exp(a: np.ndarray):
    """ln sum exp(a) over the last axis of a finite ``a``, as :func:`scipy.special.logsumexp`
    computes it (the largest terms apart: ln(m) + ln1p(s/m) + max, s the others' shifted sum,
    m how many are largest), the same number without its array-API dispatch, which cost more
    than the rest of :func:`laplace_log_evidence` on its 401 noise scales. A float for 1-D
    ``a``."""
    top = np.max(a, axis=-1, keepdims=True)
    largest = a == top
    m = np.count_nonzero(largest, axis=-1).astype(float)
    s = np.sum(np.exp(np.where(largest, -np.inf, a) - top), axis=-1)
    out = np.log1p(np.where(s != 0, s / m, s)) + np.log(m) + top[..., 0]
    return float(out) if np.ndim(a) == 1 else out


#: A parameter within this of a bound (in its scaled fit variable x, of order 1) is on it.
ON_BOUND = 1e-9
#: Models whose evidence with the noise scale marginalized is computed in one stacked call at
#: most (:func:`laplace_log_evidences`).
EVIDENCE_BLOCK = 64


def laplace_log_evidence(
    model: ProblemModel,
    r: np.ndarray,
    J: np.ndarray,
    x: np.ndarray,
    noise_scale: bool = False,
    n_residuals: int | None = None,
) -> float:
    """ln Z of the module doc at the maximum a posteriori ``x`` with weighted residuals ``r``
    (in units of the noise) and their Jacobian ``J`` in x, of the fit whose problem is
    ``model`` (:class:`ProblemModel`: its Gaussian priors in x, its fit ranges, and its
    posterior covariance as the Laplace Gaussian's), the Gaussian cut to the parameters'
    ranges (parameter by parameter: 1/2 for a parameter on its bound, a one-sided effect
    fitted at "off"; about 1 far inside: without it a one-sided effect the data barely see
    would gain ln 2 from its half-normal's normalisation alone). A parameter on a bound
    (:data:`ON_BOUND`) is integrated over its own side alone, with the others at their optimum for each of its values: the fit's
    gradient need not vanish there, and the Gaussian of the quadratic model, centred where the
    data would take the parameter beyond its bound, would credit the model with a misfit it
    cannot reach (an effect fitted at "off" gaining evidence from the data's pull away from
    it). That one-sided integral is exact for a linear model with one parameter on its bound;
    with several, each is taken given the free ones only, their product capped by the
    quadratic model's integral over the whole space (a fit stopped away from its optimum is
    otherwise credited with one misfit once per correlated parameter on a bound; at an optimum
    the cap never binds). ``noise_scale``: the noise is an
    estimate known up to a factor s, marginalized with a flat prior in ln s over
    [1/:data:`NOISE_SCALE_RANGE`, :data:`NOISE_SCALE_RANGE`]: ``Z = int Z(s) p(ln s) dln s``,
    each ``Z(s)`` the Laplace evidence at the optimum for that noise (from the quadratic
    model at ``x``; exact for a linear model, ``tests/test_evidence.py``). A noise estimate
    from the data (second differences of a misfitting base fit's residual) is too large
    where the frequency grid is coarse: with it fixed, every misfit below it looks like
    noise, and the choice of model changes with the grid. Only the inner products of ``J``'s
    columns and ``r`` enter: they may be given rotated, ``Q^T J`` and ``Q^T r`` for any Q of
    orthonormal columns whose span holds them (:func:`linearized_evidence`: as many rows as
    columns), with ``n_residuals`` the number of residuals (default ``len(r)``)."""
    return float(laplace_log_evidences([evidence_problem(model, r, J, x)], noise_scale, [n_residuals or len(r)])[0])


def evidence_problem(model: ProblemModel, r: np.ndarray, J: np.ndarray, x: np.ndarray) -> tuple:
    """The (mu, sd, lo, hi, r, J, x) of :func:`laplace_log_evidences` of a fit whose problem
    is ``model`` (its priors and fit ranges in x), at ``x`` with residuals ``r`` and their
    Jacobian ``J``."""
    if model.prior_sd is None or not np.all(np.isfinite(model.prior_sd)):
        raise ValueError(f"laplace_log_evidence: {model.names}: every parameter needs a proper prior")
    lo, hi = model.bounds_x()
    prior = [np.asarray(a, dtype=float) for a in (model.prior_mu, model.prior_sd, lo, hi)]
    return (*prior, np.asarray(r, dtype=float), np.asarray(J, dtype=float), np.asarray(x, dtype=float))


def laplace_log_evidences(models: list[tuple], noise_scale: bool = False, n_residuals=None) -> np.ndarray:
    """:func:`laplace_log_evidence` of many models at once: ``models`` a list of (mu, sd, lo,
    hi, r, J, x), each model's priors in x and their ranges (k,), its weighted residuals (n,),
    their Jacobian (n, k) and its solution (k,); ``n_residuals`` a list (default each
    ``len(r)``). The models with as many rows, parameters and parameters on a bound share
    their linear algebra (stacked LAPACK calls): the 614 models of a linearization
    (:func:`linearized_evidence`) of the loop bench's clean case took 0.25 s one by one on
    a 2-core machine, most of it numpy's per-call cost, and 0.05 s stacked. Inside
    :func:`tawarp.fit.lockstep.run_together` the call waits for the other threads' and
    stacks their models with its own (loops run together: :func:`tawarp.loop.run_loops`):
    each model's ln Z is the one it gets alone, to rounding (tests/test_evidence.py)."""
    n_res = [len(m[4]) for m in models] if n_residuals is None else list(n_residuals)
    return _block_evidences([tuple(np.asarray(a, dtype=float)[None] for a in m) for m in models], noise_scale, n_res)


def _block_evidences(blocks: list[tuple], noise_scale: bool, n_res: list) -> np.ndarray:
    """:func:`laplace_log_evidences` of models given stacked: ``blocks`` a list of (mu, sd,
    lo, hi, r, J, x) with a leading axis over the block's models (each of one shape: (M, k),
    (M, n), (M, n, k)), ``n_res`` one entry per model, in the blocks' order. Inside
    :func:`tawarp.fit.lockstep.run_together` the other threads' requests join the call."""
    together = lockstep.current()
    if together is not None and not together.running:
        return together.call((blocks, bool(noise_scale), n_res), _stacked_evidences, eager=True)
    return _log_evidences(blocks, noise_scale, n_res)


def _stacked_evidences(requests: list[tuple], _state=None) -> list[np.ndarray]:
    """:func:`_block_evidences` of several callers' ``(blocks, noise_scale, n_residuals)``
    requests, those alike in ``noise_scale`` in one call."""
    out: list = [None] * len(requests)
    for scale in (False, True):
        idx = [i for i, req in enumerate(requests) if req[1] == scale]
        if not idx:
            continue
        got = _log_evidences([b for i in idx for b in requests[i][0]], scale, [n for i in idx for n in requests[i][2]])
        k = 0
        for i in idx:
            out[i] = got[k : k + len(requests[i][2])]
            k += len(requests[i][2])
    return out


def _log_evidences(blocks: list[tuple], noise_scale: bool, n_res: list) -> np.ndarray:
    """:func:`_block_evidences` in this thread.

    In the prior-whitened variables t_j = c_j dx_j / sd_j, c_j = 1 for a free parameter and
    its direction into the range for one on a bound, -2 ln posterior's quadratic model is
    the squared norm of [J diag(sd c), r; diag(c), g] [t; 1], g = (x - mu) / sd (the priors
    as K more rows). Only the inner products of its columns enter ln Z: each model is taken
    to the triangular factor of that matrix (of [J diag(sd c), r] alone with ``noise_scale``,
    where the priors weigh differently at each noise scale), its columns ordered free
    parameters first, then those on a bound, then r; the models of one shape (rows,
    parameters) in one stacked QR."""
    out = np.empty(len(n_res))
    n_res = np.asarray(n_res)
    # the blocks of each shape (rows, parameters), with the index of each block's first model
    shapes: dict[tuple[int, int], list[tuple[int, tuple]]] = {}
    start = 0
    for b in blocks:
        shapes.setdefault((b[4].shape[1], b[6].shape[1]), []).append((start, b))
        start += len(b[6])
    for (n, K), group in shapes.items():
        idx = np.concatenate([np.arange(i, i + len(b[6])) for i, b in group])
        M = len(idx)
        # (mu, sd, lo, hi, x) of the models of one shape, (M, 5, K)
        table = np.stack([np.concatenate([b[j] for _, b in group]) for j in (0, 1, 2, 3, 6)], axis=1)
        x, lo, hi = table[:, 4], table[:, 2], table[:, 3]
        # +1 on a lower bound, -1 on an upper one: the direction into the range
        side = np.where(x <= lo + ON_BOUND, 1.0, np.where(x >= hi - ON_BOUND, -1.0, 0.0))
        # each model's parameters reordered: the free ones first, then those on a bound
        order = np.argsort(side != 0, axis=1, kind="stable")
        mu, sd, lo, hi, x = np.take_along_axis(table, order[:, None, :], 2).transpose(1, 0, 2)
        c = np.take_along_axis(np.where(side == 0, 1.0, side), order, 1)
        free = np.count_nonzero(side == 0, axis=1)
        # the matrices transposed, (M, K + 1, rows), each column contiguous: numpy's QR copies
        # them column by column for LAPACK, and the scaling by sd c runs along the columns
        # instead of along many rows of K + 1 (fill, scaling and QR of 888 rows took 30 %
        # less); the blocks copied in, then the columns of the models with parameters on a
        # bound reordered
        At = np.empty((M, K + 1, n if noise_scale else n + K))
        np.concatenate([np.swapaxes(b[5], 1, 2) for _, b in group], out=At[:, :K, :n])
        moved = np.any(order != np.arange(K), axis=1)
        if moved.any():
            At[moved, :K, :n] = At[np.flatnonzero(moved)[:, None], order[moved], :n]
        np.concatenate([b[4] for _, b in group], out=At[:, K, :n])
        At[:, :K, :n] *= (sd * c)[:, :, None]
        if not noise_scale:
            At[:, :K, n:] = c[:, :, None] * np.eye(K)
            At[:, K, n:] = (x - mu) / sd
        Ra = r_factor(np.swapaxes(At, 1, 2))
        norm = np.sum(log_norms(mu, sd, lo, hi), axis=1) + np.sum(np.log(sd), axis=1)
        for kf in dict.fromkeys(free.tolist()):
            rows = np.flatnonzero(free == kf)
            if not noise_scale:
                out[idx[rows]] = _known_noise_group(Ra[rows], sd[rows], lo[rows], hi[rows], x[rows], norm[rows], kf)
                continue
            # in blocks of at most EVIDENCE_BLOCK models (the noise scales' arrays, M x 401
            # x k, of thousands of models stacked would stream from memory)
            for a in range(0, rows.size, EVIDENCE_BLOCK):
                b = rows[a : a + EVIDENCE_BLOCK]
                members = idx[b]
                out[members] = _noise_scale_group(
                    Ra[b], sd[b], lo[b], hi[b], x[b], mu[b], c[b], norm[b], kf, n_res[members]
                )
    return out


def _known_noise_group(Ra, sd, lo, hi, x, norm, k) -> np.ndarray:
    """ln Z of :func:`laplace_log_evidences` (noise known, s = 1) for M models (leading
    axis) whose first ``k`` parameters are free and the others, ``m``, on a bound: ``Ra``
    the triangular factor of [J diag(sd c), r; diag(c), g] (:func:`_log_evidences`), ``norm``
    the priors' ln normalisation plus sum ln sd.

    The factor's blocks are [F, ., .; 0, T, w; 0, 0, rho] (free, on a bound, r). With those
    on a bound at t = 0, the minimum over the free ones is phi = |w|^2 + rho^2, and F^T F =
    J_f^T J_f + I (whitened) is their posterior precision: ln det = 2 sum ln |F_ii|. Along
    the parameters on their bounds, the free ones at their optimum, phi(t) = |T t + w|^2 +
    rho^2: C = T^T T, G = T^T w, ln det C = 2 sum ln |T_jj| and G^T C^-1 G = |w|^2. All by
    orthogonal steps (no cancellation where a parameter sits at a bound with a large
    gradient) and no decomposition per model besides the QR."""
    M, K = x.shape
    F, T, w, rho = Ra[:, :k, :k], Ra[:, k:K, k:K], Ra[:, k:K, K], Ra[:, K, K]
    w2 = np.sum(w**2, axis=1)
    terms = -0.5 * (w2 + rho**2) - np.sum(np.log(np.abs(np.diagonal(F, axis1=1, axis2=2))), axis=1)
    if K > k:
        logdet = 2 * np.sum(np.log(np.abs(np.diagonal(T, axis1=1, axis2=2))), axis=1)
        terms = terms + _orthant(np.einsum("mij,mi->mj", T, w), np.sum(T**2, axis=1), logdet, w2)
    if not k:
        return norm + terms
    # the free parameters' covariance (whitened) is F^-1 F^-T: its diagonal, row norms of F^-1
    var = sd[:, :k] ** 2 * np.sum(np.linalg.inv(F) ** 2, axis=2)
    inside = _inside_mass(var, F, np.zeros(M), np.ones(M), sd[:, :k], x[:, :k], lo[:, :k], hi[:, :k])
    return norm + 0.5 * k * math.log(2 * math.pi) + terms + inside


def _noise_scale_group(Ra, sd, lo, hi, x, mu, c, norm, k, n_residuals) -> np.ndarray:
    """ln Z of :func:`laplace_log_evidences` with the noise scale marginalized for M models
    (leading axis) whose first ``k`` parameters are free and the others, ``m``, on a bound
    (``c``: their directions into the range), with as many residuals each: ``Ra`` the
    triangular factor of [J diag(sd c), r] (:func:`_log_evidences`), ``norm`` the priors'
    ln normalisation plus sum ln sd."""
    M, m = x.shape[0], x.shape[1] - k
    # In the prior-whitened variables d = dx/sd, with J_free = Q R and R = U S W^T, each
    # direction i of W is a one-dimensional problem: at noise s the minimum over d_i of
    # (a_i + S_i d_i)^2 / s^2 + (g_i + d_i)^2 is (a_i - S_i g_i)^2 / (s^2 + S_i^2), with
    # a = U^T Q^T r and g = W^T (x - mu)/sd; the rest of r, outside J_free's range, adds
    # |r_perp|^2/s^2. Written this way every term is a square: no cancellation when a
    # parameter sits at a bound with a large gradient. The triangular factor of
    # [J_free, J_on, r] gives Q^T J_on, Q^T r and, below them, the parts of J_on and r
    # outside J_free's range (whose inner products are all that is needed of them).
    g0 = (x - mu) / sd
    gf, go, so = g0[:, :k], g0[:, k:], c[:, k:]
    R, B, z = Ra[:, :k, :k], Ra[:, :k, k : k + m], Ra[:, :k, k + m]
    rest = np.zeros((M, 1, m + 1)) if Ra.shape[1] <= k else Ra[:, k:, k:]
    if k:
        U, S, Wt = np.linalg.svd(R)
    else:
        U, S, Wt = np.zeros((M, 0, 0)), np.zeros((M, 0)), np.zeros((M, 0, 0))
    alpha = np.einsum("mji,mj->mi", U, z) - S * np.einsum("mij,mj->mi", Wt, gf)
    v = np.einsum("mji,mjl->mil", U, B)  # (M, k, m)
    u = NOISE_LOG_SCALES
    s2 = np.exp(2 * u)  # (ns,)
    rz, Rr = rest[:, :, m], rest[:, :, :m]
    # Every sum over the free directions of a term over s^2 + S_i^2 (phi's alpha_i^2, and for
    # the parameters on a bound G's alpha_i v_ij and C's v_ij v_il, below) is one product with
    # the (M, k, ns) array of their inverses; its (M, ., ns) layout keeps each quantity's
    # noise scales contiguous for the elementwise work that follows.
    pairs = [(j, l) for j in range(m) for l in range(j, m)]
    j1, l1 = [j for j, _ in pairs], [l for _, l in pairs]
    cols = np.concatenate([alpha[:, :, None] ** 2, alpha[:, :, None] * v, v[:, :, j1] * v[:, :, l1]], axis=2)
    S2 = S[:, :, None] ** 2
    Y = np.swapaxes(cols, 1, 2) @ (1.0 / (S2 + s2))  # (M, 1 + m + len(pairs), ns)
    phi = np.sum(rz**2, axis=1)[:, None] / s2 + Y[:, 0] + np.sum(go**2, axis=1)[:, None]
    terms = -0.5 * phi - n_residuals[:, None] * u - 0.5 * np.sum(np.log1p(S2 / s2), axis=1)
    if m:
        # the quadratic model along each parameter j on its bound into its range, t_j >= 0
        # (whitened), the free ones at their optimum: phi(t) = phi(0) + 2 G.t + t^T C t,
        # C = Rr^T Rr / s^2 + sum_i v_i v_i^T / (s^2 + S_i^2) + I (its upper triangle's
        # entries, ``pairs``)
        G = np.einsum("mij,mi->mj", Rr, rz)[:, :, None] / s2 + Y[:, 1 : 1 + m] + (so * go)[:, :, None]  # (M, m, ns)
        C = (
            np.einsum("mij,mij->mj", Rr[:, :, j1], Rr[:, :, l1])[:, :, None] / s2
            + Y[:, 1 + m :]
            + np.equal(j1, l1)[:, None]
        )  # (M, len(pairs), ns)
        logdet, quad = _logdet_and_quadratic(C, G, pairs)
        terms = terms + _orthant(G, C[:, [pairs.index((j, j)) for j in range(m)]], logdet, quad)
    s2_best = s2[np.argmax(terms, axis=1)]
    if k:
        # the free parameters' covariance (whitened) at s2: s2 W diag(1 / (S^2 + s2)) W^T
        var = s2_best[:, None] * sd[:, :k] ** 2 * np.einsum("mij,mi->mj", Wt**2, 1.0 / (S**2 + s2_best[:, None]))
        inside = _inside_mass(var, R, s2_best, s2_best, sd[:, :k], x[:, :k], lo[:, :k], hi[:, :k])
    else:
        inside = np.zeros(M)
    norm = norm + 0.5 * k * math.log(2 * math.pi)
    return norm + log_sum_exp(terms) + math.log(u[1] - u[0]) - math.log(2 * u[-1]) + inside


def _orthant(G, Cjj, logdet, quad) -> np.ndarray:
    """ln of the integral of exp(-(2 G.t + t^T C t) / 2) over the parameters on their bounds,
    t >= 0 (whitened, into their ranges), as the module doc has it: the product of the
    one-dimensional integrals (from ``G`` (M, m, ...) and C's diagonal ``Cjj``), capped by
    the integral over the whole space (from ln det C and G^T C^-1 G, ``logdet`` and
    ``quad``)."""
    m = G.shape[1]
    # each alone: int_0^inf exp(-G t - C t^2 / 2) dt = sqrt(pi / (2 C)) erfcx(G / sqrt(2 C))
    one_sided = np.sum(0.5 * np.log(math.pi / (2 * Cjj)) + log_erfcx(G / np.sqrt(2 * Cjj)), axis=1)
    # an integral over the orthant never exceeds the one over the whole space; the
    # product of the one-dimensional ones can, where parameters on their bounds share
    # a pull into the range (a fit stopped away from its optimum: two correlated
    # columns each credited with the whole of one misfit). At an optimum (every G >= 0)
    # the product is below 2^-m times the whole (Hadamard: det C <= prod C_jj)
    whole = 0.5 * m * math.log(2 * math.pi) - 0.5 * logdet + 0.5 * quad
    return np.minimum(one_sided, whole)


def _logdet_and_quadratic(C, G, pairs) -> tuple[np.ndarray, np.ndarray]:
    """(ln det C, G^T C^-1 G) of symmetric positive definite m x m matrices C given by their
    upper triangles' entries (``C[:, p]`` the entry ``pairs[p]``, each an array over the
    models and noise scales), ``G[:, j]`` likewise, from C = L D L^T (L unit lower
    triangular): ln det C = sum ln D_j, G^T C^-1 G = sum y_j^2 / D_j with L y = G. The
    factorization is unrolled over the few m (at most a handful of parameters on a bound) so
    that every step is one array operation over all models and noise scales: numpy's stacked
    slogdet and solve make a LAPACK call per m x m matrix, M x 401 of them. The C of
    :func:`_noise_scale_group` is at least the identity, so its pivots are at least 1: no
    pivoting is needed, and the result is LU's (LAPACK's) to rounding."""
    m = G.shape[1]
    at = {p: i for i, p in enumerate(pairs)}
    L = [[None] * m for _ in range(m)]  # L[j][l], l < j
    d, y = [], []
    for j in range(m):
        w = []  # w_l = L_jl D_l
        for l in range(j):
            w.append(C[:, at[(l, j)]] - sum(w[i] * L[l][i] for i in range(l)))
            L[j][l] = w[l] / d[l]
        d.append(C[:, at[(j, j)]] - sum(w[l] * L[j][l] for l in range(j)))
        y.append(G[:, j] - sum(L[j][l] * y[l] for l in range(j)))
    logdet = sum(np.log(dj) for dj in d)
    quad = sum(yj**2 / dj for yj, dj in zip(y, d))
    return logdet, quad


def _inside_mass(var, R, shift, s2, sd, x, lo, hi) -> np.ndarray:
    """ln of the share of each Laplace Gaussian (mean ``x``, the free parameters' posterior
    covariance at noise variance ``s2``, with diagonal ``var`` (M, k) in x) that lies in each
    parameter's range [``lo``, ``hi``], parameter by parameter.

    That covariance is :meth:`tawarp.fit.problem_model.ProblemModel.covariance`'s: s^2
    times :func:`tawarp.fit.problem_model.determined_inverse` of A = D^-1 P D^-1, D =
    diag(sd), P = R^T R + ``shift`` I the whitened precision times s^2 (at least s^2 I).
    ``var``, from the callers' factors, is s^2 D P^-1 D's, which is that wherever
    determined_inverse keeps every direction: A scaled to unit diagonal has its eigenvalues
    at least s^2 / max_j P_jj and at most k, so where that bound is above 2 k RCOND none is
    left out; below it (a nearly degenerate pair of strongly determined parameters) the
    model takes determined_inverse itself."""
    P_jj = np.einsum("mij,mij->mj", R, R) + shift[:, None]
    cut = s2 <= 2 * sd.shape[1] * RCOND * np.max(P_jj, axis=1)
    if cut.any():
        Rc, sdc = R[cut], sd[cut]
        P = np.swapaxes(Rc, 1, 2) @ Rc + shift[cut, None, None] * np.eye(sd.shape[1])
        unit, _ = determined_inverse(P / sdc[:, :, None] / sdc[:, None, :])
        var[cut] = s2[cut, None] * np.diagonal(unit, axis1=1, axis2=2)
    s = np.sqrt(np.maximum(var, 1e-300))
    mass = special.ndtr((hi - x) / s) - special.ndtr((lo - x) / s)
    return np.sum(np.log(np.maximum(mass, 1e-300)), axis=1)


def prior_z(x: np.ndarray, priors: list[XPrior]) -> np.ndarray:
    """Shift of ``x`` from each prior's centre, in prior standard deviations."""
    return np.array([(xi - p.mu) / p.sd for xi, p in zip(x, priors)])


@dataclass
class Model:
    """One candidate model: its effects (names, in library order), its MAP fit, the priors
    of its parameters, ln Z and ln P(M); ``probability`` P(M | data) once compared."""

    effects: tuple[str, ...]
    log_evidence: float = -math.inf
    log_model_prior: float = 0.0
    fit: FitResult | None = None
    priors: list[XPrior] = field(default_factory=list)
    probability: float = 0.0

    @property
    def label(self) -> str:
        return "+".join(self.effects) if self.effects else "base"

    @property
    def log_posterior(self) -> float:
        return self.log_evidence + self.log_model_prior

    def z(self) -> dict[str, float]:
        """Each parameter's shift from its prior in prior sds (fitted models)."""
        return dict(zip(self.fit.names, prior_z(self.fit.x[0], self.priors).tolist()))


def combinable(effects: tuple[Effect, ...]) -> bool:
    """Whether ``effects`` make one model: at most one changes the core's structure (two
    structures cannot be combined) and at most one models each physical mechanism
    (:attr:`Effect.mechanism`: a layer has one frame, limp or elastic, not both)."""
    mechanisms = [e.mechanism for e in effects if e.mechanism is not None]
    return sum(e.transform is not None for e in effects) <= 1 and len(set(mechanisms)) == len(mechanisms)


def subsets(library: list[Effect], max_effects: int) -> list[tuple[Effect, ...]]:
    """Every set of at most ``max_effects`` effects of ``library`` that makes one model
    (:func:`combinable`), the empty set first."""
    out = [()]
    for k in range(1, max_effects + 1):
        out += [s for s in itertools.combinations(library, k) if combinable(s)]
    return out


def log_model_prior(sizes: dict[int, int], k: int) -> float:
    """ln P(M) of a model of ``k`` effects: uniform over the sizes present, then over the
    ``sizes[k]`` models of that size (Scott & Berger's multiplicity correction)."""
    return -math.log(len(sizes)) - math.log(sizes[k])


def effect_columns(problem: MeasurementKind, base: FitResult, fixed: dict, library: list[Effect]) -> dict:
    """Sensitivity columns (2 rows, k) of every effect's parameters at the solution ``base``,
    forward differences from "off": the field effects in one launch (in ``base``'s structure;
    one more for each further model of a mechanism),
    each structural effect in its own (none when ``base`` has one: two structures do not
    combine); a structure without parameters has one column, its residual change there."""
    out = {}
    rows = np.arange(problem.y.size)
    # the field effects in as few launches as hold at most one effect per mechanism (two
    # frame models set one field: each needs its own launch)
    launches: list[list[Effect]] = []
    for e in (e for e in library if e.transform is None):
        into = next((g for g in launches if combinable(tuple(g) + (e,))), None)
        if into is None:
            launches.append([e])
        else:
            into.append(e)
    groups = [(base.effect, fields) for fields in launches or [[]]]
    if base.effect is None:
        groups += [(e, [e]) for e in library if e.transform is not None]
    # every launch's sets, predicted in one request (:func:`tawarp.fit.problems.predict_sets`)
    jobs, steps = [], []
    for structure, effects in groups:
        extra = [par for e in effects for par in e.params]
        if not extra:
            if structure is not None:
                # a structure without parameters of its own (another pore shape): its one
                # column is the residual change of the swap at the base solution
                jobs.append(Sets(problem, param_values(base.params, base.x[:1], fixed), 1, structure))
                steps.append(None)
            continue
        allp = base.params + extra
        p0 = len(base.params)
        x = np.concatenate([base.x[0], np.zeros(len(extra))])
        h = np.full(len(extra), FD_STEP)
        hi = np.array([par.bounds_x()[1] for par in extra])
        h[h > hi] *= -1
        X = np.vstack([x[None], x[None] + np.pad(np.diag(h), ((0, 0), (p0, 0)))])
        jobs.append(Sets(problem, param_values(allp, X, fixed), X.shape[0], structure))
        steps.append((effects, h))
    for job, step, Y in zip(jobs, steps, predict_sets(jobs)):
        if step is None:
            out[job.effect.name] = (residual(problem, Y, rows)[0] - base.residuals[0])[:, None]
            continue
        effects, h = step
        R = residual(problem, Y, rows)
        cols = ((R[1:] - R[0]) / h[:, None]).T
        k = 0
        for e in effects:
            out[e.name] = cols[:, k : k + len(e.params)]
            k += len(e.params)
    return out


def visible(effect: Effect, columns: np.ndarray, priors: list[XPrior]) -> bool:
    """Whether ``effect`` can change the data at all: its parameters moved by one prior sd
    change the weighted residuals by more than 1e-6 of the noise (a thermal effect on data
    without heat input cannot; such a model predicts the base's data and is the base)."""
    if not effect.params:  # a structure without parameters: its residual change
        return bool(np.linalg.norm(columns) > 1e-6)
    return bool(np.max(np.linalg.norm(columns, axis=0) * np.array([p.sd for p in priors]), initial=0.0) > 1e-6)


def linearized_evidence(
    at: Model, columns: dict, models: list[tuple[tuple[Effect, ...], list[XPrior]]], noise_scale: bool = False
) -> list[tuple[float, np.ndarray]]:
    """ln Z of each model (its effects and their priors, appended to ``at``'s) from the
    quadratic model of ln posterior at ``at``'s solution: ``||r + J d||^2`` with the base
    columns of ``at``'s Jacobian and each effect's ``columns`` (from "off"; a structure
    without parameters shifts r by its column instead), plus the priors.
    An effect parameter whose optimum leaves its bounds is held on the bound, and the
    Gaussian is cut to the ranges as in :func:`laplace_log_evidence` (``noise_scale`` as
    there).
    Returns (ln Z, x) per model, x the linearized optimum (``at``'s parameters, then the
    effects')."""
    fit = at.fit
    xb = fit.x[0]
    # The base columns, every effect's and the residual rotated once onto their span (Q^T of
    # their thin QR, Q never formed): the models' evidence takes only inner products of them,
    # each model's algebra then on as many rows as there are columns instead of residuals.
    names = list(dict.fromkeys([e.name for effects, _ in models for e in effects]))
    R = r_factor(np.hstack([fit.jacobian[0], fit.residuals[0][:, None]] + [columns[n] for n in names]))
    n_base = len(xb)
    # each effect's columns of R
    span, k = {}, n_base + 1
    for n in names:
        span[n] = list(range(k, k + columns[n].shape[1]))
        k += columns[n].shape[1]
    rb = R[:, n_base]
    # each model's columns of R, the base's then its effects', and the structures without
    # parameters, which move the residuals by their column instead (effect_columns)
    base = list(range(n_base))
    picks = [base + [j for e in fx if e.params for j in span[e.name]] for fx, _ in models]
    moves = [[span[e.name][0] for e in fx if not e.params] for fx, _ in models]
    # the models with as many parameters solve their quadratic models together, their
    # columns gathered from R at once
    by_size: dict[int, list[int]] = {}
    for i, pick in enumerate(picks):
        by_size.setdefault(len(pick), []).append(i)
    blocks, order = [], []
    for size, members in by_size.items():
        C = np.ascontiguousarray(np.moveaxis(R[:, np.array([picks[i] for i in members])], 0, 1))
        r0 = np.repeat(rb[None], len(members), axis=0)
        for j, i in enumerate(members):
            for col in moves[i]:
                r0[j] = r0[j] + R[:, col]
        mu, sd, lo, hi = _prior_table([models[i][1] for i in members])
        x0 = np.zeros((len(members), size))
        x0[:, :n_base] = xb
        x = _quadratic_optima(mu, sd, lo, hi, r0, C, x0, n_base)
        # the columns are linear, so the quadratic model at x is each model's own
        blocks.append((mu, sd, lo, hi, r0 + (C @ (x - x0)[:, :, None])[:, :, 0], C, x))
        order += members
    logz = _block_evidences(blocks, noise_scale, [len(fit.residuals[0])] * len(models))
    out: list = [None] * len(models)
    for i, z, xi in zip(order, logz.tolist(), (row for b in blocks for row in b[6])):
        out[i] = (z, xi)
    return out


def _prior_table(priors: list[list[XPrior]]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(mu, sd, lo, hi), each (M, k), of the priors of M models of k parameters. The models
    of a linearization share their XPrior objects (the anchor's, each effect's): each
    distinct object is read once, the objects told apart by id (they are all alive in
    ``priors`` meanwhile, so no two share one); a row per model from :func:`prior_arrays`
    took five times as long."""
    ids = np.array([list(map(id, p)) for p in priors], dtype=np.int64)
    _, first, inverse = np.unique(ids, return_index=True, return_inverse=True)
    k = ids.shape[1]
    table = np.array(prior_arrays([priors[f // k][f % k] for f in first.tolist()]))
    return tuple(table[:, inverse.reshape(ids.shape)])


def _quadratic_optima(mu, sd, lo, hi, r0, C, x0, n_base: int) -> np.ndarray:
    """The minima of ``||r0 + C d||^2`` plus the priors over x = x0 + d, for M models of as
    many parameters k (``mu``, ``sd``, ``lo``, ``hi``, ``x0`` (M, k), ``r0`` (M, n), ``C``
    (M, n, k)), an effect parameter whose optimum leaves its range held on its bound (the
    furthest out first, then solved again: an active set; the first ``n_base``, the base
    parameters, are inside at the solution); returns x (M, k) clipped to the ranges."""
    isd2 = sd**-2
    k = x0.shape[1]
    G = np.swapaxes(C, 1, 2) @ C + isd2[:, :, None] * np.eye(k)
    b = np.einsum("mij,mi->mj", C, r0) + isd2 * (x0 - mu)
    free = np.ones(x0.shape, dtype=bool)
    todo = np.arange(len(x0))
    x = x0.copy()
    while todo.size:
        f = free[todo]
        # (d = 0 where held; none is in the first pass, which takes every model, and one at
        # least in every model of a later one)
        Gf, bf = (G, b) if f.all() else held_fixed(G[todo], b[todo], f)
        xt = x0[todo] + np.linalg.solve(Gf, -bf[:, :, None])[:, :, 0]
        x[todo] = xt
        lot, hit = lo[todo], hi[todo]
        bad = f & ((xt < lot) | (xt > hit))
        bad[:, :n_base] = False
        again = bad.any(axis=1)
        worst = np.argmax(np.where(bad, np.maximum(lot - xt, xt - hit), -np.inf), axis=1)
        free[todo[again], worst[again]] = False
        todo = todo[again]
    return np.clip(x, lo, hi)


def posterior(models: list[Model]) -> None:
    """P(M | data) of each model, in place (a softmax of ln Z + ln P(M))."""
    lp = np.array([m.log_posterior for m in models])
    w = np.exp(lp - special.logsumexp(lp))
    for m, p in zip(models, w):
        m.probability = float(p)


def inclusion(models: list[Model], names: list[str]) -> dict[str, float]:
    """Posterior inclusion probability of each effect: the mass of the models holding it (at
    most 1: a sum of the normalized probabilities can round above it)."""
    return {n: min(1.0, float(sum(m.probability for m in models if n in m.effects))) for n in names}


def any_of(models: list[Model], group) -> float:
    """Posterior probability that at least one effect of ``group`` is in the model (at most 1,
    as :func:`inclusion`)."""
    return min(1.0, float(sum(m.probability for m in models if set(m.effects) & set(group))))


def claims(
    models: list[Model], names: list[str], level: float = CLAIM, max_group: int = 3
) -> tuple[list[str], list[list[str]]]:
    """Effects claimed alone (inclusion >= ``level``) and groups: effects the data cannot
    separate, each below ``level`` alone but with at least one of them in the model with
    probability >= ``level`` (built greedily from the most probable, each member adding to
    the joint probability; at most ``max_group`` members)."""
    inc = inclusion(models, names)
    alone = [n for n in names if inc[n] >= level]
    groups = []
    rest = sorted((n for n in names if n not in alone and inc[n] >= 0.05), key=lambda n: -inc[n])
    used: set = set()
    for first in rest:
        if first in used:
            continue
        group = [first]
        while any_of(models, group) < level and len(group) < max_group:
            gains = [
                (any_of(models, group + [n]) - any_of(models, group), n)
                for n in rest
                if n not in group and n not in used
            ]
            if not gains or max(gains)[0] < 0.01:
                break
            group.append(max(gains)[1])
        if len(group) > 1 and any_of(models, group) >= level:
            groups.append(sorted(group, key=names.index))
            used.update(group)
    return alone, groups
