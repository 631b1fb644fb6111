"""Nested models share their optima (:mod:`tawarp.loop.nesting`): a superset whose extra
effect ends at "off" is its nested model, so it cannot beat that model by more than the extra
parameters' Occam factor permits, however poorly the nested model's own descent ended.

The bound: with the extra parameters at "off" and the nested model at the projected optimum
(its misfit and prior no worse than the superset's there), ln Z(M') - ln Z(M) is the extras'
Occam factor, at most 0: on a one-sided prior's bound the Laplace integral is
sqrt(pi / (2 C)) erfcx(G / sqrt(2 C)) <= sqrt(pi / 2) times the half-normal's density
2 / sqrt(2 pi) (C >= 1 and G >= 0 in prior sds: the data's pull at an optimum on the bound
points out of the range), at most 1; at a two-sided prior's centre it is
sqrt(det P / det S) <= 1 (the Schur complement S of the extras >= their prior precision P).
The posterior odds P(M')/P(M) are then at most the model prior's ratio, up to the slack
:data:`tawarp.loop.nesting.GAIN`/2 in ln Z of a refit that is not taken."""

import math
from types import SimpleNamespace

import numpy as np

from tawarp.loop.evidence import ON_BOUND, Model, XPrior
from tawarp.loop.nesting import GAIN, map_cost, missing_subsets, nested_cost
from tawarp.loop.run import Comparison, compare_models, default_base_params, library_for
from tawarp.measure import TMatrixKind
from tawarp.model.forward import ForwardSettings
from test_loop import prior, reference_data

#: A base fit started with the stack's h at e^-3 of its core value: within the loop's
#: iteration cap it is still crawling along a valley, its misfit some fifteen times the
#: converged one's (the precondition below checks it).
POOR_H_START = -3.0


def poorly_started_base():
    """The radiation-only comparison on clean data (seed 1: the radiation effect's fit ends on
    its bound, "off") and its base model fitted from :data:`POOR_H_START`."""
    seed = 1
    prob = TMatrixKind(reference_data({}, seed), prior(seed), ForwardSettings(device="cpu"))
    params = default_base_params(prob)
    library = [e for e in library_for(prob) if e.name == "radiation"]
    start = np.zeros(len(params))
    start[[p.label for p in params].index("stack.h")] = POOR_H_START
    cmp = Comparison(prob, params, {}, library, {0: 1, 1: 1}, False)
    return prob, params, library, cmp, cmp.refit([((), [start])])[0]


def test_a_superset_at_off_never_beats_its_nested_model_beyond_its_occam_factor():
    prob, params, library, cmp, base = poorly_started_base()
    poor_cost = base.fit.cost[0]
    models, _ = compare_models(prob, base, params, {}, library, max_effects=1)
    sup = next(m for m in models if m.effects == ("radiation",))
    # precondition: the superset's descent found the good optimum with its extra parameter at
    # "off", on its bound, and the base's own descent ended far above it
    assert sup.fit.x[0][-1] <= library[0].params[0].bounds_x()[0] + ON_BOUND
    assert poor_cost > 10 * sup.fit.cost[0]
    assert base.fit.cost[0] <= sup.fit.cost[0] + GAIN
    assert sup.log_evidence - base.log_evidence <= GAIN / 2
    odds, prior_odds = sup.probability / base.probability, math.exp(sup.log_model_prior - base.log_model_prior)
    assert odds <= prior_odds * math.exp(GAIN / 2)


def test_a_submodel_beaten_by_the_window_is_refitted_in_its_basin():
    # the base's own descent stopped far above the optimum (the poor start above) and the
    # radiation model, which holds it, leads the window: missing_subsets refits the base from
    # the radiation model's solution, in place, and the base then reaches the optimum the
    # radiation model found with its effect at "off" (the same MAP cost up to GAIN)
    _, _, _, cmp, base = poorly_started_base()
    sup = cmp.refit([cmp.request(base, ("radiation",), None)])[0]
    cost = lambda m: map_cost(m.fit.residuals[0], m.fit.x[0], m.priors)
    assert sup.log_posterior > base.log_posterior and cost(base) > cost(sup) + 10 * GAIN
    assert missing_subsets(cmp, [base, sup]) == []
    assert cost(base) <= cost(sup) + GAIN
    # now in the radiation model's basin, the base is not refitted again even where radiation
    # were the more probable: what it takes beyond the base is noise (poorer_basin's
    # likelihood-ratio test)
    sup.log_evidence = base.log_evidence + 10.0
    refits = []
    refit, cmp.refit = cmp.refit, lambda *args: refits.append(args) or refit(*args)
    missing_subsets(cmp, [base, sup])
    assert refits == []


def test_nested_cost_is_the_submodels_optimum_on_a_linear_model():
    # nested_cost's quadratic model of the MAP objective is exact where the residuals are
    # linear in x: a superset of four parameters fitted at its MAP optimum predicts the
    # optimum of its submodel of the first two (the others held off, x = 0, and their prior
    # terms, which the submodel has not, left out) as the closed-form least squares gives it
    rng = np.random.default_rng(3)
    A, y = rng.normal(size=(40, 4)), rng.normal(size=40)
    mu, sd = np.array([0.1, -0.2, 0.3, 0.05]), np.array([1.0, 0.5, 2.0, 0.7])
    P = np.diag(sd**-2.0)
    x = np.linalg.solve(A.T @ A + P, A.T @ y + P @ mu)
    names = ["a", "b", "c", "d"]
    fit = SimpleNamespace(x=x[None], residuals=(A @ x - y)[None], jacobian=A[None], names=names)
    sup = Model(("c", "d"), fit=fit, priors=[XPrior(m, s) for m, s in zip(mu, sd)])
    k = slice(0, 2)
    xk = np.linalg.solve(A[:, k].T @ A[:, k] + P[k, k], A[:, k].T @ y + P[k, k] @ mu[k])
    want = float(np.sum((A[:, k] @ xk - y) ** 2) + np.sum(((xk - mu[k]) / sd[k]) ** 2))
    assert abs(nested_cost(sup, names[:2]) - want) <= 1e-10 * want
