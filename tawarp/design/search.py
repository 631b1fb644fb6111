"""Design search over a thermoacoustic core: the loop that asks, evaluates and stores.

Generations of ``batch`` trials are asked as a whole (:mod:`tawarp.design.samplers`),
evaluated in one kernel launch (:class:`tawarp.design.evaluate.Evaluator`) and stored
(:mod:`tawarp.design.storage`). Objectives come from the table of
:mod:`tawarp.design.objectives`; the optional constraint is ``T_max <= T_limit`` (the
paper stops the RVC foam at 18 W for fear of combustion; 673 K is a typical limit for
carbon in air).

Two engines:

- ``engine="batched"`` (default): the batched CMA-ES (one objective) or NSGA-II
  (several), populations of ``batch``; trials stored with ``study.add_trials``.
- ``engine="optuna"``: Optuna's own ``CmaEsSampler(popsize=batch)`` (QMC startup batch) or
  ``NSGAIISampler(population_size=batch)`` through ``study.ask()``/``study.tell()``; the
  reference for small runs, and the measure of what per-trial sampling costs.

Studies persist: ``storage`` is a journal file path (default for the command line), an
RDB URL (``sqlite:///...``, ``postgresql://...``) for several workers, or None (memory).
Each worker owns a *lineage* (``worker`` name) of generations, claimed for the run
(:class:`tawarp.design.storage.WorkerClaim`: a second live process of the same name is
refused). The sampler state is not stored but replayed from the lineage's stored
generations, so a run killed at any point resumes exactly: members of a generation
missing from the storage are asked again and evaluated, none is lost or stored twice.
Several workers with different names share one study (an island model); ``n_trials``
counts the worker's own trials.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

from .evaluate import DEFAULT_FREQS, Evaluator
from .objectives import DEFAULT_T_LIMIT, directions, objective, signs
from .samplers import make_sampler
from .space import DesignSpace
from .storage import ATTR, StudyConflict, WorkerClaim, add_evaluated, best_designs, lineage, make_storage, open_study
from ..model.forward import ForwardSettings

@dataclass
class SearchResult:
    """``study`` (Optuna), ``best`` (list of dicts: the best feasible trial, or the
    feasible Pareto front for several objectives), ``timing`` (seconds: ``sampler``,
    ``evaluation``, ``storage``, ``wall``; ``evaluations``, ``evaluations_per_minute``,
    ``sampler_share``, ``evaluation_share``), ``resumed``: trials of a generation cut
    short (or asked and never told, Optuna engine) evaluated at start."""

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


def search(space: DesignSpace, objectives=("gradient",), n_trials: int = 1024, batch: int = 256, storage=None,
           study_name: str = "tawarp-design", worker: str = "w0", seed: int = 0, T_limit: float | None = DEFAULT_T_LIMIT,
           engine: str = "batched", settings: ForwardSettings | None = None, freqs=DEFAULT_FREQS,
           progress: bool = False, stale_after: float = 3600.0, onset=None, client=None, _stop_after: int | None = None,
           _crash_after: int | None = None) -> SearchResult:
    """Run (or resume) a batched design search; see the module docstring.

    ``n_trials``: trials of this worker's lineage in the study when done (rounded up to
    whole batches). ``seed``: with ``worker``, the seed of the worker's sampler stream
    (:func:`worker_seed`: workers of different names never share a stream). ``T_limit`` [K]: constraint ``T_max <= T_limit`` (None: none).
    ``onset``: how the onset objectives close the core (:class:`tawarp.design.objectives.OnsetSpec`;
    default the bundled ``standing_wave`` resonator). ``stale_after`` [s]: a same-name worker on another host counts as gone once its
    heartbeat is this old. ``client``: a Dask ``distributed.Client`` whose workers (one per
    device) evaluate each batch in equal shares (:class:`tawarp.distributed.ClusterEvaluator`).
    ``_stop_after`` / ``_crash_after``: test hooks that interrupt
    after asking that many batches (raise :class:`SearchCrash` / ``os._exit``)."""
    from ..progress import progress_bar

    objectives = tuple(objectives)
    directions(objectives)
    if engine not in ("batched", "optuna"):
        raise ValueError(f"engine must be 'batched' or 'optuna', got {engine!r}")
    if batch < 1 or n_trials < 1:
        raise ValueError("batch and n_trials must be >= 1")
    if not space.continuous:
        raise ValueError("the design space needs at least one continuous variable")
    t_wall = time.perf_counter()
    st = make_storage(storage)
    study = open_study(st, study_name, objectives, space.binding())
    claim = WorkerClaim(st, study_name, worker, stale_after)
    try:
        run = _Run(space, objectives, study, st, worker, T_limit, freqs, settings, onset, client)
        n_target = -(-n_trials // batch) * batch
        bar = progress_bar(n_target, f"design ({worker})", progress, unit="trial")
        try:
            if engine == "optuna":
                _search_optuna(run, n_target, batch, worker_seed(seed, worker), bar, claim, _stop_after, _crash_after)
            else:
                _search_batched(run, n_target, batch, worker_seed(seed, worker), bar, claim, _stop_after, _crash_after)
        finally:
            bar.close()
    finally:
        claim.release()
    timing = run.timing
    timing["wall"] = time.perf_counter() - t_wall
    timing["evaluations_per_minute"] = 60.0 * timing["evaluations"] / max(timing["wall"], 1e-12)
    for k in ("sampler", "evaluation", "storage"):
        timing[f"{k}_share"] = timing[k] / max(timing["wall"], 1e-12)
    return SearchResult(study, objectives, best_designs(study, objectives, T_limit), timing, run.resumed, worker)


def worker_seed(seed: int, worker: str) -> int:
    """Seed of ``worker``'s sampler stream: ``seed`` and the worker name mixed by NumPy's
    SeedSequence, so that workers of different names sample different points whatever
    ``seed``, and a rerun of one worker samples the same."""
    name = np.frombuffer(worker.encode("utf-8"), dtype=np.uint8).astype(np.uint32)
    return int(np.random.SeedSequence([int(seed), *name.tolist()]).generate_state(1)[0] % (2**31 - 2))


class _Run:
    """What one search run shares between its engines: evaluation, timing, storage."""

    def __init__(self, space, objectives, study, storage, worker, T_limit, freqs, settings, onset=None, client=None):
        self.space, self.objectives, self.study, self.storage = space, objectives, study, storage
        self.worker, self.T_limit = worker, T_limit
        if client is None:
            self.evaluator = Evaluator(space, extra=objectives, freqs=freqs, settings=settings, onset=onset)
        else:
            from ..distributed import ClusterEvaluator

            self.evaluator = ClusterEvaluator(client, space, extra=objectives, freqs=freqs, settings=settings,
                                              onset=onset)
        self.dists = space.distributions()
        self.sign = signs(objectives)
        self.timing = dict(sampler=0.0, evaluation=0.0, storage=0.0, evaluations=0)
        self.resumed = 0

    def evaluate(self, points: list[dict]):
        """(values (n, m) as objectives, metrics per point, minimized F (n, m), violation (n,)
        or None, failed (n,))."""
        t = time.perf_counter()
        m = self.evaluator.evaluate(self.space.values_of(points))
        self.timing["evaluation"] += time.perf_counter() - t
        self.timing["evaluations"] += len(points)
        values = np.stack([m[o] for o in self.objectives], axis=1)
        failed = ~np.all(np.isfinite(values), axis=1)
        viol = (m["T_max"] - self.T_limit) if self.T_limit is not None else None
        metrics = [{k: float(m[k][j]) for k in m} for j in range(len(points))]
        return values, metrics, values * self.sign, viol, failed

    def store(self, points, values, metrics, viol, failed, attrs) -> None:
        t = time.perf_counter()
        add_evaluated(self.study, self.storage, points, self.dists, values, metrics, viol, failed, attrs)
        self.timing["storage"] += time.perf_counter() - t


def _search_batched(run: _Run, n_target, batch, seed, bar, claim, stop_after, crash_after):
    """Ask / evaluate / store / tell generations; stored generations are told again."""
    space = run.space
    t = time.perf_counter()
    gens = lineage(run.study, run.worker)
    run.timing["storage"] += time.perf_counter() - t
    for g, trs in gens.items():
        if max(trs) >= batch:
            raise StudyConflict(f"study {run.study.study_name!r}, worker {run.worker!r}: generation {g} has members "
                                f"up to index {max(trs)}; resume with the same batch (> {max(trs)}), not {batch}")
    categories = len(space.material.choices) if space.material is not None else 0
    sampler = make_sampler(len(space.continuous), categories, batch, seed, len(run.objectives))
    done, asked = 0, 0
    while done < n_target:
        t = time.perf_counter()
        g = sampler.generation
        X = sampler.ask(batch)
        points = space.points_from_unit(X)
        stored = gens.get(g, {})
        missing = [j for j in range(batch) if j not in stored]
        run.timing["sampler"] += time.perf_counter() - t
        F = np.empty((batch, len(run.objectives)))
        viol = np.zeros(batch)
        if stored:
            ok = [j for j in stored if stored[j].state.name == "COMPLETE"]
            for j, tr in stored.items():
                if not _same_point(points[j], tr.params):
                    raise StudyConflict(f"study {run.study.study_name!r}, worker {run.worker!r}: generation {g} "
                                        f"member {j} was stored as {tr.params}, the sampler now asks {points[j]}; "
                                        f"resume with the seed and batch of the first run")
                points[j] = dict(tr.params)
                F[j] = np.array(tr.values) * run.sign if j in ok else np.inf
                viol[j] = tr.system_attrs.get("constraints", [0.0])[0] if j in ok else np.inf
        if missing:
            if not stored:
                asked += 1
                _interruption_hooks(asked, stop_after, crash_after)
            new = [points[j] for j in missing]
            values, metrics, Fm, vm, failed = run.evaluate(new)
            attrs = [{ATTR + "worker": run.worker, ATTR + "generation": g, ATTR + "index": j} for j in missing]
            run.store(new, values, metrics, vm, failed, attrs)
            F[missing] = np.where(failed[:, None], np.inf, Fm)
            viol[missing] = np.where(failed, np.inf, vm if vm is not None else 0.0)
            if stored:
                run.resumed += len(missing)
            claim.heartbeat()
        t = time.perf_counter()
        sampler.tell(space.unit_from_points(points), F, viol)
        run.timing["sampler"] += time.perf_counter() - t
        done += batch
        bar.update(batch)


def _same_point(a: dict, b: dict) -> bool:
    """Same design point, up to the rounding of a unit-cube round trip (1e-9 relative)."""
    return a.keys() == b.keys() and all(
        a[k] == b[k] if isinstance(a[k], str) else abs(a[k] - b[k]) <= 1e-9 * max(abs(a[k]), abs(b[k])) for k in a)


def _search_optuna(run: _Run, n_target, batch, seed, bar, claim, stop_after, crash_after):
    """Optuna's own samplers, one ``study.ask()`` per trial, one evaluation launch per batch."""
    import warnings

    import optuna
    from optuna.trial import TrialState

    study, storage, T_limit = run.study, run.storage, run.T_limit

    def constraints_func(trial):
        return [trial.user_attrs["T_max"] - T_limit]

    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning, module="tawarp.design")
    warnings.filterwarnings("ignore", message="Constraints have been set, but CmaEsSampler")
    if len(run.objectives) > 1:
        sampler = optuna.samplers.NSGAIISampler(population_size=batch, seed=seed,
                                                constraints_func=constraints_func if T_limit is not None else None)
    else:
        sampler = optuna.samplers.CmaEsSampler(popsize=batch, n_startup_trials=batch, seed=seed,
                                               independent_sampler=optuna.samplers.QMCSampler(seed=seed, scramble=True, warn_independent_sampling=False),
                                               warn_independent_sampling=False)
    study.sampler = sampler
    study_id = storage.get_study_id_from_name(study.study_name)

    def tell(numbers, points):
        values, metrics, _, viol, failed = run.evaluate(points)
        t = time.perf_counter()
        for j, num in enumerate(numbers):
            tid = storage.get_trial_id_from_study_id_trial_number(study_id, num)
            for k, v in metrics[j].items():
                storage.set_trial_user_attr(tid, k, v)
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
        t = time.perf_counter()
        trials = []
        for _ in range(batch):
            tr = study.ask(run.dists)
            storage.set_trial_system_attr(storage.get_trial_id_from_study_id_trial_number(study_id, tr.number),
                                          ATTR + "worker", run.worker)
            trials.append(tr)
        run.timing["sampler"] += time.perf_counter() - t
        asked += 1
        _interruption_hooks(asked, stop_after, crash_after)
        tell([tr.number for tr in trials], [tr.params for tr in trials])
        done += batch
        bar.update(batch)


def objective_definitions(objectives) -> dict:
    """``{name: {direction, units, definition}}`` of the objectives table (for reports)."""
    return {o: {"direction": objective(o).direction, "units": objective(o).unit,
                "definition": objective(o).long_name} for o in objectives}
