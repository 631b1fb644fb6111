"""Design search over a thermoacoustic core: the loop that asks, evaluates and stores.

Generations of ``batch`` trials are asked as a whole on the device
(:mod:`tawarp.design.samplers`), evaluated in one kernel launch from a table built there
(:class:`tawarp.design.evaluate.Evaluator`, :class:`tawarp.design.space.DeviceTable`),
their values and metrics copied to the host once, and stored (:mod:`tawarp.design.storage`,
committed every generation or every ``commit_seconds``). Objectives come from the table of
:mod:`tawarp.design.objectives`; the optional constraint is ``T_max <= T_limit`` (the
paper stops the RVC foam at 18 W for fear of combustion; 673 K is a typical limit for
carbon in air).

Two engines:

- ``engine="batched"`` (default): the batched CMA-ES (one objective) or NSGA-II
  (several), populations of ``batch``; each generation appended in bulk to the study's
  columnar trial store (a journal study's default), the study keeping copies of the best
  (``study.add_trials``); without a store every trial goes into the study.
- ``engine="optuna"``: Optuna's own ``CmaEsSampler(popsize=batch)`` (QMC startup batch) or
  ``NSGAIISampler(population_size=batch)`` through ``study.ask()``/``study.tell()``; the
  reference for small runs, and the measure of what per-trial sampling costs.

Studies persist: ``storage`` is a journal file path (default for the command line), an
RDB URL (``sqlite:///...``, ``postgresql://...``) for several workers, or None (memory).
Each worker owns a *lineage* (``worker`` name) of generations, claimed for the run
(:class:`tawarp.design.storage.WorkerClaim`: a second live process of the same name is
refused). The sampler state is not stored but replayed from the lineage's stored
generations (:func:`tawarp.design.storage.lineage`: the trial store and the study), so
a run killed at any point resumes exactly: members of a generation missing from the
storage are asked again and evaluated (the trial store commits whole generations), none
is lost or stored twice; copies the study misses (a run killed between the store and
the study) are added. A lineage is bound to the seed and batch of its first run
(:func:`tawarp.design.storage.bind_worker`: a resume with others is refused, naming
them); its stored points are told to the sampler as stored, so it resumes whatever the
sampler would ask now (a lineage stored by an earlier version of it included).
Several workers with different names share one study (an island model); ``n_trials``
counts the worker's own trials.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from .evaluate import DEFAULT_FREQS, Evaluator
from .generation import DeviceGeneration
from .objectives import DEFAULT_T_LIMIT, directions, objective, signs
from .samplers import fronts_and_crowding, lexsort_2, lexsorted_front, make_sampler, pareto_mask, check_batch
from .space import DesignSpace, DeviceTable
from .storage import (
    ATTR,
    COPY,
    StudyConflict,
    WorkerClaim,
    _member_ids,
    add_evaluated,
    best_designs,
    bind_store,
    bind_worker,
    copies_in_study,
    journal_batch,
    lineage,
    make_storage,
    open_study,
)
from ..io import interrupt_guard
from ..model.forward import ForwardSettings, resolve_device
from ..rng import checked_seed


@dataclass
class SearchResult:
    """``study`` (Optuna), ``best`` (list of dicts: the best feasible trial, or the
    feasible Pareto front for several objectives, as the study holds it: at most
    :data:`FRONT_COPIES` members per lineage), ``timing`` (seconds: ``sampler``,
    ``evaluation`` (a generation launched with its sampler's update and sample, CMA-ES on
    a local device: those too; ``sampler`` then is the host's staging), ``storage``
    (reads, the trial store, the study, the heartbeat),
    ``trial_store`` (its part appending to the trial store), ``wall``;
    ``trial_store_thread`` (the appends' own time in the trial store's thread, beside the
    search: with ``commit_seconds`` > 0 outside the parts of ``wall``); ``evaluations``,
    ``evaluations_per_minute``, ``trials_in_study`` (trials this run added to the Optuna
    study, copies included), ``*_share``: each over ``wall``), ``resumed``: trials of a
    generation cut short (or asked and never told, Optuna engine) evaluated at start."""

    study: object
    objectives: tuple
    best: list
    timing: dict
    resumed: int = 0
    worker: str = "w0"


class SearchCrash(RuntimeError):
    """Raised by the ``_stop_after`` test hook (a simulated interruption)."""


def _interruption_hooks(asked: int, stop_after: int | None, crash_after: int | None) -> None:
    """Test hooks simulating an interruption once ``asked`` batches are asked but not told:
    ``crash_after`` kills the process, ``stop_after`` raises :class:`SearchCrash`."""
    if crash_after is not None and asked >= crash_after:
        os._exit(3)
    if stop_after is not None and asked >= stop_after:
        raise SearchCrash(f"stopped after asking {asked} batches (test hook)")


def search(
    space: DesignSpace,
    objectives=("gradient",),
    n_trials: int = 1024,
    batch: int = 256,
    storage=None,
    study_name: str = "tawarp-design",
    worker: str = "w0",
    seed: int = 0,
    T_limit: float | None = DEFAULT_T_LIMIT,
    engine: str = "batched",
    settings: ForwardSettings | None = None,
    freqs=DEFAULT_FREQS,
    progress: bool = False,
    stale_after: float = 3600.0,
    onset=None,
    client=None,
    store=None,
    commit_seconds: float = 0.0,
    _stop_after: int | None = None,
    _crash_after: int | None = None,
) -> SearchResult:
    """Run (or resume) a batched design search; see the module docstring.

    ``n_trials``: trials of this worker's lineage in the study when done (rounded up to
    whole batches). ``seed``: with ``worker``, the seed of the worker's sampler stream
    (:func:`worker_seed`: workers of different names never share a stream). ``T_limit`` [K]: constraint ``T_max <= T_limit`` (None: none).
    ``onset``: how the onset objectives close the core (:class:`tawarp.design.objectives.OnsetSpec`;
    default the bundled ``standing_wave`` resonator). ``stale_after`` [s]: a same-name worker on another host counts as gone once its
    heartbeat is this old. ``client``: a Dask ``distributed.Client`` whose workers (one per
    device) evaluate each batch in equal shares (:class:`tawarp.distributed.ClusterEvaluator`).
    ``store``: where every evaluated trial goes (:mod:`tawarp.design.storage`): a folder
    for the columnar trial store; None: the study's own store, else the default beside a
    journal file, else none (a database URL or memory: every trial in the study); False:
    every trial in the study. The batched engine only: Optuna's own samplers keep every
    trial in the study. ``commit_seconds`` [s]: the evaluated generations are committed (made
    visible in the trial store, their rows written as they gather, and the heartbeat) at
    most this often, and at the end;
    0 commits every generation; the study's copies are written once, at the end
    (:meth:`_Run.commit`). A run killed between commits loses
    the generations evaluated since the last one (a resume evaluates them again, the same);
    committing once a second keeps a fast device busy (docs/design.md). ``_stop_after`` / ``_crash_after``: test hooks that interrupt
    after asking that many batches (raise :class:`SearchCrash` / ``os._exit``)."""
    from ..progress import progress_bar

    objectives = tuple(objectives)
    directions(objectives)
    if engine not in ("batched", "optuna"):
        raise ValueError(f"engine must be 'batched' or 'optuna', got {engine!r}")
    if batch < 1 or n_trials < 1:
        raise ValueError("batch and n_trials must be >= 1")
    checked_seed(seed, "search", integer=True)
    if T_limit is not None and not (math.isfinite(T_limit) and T_limit > 0):
        raise ValueError(f"T_limit [K] must be finite and > 0 (None: no limit), got {T_limit}")
    if not space.continuous:
        raise ValueError("the design space needs at least one continuous variable")
    if engine == "batched":  # before the study is made: a refused search leaves nothing behind
        check_batch(batch, len(space.material.choices) if space.material is not None else 0, len(objectives))
    t_wall = time.perf_counter()
    st = make_storage(storage)
    study = open_study(st, study_name, objectives, space.binding())
    trial_store = bind_store(study, storage, store) if engine == "batched" else None
    claim = WorkerClaim(st, study_name, worker, stale_after)
    run = None
    try:
        run = _Run(
            space, objectives, study, st, worker, T_limit, freqs, settings, onset, client, trial_store, commit_seconds
        )
        n_target = -(-n_trials // batch) * batch
        bar = progress_bar(n_target, f"design ({worker})", progress, unit="trial")
        try:
            with interrupt_guard() as run.interrupted:
                if engine == "optuna":
                    _search_optuna(run, n_target, batch, seed, bar, claim, _stop_after, _crash_after)
                else:
                    _search_batched(run, n_target, batch, seed, bar, claim, _stop_after, _crash_after)
        finally:
            bar.close()
    finally:
        if run is not None:
            run.close(claim)
        claim.release()
    timing = run.timing
    timing["wall"] = time.perf_counter() - t_wall
    timing["evaluations_per_minute"] = 60.0 * timing["evaluations"] / max(timing["wall"], 1e-12)
    for k in TIMED:
        timing[f"{k}_share"] = timing[k] / max(timing["wall"], 1e-12)
    # the best from the study's copies (the improvements of the best; several objectives: the
    # front, spread to FRONT_COPIES per lineage): reading a trial store of millions of rows
    # back would cost a fast device's search seconds
    best = best_designs(study, objectives, T_limit, copies=True)
    return SearchResult(study, objectives, best, timing, run.resumed, worker)


#: Members of a lineage's front (several objectives) copied into the study at a run's end,
#: spread along it (:func:`_spread`): the study is the summary that Optuna's tools open,
#: and each Optuna trial costs a journal entry and its read-back (about a millisecond),
#: while a fast device's front holds tens of thousands; the trial store holds every one
#: (:func:`tawarp.design.storage.best_designs` reads the whole front there).
FRONT_COPIES = 256
#: Members joined since the front's last merge that make a merge in any case (:meth:`_Run.kept`).
MERGE_AT_LEAST = 1 << 14
#: The timed parts of a search run (:class:`SearchResult`'s ``timing``), in seconds.
TIMED = ("sampler", "evaluation", "storage", "trial_store", "trial_store_thread")
#: Rows gathered before the trial store's thread writes them (:meth:`_Run.store_gathered`):
#: about 30 MB of a typical space's columns, a few HDF5 chunks of each.
WRITE_ROWS = 1 << 18


def worker_seed(seed: int, worker: str) -> int:
    """Seed of ``worker``'s sampler stream: ``seed`` and the worker name mixed by NumPy's
    SeedSequence, so that workers of different names sample different points whatever
    ``seed``, and a rerun of one worker samples the same."""
    seed = checked_seed(seed, "worker_seed", integer=True)
    name = np.frombuffer(worker.encode("utf-8"), dtype=np.uint8).astype(np.uint32)
    return int(np.random.SeedSequence([int(seed), *name.tolist()]).generate_state(1)[0] % (2**31 - 2))


class _Run:
    """What one search run shares between its engines: evaluation, timing, storage."""

    def __init__(
        self,
        space,
        objectives,
        study,
        storage,
        worker,
        T_limit,
        freqs,
        settings,
        onset=None,
        client=None,
        store=None,
        commit_seconds=0.0,
    ):
        self.space, self.objectives, self.study, self.storage = space, objectives, study, storage
        self.worker, self.T_limit, self.store = worker, T_limit, store
        self.commit_seconds = float(commit_seconds)
        #: raises KeyboardInterrupt once Ctrl-C was pressed (:func:`tawarp.io.interrupt_guard`)
        self.interrupted = lambda: None
        self.tables = None  # DeviceTable: a local evaluator's tables from device points
        self._generation = None  # DeviceGeneration: its arrays and launches (device_generation)
        if client is None:
            self.evaluator = Evaluator(space, extra=objectives, freqs=freqs, settings=settings, onset=onset)
            self.tables = DeviceTable(space, self.evaluator.device)
            self.device = self.evaluator.device
        else:
            from ..distributed import ClusterEvaluator

            self.evaluator = ClusterEvaluator(
                client, space, extra=objectives, freqs=freqs, settings=settings, onset=onset
            )
            self.device = resolve_device((settings or ForwardSettings()).device)
        # the coordinates told to the sampler, made on the device from the design values:
        # by one kernel whether the values are a new generation's or stored ones (a resume)
        self.coords = self.tables or DeviceTable(space, self.device)
        self.dists = space.distributions()
        self.sign = signs(objectives)
        self.timing = dict.fromkeys(TIMED, 0.0) | dict(evaluations=0, trials_in_study=0)
        self.resumed = 0
        self.writer = None
        # the lineage's feasible front so far (minimized, (objectives, members), in
        # lexicographic order, :meth:`kept`) and its members' ids (:func:`_member_ids`)
        self.front = np.zeros((len(objectives), 0))
        self.front_id = np.zeros(0, dtype=np.int64)
        self.best_value = np.inf  # one objective: the lineage's best feasible F so far (:meth:`kept`)
        self.joined = []  # members joined since the front's last merge: (F rows, ids)
        self.merges = 0  # of the front
        self.copies_pruned = (0, 0)  # the merges the copies were last pruned after, the copies left (:meth:`commit`)
        self.rows = []  # evaluated generations' rows not written yet: (g, index, values, metrics, viol, failed)
        self.rows_gathered = 0  # their number
        self.uncommitted = False  # rows written to the trial store since its last commit
        self.copies = []  # their kept members: (g, index, values, metrics, viol, F minimized)
        self.last_commit = time.perf_counter()
        self._appender = None  # the thread of the trial store's appends (commit_seconds > 0)
        self._appending = []  # its appends in flight (Futures), in order
        self._keeper = None  # the thread that keeps the copies (:meth:`keep`, commit_seconds > 0)
        self._keeping = []  # its generations in flight (Futures), in order

    def evaluate(self, values: dict):
        """(metrics {name: (n,)}, values (n, m) as objectives, minimized F (n, m),
        violation (n,) or None, failed (n,)) of design points ``values`` {variable: (n,)}."""
        t = time.perf_counter()
        m = self.evaluator.evaluate(values)
        self.timing["evaluation"] += time.perf_counter() - t
        return self._objectives(m)

    def evaluate_asked(self, X):
        """(design values {variable: (n,)}, the coordinates to tell the sampler (a Warp
        array on the device: :meth:`told`), then :meth:`evaluate`'s tuple) of the sampler
        coordinates ``X`` (a Warp array on the device): a local evaluator builds the table
        from them on the device and copies back the metrics and the values once
        (:class:`~tawarp.design.generation.DeviceGeneration`); a cluster's gets the values."""
        t = time.perf_counter()
        if self.tables is None:
            values = self.space.values_from_unit(X.numpy())
            m = self.evaluator.evaluate(values)
            told = None
        else:
            gen = self.device_generation(X.shape[0])
            gen.launches(X)
            values, m = gen.read()
            told = gen.told
        self.timing["evaluation"] += time.perf_counter() - t
        if told is None:
            told = self.told(values)
        return (values, told, *self._objectives(m))

    def device_generation(self, batch: int) -> DeviceGeneration:
        """The arrays and launches of a local evaluator's generations of ``batch`` (made once)."""
        if self._generation is None or self._generation.batch != batch:
            self._generation = DeviceGeneration(self.evaluator, self.tables, batch)
        return self._generation

    def launch_generation(self, sampler, n: int):
        """:meth:`evaluate_asked`'s tuple, less the told coordinates, of the next generation of
        ``sampler`` asked and evaluated on the device in one sequence of launches, the
        generation staged before it told in the same sequence
        (:meth:`tawarp.design.samplers.BatchCmaEs.launch_generation`)."""
        t = time.perf_counter()
        gen = self.device_generation(n)
        sampler.launch_generation(lambda X: gen.launches(X, told=sampler.told_buffer))
        values, m = gen.read()
        self.timing["evaluation"] += time.perf_counter() - t
        return (values, *self._objectives(m))

    def told(self, values: dict):
        """The sampler coordinates (a Warp array on the device) of design ``values``
        {variable: (n,)} (the material as its index): :meth:`DeviceTable.coordinates`."""
        t = time.perf_counter()
        told = self.coords.coordinates(np.stack([np.asarray(values[k], dtype=np.float64) for k in self.coords.names]))
        self.timing["sampler"] += time.perf_counter() - t
        return told

    def _objectives(self, m: dict):
        n = len(next(iter(m.values())))
        self.timing["evaluations"] += n
        vals = np.stack([m[o] for o in self.objectives], axis=1)
        failed = ~np.all(np.isfinite(vals), axis=1)
        viol = (m["T_max"] - self.T_limit) if self.T_limit is not None else None
        return m, vals, vals * self.sign, viol, failed

    def store_rows(self, g: int, index: np.ndarray, values: dict, metrics: dict, viol, failed) -> None:
        """Evaluated members ``index`` of generation ``g``: gathered for the trial store when
        the run has one (written once ``WRITE_ROWS`` are gathered, visible at the next
        commit, :meth:`commit`), else each into the study."""
        if self.store is not None:
            self.rows.append((g, index, values, metrics, viol, failed))
            self.rows_gathered += len(index)
            if self.commit_seconds > 0 and self.rows_gathered >= WRITE_ROWS:
                t = time.perf_counter()
                self.store_gathered(commit=False)
                self.timing["trial_store"] += time.perf_counter() - t
            return
        t = time.perf_counter()
        self.copy_to_study(g, index, values, metrics, viol, failed, copies=False)
        self.timing["storage"] += time.perf_counter() - t

    def commit(self, claim=None, final: bool = False) -> None:
        """The generations evaluated since the last commit: their rows into the trial store
        and ``claim``'s heartbeat into the study. With ``commit_seconds`` > 0 the appends
        run in a thread while the search goes on (:meth:`store_gathered`): a run killed
        before the commit's append ends loses that commit's generations too, which its
        resume evaluates again; at 0 each generation is stored before the next is asked.
        ``final`` (the run's end,
        whatever ended it): also the copies of the run's kept members that still are the
        lineage's best (several objectives: on its front now), in one journal lock and
        sync, chosen while the last append runs and written after it ends. The copies
        wait for the end because each Optuna trial costs the study a journal entry and a
        read-back (about a millisecond): several objectives' fronts change every
        generation; a run killed before its end leaves them to its resume, which keeps
        them again from the stored generations."""
        t = time.perf_counter()
        self.wait_kept()
        stored = self.store_gathered(commit=True)
        self.timing["trial_store"] += time.perf_counter() - t
        if len(self.objectives) > 1 and self.copies:  # members since dominated by a later generation's
            if final:  # exactly: those off the whole front
                self.merge_front()
                ids = np.concatenate([_member_ids(c[0], c[1]) for c in self.copies])
                on = np.sort(self.front_id)  # a bisection: NumPy's isin hashes, several times slower here
                at = np.minimum(np.searchsorted(on, ids), len(on) - 1)
                self.copies = _select_rows(self.copies, (on[at] == ids) if len(on) else np.zeros(len(ids), bool))
            elif (
                self.merges > self.copies_pruned[0] and sum(len(c[1]) for c in self.copies) > 2 * self.copies_pruned[1]
            ):
                # those the front merged since dominates, once they doubled: memory bounded, time amortized
                F = np.concatenate([c[5] for c in self.copies])
                self.copies = _select_rows(self.copies, ~_front_dominates(self.front, F))
                self.copies_pruned = (self.merges, sum(len(c[1]) for c in self.copies))
        copies, self.copies = (self.copies, []) if final else ([], self.copies)
        if len(self.objectives) > 1:
            copies = _spread(copies, FRONT_COPIES)
        if final:
            t_store = time.perf_counter()
            self.wait_store()  # the store before the copies
            self.timing["trial_store"] += time.perf_counter() - t_store
        with journal_batch(self.storage):  # the copies and the heartbeat: one lock and one sync
            for g, keep, values, metrics, c, _ in copies:
                if len(keep):
                    self.copy_to_study(g, keep, values, metrics, c, np.zeros(len(keep), bool))
            if claim is not None and (stored or copies):
                claim.heartbeat()
        self.timing["storage"] += time.perf_counter() - t
        self.last_commit = time.perf_counter()

    def store_gathered(self, commit: bool) -> bool:
        """The rows gathered since the last write into the trial store in one append and,
        with ``commit``, every row written made visible to readers; whether anything was
        stored. With ``commit_seconds`` > 0 in a thread of their own, in order, while the
        search goes on (h5py's writes release the GIL; the rows are joined there too: on
        the main thread NumPy's copies were a fast device's largest host cost). Rows are
        written once ``WRITE_ROWS`` are gathered, not only at commits, so that the run's
        last commit waits for those rows alone: on a fast device it waited for a whole
        commit's, which took islands on four GPUs a fifth of their time (bench/README.md,
        "The trial store written as rows gather"). At most one append waits behind the one running, which
        bounds the rows held; an earlier append's error is raised here."""
        rows, self.rows, self.rows_gathered = self.rows, [], 0
        commit = commit and (bool(rows) or self.uncommitted)
        if not rows and not commit:
            return False
        if self.writer is None:
            choices = {"material": list(self.space.material.choices)} if self.space.material is not None else {}
            self.writer = self.store.writer(self.worker, rows[0][0], choices, len(rows[0][1]))
        self.uncommitted = not commit
        if self.commit_seconds <= 0:
            self._append(rows, commit)
            return True
        self.wait_store(in_flight=1)
        if self._appender is None:
            from concurrent.futures import ThreadPoolExecutor

            self._appender = ThreadPoolExecutor(1, thread_name_prefix="tawarp-trial-store")
        self._appending.append(self._appender.submit(self._append, rows, commit))
        return True

    def _append(self, rows: list, commit: bool) -> None:
        """Generations' ``rows`` (:meth:`store_rows`) into the trial store, in one append
        (none: a commit alone)."""
        t = time.perf_counter()
        try:
            if not rows:
                self.writer.commit()
                return
            params = {k: np.concatenate([r[2][k] for r in rows]) for k in rows[0][2]}
            if self.space.material is not None:
                params["material"] = self.space.material_index(params["material"])
            self.writer.append(
                rows[0][0] if len(rows) == 1 else np.concatenate([np.full(len(r[1]), r[0]) for r in rows]),
                np.concatenate([r[1] for r in rows]),
                params,
                {k: np.concatenate([r[3][k] for r in rows]) for k in rows[0][3]},
                None if rows[0][4] is None else np.concatenate([r[4] for r in rows]),
                np.concatenate([r[5] for r in rows]),
                commit=commit,
            )
        finally:
            self.timing["trial_store_thread"] += time.perf_counter() - t

    def wait_store(self, in_flight: int = 0) -> None:
        """Wait until at most ``in_flight`` trial-store appends are in flight
        (:meth:`store_gathered`); the first error of those ended is raised here."""
        while self._appending and (len(self._appending) > in_flight or self._appending[0].done()):
            self._appending.pop(0).result()

    def keep(self, g: int, F: np.ndarray, viol: np.ndarray, values: dict, metrics: dict, copied=None) -> None:
        """Copies of generation ``g``'s members that the study keeps (:meth:`kept`; less
        those ``copied`` already), for the commit at the run's end. With ``commit_seconds``
        > 0 in a thread of its own, generations in order, while the sampler and the device
        go on (NumPy's sorts and searches release the GIL): on a fast device the host's
        storage work, this bookkeeping of the lineage front included, was over half of
        the wall time; :meth:`commit` waits for it. The arguments are the generation's
        own arrays, which nothing changes later."""
        if self.commit_seconds <= 0:
            self._keep(g, F, viol, values, metrics, copied)
            return
        if self._keeper is None:
            from concurrent.futures import ThreadPoolExecutor

            self._keeper = ThreadPoolExecutor(1, thread_name_prefix="tawarp-front")
        self._keeping.append(self._keeper.submit(self._keep, g, F, viol, values, metrics, copied))

    def _keep(self, g, F, viol, values, metrics, copied) -> None:
        keep = self.kept(g, F, viol)
        if copied is not None:
            keep = keep[~np.isin(keep, copied)]
        if keep.size:  # copies of the generation's kept members that the study lacks
            c = viol[keep] if self.T_limit is not None else None
            self.copies.append((g, keep, _rows_of(values, keep), _rows_of(metrics, keep), c, F[keep]))

    def wait_kept(self) -> None:
        """Wait for the generations :meth:`keep` has in flight; the first error, if any,
        is raised here."""
        keeping, self._keeping = self._keeping, []
        for f in keeping:
            f.result()

    def commit_due(self) -> bool:
        return time.perf_counter() - self.last_commit >= self.commit_seconds

    def copy_to_study(self, g, index, values, metrics, viol, failed, copies=True) -> None:
        """Members ``index`` of generation ``g`` as trials of the study (``copies``: of
        trial-store rows, marked so)."""
        rows = range(len(index))
        vals = np.stack([np.asarray(metrics[o], dtype=np.float64) for o in self.objectives], axis=1)
        metric_dicts = [{k: float(v[j]) for k, v in metrics.items()} for j in rows]
        attrs = [
            {
                ATTR + "worker": self.worker,
                ATTR + "generation": g,
                ATTR + "index": int(index[j]),
                **({COPY: True} if copies else {}),
            }
            for j in rows
        ]
        add_evaluated(
            self.study, self.storage, self.space.points_of(values), self.dists, vals, metric_dicts, viol, failed, attrs
        )
        self.timing["trials_in_study"] += len(index)

    def kept(self, g: int, F: np.ndarray, viol: np.ndarray) -> np.ndarray:
        """Members of a whole generation ``g`` (minimized F (batch, m), violations) whose
        copies the study keeps: one objective, the best feasible where it improves the
        lineage's best so far (which this updates); several, those that join the lineage's
        feasible Pareto front (which this updates; a member of a later generation may
        dominate one joined before the front's next merge: :meth:`commit` drops those
        copies). Generations come in order, a resume's stored ones too."""
        feas = np.flatnonzero((viol <= 0) & np.all(np.isfinite(F), axis=1))
        if not feas.size:
            return feas
        if F.shape[1] == 1:
            # only improvements: each Optuna trial costs the run's end about a millisecond,
            # and a converged CMA-ES lineage's later generations rarely beat its best
            best = feas[int(np.argmin(F[feas, 0]))]
            if not F[best, 0] < self.best_value:
                return feas[:0]
            self.best_value = F[best, 0]
            return np.array([best])
        X, ids = F[feas], _member_ids(g, feas)
        on = pareto_mask(X)
        # the front of the generations before, merged with the members since joined once
        # these are twice as many: each member joined is compared with a front at most
        # that many behind (so kept members may still leave at the merge, which the copies
        # follow), and a front that grows by thousands a generation is not sorted again
        # each time (the merges cost about 1.5 sorts of the last front in all)
        on[on] = ~_front_dominates(self.front, X[on])
        self.joined.append((X[on], ids[on]))
        if sum(len(j[1]) for j in self.joined) > max(2 * self.front.shape[1], MERGE_AT_LEAST):
            self.merge_front()
        return feas[on]

    def merge_front(self) -> None:
        """The members joined since the last merge into the front (:meth:`kept`)."""
        if self.joined:
            X, ids = (np.concatenate(c) for c in zip(*self.joined))
            self.front, self.front_id = _merged_front(self.front, self.front_id, X, ids)
            self.joined = []
            self.merges += 1

    def close(self, claim=None) -> None:
        """Commit what was evaluated (whole generations, whatever ended the run), close the
        trial store's file."""
        try:
            try:
                self.wait_kept()
            finally:  # the rows are stored whatever the copies' thread raised
                if self.rows or self.copies:
                    self.commit(claim, final=True)
            self.wait_store()
        finally:
            if self._keeper is not None:  # (an earlier error: its generations end first)
                self._keeper.shutdown()
            for appending in self._appending:  # an earlier error: the appends still end before the close
                appending.exception()
            if self._appender is not None:
                self._appender.shutdown()
            if self.writer is not None:
                self.writer.close()


def _search_batched(run: _Run, n_target, batch, seed, bar, claim, stop_after, crash_after):
    """Ask / evaluate / store / tell generations; stored generations are told again (and
    their copies in the study completed: a run may die between the two writes)."""
    space = run.space
    t = time.perf_counter()
    gens = lineage(run.study, run.worker)
    copied = {}  # generation: members whose copies the study holds
    for w, g, j in copies_in_study(run.study) if run.store is not None else ():
        if w == run.worker:
            copied.setdefault(g, []).append(j)
    bind_worker(run.study, run.worker, bool(gens), seed=seed, batch=batch)
    run.timing["storage"] += time.perf_counter() - t
    for g, rows in gens.items():  # a lineage stored before its seed and batch were recorded
        if rows["index"].max() >= batch:
            raise StudyConflict(
                f"study {run.study.study_name!r}, worker {run.worker!r}: generation {g} has members "
                f"up to index {rows['index'].max()}; resume with the same batch "
                f"(> {rows['index'].max()}), not {batch}"
            )
    categories = len(space.material.choices) if space.material is not None else 0
    sampler = make_sampler(
        len(space.continuous),
        categories,
        batch,
        worker_seed(seed, run.worker),
        len(run.objectives),
        run.device,
    )
    names = [v.name for v in space.variables]
    # a sampler that launches its own generations (CMA-ES) is told, asked and evaluated in
    # one sequence of launches from its generation 1 on, where the evaluator is this device's
    on_device = run.tables is not None and hasattr(sampler, "launch_generation")
    done, asked = 0, 0
    while done < n_target:
        run.interrupted()
        g = sampler.generation
        stored = gens.get(g)
        F = np.empty((batch, len(run.objectives)))
        viol = np.zeros(batch)
        told = None
        if stored is None and on_device and g > 0:
            asked += 1
            _interruption_hooks(asked, stop_after, crash_after)
            values, metrics, _, Fm, vm, failed = run.launch_generation(sampler, batch)
        else:
            t = time.perf_counter()
            if on_device:
                sampler.flush()
            X = sampler.ask(batch)
            if not isinstance(X, wp.array):
                X = wp.array(np.asarray(X, dtype=np.float64), dtype=wp.float64, device=run.device)
            run.timing["sampler"] += time.perf_counter() - t
            if stored is None:  # a new generation, evaluated from the points on the device
                asked += 1
                _interruption_hooks(asked, stop_after, crash_after)
                values, told, metrics, _, Fm, vm, failed = run.evaluate_asked(X)
        if stored is None:
            run.store_rows(g, np.arange(batch), values, metrics, vm, failed)
            F[:] = np.where(failed[:, None], np.inf, Fm)
            viol[:] = np.where(failed, np.inf, vm if vm is not None else 0.0)
        else:  # stored (a resume): the stored points are told, whatever the sampler asks now
            values, metrics = _stored_generation(run, g, stored, space.values_from_unit(X.numpy()), names, F, viol)
            told = run.told(values)
        t = time.perf_counter()
        if run.store is not None:
            run.keep(g, F, viol, values, metrics, copied.get(g))
        run.timing["storage"] += time.perf_counter() - t
        if run.commit_due():
            run.commit(claim)
        t = time.perf_counter()
        if told is None:  # its coordinates are on the device: told with the next launches
            sampler.stage_told(F, viol)
        else:
            sampler.tell(told, F, viol)
        run.timing["sampler"] += time.perf_counter() - t
        done += batch
        bar.update(batch)
    if on_device:
        sampler.flush()


def _spread(copies: list, k: int) -> list:
    """At most ``k`` of the front members ``copies`` (per generation: (g, index, values,
    metrics, violations, F)): all when they are no more, else the two ends of each
    objective and the members of largest crowding distance (ties: in order), so that the
    ones kept spread along the front."""
    from .samplers import crowding

    F = np.concatenate([c[5] for c in copies]) if copies else np.zeros((0, 0))
    if len(F) <= k:
        return copies
    # two objectives: the members are the front, whose crowding is one sequential pass
    # (the per-objective sorts of crowding() cost a fast device's search 0.3 s at 1M trials)
    dist = fronts_and_crowding(F)[1] if F.shape[1] == 2 else crowding(F, np.zeros(len(F), dtype=int))
    # the k largest, ties in order: those above the k-th largest, then the first at it
    kth = np.partition(dist, len(dist) - k)[len(dist) - k]
    keep = dist > kth
    keep[np.flatnonzero(dist == kth)[: k - int(keep.sum())]] = True
    return _select_rows(copies, keep)


def _select_rows(copies: list, on: np.ndarray) -> list:
    """``copies`` (per generation: (g, index, values, metrics, violations, F)) less the members where ``on`` (over all of
    them, in order) is False; generations left empty are dropped."""
    out, lo = [], 0
    for g, index, values, metrics, c, F in copies:
        m = on[lo : lo + len(F)]
        lo += len(F)
        if m.any():
            out.append((g, index[m], _rows_of(values, m), _rows_of(metrics, m), None if c is None else c[m], F[m]))
    return out


def _staircase_dominates(a: np.ndarray, b: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Rows of F (n, 2) that a row of a two-objective set dominates (all minimized), the
    set given sorted by its first objective ``a`` with ``b`` the least second objective
    of its rows so far: a row with a smaller first and a second <= F's, or a first <= F's
    and a smaller second, found by bisection."""

    def least_second(side):  # the least second objective of the sorted rows before F's
        k = np.empty(len(F), dtype=np.int64)
        k[order] = np.searchsorted(a, F[order, 0], side=side)  # sorted queries: a large set's cache
        return np.where(k > 0, b[np.maximum(k - 1, 0)], np.inf) if len(b) else np.full(len(k), np.inf)

    order = np.argsort(F[:, 0], kind="stable")
    return (least_second("left") <= F[:, 1]) | (least_second("right") < F[:, 1])


def _dominated(F: np.ndarray, front: np.ndarray, block: int = 1024) -> np.ndarray:
    """Rows of F (n, m) that a row of ``front`` dominates (all minimized): two objectives
    by :func:`_staircase_dominates`, more in blocks of rows (an (n, len(front)) comparison
    at once would not fit)."""
    if F.shape[1] == 2:
        order = lexsort_2(front[:, 0], front[:, 1])
        return _staircase_dominates(front[order, 0], np.minimum.accumulate(front[order, 1]), F)
    out = np.zeros(len(F), dtype=bool)
    for lo in range(0, len(F), block):
        f = F[lo : lo + block, None, :]
        out[lo : lo + block] = np.any(np.all(front <= f, axis=2) & np.any(front < f, axis=2), axis=1)
    return out


def _merged_front(front: np.ndarray, ids: np.ndarray, X: np.ndarray, xids: np.ndarray):
    """(front, ids) of the Pareto front (all minimized; duplicates kept, as
    :func:`pareto_mask` keeps them) of ``front`` (objectives, F) with ids ``ids`` and rows
    X (n, objectives) with ids ``xids``, its columns in lexicographic order (two
    objectives: a staircase for :func:`_staircase_dominates`)."""
    G, gid = np.concatenate([front.T, X]), np.concatenate([ids, xids])
    if G.shape[1] == 2:
        order, on = lexsorted_front(G)
        on = order[on]
    else:
        on = np.flatnonzero(pareto_mask(G))
        on = on[np.lexsort(G[on].T[::-1])]
    return np.ascontiguousarray(G[on].T), gid[on]


def _front_dominates(front: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Rows of X (n, objectives) that a row of ``front`` ((objectives, F), in
    lexicographic order: :func:`_merged_front`) dominates."""
    if X.shape[1] == 2:
        return _staircase_dominates(front[0], front[1], X)
    return _dominated(X, front.T)


def _rows_of(columns: dict, rows) -> dict:
    return {k: v[rows] for k, v in columns.items()}


def _stored_generation(run: _Run, g: int, stored: dict, values: dict, names, F, viol):
    """(values, metrics) of a generation stored in part or whole: the stored members as
    stored (filling ``F`` and ``viol`` at their places), the missing ones evaluated at the
    points asked and stored."""
    space, batch = run.space, len(F)
    idx = stored["index"]
    missing = np.setdiff1d(np.arange(batch), idx)
    metrics: dict[str, np.ndarray] = {}  # of the whole generation, by member

    def put(rows, cols):
        for k, v in cols.items():
            metrics.setdefault(k, np.full(batch, np.nan))[rows] = v

    for k in names:
        values[k][idx] = (
            space.material_index(stored["param:material"])
            if k == "material"
            else stored["param:" + k].astype(np.float64)
        )
    bad = stored["failed"].astype(bool)
    F[idx] = np.where(
        bad[:, None],
        np.inf,
        np.stack([stored["metric:" + o].astype(np.float64) for o in run.objectives], 1) * run.sign,
    )
    c = np.nan_to_num(stored["constraint"].astype(np.float64), nan=0.0)
    viol[idx] = np.where(bad, np.inf, c)
    put(idx, {k[7:]: v.astype(np.float64) for k, v in stored.items() if k.startswith("metric:")})
    if missing.size:
        new = _rows_of(values, missing)
        m, _, Fm, vm, failed = run.evaluate(new)
        run.store_rows(g, missing, new, m, vm, failed)
        F[missing] = np.where(failed[:, None], np.inf, Fm)
        viol[missing] = np.where(failed, np.inf, vm if vm is not None else 0.0)
        put(missing, m)
        run.resumed += len(missing)
    return values, metrics


def _search_optuna(run: _Run, n_target, batch, seed, bar, claim, stop_after, crash_after):
    """Optuna's own samplers, one ``study.ask()`` per trial, one evaluation launch per batch."""
    import warnings

    import optuna
    from optuna.trial import TrialState

    study, storage, T_limit = run.study, run.storage, run.T_limit
    seed = worker_seed(seed, run.worker)

    def constraints_func(trial):
        return [trial.user_attrs["T_max"] - T_limit]

    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning, module="tawarp.design")
    warnings.filterwarnings("ignore", message="Constraints have been set, but CmaEsSampler")
    if len(run.objectives) > 1:
        sampler = optuna.samplers.NSGAIISampler(
            population_size=batch, seed=seed, constraints_func=constraints_func if T_limit is not None else None
        )
    else:
        sampler = optuna.samplers.CmaEsSampler(
            popsize=batch,
            n_startup_trials=batch,
            seed=seed,
            independent_sampler=optuna.samplers.QMCSampler(seed=seed, scramble=True, warn_independent_sampling=False),
            warn_independent_sampling=False,
        )
    study.sampler = sampler
    study_id = storage.get_study_id_from_name(study.study_name)

    def tell(numbers, points):
        metrics, values, _, viol, failed = run.evaluate(run.space.values_of(points))
        t = time.perf_counter()
        for j, num in enumerate(numbers):
            tid = storage.get_trial_id_from_study_id_trial_number(study_id, num)
            for k, v in metrics.items():
                storage.set_trial_user_attr(tid, k, float(v[j]))
            if viol is not None:  # Optuna's own key: NSGA-II reads it, best_designs too
                storage.set_trial_system_attr(tid, "constraints", [float(viol[j])])
            if failed[j]:
                study.tell(num, state=TrialState.FAIL)
            else:
                study.tell(num, [float(x) for x in values[j]])
        run.timing["sampler"] += time.perf_counter() - t  # tell runs the sampler's after_trial
        claim.heartbeat()

    # the claim is ours: every RUNNING trial of this lineage was asked by a process now gone
    mine = [tr for tr in study.get_trials(deepcopy=False) if tr.system_attrs.get(ATTR + "worker") == run.worker]
    orphans = [tr for tr in mine if tr.state == TrialState.RUNNING]
    if orphans:
        tell([tr.number for tr in orphans], [tr.params for tr in orphans])
        run.resumed = len(orphans)
    done = len(mine)
    bar.update(min(done, n_target))
    asked = 0
    while done < n_target:
        run.interrupted()
        t = time.perf_counter()
        trials = []
        for _ in range(batch):
            tr = study.ask(run.dists)
            storage.set_trial_system_attr(
                storage.get_trial_id_from_study_id_trial_number(study_id, tr.number), ATTR + "worker", run.worker
            )
            trials.append(tr)
        run.timing["sampler"] += time.perf_counter() - t
        asked += 1
        _interruption_hooks(asked, stop_after, crash_after)
        tell([tr.number for tr in trials], [tr.params for tr in trials])
        done += batch
        bar.update(batch)


def objective_definitions(objectives) -> dict:
    """``{name: {direction, units, definition}}`` of the objectives table (for reports)."""
    return {
        o: {"direction": objective(o).direction, "units": objective(o).unit, "definition": objective(o).long_name}
        for o in objectives
    }
