"""Batched samplers (tawarp.design.samplers): one protocol, facts on hand-made sets and
closed-form optima."""

from __future__ import annotations

import numpy as np
import pytest

from tawarp.design.samplers import (
    BatchCmaEs,
    BatchNsga2,
    Sampler,
    constrained_objectives,
    crowding,
    make_sampler,
    nondominated_ranks,
    pareto_mask,
)

# hand-made set (both minimized): fronts by inspection
POINTS = np.array(
    [
        [1, 5],
        [2, 3],
        [4, 1],  # front 0
        [3, 4],
        [5, 2],  # front 1: each dominated only by front 0
        [6, 6],  # front 2
        [2, 3],
    ],
    dtype=float,
)  # a duplicate of a front-0 point: same front
RANKS = [0, 0, 0, 1, 1, 2, 0]


def test_nondominated_ranks_of_a_hand_made_set():
    assert list(nondominated_ranks(POINTS)) == RANKS  # two objectives: the sweep
    three = np.concatenate([POINTS, np.zeros((len(POINTS), 1))], axis=1)
    assert list(nondominated_ranks(three)) == RANKS  # a constant third column changes nothing: Deb's sort
    assert list(pareto_mask(POINTS)) == [r == 0 for r in RANKS]
    assert list(pareto_mask(three)) == [r == 0 for r in RANKS]


def test_crowding_distance_by_hand():
    F = np.array([[0.0, 4.0], [1.0, 2.0], [3.0, 1.0], [4.0, 0.0]])
    d = crowding(F, np.zeros(4, dtype=int))
    assert np.isinf(d[0]) and np.isinf(d[3])
    # (3 - 0)/4 + (4 - 1)/4 and (4 - 1)/4 + (2 - 0)/4
    assert d[1] == pytest.approx(1.5, abs=1e-15) and d[2] == pytest.approx(1.25, abs=1e-15)


def test_constrained_domination():
    """Deb's rule: every feasible point dominates every infeasible one; infeasible points
    are ordered by their violation."""
    F = np.array([[5.0, 5.0], [0.0, 0.0], [0.0, 0.0], [1.0, 1.0]])
    viol = np.array([0.0, 2.0, 1.0, 0.0])
    assert list(nondominated_ranks(constrained_objectives(F, viol))) == [1, 3, 2, 0]


def test_both_samplers_follow_one_protocol():
    for s in (BatchCmaEs(3, 2, 8, 0), BatchNsga2(3, 2, 8, 0)):
        assert isinstance(s, Sampler)
        X = s.ask(8)
        assert X.shape == (8, 4) and np.all((X[:, :3] >= 0) & (X[:, :3] <= 1)) and set(X[:, 3]) == {0.0, 1.0}
        with pytest.raises(ValueError, match="populations of 8"):
            s.ask(7)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cma_es_reaches_the_minimum_of_a_quadratic(seed):
    """f = sum (x - c)^2 in the unit cube, minimum 0 at c: after 40 generations of 16 the
    best point is within 1e-3 of c (a generous tolerance: CMA-ES converges linearly)."""
    c = np.array([0.3, 0.7, 0.55])
    s = make_sampler(3, 0, 16, seed, 1)
    best = np.inf, None
    for _ in range(40):
        X = s.ask(16)
        f = np.sum((X - c) ** 2, axis=1)
        s.tell(X, f[:, None], np.zeros(16))
        j = int(np.argmin(f))
        if f[j] < best[0]:
            best = f[j], X[j]
    assert np.linalg.norm(best[1] - c) < 1e-3


def test_cma_es_respects_a_constraint():
    """Minimize x0 subject to x0 >= 0.4 (violation 0.4 - x0): the best feasible point
    approaches 0.4 from above and none of the last generation is far infeasible."""
    s = make_sampler(2, 0, 16, 0, 1)
    for _ in range(40):
        X = s.ask(16)
        s.tell(X, X[:, :1], 0.4 - X[:, 0])
    X = s.ask(16)
    assert np.min(X[X[:, 0] >= 0.4, 0]) == pytest.approx(0.4, abs=1e-3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nsga2_converges_to_the_pareto_set(seed):
    """f = (x^2 + y^2, (x - 1)^2 + y^2) on the unit square: the Pareto set is y = 0,
    x in [0, 1]. After 30 generations of 32 the first front of the population lies on it
    (median y < 1e-3; mean y < 0.015: mutation keeps injecting points off it) and spans x
    from below 0.1 to above 0.9."""
    s = make_sampler(2, 0, 32, seed, 2)
    for _ in range(30):
        X = s.ask(32)
        F = np.stack([X[:, 0] ** 2 + X[:, 1] ** 2, (X[:, 0] - 1) ** 2 + X[:, 1] ** 2], axis=1)
        s.tell(X, F, np.zeros(32))
    u = s.pop[0][s._rank == 0]
    assert np.median(u[:, 1]) < 1e-3 and np.mean(u[:, 1]) < 0.015
    assert u[:, 0].min() < 0.1 and u[:, 0].max() > 0.9


def test_replay_is_exact():
    """A sampler told the same generations asks the same next generation (the search
    resumes by replaying its stored generations)."""

    def run(n_gen):
        s = make_sampler(2, 2, 8, 5, 1)
        for _ in range(n_gen):
            X = s.ask(8)
            s.tell(X, np.sum(X[:, :2] ** 2, axis=1)[:, None], np.zeros(8))
        return s.ask(8)

    np.testing.assert_array_equal(run(3), run(3))


@pytest.mark.parametrize("kind", ["interior", "corner"])
def test_cma_es_restarts_instead_of_degenerating(kind):
    """A converging CMA-ES shrinks its step size without bound: on f = |x - c|^2 (minimum
    inside the box) or f = -(x0 + x1) (minimum at the corner (1, 1)) with 64 trials per
    generation, ``cmaes`` left alone asks NaN points after 53 (interior) or 233 (corner)
    generations and its ``tell`` then raises "Abs of all param values must be less than
    1e+32". Over 300 generations every point asked is finite and in the box, the instance
    restarts at least once, and the best point is the minimum to 1e-6."""
    c = np.array([0.3, 0.7]) if kind == "interior" else np.ones(2)
    f = (lambda X: np.sum((X - c) ** 2, axis=1)) if kind == "interior" else (lambda X: -X.sum(axis=1))
    s = make_sampler(2, 0, 64, 0, 1)
    best = np.inf, None
    for _ in range(300):
        X = s.ask(64)
        assert np.all(np.isfinite(X)) and np.all((X >= 0) & (X <= 1))
        y = f(X)
        s.tell(X, y[:, None], np.zeros(64))
        j = int(np.argmin(y))
        if y[j] < best[0]:
            best = y[j], X[j]
    assert s.restarts[0] >= 1
    assert np.linalg.norm(best[1] - c) < 1e-6


def test_cma_es_told_points_that_are_not_finite_goes_on():
    """A store written before the restarts existed may hold a generation of NaN points;
    told them on a resume, the sampler counts them failed and asks finite points next."""
    s = make_sampler(2, 2, 8, 0, 1)
    for g in range(3):
        X = s.ask(8)
        if g == 1:
            X[:, :2] = np.nan
        s.tell(X, np.sum(X[:, :2] ** 2, axis=1)[:, None], np.zeros(8))
    X = s.ask(8)
    assert np.all(np.isfinite(X)) and np.all((X[:, :2] >= 0) & (X[:, :2] <= 1))
