"""Batched population samplers of the design search, behind one protocol.

A sampler works in sampler coordinates ``X`` (n, dim [+ 1]): the unit cube of the
continuous variables, then, when there are ``categories`` (materials), the category
index as a last column. ``ask(n)`` returns the next generation (n = the population
size), ``tell(X, F, violation)`` gives it back with its minimized objectives ``F``
(n, m) and constraint violations (n,) (feasible when <= 0; ``inf`` for a failed
evaluation). Samplers are deterministic functions of their seed and of what they were
told: a search resumes by asking and telling its stored generations again (no sampler
state is stored).

- :class:`BatchCmaEs` (one objective): CMA-ES (the ``cmaes`` library that Optuna's
  ``CmaEsSampler`` wraps), one instance per category, the population split evenly
  between them; generation 0 is a scrambled Sobol batch from which CMA-ES is
  warm-started (``cmaes.get_warm_start_mgd``); constraints by Deb's rule; an instance
  that has converged or degenerated is restarted (see :class:`BatchCmaEs`).
- :class:`BatchNsga2` (several objectives): NSGA-II with constrained domination,
  crowding distance, binary tournament, SBX crossover and polynomial mutation;
  generation 0 scrambled Sobol.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Sampler(Protocol):
    """What the search needs of a sampler (see the module docstring)."""

    generation: int

    def ask(self, n: int) -> np.ndarray:
        """Sampler coordinates (n, dim [+ 1]) of the next generation."""

    def tell(self, X: np.ndarray, F: np.ndarray, violation: np.ndarray) -> None:
        """The generation last asked, evaluated: minimized objectives F (n, m), violations (n,)."""


def make_sampler(dim: int, categories: int, batch: int, seed: int, n_objectives: int) -> Sampler:
    """CMA-ES for one objective, NSGA-II for several."""
    if n_objectives > 1:
        return BatchNsga2(dim, categories, batch, seed, n_objectives=n_objectives)
    return BatchCmaEs(dim, categories, batch, seed)


def sobol_unit(n: int, d: int, seed: int, skip: int = 0) -> np.ndarray:
    """n scrambled Sobol points in [0, 1)^d (points skip.. of the seeded sequence)."""
    from scipy.stats import qmc

    if d == 0:
        return np.zeros((n, 0))
    import warnings

    eng = qmc.Sobol(d, scramble=True, seed=seed)
    if skip:
        eng.fast_forward(skip)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # balance needs powers of 2; any n is fine here
        return eng.random(n)


#: Points of a scrambled Sobol sequence of :func:`sobol_unit` (scipy's default 30 bits).
SOBOL_MAX_POINTS = 2**30


def sobol_directions(d: int, seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(directions (d, bits), shift (d,), scale) of the scrambled Sobol sequence of
    :func:`sobol_unit` for (d, seed): its point i is ``scale`` times ``shift`` XOR the
    ``directions[:, j]`` of the set bits j of i ^ (i >> 1) (the Gray-code construction of
    scipy.stats.qmc.Sobol; the numbers are its engine's, after scrambling, and
    tests/test_sweep_tables.py checks the points made from them against :func:`sobol_unit`).
    At most ``1 / scale`` = :data:`SOBOL_MAX_POINTS` points."""
    from scipy.stats import qmc

    eng = qmc.Sobol(d, scramble=True, seed=seed)
    return eng._sv.astype(np.int64), eng._shift.astype(np.int64), float(eng._scale)


def _penalized(f: np.ndarray, violation: np.ndarray) -> np.ndarray:
    """Deb's rule for a minimized scalar: infeasible points rank after every feasible one,
    by their violation."""
    f = np.where(np.isfinite(f), f, np.inf)
    feas = (violation <= 0) & np.isfinite(f)
    worst = np.max(f[feas]) if np.any(feas) else 0.0
    big = np.where(np.isfinite(violation), violation, 1e300)
    return np.where(feas, f, worst + 1.0 + np.abs(worst) + big)


#: Initial step size of a CMA-ES (re)started without a warm start: a sixth of the unit
#: box, so that +-3 sigma spans it.
SIGMA0 = 1.0 / 6.0


def _degenerate(opt) -> bool:
    """Whether a CMA-ES instance can no longer sample: its state is not finite, or
    ``cmaes``' own stopping test holds (converged: step size or function values below
    tolerance, a step with no effect on the mean, covariance condition number > 1e14).
    Left running, such an instance divides by a vanishing step size and asks NaN points
    (a quadratic with 256 trials per generation does so within 60 generations)."""
    state = (opt.mean, np.asarray(opt._sigma), opt._C)  # cmaes has no public accessor
    if not all(np.all(np.isfinite(a)) for a in state) or not opt._sigma > 0:
        return True
    with np.errstate(all="ignore"):
        return bool(opt.should_stop())


class BatchCmaEs:
    """CMA-ES over ``dim`` unit-cube coordinates, one instance per category (``categories``
    0 or 1: none), population = ``batch`` split between categories. Generation 0 is
    scrambled Sobol; CMA-ES is warm-started from it. Constraints: Deb's rule.

    Points stay in the unit box (``cmaes`` resamples, then clips). An instance that has
    converged or degenerated (:func:`_degenerate`) is restarted, before it asks, from a
    random point of the box with step size :data:`SIGMA0` and the same population (the
    batch is already far above CMA-ES's default 4 + 3 ln d, so IPOP's doubling of the
    population buys nothing); ``restarts[m]`` counts them. Restarts depend only on what
    was told, so a replay restarts alike. Points told that are not finite (none are asked;
    a store may hold some) are told as the points asked, failed."""

    def __init__(self, dim: int, categories: int, batch: int, seed: int):
        self.dim, self.categories, self.batch, self.seed = dim, categories, batch, seed
        self.n_cat = max(categories, 1)
        if batch < 2 * self.n_cat:
            raise ValueError(
                f"batch {batch} too small: CMA-ES needs at least 2 trials per material ({self.n_cat} materials)"
            )
        self.d = max(dim, 2)  # cmaes needs >= 2 dimensions: pad a dummy one, kept internal
        self.sizes = [batch // self.n_cat + (1 if m < batch % self.n_cat else 0) for m in range(self.n_cat)]
        self.opts = [None] * self.n_cat
        self.restarts = [0] * self.n_cat
        self.generation = 0
        self._asked = None  # (internal coordinates (batch, d), category (batch,)) of the last ask

    def _start(self, m: int, mean, sigma: float, cov, seed: int) -> None:
        import cmaes

        self.opts[m] = cmaes.CMA(
            mean=np.clip(mean, 0.0, 1.0),
            sigma=max(float(sigma), 1e-8),
            cov=cov,
            bounds=np.tile([0.0, 1.0], (self.d, 1)),
            seed=seed,
            n_max_resampling=10 * self.d,
            population_size=self.sizes[m],
        )

    def _restart(self, m: int) -> None:
        self.restarts[m] += 1
        seq = np.random.SeedSequence([self.seed, m, self.restarts[m]])
        self._start(
            m, np.random.default_rng(seq).random(self.d), SIGMA0, None, int(seq.generate_state(1)[0] % (2**31 - 2)) + 1
        )

    def _population(self, m: int) -> np.ndarray:
        """Instance m's next population (sizes[m], d), restarting it first if it degenerated."""
        if _degenerate(self.opts[m]):
            self._restart(m)
        with np.errstate(all="ignore"):
            u = np.array([self.opts[m].ask() for _ in range(self.sizes[m])])
        if not np.all(np.isfinite(u)):  # a state finite yet too extreme to sample from
            self._restart(m)
            u = np.array([self.opts[m].ask() for _ in range(self.sizes[m])])
        return u

    def ask(self, n: int) -> np.ndarray:
        if n != self.batch:
            raise ValueError(f"CMA-ES asks whole populations of {self.batch}, not {n}")
        if self.generation == 0:
            u = sobol_unit(self.batch, self.d, self.seed)
            cat = np.arange(self.batch) % self.n_cat
        else:
            u = np.concatenate([self._population(m) for m in range(self.n_cat)])
            cat = np.concatenate([np.full(size, m) for m, size in enumerate(self.sizes)])
        self._asked = (u, cat)
        X = u[:, : self.dim]
        return np.concatenate([X, cat[:, None].astype(float)], axis=1) if self.categories else X

    def tell(self, X: np.ndarray, F: np.ndarray, violation: np.ndarray) -> None:
        import cmaes

        if self._asked is None:
            raise RuntimeError("tell without ask: tell the generation last asked")
        u_asked, cat_asked = self._asked
        u = np.concatenate([X[:, : self.dim], u_asked[:, self.dim :]], axis=1)
        cat = X[:, self.dim].astype(int) if self.categories else np.zeros(len(X), dtype=int)
        f = np.asarray(F, dtype=float).reshape(len(X), -1)[:, 0]
        bad = ~np.all(np.isfinite(u), axis=1)
        u[bad], cat[bad] = u_asked[bad], cat_asked[bad]
        f = _penalized(np.where(bad, np.inf, f), np.where(bad, np.inf, np.asarray(violation, dtype=float)))
        if self.generation == 0:
            for m in range(self.n_cat):
                sols = [(u[i], f[i]) for i in np.flatnonzero(cat == m)]
                gamma = min(1.0, max(0.1, 1.0001 / len(sols)))
                try:
                    mean, sigma, cov = cmaes.get_warm_start_mgd(sols, gamma=gamma, alpha=0.1)
                    ok = np.all(np.isfinite(cov)) and np.isfinite(sigma) and sigma > 0
                except (AssertionError, np.linalg.LinAlgError, ValueError):
                    ok = False
                if not ok:
                    mean, sigma, cov = np.full(self.d, 0.5), SIGMA0, None
                self._start(m, mean, sigma, cov, (self.seed + 1000 * m) % (2**31 - 1) + 1)
        else:
            with np.errstate(all="ignore"):  # a degenerating update is caught before the next ask
                for m, opt in enumerate(self.opts):
                    opt.tell([(u[i], float(f[i])) for i in np.flatnonzero(cat == m)])
        self._asked = None
        self.generation += 1


def nondominated_ranks(F: np.ndarray) -> np.ndarray:
    """Front index (0 = non-dominated) of each row of F (N, M), all minimized.

    Two objectives: O(N log N) sweep (points in lexicographic order; each front keeps its
    smallest second objective, a sorted list searched by bisection). More: Deb's fast
    non-dominated sort on the domination matrix (O(N^2) memory)."""
    import bisect

    F = np.asarray(F, dtype=float)
    N = F.shape[0]
    if F.shape[1] == 2:
        order = np.lexsort((F[:, 1], F[:, 0]))
        rank = np.empty(N, dtype=int)
        last: list[float] = []
        prev = None
        for i in order:
            f0, f1 = F[i, 0], F[i, 1]
            if prev is not None and f0 == F[prev, 0] and f1 == F[prev, 1]:
                rank[i] = rank[prev]  # identical points do not dominate each other
            else:
                k = bisect.bisect_right(last, f1)
                if k == len(last):
                    last.append(f1)
                else:
                    last[k] = f1
                rank[i] = k
            prev = i
        return rank
    dom = np.zeros((N, N), dtype=bool)  # dom[p, q]: p dominates q
    for lo in range(0, N, 1024):
        a = F[lo : lo + 1024, None, :]
        dom[lo : lo + 1024] = np.all(a <= F[None, :, :], axis=2) & np.any(a < F[None, :, :], axis=2)
    count = dom.sum(axis=0)
    rank = np.full(N, -1)
    front = np.flatnonzero(count == 0)
    r = 0
    while front.size:
        rank[front] = r
        count = count - dom[front].sum(axis=0)
        count[rank >= 0] = -1
        front = np.flatnonzero(count == 0)
        r += 1
    return rank


def pareto_mask(F: np.ndarray) -> np.ndarray:
    """Rows of F (N, M), all minimized, that no other row dominates. O(N x front size)."""
    F = np.asarray(F, dtype=float)
    if F.shape[1] == 2:
        return nondominated_ranks(F) == 0
    order = np.lexsort(F.T[::-1])
    front: list[int] = []
    for i in order:
        if front:
            P = F[front]
            if np.any(np.all(P <= F[i], axis=1) & np.any(P < F[i], axis=1)):
                continue
        front.append(i)
    mask = np.zeros(F.shape[0], dtype=bool)
    mask[front] = True
    return mask


def crowding(F: np.ndarray, rank: np.ndarray) -> np.ndarray:
    dist = np.zeros(F.shape[0])
    for r in np.unique(rank):
        idx = np.flatnonzero(rank == r)
        if idx.size <= 2:
            dist[idx] = np.inf
            continue
        for j in range(F.shape[1]):
            order = idx[np.argsort(F[idx, j], kind="stable")]
            span = F[order[-1], j] - F[order[0], j]
            dist[order[0]] = dist[order[-1]] = np.inf
            if span > 0:
                dist[order[1:-1]] += (F[order[2:], j] - F[order[:-2], j]) / span
    return dist


def constrained_objectives(F: np.ndarray, violation: np.ndarray) -> np.ndarray:
    """Objectives (minimized) under which plain Pareto domination is Deb's constrained
    domination: infeasible rows get ``max feasible + 1 + violation`` in every column."""
    F = np.where(np.isfinite(F), F, np.inf)
    feas = (violation <= 0) & np.all(np.isfinite(F), axis=1)
    top = np.max(F[feas], axis=0) if np.any(feas) else np.zeros(F.shape[1])
    span = np.abs(top) + 1.0
    v = np.where(np.isfinite(violation), np.maximum(violation, 0), 1e300)
    return np.where(feas[:, None], F, top + span + v[:, None])


class BatchNsga2:
    """NSGA-II over ``dim`` unit-cube coordinates and ``categories`` (0: none; a category
    is inherited from a parent and mutated with probability 1/(dim + 1)), population =
    ``batch``; generation 0 scrambled Sobol."""

    def __init__(
        self,
        dim: int,
        categories: int,
        batch: int,
        seed: int,
        eta_c: float = 15.0,
        eta_m: float = 20.0,
        n_objectives: int = 2,
    ):
        self.batch, self.seed, self.categories = batch, seed, categories
        if n_objectives > 2 and batch > 4096:
            raise ValueError("NSGA-II with more than two objectives: batch at most 4096 (O(batch^2) sorting memory)")
        self.n_mat = max(categories, 1)
        self.d = dim
        self.eta_c, self.eta_m = eta_c, eta_m
        self.pop = None  # (u, mat, F, violation)
        self.generation = 0

    def _select(self, u, mat, F, viol):
        G = constrained_objectives(F, viol)
        rank = nondominated_ranks(G)
        cd = crowding(G, rank)
        order = np.lexsort((-cd, rank))[: self.batch]
        self._rank, self._cd = rank[order], cd[order]
        return u[order], mat[order], F[order], viol[order]

    def ask(self, n: int) -> np.ndarray:
        if n != self.batch:
            raise ValueError(f"NSGA-II asks whole populations of {self.batch}, not {n}")
        u, cm = self._offspring()
        return np.concatenate([u, cm[:, None].astype(float)], axis=1) if self.categories else u

    def _offspring(self) -> tuple[np.ndarray, np.ndarray]:
        g = self.generation
        if g == 0:
            return sobol_unit(self.batch, self.d, self.seed), np.arange(self.batch) % self.n_mat
        rng = np.random.default_rng([self.seed, g])
        u, mat = self.pop[0], self.pop[1]
        n, B = len(u), self.batch

        def tournament(k):
            a, b = rng.integers(0, n, k), rng.integers(0, n, k)
            better = (self._rank[a] < self._rank[b]) | ((self._rank[a] == self._rank[b]) & (self._cd[a] > self._cd[b]))
            return np.where(better, a, b)

        p1, p2 = tournament(B), tournament(B)
        x1, x2 = u[p1].copy(), u[p2].copy()
        child = x1.copy()
        if self.d:
            # SBX crossover, probability 0.9 per pair, each gene with probability 0.5
            do = (rng.random(B) < 0.9)[:, None] & (rng.random((B, self.d)) < 0.5)
            r = rng.random((B, self.d))
            beta = np.where(r <= 0.5, (2 * r) ** (1 / (self.eta_c + 1)), (1 / (2 * (1 - r))) ** (1 / (self.eta_c + 1)))
            c1 = 0.5 * ((1 + beta) * x1 + (1 - beta) * x2)
            c2 = 0.5 * ((1 - beta) * x1 + (1 + beta) * x2)
            pick = rng.random((B, self.d)) < 0.5
            child = np.where(do, np.where(pick, c1, c2), x1)
            # polynomial mutation, probability 1/d per gene
            mut = rng.random((B, self.d)) < 1.0 / max(self.d, 1)
            r = rng.random((B, self.d))
            delta = np.where(
                r < 0.5, (2 * r) ** (1 / (self.eta_m + 1)) - 1, 1 - (2 * (1 - r)) ** (1 / (self.eta_m + 1))
            )
            child = np.clip(np.where(mut, child + delta, child), 0.0, 1.0)
        cm = np.where(rng.random(B) < 0.5, mat[p1], mat[p2])
        if self.n_mat > 1:
            flip = rng.random(B) < 1.0 / (self.d + 1)
            cm = np.where(flip, rng.integers(0, self.n_mat, B), cm)
        return child, cm

    def tell(self, X: np.ndarray, F: np.ndarray, violation: np.ndarray) -> None:
        u = np.asarray(X[:, : self.d], dtype=float)
        mat = X[:, self.d].astype(int) if self.categories else np.zeros(len(X), dtype=int)
        F = np.where(np.isfinite(F), np.asarray(F, dtype=float), np.inf)
        viol = np.asarray(violation, dtype=float)
        if self.pop is None:
            self.pop = self._select(u, mat, F, viol)
        else:
            P = self.pop
            self.pop = self._select(
                np.concatenate([P[0], u]),
                np.concatenate([P[1], mat]),
                np.concatenate([P[2], F]),
                np.concatenate([P[3], viol]),
            )
        self.generation += 1
