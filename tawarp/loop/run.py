"""The loop (steps of the package doc :mod:`tawarp.loop`): the paper's base fit under the
priors, the Bayesian comparison of the library's models (:func:`compare_models`: the
search and the refits; the evidence itself in :mod:`.evidence`), the posterior predictive
checks, prior tension, the verdict, the next measurement and the drift of h."""

from __future__ import annotations

import contextlib
import copy
import functools
import gc
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..fit.lockstep import run_together
from ..fit.problems import Families, fit_batch, fit_one
from ..fit.result import FitResult
from ..measure.impedance import ImpedanceKind
from ..measure.kind import MeasurementKind
from ..model.effects import Effect, Param, base_params
from ..model.forward import ForwardSettings
from ..model.layer import jca_equivalent
from ..progress import progress_bar
from .goodness import NOISE_ESTIMATE, goodness_of_fit, noise_sigma, residual_location, residual_structure
from .evidence import (
    REFITS,
    TENSION_Z,
    WINDOW,
    Model,
    XPrior,
    any_of,
    claims,
    effect_columns,
    inclusion,
    evidence_problem,
    laplace_log_evidences,
    linearized_evidence,
    log_model_prior,
    model_priors,
    posterior,
    prior_arrays,
    subsets,
    visible,
)
from .nesting import GAIN, map_cost, share_optima
from .plans import next_measurement
from .records import Candidate, LoopReport, ModelsCompared, step_label

#: Effects per model: every subset of the library up to this size is compared.
MAX_EFFECTS = 3
#: A base fit whose reduced chi^2 exceeds this (its error more than 5 noise floors) and
#: whose best model does not bring it to the noise is the wrong model (another core,
#: another material, a geometry the core file does not describe).
WRONG_MODEL_CHI2 = 25.0
#: Iteration cap and step tolerance of the loop's LM fits (a misfitting model crawls along
#: a valley: 1e-8 in the scaled variables is far below any parameter's uncertainty).
MAX_ITER = 40
XTOL = 1e-8
#: The models' fits (:func:`fit_models`) stop where the Gauss-Newton step would lower their
#: posterior cost (chi^2 plus the priors' squares) by less than this
#: (:meth:`tawarp.fit.lm.NewtonSteps.decrement`), at most 0.01 posterior sd from the minimum: the
#: gradient-cosine test alone (GTOL) went on for 5-20 % of the loop bench's fit iterations
#: below that. There no model's ln Z moved by more than 0.007 and no model or inclusion
#: probability by more than 4e-4; at 1e-3 (0.03 sd) the Laplace terms' change over that
#: distance moved ln Z by up to 0.05.
DECREMENT = 1e-4
#: The starts of the refits race (:func:`fit_models`): from iteration RACE_AFTER on, a start
#: stops when its posterior cost (chi^2 plus the priors' squares) is more than RACE_MARGIN
#: above the best start of its model and its last iteration's decrease, kept up for RACE_PACE
#: iterations, would not close that gap, but only in a model whose best start is more than
#: RACE_HOPELESS above the best model of the same number of effects in the batch (odds below
#: e^-25 against it): each size's leader (the next round's anchors) and every model that can
#: matter keep all their starts. Most of a batch's work went to misfitting models whose starts
#: crawl to MAX_ITER. On the bench's cases and the loop tests' no model with a posterior
#: probability above 1e-12 and no size's leader changed its evidence by more than 1e-4;
#: racing from the third iteration without the pace test changed the leader of the single
#: effects on the measured foam's impedance (a start that crawls to the best optimum).
RACE_AFTER = 5
RACE_MARGIN = 10.0
RACE_PACE = 5.0
RACE_HOPELESS = 50.0
#: A whole model stops, its best start too, when it is out of reach: not its size's leader,
#: and no start of it, after RACE_PACE more iterations at that start's last pace, would
#: bring the log-likelihood ratio of its cost to the batch's best cost F*,
#: ``(n/2) ln(F / F*)``, within RACE_OUT (n residuals: the likelihood with the noise level
#: free, the smaller of the two readings of a cost gap). The Occam factors of models of at
#: most three effects differ by far less (each well determined parameter costs about
#: ln(prior sd / posterior sd), ~10), so such a model's posterior probability is 0 to double
#: precision; its evidence is reported at the point where it stopped. A data set with one
#: strong effect left every other single effect 2000 below it, each crawling to MAX_ITER.
RACE_OUT = 250.0
#: A refit's start stops where its Gauss-Newton model and that of a start of its model at
#: a lower cost predict one minimum, in place within MERGE posterior standard deviations
#: and in cost (:func:`tawarp.fit.lm.stop_tests`): both descend into it, at one ln Z.
#: A model's starts mostly do: half of the refits' iterations went to starts that ended
#: within 1e-3 in cost of their model's best. The predictions meet before the points do
#: (at 0.1 sd between the points a start stopped three or four iterations before its
#: end), and the tests of cost, not the distance, bind: 30 sd stopped no more starts.
MERGE = 10.0


def library_for(problem: MeasurementKind) -> list[Effect]:
    """The candidate effects of a kind (:meth:`MeasurementKind.effect_library`: 2-port data,
    a rigid-backed layer's impedance; none for other kinds)."""
    return problem.effect_library()


def refit_starts(e: Effect) -> list[np.ndarray]:
    """Start points (the effect's fit variables) of its refits, all in one batch: off; its
    typical size where it has several parameters (at "off" the others can be undetermined:
    an exchanger of zero length has no porosity); and its own further ``starts`` (a fit from
    "off" that stays in a local minimum, the elastic frame)."""
    points = [{}] + ([e.typical] if len(e.params) > 1 and e.typical else []) + list(e.starts)
    return [np.array([float(par.x_of(pt.get(par.label, par.start))) for par in e.params]) for pt in points]


def base_names(problem: MeasurementKind) -> list[str]:
    """The paper's full base fit of the kind (:meth:`MeasurementKind.base_names`), less the
    names in the core's ``[fit] pinned`` list, which stay at their core values."""
    return [n for n in problem.base_names() if n not in problem.core.pinned]


def default_base_params(problem: MeasurementKind, names=None) -> list[Param]:
    """Fit parameters for ``names`` (default :func:`base_names`), scaling and bounds from
    :mod:`tawarp.model.fields`, each also setting the parameters the kind ties to it
    (:meth:`MeasurementKind.ties`) that are not fitted on their own."""
    names = list(names if names is not None else base_names(problem))
    ties = {k: v for k, v in problem.ties().items() if k in names and not set(v) & set(names)}
    return base_params(problem.core, names, ties)


def fit_base(
    problem: MeasurementKind, params: list[Param], fixed: dict | None = None, priors: list | None = None
) -> FitResult:
    """The base fit; where the kind has first-step rows (a core's Q = 0 rows) and heat
    inputs, the paper's two steps: the geometry on those rows first (the h's do not act
    there), then everything together from there.
    ``priors``: (mu, sd) in x per parameter (a MAP fit), or None (least squares)."""
    hs = [par.label.endswith(".h") for par in params]
    Q0 = problem.first_step_rows()
    if any(hs) and not all(hs) and 0 < Q0.size < problem.y.size:
        geo = [par for par, h in zip(params, hs) if not h]
        geo_prior = None if priors is None else [tuple(a[[not h for h in hs]] for a in priors[0])]
        step1 = fit_one(problem, geo, fixed, rows=Q0, max_iter=MAX_ITER, xtol=XTOL, priors=geo_prior)
        x0, it = np.zeros(len(params)), iter(step1.x[0])
        for j, h in enumerate(hs):
            if not h:
                x0[j] = next(it)
        return fit_one(problem, params, fixed, x0=x0, max_iter=MAX_ITER, xtol=XTOL, priors=priors)
    return fit_one(problem, params, fixed, max_iter=MAX_ITER, xtol=XTOL, priors=priors)


def noise_weighted(problem: MeasurementKind, sigma: np.ndarray) -> MeasurementKind:
    """A view of ``problem`` whose weights are divided by the estimated noise ``sigma`` (per
    real residual, :func:`tawarp.loop.goodness.noise_sigma`): residuals in units of the
    noise, as the likelihood of every model needs them."""
    out = copy.copy(problem)
    n = problem.y.size
    out.w = problem.w / np.stack([sigma[:n], sigma[n:]], -1)
    out.has_sigma = True
    return out


def drift(
    problem: MeasurementKind, base_params: list[Param], sol: FitResult, fixed: dict, effect: Effect | None
) -> dict | None:
    """h's refitted at each heat input alone (all heat inputs in one batch), the rest fixed
    at ``sol``: their ``values`` and ``std`` per heat input, ``relative_spread`` (range over
    mean) and ``consistency_p``, whether each h is one value at every heat input
    (:func:`split_score_p` at ``sol``), per h."""
    hp = [par for par in base_params if par.label.endswith(".h")]
    Qs = problem.heat_groups()
    if not hp or len(Qs) < 2:
        return None
    fx = dict(fixed)
    for par in sol.params:
        if par not in hp:
            par.assign(float(sol.value_dict()[par.label]), fx)
    hp_start = [par.with_start(sol.value_dict()[par.label]) for par in hp]
    fits = fit_batch(
        problem,
        [(hp_start, effect, None, np.flatnonzero(problem.group == q)) for q in Qs],
        fx,
        max_iter=MAX_ITER,
        xtol=XTOL,
    )
    out = {par.label: [f.value_dict()[par.label] for f in fits] for par in hp}
    std = {k: [f.std_dict()[k] for f in fits] for k in out}
    res = {"Q_W": [float(q) for q in Qs], "values": out, "std": std}
    res["relative_spread"] = {k: float(np.ptp(v) / np.mean(v)) if np.mean(v) else None for k, v in out.items()}
    labels = np.concatenate([problem.group, problem.group])  # (the residuals: real parts, then imaginary)
    res["consistency_p"] = {
        k: split_score_p(
            sol.jacobian[0],
            sol.residuals[0],
            float(sol.s2[0]),
            sol.problem_model.precision(),
            labels,
            Qs,
            sol.names.index(k),
        )
        for k in out
    }
    return res


def split_score_p(
    J: np.ndarray, r: np.ndarray, s2: float, precision: np.ndarray, labels: np.ndarray, levels, column: int
) -> float | None:
    """The p-value of Rao's score test (Rao 1948; Buse 1982) of a fit's parameter ``column``
    taking one value at every level of ``labels`` against one value per level, at the fit:
    ``J`` (n, p) the Jacobian of its weighted residuals ``r`` (n,) in x, ``s2`` their
    variance scale, ``precision`` (p,) the priors' (0: none), ``labels`` (n,) each
    residual's level, ``levels`` those to split (the first the reference). The statistic
    g^T S^-1 g, with g the gradient of the misfit in the split parameters and S their
    information after the fit's own parameters take their share, is chi^2 with
    len(levels) - 1 degrees of freedom when the value is one. None where the split is not
    determined (a level without residuals the parameter moves, or fewer than two)."""
    from scipy.stats import chi2

    add = np.stack([J[:, column] * (labels == q) for q in levels[1:]], 1) if len(levels) > 1 else None
    if add is None or not np.all(np.any(add != 0.0, axis=0)) or not np.any(J[labels == levels[0], column]):
        return None
    info = J.T @ J / s2 + np.diag(precision)
    cross = J.T @ add / s2
    schur = add.T @ add / s2 - cross.T @ np.linalg.lstsq(info, cross, rcond=None)[0]
    g = add.T @ r / s2
    try:
        stat = float(g @ np.linalg.solve(schur, g))
    except np.linalg.LinAlgError:
        return None
    return float(chi2.sf(stat, len(levels) - 1)) if np.isfinite(stat) and stat >= 0.0 else None


#: What the report's ``method`` says of the comparison.
METHOD = (
    "Bayesian model comparison: every parameter has a Gaussian prior in its fit variable (log-normal for log "
    "fields; the core file's declared uncertainty or the documented default; an effect's parameters around off "
    "with twice its typical size as one sd); fits are maximum a posteriori; each model (the base plus a set of effects) is scored "
    "by its Laplace log-evidence ln L(x*) + ln pi(x*) + k/2 ln 2 pi - 1/2 ln det H (Kass & Raftery 1995), with "
    "the model prior uniform over the number of effects and within it (Scott & Berger 2010); every subset up to "
    "the largest size is linearized at the base solution, the base, every single effect and the most probable "
    "others refitted (Occam's window, Madigan & Raftery 1994). An effect is claimed when its posterior inclusion "
    "probability is >= 0.95, effects the data cannot separate as a group whose joint probability is >= 0.95, "
    "and only when the most probable model passes the posterior predictive checks (chi^2 and whiteness of the "
    "residual under the noise model) with no parameter more than 3 prior sd from its prior."
)


#: The loop's stages, in order, as its progress bar names them.
STAGES = ("base fit", "evidence", "checks", "drift")


def _as_pairs(priors: list[XPrior]) -> tuple[np.ndarray, np.ndarray]:
    return np.array([p.mu for p in priors]), np.array([p.sd for p in priors])


def out_of_reach(cost, best, n_residuals: int):
    """Whether the MAP cost ``cost`` (or each of an array) is out of reach of the best cost
    ``best`` on ``n_residuals`` real residuals: their log-likelihood ratio
    ``(n/2) ln(cost / best)`` exceeds :data:`RACE_OUT` (never where it is undefined: a cost
    extrapolated below 0)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return 0.5 * n_residuals * np.log(np.asarray(cost) / best) > RACE_OUT


def start_race(owner: np.ndarray, sizes: np.ndarray, n_residuals: int, reference: dict | None = None):
    """The ``drop`` of :func:`tawarp.fit.lm.levenberg_marquardt` for a batch of starts (fit i
    a start of model ``owner[i]``, which has ``sizes[owner[i]]`` effects) on ``n_residuals``
    real residuals: the race of :data:`RACE_AFTER` and :data:`RACE_OUT`. ``reference``:
    {number of effects: the lowest posterior cost of the models of that size fitted before
    this batch} (:func:`race_reference`), which lead their size and set the best cost
    beside the batch's own (a refit of models already compared races against them all)."""
    state = {"calls": 0, "last": None}
    reference = reference or {}

    def drop(slots: np.ndarray, cost: np.ndarray) -> np.ndarray:
        last, state["last"] = state["last"], np.array(cost)
        state["calls"] += 1
        if state["calls"] < RACE_AFTER:
            return np.zeros(slots.size, dtype=bool)
        best = np.full(sizes.size, np.inf)
        np.minimum.at(best, owner, cost)
        # each model's leader: the lowest cost of its size, in this batch or before it
        lead = np.array([reference.get(k, np.inf) for k in range(sizes.max(initial=0) + 1)])
        np.minimum.at(lead, sizes, best)
        leader = lead[sizes]
        top = min(best.min(), min(reference.values(), default=np.inf))
        m = owner[slots]
        gap = cost[slots] - best[m]
        # inf - inf: a start whose every trial failed (NaN: never dropped for it)
        with np.errstate(invalid="ignore", divide="ignore"):
            pace = (last - cost) * RACE_PACE
            # a model is within reach while any of its starts, at its pace, would get there
            reach = np.full(sizes.size, np.nan)
            np.fmin.at(reach, owner, cost - pace)
            out = out_of_reach(reach, top, n_residuals)
            hopeless = (gap > RACE_MARGIN) & (pace[slots] < gap) & (best[m] > leader[m] + RACE_HOPELESS)
        return hopeless | (out[m] & (best[m] > leader[m]))

    return drop


def fit_models(
    problem: MeasurementKind,
    base_params: list[Param],
    fixed: dict,
    library: list[Effect],
    requests: list[tuple[tuple[str, ...], list[np.ndarray]]],
    sizes: dict[int, int],
    noise_scale: bool = False,
    known: list[Model] = (),
    priors_of: Callable[[tuple[str, ...]], list[XPrior]] | None = None,
) -> list[Model]:
    """MAP fits of the models ``requests`` = [(effect names, [start x, ...]), ...] in one
    lockstep batch (every start of every model, racing: :data:`RACE_AFTER`, against the
    models ``known`` too: :func:`race_reference`); per model the
    start with the highest Laplace ln Z is kept (the posterior objective would pick the same optimum, but with an
    estimated noise the data's weight depends on that estimate), and its model prior set from the
    number of models of each size ``sizes`` (``noise_scale``: the noise is an estimate,
    :func:`laplace_log_evidence`). ``priors_of``: the priors of a model's parameters by its
    effect names (default :func:`model_priors`; :meth:`Comparison.priors_of` keeps them)."""
    by_name = {e.name: e for e in library}
    specs, priors, owner = [], [], []
    out = []
    for k, (names, starts) in enumerate(requests):
        effects = tuple(by_name[n] for n in names)
        params = list(base_params) + [par for e in effects for par in e.params]
        structure = next((e for e in effects if e.transform is not None), None)
        pri = priors_of(names) if priors_of is not None else model_priors(problem.core, params, effects)
        # a prior's range is its parameter's fit range (x_prior)
        _, _, lo, hi = prior_arrays(pri)
        out.append(Model(names, priors=pri, log_model_prior=log_model_prior(sizes, len(names))))
        for x0 in starts:
            specs.append((params, structure, np.clip(x0, lo, hi)))
            priors.append(_as_pairs(pri))
            owner.append(k)
    race = start_race(
        np.array(owner), np.array([len(names) for names, _ in requests]), 2 * problem.y.size, race_reference(known)
    )
    fits = fit_batch(
        problem,
        specs,
        fixed,
        max_iter=MAX_ITER,
        xtol=XTOL,
        priors=priors,
        drop=race,
        decrement=DECREMENT,
        starts=np.array(owner),
        merge=MERGE,
    )
    # fit_batch returns None for a start that stopped dropped or merged beside a start of its
    # model that did neither; a model out of reach (RACE_OUT) has only dropped starts, all
    # returned: its best as it stopped
    kept = [[f for f, o in zip(fits, owner) if o == k and f is not None] for k in range(len(out))]
    scores = iter(_log_evidences([f for fs in kept for f in fs], noise_scale))
    for m, fs in zip(out, kept):
        scored = [(next(scores), f) for f in fs]
        m.log_evidence, m.fit = max(scored, key=lambda t: t[0])
    return out


def race_reference(models: list[Model]) -> dict[int, float]:
    """{number of effects: the lowest posterior cost (chi^2 plus the priors' squares,
    :func:`tawarp.loop.nesting.map_cost`) of the fitted ``models`` of that size}: the
    ``reference`` of :func:`start_race`."""
    out: dict[int, float] = {}
    for m in models:
        cost = map_cost(m.fit.residuals[0], m.fit.x[0], m.priors)
        out[len(m.effects)] = min(out.get(len(m.effects), np.inf), cost)
    return out


def _log_evidences(fits: list[FitResult], noise_scale: bool) -> list[float]:
    """:func:`laplace_log_evidence` of each MAP fit of ``fits`` on its own problem model (the
    priors it was fitted under, its covariance), all in one call."""
    problems = [evidence_problem(f.problem_model, f.residuals[0], f.jacobian[0], f.x[0]) for f in fits]
    return laplace_log_evidences(problems, noise_scale).tolist()


def _typical_x(e: Effect) -> np.ndarray:
    """An effect's fit variables at its typical size."""
    return np.array([float(par.x_of(e.typical.get(par.label, par.start))) for par in e.params])


def _effect_parts(x: np.ndarray, n_base: int, effects: list[Effect]) -> dict[str, np.ndarray]:
    """{effect name: its fit variables} of ``x``, which holds the base parameters and then
    the parameters of ``effects`` in that order."""
    out, k = {}, n_base
    for e in effects:
        out[e.name] = x[k : k + len(e.params)]
        k += len(e.params)
    return out


def _starts(at: Model, n_base: int, effects: tuple[Effect, ...], x_lin: np.ndarray | None) -> list[np.ndarray]:
    """Starts of the refit of the model of ``effects``, which extends ``at`` (the base, or
    the best model so far): ``at``'s solution with its own effects at their fitted values and
    the others off (for a single effect also its further ``starts`` and, where it has
    several parameters, its typical size: at "off" the others can be undetermined; beside
    others, each new effect's own ``starts``); the base parameters at the core file's values with every effect at its typical size (a strong
    effect pulls the base fit away from where the augmented optimum lies, and a descent
    from there can stay in that valley); and the linearized optimum."""
    own = _effect_parts(at.fit.x[0], n_base, [e for e in effects if e.name in at.effects])
    base_x = at.fit.x[0][:n_base]
    parts = [own.get(e.name, np.zeros(len(e.params))) for e in effects]
    out = [np.concatenate([base_x] + parts)]
    if len(effects) == 1:
        out += [np.concatenate([base_x, x]) for x in refit_starts(effects[0])[1:]]
    else:
        # an effect whose descent from "off" stays at its bound does so beside others too
        for k, e in enumerate(effects):
            if e.starts and e.name not in at.effects:
                out += [
                    np.concatenate([base_x] + parts[:k] + [x] + parts[k + 1 :])
                    for x in refit_starts(e)[-len(e.starts) :]
                ]
    out.append(np.concatenate([np.zeros(n_base)] + [_typical_x(e) for e in effects]))
    if x_lin is not None:
        out.append(x_lin)
    return out


@dataclass
class Comparison:
    """What the rounds of :func:`compare_models` share: the problem (residuals in units of
    the noise), the base parameters, the fixed values, the visible ``library``, the number
    of models of each size ``sizes`` (the model prior) and ``noise_scale`` (the noise is an
    estimate, :func:`laplace_log_evidence`)."""

    problem: MeasurementKind
    base_params: list[Param]
    fixed: dict
    library: list[Effect]
    sizes: dict[int, int]
    noise_scale: bool
    #: {effect names: the priors of that model's parameters} (:meth:`priors_of`)
    priors: dict[tuple[str, ...], list[XPrior]] = field(default_factory=dict)

    @property
    def n_base(self) -> int:
        return len(self.base_params)

    def priors_of(self, names: tuple[str, ...]) -> list[XPrior]:
        """:func:`model_priors` of the model of the effects ``names`` (the base parameters,
        then each effect's), made once per model: they depend on the core, the base
        parameters and those effects alone, all fixed within a comparison, and a model is
        scored and refitted in several rounds."""
        if names not in self.priors:
            effects = tuple(self.effect(n) for n in names)
            params = self.base_params + [par for e in effects for par in e.params]
            self.priors[names] = model_priors(self.problem.core, params, effects)
        return self.priors[names]

    def effect(self, name: str) -> Effect:
        return next(e for e in self.library if e.name == name)

    def out_of_reach(self, cost: float, best: float) -> bool:
        """:func:`out_of_reach` of the MAP cost ``cost`` against the best ``best``, on this
        problem's residuals."""
        return bool(out_of_reach(cost, best, 2 * self.problem.y.size))

    def linearize(self, at: Model, candidates: list[tuple[Effect, ...]], cols: dict | None = None) -> list[Candidate]:
        """Each of ``candidates`` (sets of effects that contain ``at``'s) scored at ``at``'s
        solution (a structural effect added only at a model without one; a model with one
        takes field effects beside it); ``cols`` the effects' sensitivity columns there, when
        known."""
        structure = at.fit.effect
        cand = [
            c
            for c in candidates
            if structure is None or not any(e.transform is not None and e.name not in at.effects for e in c)
        ]
        cols = cols or effect_columns(
            self.problem, at.fit, self.fixed, [e for e in self.library if e.name not in at.effects]
        )
        extra = [tuple([e for e in c if e.name not in at.effects]) for c in cand]
        # an effect's priors are its own (:func:`model_priors`): those of its one-effect model
        # past the base parameters
        added = {e.name for ex in extra for e in ex}
        own = {n: self.priors_of((n,))[self.n_base :] for n in added}
        pri = [at.priors + [p for e in ex for p in own[e.name]] for ex in extra]
        lin = linearized_evidence(at, cols, list(zip(extra, pri)), self.noise_scale)
        own_effects = [self.effect(n) for n in at.effects]
        log_prior = {k: log_model_prior(self.sizes, k) for k in self.sizes}
        out = []
        for c, ex, (logz, x) in zip(cand, extra, lin):
            names = tuple([e.name for e in c])
            if own_effects:
                # x holds at's parameters, then the extra effects': taken to the model's own
                # order (at the base, with no effects of its own, that is x's)
                parts = _effect_parts(x, self.n_base, own_effects + list(ex))
                x = np.concatenate([x[: self.n_base]] + [parts[n] for n in names])
            out.append(Candidate(names, logz + log_prior[len(names)], x))
        return out

    def request(self, at: Model, names: tuple[str, ...], x_lin: np.ndarray | None) -> tuple:
        """The refit of the model ``names`` from :func:`_starts` at ``at``."""
        return names, _starts(at, self.n_base, tuple(self.effect(n) for n in names), x_lin)

    def refit(self, requests: list, known: list[Model] = ()) -> list[Model]:
        """:func:`fit_models` of ``requests``, racing against the models ``known``."""
        return fit_models(
            self.problem,
            self.base_params,
            self.fixed,
            self.library,
            requests,
            self.sizes,
            self.noise_scale,
            known,
            self.priors_of,
        )


def compare_models(
    problem: MeasurementKind,
    base: Model,
    base_params: list[Param],
    fixed: dict,
    library: list[Effect],
    max_effects: int = MAX_EFFECTS,
    refits: int = REFITS,
    noise_scale: bool = False,
) -> tuple[list[Model], ModelsCompared]:
    """The models of the library up to ``max_effects`` effects compared by their evidence
    (module :mod:`.evidence`): linearized at the base solution for every subset, the base,
    every single effect and the ``refits`` most probable others refitted; then linearized at
    the most probable refitted model that can take another effect and at the most probable
    single effect, and the most probable supersets of each refitted (``noise_scale``: the
    noise is an estimate, known up to a factor). Returns the refitted models (posterior probabilities set, most probable
    first) and what was compared."""
    at_base = effect_columns(problem, base.fit, fixed, library)
    hidden = [
        e.name for e in library if not visible(e, at_base[e.name], model_priors(problem.core, list(e.params), (e,)))
    ]
    library = [e for e in library if e.name not in hidden]
    sets = subsets(library, max_effects)
    sizes: dict[int, int] = {}
    for s_ in sets:
        sizes[len(s_)] = sizes.get(len(s_), 0) + 1
    base.log_model_prior = log_model_prior(sizes, 0)
    cmp = Comparison(problem, list(base_params), fixed, library, sizes, noise_scale)

    # first round: every subset linearized at the base solution; the base, every single
    # effect and the most probable others (inside Occam's window) refitted
    lin = sorted(cmp.linearize(base, [s_ for s_ in sets if s_], at_base), key=lambda c: -c.log_posterior)
    singles = {(e.name,) for e in library}
    best_lin = max((c.log_posterior for c in lin), default=-math.inf)
    top = [c for c in lin if c.effects not in singles and c.log_posterior >= best_lin + math.log(WINDOW)][:refits]
    lin_x = {c.effects: c.x for c in lin}
    requests = [cmp.request(base, (e.name,), lin_x.get((e.name,))) for e in library]
    requests += [cmp.request(base, c.effects, c.x) for c in top]
    models = [base] + cmp.refit(requests)
    counts = ModelsCompared(len(sets), len(lin) + 1, len(models), hidden)
    posterior(models)
    # second round: linearized again at the most probable model that can take another
    # effect and at the most probable single effect (far from the base, as a strong effect
    # leaves it, the first round's quadratic model is poor, and a weaker effect is found
    # only beside the strong ones; a best model already of the largest size has no
    # supersets, and the one just below it is where a third effect is looked for)
    growable = [m for m in models if 0 < len(m.effects) < max_effects]
    best = max(growable, key=lambda m: m.probability, default=None)
    single = max((m for m in growable if len(m.effects) == 1), key=lambda m: m.probability, default=None)
    anchors = [m for m in (best, single) if m is not None]
    anchors = [m for k, m in enumerate(anchors) if m not in anchors[:k]]
    done = {m.effects for m in models}
    requests = []
    for at in anchors:
        supersets = [s_ for s_ in sets if set(at.effects) < {e.name for e in s_}]
        counts.linearized += len(supersets)
        lin2 = sorted(
            (c for c in cmp.linearize(at, supersets) if c.effects not in done), key=lambda c: -c.log_posterior
        )
        for c in [c for c in lin2 if c.log_posterior >= at.log_posterior + math.log(WINDOW)][:refits]:
            done.add(c.effects)
            requests.append(cmp.request(at, c.effects, c.x))
    if requests:
        more = cmp.refit(requests)
        models += more
        counts.refitted += len(more)
        posterior(models)
    # nested models share their optima (.nesting): each from its subsets' and supersets' solutions
    share_optima(cmp, models)
    converge_window(cmp, models)
    models.sort(key=lambda m: -m.probability)
    return models, counts


#: Rounds of :func:`converge_window`: each continues the stopped fits by MAX_ITER iterations.
CONTINUATIONS = 3


def converge_window(cmp: Comparison, models: list[Model], rounds: int = CONTINUATIONS) -> int:
    """Continue, from where they stopped, the fits of the models inside Occam's window
    (:data:`tawarp.loop.evidence.WINDOW`) that reached the iteration cap :data:`MAX_ITER`,
    each continuation kept (the same MAP objective, descended further), until the window
    holds no such fit or after ``rounds`` rounds; the posterior probabilities set, in place.
    The evidence and the checks hold at a maximum a posteriori: an ambient exchanger's
    length, porosity and pore radius descend along a long valley, and a fit stopped on it
    leaves a misfit that fails the posterior predictive check though the model's optimum is
    at the noise (and its Laplace ln Z, from the quadratic model at the stopped point, is
    that of another optimum). Only the probable models are continued (the others' fits
    change no probability), and a fit whose continuation lowered its MAP cost by less than
    :data:`tawarp.loop.nesting.GAIN` is not continued again (it crawls along a direction
    the data barely see: no comparison changes). Returns the number of fits continued."""

    def cost(m: Model) -> float:
        return map_cost(m.fit.residuals[0], m.fit.x[0], m.priors)

    done, crawling = 0, set()
    for _ in range(rounds):
        posterior(models)
        best = max(m.log_posterior for m in models)
        todo = [
            i
            for i, m in enumerate(models)
            if m.log_posterior >= best + math.log(WINDOW) and m.fit.reason[0] == "max_iterations" and i not in crawling
        ]
        if not todo:
            break
        for i, new in zip(todo, cmp.refit([(models[i].effects, [models[i].fit.x[0]]) for i in todo])):
            if map_cost(new.fit.residuals[0], new.fit.x[0], new.priors) > cost(models[i]) - GAIN:
                crawling.add(i)
            models[i].fit, models[i].log_evidence = new.fit, new.log_evidence
        done += len(todo)
    posterior(models)
    return done


def prior_tension(problem: MeasurementKind, models: list[Model]) -> list[dict]:
    """Parameters further than :data:`TENSION_Z` prior sds from their prior in each of
    ``models``, by name, with what the most probable model that keeps it inside does."""
    out = []
    for m in models:
        for j, (name, z) in enumerate(m.z().items()):
            if abs(z) <= TENSION_Z:
                continue
            par, pr = m.fit.params[j], m.priors[j]
            value, centre = float(m.fit.values[0][j]), float(par.value(pr.mu))
            size = (
                f"{value / centre:.3g}x its prior"
                if par.log and centre > 0
                else f"{value - centre:+.3g} from its prior"
            )
            calm = next(
                (
                    o
                    for o in models
                    if o is not m and name in o.fit.names and abs(o.z()[name]) <= TENSION_Z and o.probability > 0
                ),
                None,
            )
            msg = f"{name} is {size} ({z:+.1f} prior sd) in the model {m.label}"
            if calm is not None:
                msg += f"; {calm.label} explains the data with {name} inside it ({calm.z()[name]:+.1f} sd)"
            out.append(
                {
                    "model": m.label,
                    "parameter": name,
                    "value": value,
                    "prior_centre": centre,
                    "z": float(z),
                    "message": msg,
                }
            )
    return out


def run_loop(
    problem: MeasurementKind,
    base_params: list[Param] | None = None,
    library: list[Effect] | None = None,
    max_effects: int = MAX_EFFECTS,
    drift_h: bool | None = None,
    progress: bool = False,
    plans: bool = True,
) -> LoopReport:
    """The loop of the package docstring; returns its report (:class:`LoopReport`, a
    Mapping of report.json's keys). ``base_params``: default :func:`default_base_params`;
    ``library``: candidate effects (default :func:`library_for` the kind); ``max_effects``:
    the largest set of effects compared; ``plans``: evaluate the next measurement when the
    top models are close; ``drift_h``: refit the h's per heat input (default: where the
    kind's groups are heat inputs, :attr:`MeasurementKind.groups_are_heat_inputs`);
    ``progress``: a bar over the :data:`STAGES` (on a terminal only)."""
    bar = progress_bar(len(STAGES), "closing the loop", progress, unit="stage")
    base_params = list(base_params or default_base_params(problem))
    library = library_for(problem) if library is None else library
    fixed: dict = {}
    if problem.has_sigma:
        weighted, sigma, source = problem, None, "sigma"
    else:
        # the noise is estimated once, from the least-squares base fit, and every model's
        # likelihood uses the same estimate
        lsq = fit_base(problem, base_params, fixed)
        weighted = noise_weighted(problem, noise_sigma(problem, lsq.residuals[0]))
        sigma, source = np.ones(2 * problem.y.size), NOISE_ESTIMATE
    base_priors = model_priors(problem.core, base_params, ())
    base = Model((), priors=base_priors)
    base.fit = fit_base(weighted, base_params, fixed, [_as_pairs(base_priors)])
    estimated = source == NOISE_ESTIMATE
    (base.log_evidence,) = _log_evidences([base.fit], estimated)
    _finished(bar, "base fit")
    models, counts = compare_models(weighted, base, base_params, fixed, library, max_effects, noise_scale=estimated)
    _finished(bar, "evidence")
    names = [e.name for e in library]
    best = models[0]
    gof_before = goodness_of_fit(weighted, base.fit, sigma, source)
    gof = goodness_of_fit(weighted, best.fit, sigma, source)
    floor = weighted.noise_floor(None)
    tension = prior_tension(weighted, [base] + [m for m in models if m is not base][:5])
    best_tension = [t for t in tension if t["model"] == best.label]
    alone, groups = claims(models, names)
    passes = gof["adequate"] and gof["white"] and not best_tension
    if passes and not best.effects:
        verdict = "adequate"
    elif passes and (alone or groups):
        verdict = "explained"
    elif passes:
        verdict = "indistinguishable"
    elif gof_before["reduced_chi2"] > WRONG_MODEL_CHI2:
        verdict = "wrong_model"
    else:
        verdict = "unexplained_residual"
    claimed = verdict == "explained"
    accepted = alone if claimed else []
    _finished(bar, "checks")
    report = LoopReport(
        kind=problem.name,
        n_residuals=base.fit.n,
        verdict=verdict,
        noise_floor=floor,
        noise_source=source,
        base=base,
        models=models,
        accepted_effects=accepted,
        accepted_groups=([[n] for n in alone] + groups) if claimed else [],
        chosen_description=next((e.description for e in library if accepted and e.name == accepted[0]), None),
        inclusion_probabilities=inclusion(models, names),
        group_probabilities={step_label(g): any_of(models, g) for g in groups},
        supported_alone=alone,
        supported_groups=groups,
        prior_tension=tension,
        counts=counts,
        goodness_of_fit_before=gof_before,
        goodness_of_fit_after=gof,
        unexplained_residual=None
        if verdict in ("adequate", "explained", "indistinguishable")
        else residual_location(problem, best.fit.model[0], floor),
        base_parameters=[par.label for par in base_params],
        pinned=list(problem.core.pinned),
        ties={par.label: list(par.targets[1:]) for par in base_params if len(par.targets) > 1},
        method=METHOD,
        residual_structure_before=residual_structure(weighted, base.fit.model[0]),
        residual_structure_after=residual_structure(weighted, best.fit.model[0]),
        next_measurement=next_measurement(weighted, models, fixed) if plans else [],
    )
    if problem.groups_are_heat_inputs if drift_h is None else drift_h:
        before = drift(problem, base_params, base.fit, fixed, None)
        after = (
            drift(problem, base_params, best.fit, _effect_fixed(best.fit, base_params), best.fit.effect)
            if best.effects
            else before
        )
        report.drift = (before, after)
    _finished(bar, "drift")
    bar.close()
    return report


#: Allocations between the cyclic garbage collector's young collections while loops run
#: together (:func:`run_loops`; Python's default is 700).
LOOPS_GC_THRESHOLD = 20_000


@contextlib.contextmanager
def _fewer_collections():
    """Python's cyclic garbage collector while loops run together: the objects alive before
    (the modules', Warp's and the engines': some 235 000 after a batch of four loops, whose
    full collection took 90 ms on the CPU) frozen out of its scans (:func:`gc.freeze`), and
    a young collection every :data:`LOOPS_GC_THRESHOLD` allocations. A batch of loops
    allocates millions of small objects; with the defaults its collections took 4 % of its
    host work (bench/loop.py --host-time). Both are undone after: the objects unfrozen and
    the thresholds restored, so that nothing escapes collection beyond the call."""
    threshold = gc.get_threshold()
    gc.freeze()
    gc.set_threshold(LOOPS_GC_THRESHOLD, *threshold[1:])
    try:
        yield
    finally:
        gc.set_threshold(*threshold)
        gc.unfreeze()


def run_loops(problems: list[MeasurementKind], progress: bool = False, **kw) -> list[LoopReport]:
    """:func:`run_loop` of each of ``problems`` (its other arguments ``kw``), their fits and
    predictions in one batch at each step (:func:`tawarp.fit.lockstep.run_together`; the
    kinds of one family, :meth:`MeasurementKind.family`, in one launch per structure, at
    the finest of their fixed cells): fewer launches and less host work a loop where a GPU
    host's loops are bound by their host work. Each report decides as :func:`run_loop`
    alone, to the fits' stopping rules (a batch's shared launches hold the union of its
    fits' parameters, as one loop's do). ``progress``: a bar over the loops finished (on a
    terminal only). A loop that raised raises here, once every loop has ended."""
    bar = progress_bar(len(problems), "closing the loops", progress, unit="loop")

    def one(problem):
        try:
            return run_loop(problem, **kw)
        finally:
            bar.update(1)

    with _fewer_collections():
        got = run_together([functools.partial(one, p) for p in problems], Families(problems))
    bar.close()
    for i, g in enumerate(got):
        if isinstance(g, Exception):
            g.add_note(f"in the loop of problem {i} ({g.__class__.__name__} raised there)")
            raise g
    return got


def _finished(bar, stage: str) -> None:
    """Advance the progress ``bar`` past ``stage`` (one of :data:`STAGES`)."""
    bar.set_postfix_str(stage)
    bar.update(1)


def _effect_fixed(f: FitResult, base_params: list[Param]) -> dict:
    out = {}
    for par in f.params:
        if par not in base_params:
            par.assign(float(f.value_dict()[par.label]), out)
    return out


def impedance_loop(
    data: list, reference: dict | None = None, settings=None, names=None
) -> tuple[MeasurementKind, LoopReport]:
    """Fit the circular-pore model (porosity, pore radius, tortuosity, or ``names``) to all
    layers of one material together, then let the loop find what it lacks. ``reference``:
    the paper's values (``phi``, ``alpha_inf``, ``Lambda``, ``Lambda_prime``, ``sigma``)
    for the comparison table."""
    prob = ImpedanceKind(data, settings or ForwardSettings(device="cpu"))
    rep = run_loop(prob, default_base_params(prob, names), drift_h=False)
    if reference:
        before = jca_equivalent(rep.base.fit.value_dict(), prob.core)
        after = jca_equivalent(rep.best.fit.value_dict(), prob.core)
        rep.comparison = {
            k: {"before": before[k], "after": after[k], "reference": reference[k]}
            for k in ("phi", "alpha_inf", "Lambda", "Lambda_prime", "sigma")
        }
        rep.comparison_note = (
            "circular pores: Lambda = Lambda' = r (Lambda' = ratio r with the thermal radius "
            "effect), alpha_inf = q^2, sigma = 8 mu q^2 / (phi r^2)"
        )
    return prob, rep
