"""Batched population samplers of the design search, behind one protocol, on the device.

A sampler works in sampler coordinates ``X`` (n, dim [+ 1]): the unit cube of the
continuous variables, then, when there are ``categories`` (materials), the category
index as a last column. ``ask(n)`` returns the next generation (n = the population
size) as a float64 Warp array on the sampler's device; ``tell(X, F, violation)`` gives it
back (Warp arrays or NumPy) with its minimized objectives ``F`` (n, m) and constraint
violations (n,) (feasible when <= 0; ``inf`` for a failed evaluation). Samplers are
deterministic functions of their seed and of what they were told: a search resumes by
asking and telling its stored generations again (no sampler state is stored).

- :class:`BatchCmaEs` (one objective): CMA-ES, one instance per category, the population
  split evenly between them, its state and its ask/tell in Warp kernels
  (:mod:`tawarp.kernels.sampler`); generation 0 is a scrambled Sobol batch whose best half
  gives the first mean; constraints by Deb's rule; an instance that has converged or
  degenerated is restarted (see :class:`BatchCmaEs`).
- :class:`BatchNsga2` (several objectives): NSGA-II with constrained domination,
  crowding distance, binary tournament, SBX crossover and polynomial mutation;
  generation 0 scrambled Sobol; the children made on the device, the survivors chosen
  on the host (one sequential pass for two objectives).

Why a small Warp implementation rather than a GPU evolutionary library: docs/design.md.
"""

from __future__ import annotations

import threading
from typing import Protocol, runtime_checkable

import numpy as np
import warp as wp

from ..rng import checked_seed


@runtime_checkable
class Sampler(Protocol):
    """What the search needs of a sampler (see the module docstring)."""

    generation: int

    def ask(self, n: int):
        """Sampler coordinates (n, dim [+ 1]) of the next generation (a Warp array)."""

    def tell(self, X, F, violation) -> None:
        """The generation last asked, evaluated: minimized objectives F (n, m), violations (n,)."""


def check_batch(batch: int, categories: int, n_objectives: int, name: str = "batch") -> None:
    """Refuse a population :func:`make_sampler` cannot take (``name``: the parameter as the
    caller knows it): CMA-ES (one objective) needs two trials per category (one CMA-ES per
    material, each with at least one parent)."""
    if n_objectives == 1 and batch < 2 * max(categories, 1):
        raise ValueError(
            f"{name} {batch} too small: CMA-ES needs at least 2 trials per material ({max(categories, 1)} materials)"
        )


def make_sampler(
    dim: int, categories: int, batch: int, seed: int, n_objectives: int, device: str | None = None
) -> Sampler:
    """CMA-ES for one objective, NSGA-II for several, on ``device`` (default Warp's)."""
    if n_objectives > 1:
        return BatchNsga2(dim, categories, batch, seed, n_objectives=n_objectives, device=device)
    return BatchCmaEs(dim, categories, batch, seed, device=device)


def sobol_unit(n: int, d: int, seed: int, skip: int = 0) -> np.ndarray:
    """n scrambled Sobol points in [0, 1)^d (points skip.. of the seeded sequence)."""
    from scipy.stats import qmc

    seed = checked_seed(seed, "sobol_unit")
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

    eng = qmc.Sobol(d, scramble=True, seed=checked_seed(seed, "sobol_directions"))
    return eng._sv.astype(np.int64), eng._shift.astype(np.int64), float(eng._scale)


def _stream_seed(seed: int, generation: int, stream: int) -> int:
    """A kernel's seed (int32) for ``stream`` of ``generation``: NumPy's SeedSequence of the
    three, so that generations and streams never share random numbers."""
    return int(np.random.SeedSequence([int(seed), int(generation), int(stream)]).generate_state(1)[0] & 0x7FFFFFFF)


def _first_generation(batch: int, dim: int, categories: int, seed: int, device) -> wp.array:
    """The space-filling generation both samplers start from: ``batch`` scrambled Sobol
    points of the unit cube, with ``categories`` (when there are) dealt in turn in column
    ``dim``."""
    X = sobol_unit(batch, dim, seed)
    if categories:
        X = np.concatenate([X, (np.arange(batch) % categories)[:, None].astype(float)], axis=1)
    return wp.array(X, dtype=wp.float64, device=device)


def _on(device, a, dtype=wp.float64) -> wp.array:
    """``a`` (NumPy or Warp) as a new contiguous Warp array of ``dtype`` on ``device`` (the
    kernels write into it)."""
    if isinstance(a, wp.array):
        return wp.clone(a, device=device) if a.dtype == dtype else wp.array(a.numpy(), dtype=dtype, device=device)
    return wp.array(
        np.ascontiguousarray(a, dtype=np.float64 if dtype == wp.float64 else np.int32), dtype=dtype, device=device
    )


def _host(a) -> np.ndarray:
    """A float64 NumPy array of ``a`` (Warp arrays copied from their device)."""
    return np.asarray(a.numpy() if isinstance(a, wp.array) else a, dtype=np.float64)


#: Slices of the ranked members summed apart by :func:`tawarp.kernels.sampler.cma_moments`
#: (parallel, and summed in a fixed order: reproducible).
MOMENT_SLICES = 32


#: Held while a CMA-ES sampler makes its kernels and records its launches. Warp builds and
#: loads a kernel's module at its first launch in the process, and a recorded launch keeps
#: the code it was recorded with: two samplers made at once in threads of one process (the
#: islands of a thread cluster) each built and loaded the modules, and the launches
#: recorded against a copy that the other replaced crashed the process
#: (``tests/test_samplers.py``, two samplers made in two threads of a fresh process).
_KERNELS_LOCK = threading.Lock()


class BatchCmaEs:
    """CMA-ES over ``dim`` unit-cube coordinates, one instance per category (``categories``
    0 or 1: none), population = ``batch`` split between categories (lambda each, mu =
    lambda / 2 parents, the tutorial's default weights, c_sigma, d_sigma, c_c, c_1 and
    c_mu), on ``device``. Generation 0 is scrambled Sobol; its best half (by category)
    gives each instance's first mean, with sigma0 = :data:`SIGMA0` and C = I.
    Constraints: Deb's rule (a feasible member ranks before every infeasible one, the
    infeasible by their violation).

    Points stay in the unit box: resampled up to 10 dim times, then clipped (the told,
    repaired point is the one the update reads). An instance restarts from a uniform
    random point with sigma0, C = I when it stops (its step below 1e-11 of the box, the
    covariance's condition number above 1e14, the objective flat to 1e-12 relative over
    a generation and the last 10 + 30 dim / lambda ones) or when its state is not finite;
    ``restarts[m]`` counts them. The population stays the batch's share: IPOP's doubling
    of lambda at each restart is moot when lambda already is thousands (docs/design.md).
    Restarts depend only on what was told, so a replay restarts alike. Rows told that are
    not finite (none are asked; a store may hold some) are told as the rows asked, failed."""

    def __init__(self, dim: int, categories: int, batch: int, seed: int, device: str | None = None):
        from ..kernels.eigen import eigh_kernel
        from ..kernels.sampler import SEEDS, CmaState

        self.dim, self.categories, self.batch, self.seed = dim, categories, batch, seed
        checked_seed(seed, "BatchCmaEs", integer=True)
        self.device = wp.get_device(device)
        self.n_cat = max(categories, 1)
        if dim < 1:
            raise ValueError("CMA-ES needs at least one continuous variable")
        check_batch(batch, categories, 1)
        self.sizes = [batch // self.n_cat + (1 if m < batch % self.n_cat else 0) for m in range(self.n_cat)]
        K, d, dev = self.n_cat, dim, self.device
        eye = np.broadcast_to(np.eye(d), (K, d, d))

        def put(a, dtype=wp.float64):
            return wp.array(np.ascontiguousarray(a), dtype=dtype, device=dev)

        self.state = CmaState()
        # the Sobol start is told against m = 1/2, sigma = 1: its update sets the first mean
        self.state.mean, self.state.sigma = put(np.full((K, d), 0.5)), put(np.ones(K))
        self.state.C, self.state.B, self.state.eig = put(eye), put(eye), put(np.ones((K, d)))
        for path in ("p_sigma", "p_c", "yw"):
            setattr(self.state, path, put(np.zeros((K, d))))
        self.state.age, self.state.restarts = put(np.zeros(K), wp.int32), put(np.zeros(K), wp.int32)
        horizon = 10 + int(np.ceil(30 * d / min(self.sizes)))
        self.state.history = put(np.full((K, horizon), np.inf))
        self.part = wp.zeros((K, MOMENT_SLICES, d + d * d), dtype=wp.float64, device=dev)
        self.category = put(np.repeat(np.arange(K), self.sizes), wp.int32)
        self._w, self._V = (
            wp.empty((K, d), dtype=wp.float64, device=dev),
            wp.empty((K, d, d), dtype=wp.float64, device=dev),
        )
        n = batch
        self._z = wp.empty((n, d), dtype=wp.float64, device=dev)
        self._U = wp.empty((n, d), dtype=wp.float64, device=dev)
        self._told_cat = wp.empty(n, dtype=wp.int32, device=dev)
        self._counts = wp.zeros(K, dtype=wp.int32, device=dev)
        self._key = wp.empty(2 * n, dtype=wp.float64, device=dev)
        self._ckey = wp.empty(2 * n, dtype=wp.int32, device=dev)
        self._member = wp.empty(2 * n, dtype=wp.int32, device=dev)
        cols = dim + (1 if categories else 0)
        self._X = wp.empty((n, cols), dtype=wp.float64, device=dev)  # the generation asked
        self._told = wp.empty((n, cols), dtype=wp.float64, device=dev)
        self._F, self._viol = wp.empty(n, dtype=wp.float64, device=dev), wp.empty(n, dtype=wp.float64, device=dev)
        self._seeds = wp.zeros(SEEDS, dtype=wp.int32, device=dev)
        # what the device reads from the host each generation, page-locked on a GPU (the
        # launches that copy them may be a CUDA graph's, which reads them when it runs);
        # written again once the device has read them (``_staged``)
        pinned = self.device.is_cuda
        self._F_host = wp.empty(n, dtype=wp.float64, device="cpu", pinned=pinned)
        self._viol_host = wp.empty(n, dtype=wp.float64, device="cpu", pinned=pinned)
        self._seeds_host = wp.zeros(SEEDS, dtype=wp.int32, device="cpu", pinned=pinned)
        self._staged = None  # the event after the last launches that read them (CUDA)
        self._pending = False  # a generation staged by stage_told, its update not launched yet
        self._updated = False  # whether an update ran (its sorts' scratch sized: capture may follow)
        self._graph = None  # launch_generation's steady state as one CUDA graph
        self.generation = 0
        self._asked = False  # whether a generation was asked and not told yet
        with _KERNELS_LOCK:
            self._eigh = eigh_kernel(d)
            self._launches = self._record()

    def _record(self) -> dict:
        """The generation's launches with their arguments packed once (Warp's recorded
        launch commands) on the sampler's own buffers, the seeds read on the device: the
        same launches every generation, so that the host's work per generation does not
        grow with the kernels' arguments and the sequence can be one CUDA graph."""
        from ..kernels.sampler import class_keys, cma_moments, cma_sample, cma_update, eig_factor, rank_keys, told_rows

        dev, n, K = self.device, self.batch, self.n_cat

        def rec(kernel, dim, inputs):
            return wp.launch(kernel, dim=dim, device=dev, inputs=inputs, record_cmd=True)

        return {
            "sample": rec(cma_sample, n, [self._seeds, self.state, self.category, 10 * self.dim, self._z, self._X]),
            "told": rec(
                told_rows,
                n,
                [self._told, self._X, K, self.dim, self._F, self._viol, self._U, self._told_cat, self._counts],
            ),
            "rank": rec(rank_keys, n, [self._F, self._viol, self._key, self._member]),
            "class": rec(class_keys, n, [self._member, self._F, self._viol, self._told_cat, self._ckey]),
            "moments": rec(
                cma_moments, (K, MOMENT_SLICES), [self._U, self._member, self._counts, self.state, self.part]
            ),
            "update": rec(
                cma_update, K, [self._seeds, self.part, self._member, self._counts, self._F, self._viol, self.state]
            ),
            "eigh": rec(self._eigh, K, [self.state.C, self._w, self._V]),
            "factor": rec(eig_factor, (K, self.dim), [self._w, self._V, self.state]),
        }

    @property
    def restarts(self) -> list[int]:
        """Restarts of each instance so far."""
        return self.state.restarts.numpy().tolist()

    @property
    def told_buffer(self) -> wp.array:
        """The device array (batch, dim [+ 1]) that :meth:`stage_told` tells: the caller of
        :meth:`launch_generation` writes the evaluated generation's coordinates there."""
        return self._told

    def ask(self, n: int) -> wp.array:
        if n != self.batch:
            raise ValueError(f"CMA-ES asks whole populations of {self.batch}, not {n}")
        if self._pending:
            raise RuntimeError("ask with a generation staged: launch_generation tells it")
        if self.generation == 0:
            X = _first_generation(self.batch, self.dim, self.categories, self.seed, self.device)
            wp.copy(self._X, X)
        else:
            self._stage_sample()
            wp.copy(self._seeds, self._seeds_host)
            self._launches["sample"].launch()
            self._record_staged()
            # a copy: a caller may keep it (a CPU array's NumPy view is the array itself)
            X = wp.clone(self._X)
        self._asked = True
        return X

    def tell(self, X, F, violation) -> None:
        if not self._asked:
            raise RuntimeError("tell without ask: tell the generation last asked")
        wp.copy(self._told, X if isinstance(X, wp.array) and X.device == self.device else _on(self.device, X))
        self.stage_told(F, violation)
        self.flush()

    def stage_told(self, F, violation) -> None:
        """Tell the generation asked, its coordinates in :attr:`told_buffer`: minimized F
        (n,) or (n, 1) and violations (n,) staged on the host; the device's update runs with
        the next :meth:`launch_generation` (or at :meth:`tell`, which calls this)."""
        if not self._asked:
            raise RuntimeError("tell without ask: tell the generation last asked")
        self._wait_staged()
        n = self.batch
        # the kernels mark failed members in F and the violations: copies, not the caller's
        self._F_host.numpy()[:] = _host(F).reshape(n, -1)[:, 0]
        self._viol_host.numpy()[:] = _host(violation).reshape(n)
        seeds = self._seeds_host.numpy()
        seeds[1], seeds[2] = _stream_seed(self.seed, self.generation, 1), int(self.generation == 0)
        self._pending, self._asked = True, False
        self.generation += 1

    def launch_generation(self, launch_evaluation) -> None:
        """The staged generation's update (:meth:`stage_told`, if one is staged), the next
        generation asked into its buffer, then ``launch_evaluation(asked)`` (launches on the
        device that evaluate it and write its coordinates into :attr:`told_buffer`): one
        sequence of launches with no host round trip, from generation 1 on. On a GPU the
        steady state (a staged update) is one CUDA graph, captured once an update has run
        (its sorts' scratch sized): a generation's dozen launches, two sorts and copies
        cost the host far more than the device's work on them (bench/README.md, "A
        generation as one graph"); ``launch_evaluation`` must launch the same work on the
        same arrays every call. The CPU launches them one by one (Warp's CPU capture is
        global to the process). The host reads the evaluation's results after a
        synchronization."""
        if self.generation == 0:
            raise RuntimeError("launch_generation asks from generation 1 on: ask the space-filling start")
        self._wait_staged()
        self._stage_sample()

        def launches():
            self._upload()
            if self._pending:
                self._update_launches()
            self._launches["sample"].launch()
            launch_evaluation(self._X)

        if self._pending and self._updated and self.device.is_cuda:
            if self._graph is None:
                with _KERNELS_LOCK, wp.ScopedCapture(self.device) as capture:
                    launches()
                self._graph = capture.graph
            wp.capture_launch(self._graph)
        else:
            launches()
        self._record_staged()
        self._pending, self._asked = False, True

    def flush(self) -> None:
        """Launch the update of a generation staged by :meth:`stage_told` (a search's last;
        :meth:`tell`'s own)."""
        if self._pending:
            self._wait_staged()
            self._upload()
            self._update_launches()
            self._record_staged()
            self._pending = False

    def _stage_sample(self) -> None:
        self._seeds_host.numpy()[0] = _stream_seed(self.seed, self.generation, 0)

    def _upload(self) -> None:
        wp.copy(self._F, self._F_host)
        wp.copy(self._viol, self._viol_host)
        wp.copy(self._seeds, self._seeds_host)

    def _record_staged(self) -> None:
        if self.device.is_cuda:
            self._staged = self.device.stream.record_event()

    def _wait_staged(self) -> None:
        if self._staged is not None:  # the last launches read the staged values
            wp.synchronize_event(self._staged)

    def _update_launches(self) -> None:
        n, cmds = self.batch, self._launches
        self._counts.zero_()
        cmds["told"].launch()
        cmds["rank"].launch()
        wp.utils.radix_sort_pairs(self._key, self._member, n)
        cmds["class"].launch()
        wp.utils.radix_sort_pairs(self._ckey, self._member, n)
        cmds["moments"].launch()
        cmds["update"].launch()
        cmds["eigh"].launch()
        cmds["factor"].launch()
        self._updated = True


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
    """Rows of F (N, M), all minimized, that no other row dominates: two objectives
    vectorized, O(N log N) (in lexicographic order a row is dominated exactly when an
    earlier, different row has a second objective <= its own; identical rows share their
    first one's fate); more, O(N x front size)."""
    F = np.asarray(F, dtype=float)
    if F.shape[1] == 2:
        mask = np.zeros(len(F), dtype=bool)
        order, on = lexsorted_front(F)
        mask[order] = on
        return mask
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


def lexsort_2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.lexsort((b, a))`` (by ``a``, then ``b``, then place), several times faster: one
    unstable ``argsort`` of ``a`` (NumPy's vectorized sort), then the runs of equal ``a``
    (NaN with NaN) put in order by ``lexsort`` alone; without ties that costs one compare.
    NSGA-II's survivors and the search's lineage front sort tens of thousands of rows a
    generation (``lexsort`` was most of the sampler's time)."""
    a, b = np.asarray(a), np.asarray(b)
    order = np.argsort(a)
    s = a[order]
    tie = (s[1:] == s[:-1]) | (np.isnan(s[1:]) & np.isnan(s[:-1]))
    if tie.any():
        run = np.zeros(len(a), dtype=bool)
        run[1:] |= tie
        run[:-1] |= tie
        at = np.flatnonzero(run)  # the runs stay where they are: only their members move
        sub = order[at]
        order[at] = sub[np.lexsort((sub, b[sub], a[sub]))]
    return order


def lexsorted_front(F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(order, on) of two-objective rows F (N, 2), both minimized: ``order`` sorts them
    lexicographically, ``on`` (over the sorted rows) marks those no other row dominates
    (:func:`pareto_mask`): ``order[on]`` is the front in lexicographic order."""
    order = lexsort_2(F[:, 0], F[:, 1])
    if not len(F):
        return order, np.zeros(0, dtype=bool)
    a, b = F[order, 0], F[order, 1]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (a[1:] != a[:-1]) | (b[1:] != b[:-1])
    firsts = np.flatnonzero(new)
    on = np.ones(len(firsts), dtype=bool)  # the first row: nothing before it
    on[1:] = b[firsts[1:]] < np.minimum.accumulate(b[firsts])[:-1]
    return order, on[np.cumsum(new) - 1]


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
    F = np.asarray(F, dtype=np.float64)
    feas = violation <= 0
    for j in range(F.shape[1]):  # column by column: a reduction along rows of 2 is slow
        feas &= np.isfinite(F[:, j])
    top = np.max(F[feas], axis=0) if np.any(feas) else np.zeros(F.shape[1])
    v = np.where(np.isfinite(violation), np.maximum(violation, 0), 1e300)
    G = (top + (np.abs(top) + 1.0)) + v[:, None]
    np.copyto(G, F, where=feas[:, None])
    return G


def fronts_and_crowding(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(front index, crowding distance) of each row of G (N, M), all minimized: two
    objectives in one sequential O(N log N) pass on the CPU
    (:func:`tawarp.kernels.sampler.fronts_2d`), more by :func:`nondominated_ranks` and
    :func:`crowding`."""
    from ..kernels.sampler import fronts_2d

    if G.shape[1] != 2:
        rank = nondominated_ranks(G)
        return rank, crowding(G, rank)
    N = G.shape[0]
    G = np.ascontiguousarray(G, dtype=np.float64)
    order = lexsort_2(G[:, 0], G[:, 1]).astype(np.int32)
    rank, crowd, last = np.empty(N, np.int32), np.empty(N), np.empty(N)
    links = np.empty((4, N), np.int32)  # head, tail, prev, succ

    def on_cpu(a):  # NumPy's memory seen by the kernel: no copies each generation
        return wp.array(a, dtype=wp.float64 if a.dtype == np.float64 else wp.int32, device="cpu", copy=False)

    wp.launch(
        fronts_2d,
        dim=1,
        device="cpu",
        inputs=[on_cpu(a) for a in (order, G, rank, crowd, last, *links)],
    )
    return rank.astype(np.int64), crowd


def survivors(rank: np.ndarray, crowd: np.ndarray, k: int) -> np.ndarray:
    """Places of the ``k`` best rows by front ``rank``, then crowding distance ``crowd``
    (larger first, ties by place), in place order: NSGA-II's truncation, the fronts before
    the one that fills ``k`` taken whole and only that one sorted."""
    if len(rank) <= k:
        return np.arange(len(rank))
    filled = np.cumsum(np.bincount(rank))
    r = int(np.searchsorted(filled, k))  # the first front with filled[r] >= k
    last = np.flatnonzero(rank == r)
    keep = rank < r
    keep[last[np.argsort(-crowd[last], kind="stable")[: k - (int(filled[r - 1]) if r else 0)]]] = True
    return np.flatnonzero(keep)


class BatchNsga2:
    """NSGA-II over ``dim`` unit-cube coordinates and ``categories`` (0: none; a category
    is inherited from a parent and redrawn with probability 1/(dim + 1)), population =
    ``batch``; generation 0 scrambled Sobol. The children are made on ``device``
    (:func:`tawarp.kernels.sampler.nsga_offspring`: binary tournament, SBX with ``eta_c``,
    polynomial mutation with ``eta_m``); the survivors of parents and children are chosen
    on the host by front, then crowding distance (:func:`fronts_and_crowding`) and the
    parents sent to the device: one copy per generation each way."""

    def __init__(
        self,
        dim: int,
        categories: int,
        batch: int,
        seed: int,
        eta_c: float = 15.0,
        eta_m: float = 20.0,
        n_objectives: int = 2,
        device: str | None = None,
    ):
        self.batch, self.seed, self.categories = batch, seed, categories
        checked_seed(seed, "BatchNsga2", integer=True)
        if n_objectives > 2 and batch > 4096:
            raise ValueError("NSGA-II with more than two objectives: batch at most 4096 (O(batch^2) sorting memory)")
        self.device = wp.get_device(device)
        self.n_mat = max(categories, 1)
        self.d = dim
        self.eta_c, self.eta_m = eta_c, eta_m
        self.pop = None  # (u, mat, F, violation) of the parents, on the host
        self._parents = None  # (u, mat, rank, crowding) of the parents, on the device
        self.generation = 0

    def _select(self, u, mat, F, viol):
        rank, cd = fronts_and_crowding(constrained_objectives(F, viol))
        order = survivors(rank, cd, self.batch)
        self._rank, self._cd = rank[order], cd[order]
        dev = self.device
        self._parents = (
            wp.array(np.ascontiguousarray(u[order]), dtype=wp.float64, device=dev),
            wp.array(mat[order].astype(np.int32), dtype=wp.int32, device=dev),
            wp.array(self._rank.astype(np.int32), dtype=wp.int32, device=dev),
            wp.array(self._cd, dtype=wp.float64, device=dev),
        )
        return u[order], mat[order], F[order], viol[order]

    def ask(self, n: int) -> wp.array:
        from ..kernels.sampler import nsga_offspring

        if n != self.batch:
            raise ValueError(f"NSGA-II asks whole populations of {self.batch}, not {n}")
        cols = self.d + (1 if self.categories else 0)
        if self.generation == 0:
            return _first_generation(self.batch, self.d, self.categories, self.seed, self.device)
        X = wp.empty((self.batch, cols), dtype=wp.float64, device=self.device)
        wp.launch(
            nsga_offspring,
            dim=self.batch,
            device=self.device,
            inputs=[
                _stream_seed(self.seed, self.generation, 0),
                *self._parents,
                float(self.eta_c),
                float(self.eta_m),
                self.n_mat,
                X,
            ],
        )
        return X

    def tell(self, X, F, violation) -> None:
        X = _host(X)
        u = X[:, : self.d]
        mat = X[:, self.d].astype(int) if self.categories else np.zeros(len(X), dtype=int)
        F = _host(F).reshape(len(X), -1)
        F = np.where(np.isfinite(F), F, np.inf)
        viol = _host(violation)
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
