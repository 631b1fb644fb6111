"""The batched design search as islands, one per worker of a Dask cluster (one per GPU):
each island is :func:`tawarp.design.search.search` on its worker's device, all storing into
one study. Apart from :mod:`tawarp.distributed`, which serves the search itself (the
search's ``client=`` evaluates a batch across the workers), so that neither imports the
other."""

from __future__ import annotations

import time

from ..distributed import worker_settings
from .objectives import DEFAULT_T_LIMIT
from .search import SearchResult, search
from .storage import best_designs, open_study


def _island(name: str, kw: dict) -> dict:
    """One island's :func:`~tawarp.design.search.search` (lineage ``name``) on this
    worker's device: its timing, best and resumed count (the study stays in the shared storage)."""
    res = search(worker=name, **dict(kw, settings=worker_settings(kw.get("settings"))))
    best = best_designs(res.study, res.objectives, kw.get("T_limit", DEFAULT_T_LIMIT), copies=True, worker=name)
    return {"worker": name, "timing": res.timing, "best": [d["values"] for d in best], "resumed": res.resumed}


def search_islands(client, space, objectives=("gradient",), *, storage, islands: int | None = None, **kw):
    """The batched design search as islands, one per worker of ``client``: island i runs
    :func:`~tawarp.design.search.search` as worker ``island{i}`` (its own sampler stream,
    :func:`tawarp.design.search.worker_seed`) on its device, ``n_trials`` of its own, all
    storing into the one study ``storage`` (a journal file or database URL the workers
    reach). The islands are independent (no migration): each is what it is run alone, so
    the study equals running them one after another, resumes per island, and nothing waits
    on the slowest island; CMA-ES islands are parallel restarts from other streams, NSGA-II
    islands' fronts meet in the study's front. Returns a
    :class:`~tawarp.design.search.SearchResult`: the study opened here, the best of all
    islands, ``timing`` summed over the islands (``wall`` and ``evaluations_per_minute``
    here; ``islands``: each one's timing and the objectives of its own best). ``islands``:
    how many (default: one per worker; more take turns on the workers). Other keywords go
    to ``search``."""
    if storage is None:
        raise ValueError("search_islands: the islands share one study; give storage= (a journal file or database URL)")
    t0 = time.perf_counter()
    workers = list(client.scheduler_info()["workers"])
    islands = len(workers) if islands is None else int(islands)
    kw = dict(kw, space=space, objectives=tuple(objectives), storage=storage)
    futures = [
        client.submit(_island, f"island{i}", kw, workers=[workers[i % len(workers)]], pure=False)
        for i in range(islands)
    ]
    runs = client.gather(futures)
    wall = time.perf_counter() - t0
    study = open_study(storage, kw.get("study_name", "tawarp-design"), objectives, space.binding())
    timing = {
        k: sum(r["timing"][k] for r in runs)
        for k in ("sampler", "evaluation", "storage", "trial_store", "evaluations", "trials_in_study")
    }
    timing.update(wall=wall, evaluations_per_minute=60.0 * timing["evaluations"] / max(wall, 1e-12))
    timing["islands"] = [dict(r["timing"], worker=r["worker"], best=r["best"]) for r in runs]
    best = best_designs(study, objectives, kw.get("T_limit", DEFAULT_T_LIMIT), copies=True)
    return SearchResult(
        study, tuple(objectives), best, timing, sum(r["resumed"] for r in runs), ",".join(r["worker"] for r in runs)
    )
