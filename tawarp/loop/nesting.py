"""Nested models share their optima.

A model M and a superset M' = M + effects are nested: M' with its extra effects' parameters
at "off" (x = 0, their :attr:`Param.start`) is M. The projection of M''s solution onto M
(the extras dropped, the rest kept) is therefore a point of M, and M's solution with the
extras off a point of M'. Each model's MAP fit descends from its own starts and can end in a
worse local optimum than a relative's solution gives it; the evidence comparison would then
weigh two descents instead of two models: a superset whose extra effect ends at "off" would
beat its own nested model by the depth of that model's poorer optimum, though at "off" the
extra parameters' Occam factor is at most 1 (:func:`tawarp.loop.evidence.laplace_log_evidence`).

:func:`share_optima` evaluates every such point in its model's MAP objective (chi^2 plus the
priors' squares; one :meth:`MeasurementKind.predict` launch per structure for all of them) and
refits each model from the best point that beats its own optimum, keeping the refit where its
Laplace ln Z is higher (the rule by which :func:`tawarp.loop.run.fit_models` chooses between
a model's starts). The search fits only some subsets of a probable model: those it left out
are fitted first, from that model's projected solution (:func:`missing_subsets`), so that a
model with an effect at "off" always has its nested model beside it. ``tests/test_nesting.py``
guards the bound this gives.

Every refit races against all the models compared (:func:`tawarp.loop.run.start_race` with
their costs as its reference): most relatives of a probable model are far out of reach (its
subsets without the effect the data need), and a refit of such a model stops after a few
iterations where it cannot come within :data:`tawarp.loop.run.RACE_OUT` of the best, as in
the search's own batches (its posterior probability is 0 to double precision either way).
Where the model's own fit and the relative's basin are both that far out (:func:`futile`),
the refit is not made at all: on a case with two strong effects the passes otherwise refitted
some twenty such models each, every one that improved offering its point to its relatives in
the next pass, a quarter of the loop's forward evaluations.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from scipy import stats

from ..fit.problems import KindProblems, residual
from ..fit.result import FitResult
from ..model.effects import Param
from .evidence import WINDOW, Model, XPrior, prior_arrays

#: A relative's point is a better start only when it lowers a model's MAP cost (chi^2 plus the
#: priors' squares) by more than this: 0.05 in ln posterior, the odds within 5 %; below it a
#: refit changes no comparison and costs a batch.
GAIN = 0.1
#: Passes of :func:`share_optima`: a solution found by a refit reaches the models one effect
#: away in the next pass (its subsets all in the first); three reach from the base to a
#: three-effect model (:data:`tawarp.loop.run.MAX_EFFECTS`).
PASSES = 3


def map_cost(r: np.ndarray, x: np.ndarray, priors: list[XPrior]) -> float:
    """The MAP objective the loop's fits minimize: ``r^T r`` of the residuals (in units of the
    noise) plus ``sum ((x - mu) / sd)^2`` of the priors."""
    mu, sd, _, _ = prior_arrays(priors)
    return float(r @ r + np.sum(((np.asarray(x) - mu) / sd) ** 2))


def relative_point(source: FitResult, params: list[Param]) -> np.ndarray:
    """The solution ``source`` as a point of a relative's ``params``: the parameters they share
    at ``source``'s values, the others off (x = 0), within ``params``' bounds."""
    at = dict(zip(source.names, source.x[0]))
    x = np.array([at.get(par.label, 0.0) for par in params])
    lo, hi = np.array([par.bounds_x() for par in params]).reshape(-1, 2).T
    return np.clip(x, lo, hi)


def nested_cost(model: Model, names: list[str]) -> float:
    """The MAP cost (:func:`map_cost`) of ``model``'s submodel of the parameters ``names`` near
    ``model``'s solution, from the quadratic model of ``model``'s MAP objective there (its
    gradient and Gauss-Newton Hessian ``J^T J`` plus the priors' precisions): the other
    parameters held at their nested values (:func:`relative_point`: off, inside their
    bounds), ``names`` at that quadratic model's minimum, and the held parameters' prior terms,
    which the submodel has not, taken out. A refit of the submodel from ``model``'s projected
    solution descends in this basin."""
    f = model.fit
    x, r, J = f.x[0], f.residuals[0], f.jacobian[0]
    mu, sd, lo, hi = prior_arrays(model.priors)
    keep = np.isin(f.names, names)
    held = np.clip(0.0, lo, hi)[~keep]
    # F(x + d) = F + 2 g.d + d.H.d
    g = J.T @ r + (x - mu) / sd**2
    H = J.T @ J + np.diag(sd**-2.0)
    d = np.zeros_like(x)
    d[~keep] = held - x[~keep]
    d[keep] = -np.linalg.solve(H[np.ix_(keep, keep)], g[keep] + H[np.ix_(keep, ~keep)] @ d[~keep])
    prior_held = np.sum(((held - mu[~keep]) / sd[~keep]) ** 2)
    return float(map_cost(r, x, model.priors) + 2 * g @ d + d @ H @ d - prior_held)


def map_costs(models: list[Model]) -> dict[int, float]:
    """{id of each of ``models``: its :func:`map_cost` at its solution}."""
    return {id(m): map_cost(m.fit.residuals[0], m.fit.x[0], m.priors) for m in models}


def futile(comparison, costs: dict[int, float], names: list[str], own: Model | None, source: Model) -> bool:
    """Whether a refit of the model of the parameters ``names`` (``own``: its fit, None where
    it has none) from the solution of its nested relative ``source`` can change no posterior
    probability: its own fit is out of reach of the best of the models compared (``costs``:
    their :func:`map_costs`; :meth:`tawarp.loop.run.Comparison.out_of_reach`: the race's
    RACE_OUT, a probability of 0 to double precision) and so is the relative's basin for it:
    for a submodel of ``source``, :func:`nested_cost` (in that basin it fits no better than
    ``source`` with the extra effects off); for a supermodel, ``source``'s own cost (a point
    out of reach with the extra effects off, as the supermodel's own descents started from
    the base solution). The base model is always refitted: its fit is the report's "before"
    (its error, goodness of fit and drift, and the wrong-model test of a best model that
    fails its checks)."""
    best = min(costs.values())
    if not set(names) - {p.label for p in comparison.base_params}:
        return False
    if own is not None and not comparison.out_of_reach(costs[id(own)], best):
        return False
    if set(names) <= set(source.fit.names):
        return comparison.out_of_reach(nested_cost(source, names), best)
    return comparison.out_of_reach(costs[id(source)], best)


def nested_starts(comparison, models: list[Model], sources: set[int] | None = None) -> dict[int, np.ndarray]:
    """{index in ``models``: the point from a nested relative (a subset or a superset; among
    ``sources``, default all) of lowest MAP cost}, for the models where that point beats their
    own optimum by more than :data:`GAIN` and the refit is not :func:`futile`; all points in one
    evaluation (one launch per structure)."""
    problem = comparison.problem
    costs = map_costs(models)
    pairs = [
        (i, j)
        for i, a in enumerate(models)
        for j, b in enumerate(models)
        if (sources is None or j in sources)
        and (set(a.effects) < set(b.effects) or set(b.effects) < set(a.effects))
        and not futile(comparison, costs, a.fit.names, a, b)
    ]
    if not pairs:
        return {}
    points = [relative_point(models[j].fit, models[i].fit.params) for i, j in pairs]
    lm = KindProblems(
        problem,
        [(models[i].fit.params, models[i].fit.effect, x) for (i, _), x in zip(pairs, points)],
        comparison.fixed,
    )
    Y = lm.predict([(c, x[None]) for c, x in enumerate(points)])
    rows = np.arange(problem.y.size)
    own = [costs[id(m)] for m in models]
    best: dict[int, tuple[float, np.ndarray]] = {}
    for (i, _), x, y in zip(pairs, points, Y):
        with np.errstate(over="ignore", invalid="ignore"):  # a point where the model diverges
            cost = map_cost(residual(problem, y, rows)[0], x, models[i].priors)
        if np.isfinite(cost) and cost < own[i] - GAIN and cost < best.get(i, (np.inf,))[0]:
            best[i] = (cost, x)
    return {i: x for i, (_, x) in best.items()}


#: Level of :func:`poorer_basin`'s test.
BASIN_P = 0.01


def poorer_basin(sub: Model, model: Model) -> bool:
    """Whether the fitted submodel ``sub`` of ``model`` may sit in a poorer basin than
    ``model`` found: ``model`` is the more probable, and its MAP cost is below ``sub``'s by
    more than its extra parameters take from noise alone (the chi^2 quantile of their number
    at 1 - :data:`BASIN_P`: a likelihood-ratio test of the extras, each removing one chi^2
    of noise on average). Below that, the extras fit noise in the same basin, and a refit
    of ``sub`` from ``model``'s solution would end where ``sub`` is."""
    if sub.log_posterior >= model.log_posterior:
        return False
    extra = len(model.fit.names) - len(sub.fit.names)
    gap = map_cost(sub.fit.residuals[0], sub.fit.x[0], sub.priors) - map_cost(
        model.fit.residuals[0], model.fit.x[0], model.priors
    )
    return gap > stats.chi2.ppf(1 - BASIN_P, max(extra, 1))


def missing_subsets(comparison, models: list[Model]) -> list[Model]:
    """The subsets of the models inside Occam's window (ln P(M | data) within ln
    :data:`tawarp.loop.evidence.WINDOW` of the best) fitted from the projection of that
    model's solution (one batch): those the search did not fit, returned, and those it fitted
    that the window's model beats, each keeping the refit where its Laplace ln Z is higher, in
    place. A model the window holds is not credited with its effects before its own submodels
    had their chance (Madigan & Raftery's Occam's razor compares a model with its submodels)
    in the basin it found: where the misfit has several minima in a submodel's parameters (a
    bypass gap absorbed by the base fit), a submodel's own descents can all end above the
    one its superset reached with an extra effect near "off", and the nested point, its
    parameters tuned to that effect, need not be lower than its own optimum to lead there.
    A subset out of reach both on its own and in that basin (:func:`futile`: it lacks an
    effect the window's model needs) is left out."""
    best = max(m.log_posterior for m in models)
    fitted = {frozenset(m.effects): m for m in models}
    costs = map_costs(models)
    requests: dict[tuple[str, ...], list[np.ndarray]] = {}
    for m in sorted(models, key=lambda m: -m.log_posterior):
        if m.log_posterior < best + math.log(WINDOW):
            break
        for k in range(len(m.effects)):
            for sub in itertools.combinations(m.effects, k):
                own = fitted.get(frozenset(sub))
                if sub in requests or (own is not None and not poorer_basin(own, m)):
                    continue
                params = list(comparison.base_params) + [p for n in sub for p in comparison.effect(n).params]
                if futile(comparison, costs, [p.label for p in params], own, m):
                    continue
                requests[sub] = [relative_point(m.fit, params)]
    added = []
    for sub, new in zip(requests, comparison.refit(list(requests.items()), models) if requests else []):
        own = fitted.get(frozenset(sub))
        if own is None:
            added.append(new)
        elif new.log_evidence > own.log_evidence:
            own.fit, own.log_evidence = new.fit, new.log_evidence
    return added


def share_optima(comparison, models: list[Model], passes: int = PASSES) -> int:
    """Add the :func:`missing_subsets` to ``models`` (fitted, of one comparison: its problem,
    fixed values, library and ``refit``, :class:`tawarp.loop.run.Comparison`), then refit each
    model from its :func:`nested_starts`, in one batch per pass, and keep each refit whose
    Laplace ln Z is higher, in place; a further pass offers the models that changed to their
    relatives. Returns the number of refits."""
    added = missing_subsets(comparison, models)
    models += added
    sources, done = None, len(added)
    for _ in range(passes):
        starts = nested_starts(comparison, models, sources)
        order = sorted(starts)
        sources = set()
        for i, new in zip(order, comparison.refit([(models[i].effects, [starts[i]]) for i in order], models)):
            if new.log_evidence > models[i].log_evidence:
                models[i].fit, models[i].log_evidence = new.fit, new.log_evidence
                sources.add(i)
        done += len(order)
        if not sources:
            break
    return done
