"""The batched design search as islands, one per worker of a Dask cluster (one per GPU):
each island is :func:`tawarp.design.search.search` on its worker's device. Apart from
:mod:`tawarp.distributed`, which serves the search itself (the search's ``client=``
evaluates a batch across the workers), so that neither imports the other.

Where the islands write. With a journal file ``storage`` each island keeps its own
journal, ``<journal>.islands/<study name>/<island>.journal`` (its claim, heartbeat,
binding and copies of its best), and appends its trials to the study's trial store
(one file per island run there already): nothing of one island waits on another's lock
or reads another's log. The client then merges the islands' summaries
(:func:`island_summary`) into the study: with one objective each island's as it ends,
in island order, while the later ones still run (the client's trials take it about a
third of a millisecond each, so four islands' summaries merged after the last had ended
were two thirds of the call's tail on four H100s); with several, the front of all
islands' fronts once all are done, in one journal lock. A
journal's lock serializes every writer of the file, and each Optuna trial written costs
its writer a read-back of everything the others wrote since (half a millisecond a trial
on the 2-core development machine): with one journal for all, four islands on four H100s,
each writing its generations' bests at its end, spent 38 % of their wall time storing
and 19 % evaluating (``bench/multi_gpu.py``). A database URL serves concurrent
writers itself: there the islands store into the one study as :func:`search` does.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from urllib.parse import quote

import numpy as np

from ..distributed import submit_all, worker_addresses, worker_settings
from .objectives import DEFAULT_T_LIMIT, signs
from .search import FRONT_COPIES, TIMED, SearchResult, search
from .storage import (
    ATTR,
    COPY,
    _rows,
    add_evaluated,
    best_designs,
    bind_store,
    copies_in_study,
    journal_batch,
    make_storage,
    open_study,
)

#: Improvements of an island's best (one objective) its summary keeps at most, the latest:
#: each trial the client adds to the study costs it about half a millisecond (a journal
#: entry and its read-back), and a CMA-ES island improves its best in most generations
#: until it converges (every trial stays in the trial store, every improvement in the
#: island's journal).
SUMMARY_COPIES = 32


def island_journal(storage, study_name: str, island: str) -> Path:
    """The journal of ``island`` of the study ``study_name`` in the journal file ``storage``:
    ``<journal>.islands/<study name>/<island>.journal`` beside it."""
    folder = Path(storage).with_suffix(".islands") / quote(study_name, safe="")
    return folder / f"{quote(island, safe='')}.journal"


def island_summary(study, worker: str, objectives, T_limit) -> dict[str, np.ndarray]:
    """The copies of ``worker``'s trials in ``study`` that the islands' study keeps, as
    columns (those of :func:`tawarp.design.storage.trials_table`'s rows): one objective,
    the generations' bests that improved the island's best so far, in generation order
    (the last :data:`SUMMARY_COPIES`; the last is the island's best); several, the
    island's copies on its feasible front (its runs' fronts, spread along them)."""
    cols = _rows(study, copies=True)
    if not cols:
        return {}
    mine = np.flatnonzero(cols["worker"] == worker)
    mine = mine[np.lexsort((cols["index"][mine], cols["generation"][mine]))]
    F = _minimized(cols, mine, objectives, T_limit)
    ok = np.all(np.isfinite(F), axis=1)
    if len(objectives) == 1:
        f = np.where(ok, F[:, 0], np.inf)
        before = np.minimum.accumulate(np.concatenate([[np.inf], f[:-1]]))
        keep = np.flatnonzero(f < before)[-SUMMARY_COPIES:]
    else:
        from .samplers import pareto_mask

        keep = np.flatnonzero(ok)
        keep = keep[pareto_mask(F[keep])]
    return {k: v[mine[keep]] for k, v in cols.items()}


def _minimized(cols: dict, rows: np.ndarray, objectives, T_limit) -> np.ndarray:
    """The objectives of ``rows`` minimized (n, m); inf where a trial failed or is infeasible."""
    F = np.stack([cols["metric:" + o][rows].astype(np.float64) for o in objectives], axis=1) * signs(objectives)
    bad = cols["failed"][rows].astype(bool)
    if T_limit is not None:
        bad |= np.nan_to_num(cols["constraint"][rows].astype(np.float64), nan=0.0) > 0
    F[bad] = np.inf
    return F


def _island(island: tuple, kw: dict) -> dict:
    """One island's :func:`~tawarp.design.search.search`, ``island`` = (its lineage
    ``name``, ``own_journal``), on this worker's device, in its own journal where given:
    its timing, best, resumed count, and (own journal) its summary and binding for the
    islands' study."""
    name, own_journal = island
    kw = dict(kw, settings=worker_settings(kw.get("settings")))
    if own_journal is not None:
        kw["storage"] = own_journal
    res = search(worker=name, **kw)
    T_limit = kw.get("T_limit", DEFAULT_T_LIMIT)
    best = best_designs(res.study, res.objectives, T_limit, copies=True, worker=name)
    out = {"worker": name, "timing": res.timing, "best": [d["values"] for d in best], "resumed": res.resumed}
    if own_journal is not None:
        t = time.perf_counter()
        out["summary"] = island_summary(res.study, name, res.objectives, T_limit)
        out["binding"] = res.study.user_attrs.get(f"tawarp_worker:{name}")
        out["timing"] = dict(res.timing, summary=time.perf_counter() - t)
    return out


def search_islands(client, space, objectives=("gradient",), *, storage, islands: int | None = None, **kw):
    """The batched design search as islands, one per worker of ``client``: island i runs
    :func:`~tawarp.design.search.search` as worker ``island{i}`` (its own sampler stream,
    :func:`tawarp.design.search.worker_seed`) on its device, ``n_trials`` of its own, into
    the one study ``storage`` (a journal file or database URL the workers reach). The
    islands are independent (no migration): each is what it is run alone, so the study's
    trials equal running them one after another, an island resumes alone, and nothing
    waits on the slowest island; CMA-ES islands are parallel restarts from other streams,
    NSGA-II islands' fronts meet in the study's front.

    With a journal file (and a trial store: ``store`` not False) each island writes its
    own journal and the study's trial store (see the module docstring); the study gets
    each island's summary (:func:`island_summary`: one objective, the improvements of its
    best, each island's in one write once it and those before it have ended; several,
    the study's feasible front of the islands' fronts, at most
    :data:`~tawarp.design.search.FRONT_COPIES` spread along it, in one write once all
    have ended) and each lineage's binding (seed, batch). Every trial is in the trial store either way
    (:func:`tawarp.design.storage.trials_table`, :func:`~tawarp.design.storage.best_designs`).

    Returns a :class:`~tawarp.design.search.SearchResult`: the study opened here, the best
    of all islands, ``timing`` summed over the islands (``wall``, ``evaluations_per_minute``,
    ``merge`` (the summaries written here; ``merged``: the trials they added) and ``client``
    (this process's time outside the islands: opening, merging, the best) here; ``islands``: each one's timing, the
    objectives of its own best and its ``resumed`` count). ``islands``: how many (default: one per worker; more take
    turns on the workers). Other keywords go to ``search``."""
    if storage is None:
        raise ValueError("search_islands: the islands share one study; give storage= (a journal file or database URL)")
    t0 = time.perf_counter()
    workers = worker_addresses(client, fresh=True)
    islands = len(workers) if islands is None else int(islands)
    objectives = tuple(objectives)
    study_name = kw.get("study_name", "tawarp-design")
    T_limit = kw.get("T_limit", DEFAULT_T_LIMIT)
    st = make_storage(storage)
    study = open_study(st, study_name, objectives, space.binding())
    separate = _journal_path(storage) and kw.get("store") is not False and kw.get("engine", "batched") == "batched"
    kw = dict(kw, space=space, objectives=objectives, storage=storage)
    if separate:  # every island into the study's trial store, bound here once
        kw["store"] = str(bind_store(study, storage, kw.get("store")).path)
    names = [f"island{i}" for i in range(islands)]
    journals = [str(island_journal(storage, study_name, n)) if separate else None for n in names]
    for name, own in zip(names, journals):
        bound = study.user_attrs.get(f"tawarp_worker:{name}")
        if own is not None and bound is not None and not os.path.exists(own):
            # a lineage searched into the study itself (as search(worker=...) does) goes on in
            # its own journal bound to the same seed and batch, so that a resume with others is
            # refused as search refuses it
            open_study(own, study_name, objectives, space.binding()).set_user_attr(f"tawarp_worker:{name}", bound)
    t_client = time.perf_counter() - t0
    # in one message (submit_all): submitted one by one, the first island started 10 ms
    # before the others
    futures = submit_all(
        client, _island, list(zip(names, journals)), kw, workers=[workers[i % len(workers)] for i in range(islands)]
    )
    runs, merged, t_merge = [], 0, 0.0
    if separate and len(objectives) == 1:  # each island's summary its own: merged as it comes, in order
        for future in futures:
            runs.append(future.result())
            t = time.perf_counter()  # (the last island's: from here on the client alone)
            merged += _merge(study, st, space, runs[-1:], objectives, T_limit)
            t_merge += time.perf_counter() - t
    else:
        runs = client.gather(futures)
        t = time.perf_counter()
        merged = _merge(study, st, space, runs, objectives, T_limit) if separate else 0
        t_merge = time.perf_counter() - t
    best = best_designs(study, objectives, T_limit, copies=True)
    wall = time.perf_counter() - t0
    timing = {k: sum(r["timing"][k] for r in runs) for k in (*TIMED, "evaluations", "trials_in_study")}
    timing.update(
        wall=wall,
        evaluations_per_minute=60.0 * timing["evaluations"] / max(wall, 1e-12),
        merge=t_merge,
        merged=merged,
        client=t_client + time.perf_counter() - t,
    )
    timing["islands"] = [dict(r["timing"], worker=r["worker"], best=r["best"], resumed=r["resumed"]) for r in runs]
    return SearchResult(study, objectives, best, timing, sum(r["resumed"] for r in runs), ",".join(names))


def _journal_path(storage) -> bool:
    return isinstance(storage, (str, os.PathLike)) and "://" not in str(storage)


def _merge(study, storage, space, runs: list, objectives, T_limit) -> int:
    """The islands' summaries and bindings into ``study`` (in ``storage``), in one journal
    lock: one objective, every island's summary; several, the feasible front of all
    islands' summaries, at most FRONT_COPIES spread along it; none the study holds already
    (a resumed run's). Returns the trials added."""
    from .samplers import crowding, pareto_mask
    from .storage import _concat

    cols = _concat([r["summary"] for r in runs])
    n = len(cols.get("generation", ()))
    keep = np.arange(n)
    if n and len(objectives) > 1:
        F = _minimized(cols, keep, objectives, T_limit)
        keep = keep[pareto_mask(F)]
        if len(keep) > FRONT_COPIES:  # the widest spread: largest crowding distances, ties in order
            dist = crowding(F[keep], np.zeros(len(keep), dtype=int))
            keep = np.sort(keep[np.argsort(-dist, kind="stable")[:FRONT_COPIES]])
    held = copies_in_study(study)
    keys = zip(cols["worker"][keep], cols["generation"][keep].tolist(), cols["index"][keep].tolist()) if n else ()
    keep = np.array([i for i, k in zip(keep, keys) if k not in held], dtype=np.int64)
    bindings = {
        f"tawarp_worker:{r['worker']}": r["binding"]
        for r in runs
        if r["binding"] is not None and study.user_attrs.get(f"tawarp_worker:{r['worker']}") != r["binding"]
    }
    if not keep.size and not bindings:
        return 0
    with journal_batch(storage):
        for key, value in bindings.items():
            study.set_user_attr(key, value)
        if keep.size:
            params = [c for c in cols if c.startswith("param:")]
            metrics = [c for c in cols if c.startswith("metric:")]
            points = [
                {c[6:]: (v if isinstance(v, str) else float(v)) for c in params if (v := cols[c][i]) is not None}
                for i in keep
            ]
            add_evaluated(
                study,
                storage,
                points,
                space.distributions(),
                np.stack([cols["metric:" + o][keep].astype(np.float64) for o in objectives], axis=1),
                [{c[7:]: float(cols[c][i]) for c in metrics} for i in keep],
                None if T_limit is None else cols["constraint"][keep].astype(np.float64),
                cols["failed"][keep].astype(bool),
                [
                    {
                        ATTR + "worker": str(cols["worker"][i]),
                        ATTR + "generation": int(cols["generation"][i]),
                        ATTR + "index": int(cols["index"][i]),
                        COPY: True,
                    }
                    for i in keep
                ],
            )
    return int(keep.size)
