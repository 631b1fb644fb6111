"""The host's CPU time of the loop, function by function (``bench/loop.py --host-time``).

Each function of :data:`TIMED` is wrapped to add up its thread's CPU time
(:func:`time.thread_time`) over its calls, less the time of the timed functions it calls:
its exclusive time, with the untimed code it runs (NumPy, Warp's launches and copies) in it.
A thread waiting for the GPU by blocking, or for its turn among loops run together
(:mod:`tawarp.fit.lockstep`), spends no CPU, so the times add up to the process's CPU time
on the loop's threads. Python's cyclic garbage collector has a line of its own
(:data:`GARBAGE_COLLECTION`), taken out of the function it interrupted. ``cProfile`` is no
guide here: it charges every Python call a few
microseconds of its own, and so weighs code of many small calls (Warp's launches and arrays,
the fits' bookkeeping) several times heavier than it is.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import importlib
import pkgutil
import threading
import time

import tawarp

#: {module: [function or Class.method, ...]}: the loop's stages (run, nesting, evidence),
#: the fits (LM, evaluations, covariances), the T-matrix kind and the forward engine's
#: launch, down to the functions that showed a share of their own.
TIMED = {
    "tawarp.loop.run": [
        "run_loop",
        "fit_base",
        "fit_models",
        "drift",
        "compare_models",
        "converge_window",
        "Comparison.linearize",
    ],
    "tawarp.loop.nesting": ["share_optima", "missing_subsets"],
    "tawarp.loop.goodness": ["smooth_fraction"],
    "tawarp.loop.evidence": [
        "effect_columns",
        "linearized_evidence",
        "model_priors",
        "_quadratic_optima",
        "_log_evidences",
        "_known_noise_group",
        "_noise_scale_group",
    ],
    "tawarp.fit.lockstep": ["Together._settle"],
    "tawarp.fit.lm": ["levenberg_marquardt", "stop_tests"],
    "tawarp.fit.problem_model": ["covariances"],
    "tawarp.fit.problems": [
        "_fit_together",
        "KindProblems._setup",
        "KindProblems.evaluate",
        "KindProblems._reduced_on_device",
        "KindProblems._reduced_on_host",
        "KindProblems.prediction",
        "KindProblems.at_solutions",
        "ValueLayout.table",
        "ValueLayout.neighbour_table",
        "kind_result",
        "run_sets",
        "residual",
    ],
    "tawarp.measure.tmatrix": ["TMatrixKind.predict", "TMatrixKind.predict_on_device", "TMatrixKind._launch"],
    "tawarp.model.effects": ["graded_parts"],
    "tawarp.model.forward": [
        "distinct_columns",
        "Engine.distinct",
        "Engine._computed",
        "Engine.device_table",
        "Engine.heat",
        "Engine._iterate_cells",
        "Engine.evaluate_serial",
        "Engine._adapted",
        "Engine._cascade",
        "Engine._cell_counts",
        "Engine._rerun",
    ],
    "tawarp.model.warm_starts": [
        "WarmStarts.starts",
        "WarmStarts.put",
        "DeviceWarmStarts.starts",
        "DeviceWarmStarts.put",
    ],
}


def _add(totals: dict, label: str, exclusive: float, inclusive: float) -> None:
    """One call of ``label`` into ``totals`` ({label: [exclusive s, inclusive s, calls]})."""
    got = totals.setdefault(label, [0.0, 0.0, 0])
    got[0] += exclusive
    got[1] += inclusive
    got[2] += 1


def _timed(label: str, f, totals: dict, local: threading.local):
    @functools.wraps(f)
    def timed(*args, **kw):
        stack = local.__dict__.setdefault("stack", [])
        start = time.thread_time()
        stack.append(0.0)
        try:
            return f(*args, **kw)
        finally:
            took = time.thread_time() - start
            inner = stack.pop()
            _add(totals, label, took - inner, took)
            if stack:
                stack[-1] += took

    return timed


#: The label of Python's cyclic garbage collector's time in :func:`thread_times`.
GARBAGE_COLLECTION = "(garbage collection)"


def _collections(totals: dict, local: threading.local):
    """A :data:`gc.callbacks` entry that adds each collection's thread time to
    :data:`GARBAGE_COLLECTION` and takes it out of the timed function it interrupted: a
    full collection of a large batch's objects takes tens of milliseconds, and fell on
    whichever function allocated at that moment."""

    def collection(phase: str, info: dict) -> None:
        if phase == "start":
            local.collecting = time.thread_time()
            return
        took = time.thread_time() - local.__dict__.pop("collecting", time.thread_time())
        _add(totals, GARBAGE_COLLECTION, took, took)
        stack = local.__dict__.get("stack")
        if stack:
            stack[-1] += took

    return collection


@contextlib.contextmanager
def thread_times():
    """While inside, every function of :data:`TIMED` adds up its time: yields {label:
    [exclusive s, inclusive s, calls]}, the garbage collector's under
    :data:`GARBAGE_COLLECTION`. A module-level function is replaced wherever a module of the
    package holds it (``from ... import`` copies included); all are put back on leaving. A
    name that is no longer there is an error: the list follows the code."""
    found = pkgutil.walk_packages(tawarp.__path__, "tawarp.")
    modules = [importlib.import_module(m.name) for m in found if not m.name.endswith("__main__")]
    totals: dict = {}
    local = threading.local()
    undo: list = []
    collection = _collections(totals, local)
    gc.callbacks.append(collection)
    try:
        for module_name, names in TIMED.items():
            module = importlib.import_module(module_name)
            for name in names:
                owner_name, _, attr = name.rpartition(".")
                owner = getattr(module, owner_name) if owner_name else module
                if attr not in vars(owner):
                    raise AttributeError(
                        f"bench/_host_time.py: {module_name}.{name} is not there (TIMED follows the code)"
                    )
                f = vars(owner)[attr]
                wrapped = _timed(name, f, totals, local)
                holders = [owner] if owner_name else [m for m in modules if vars(m).get(attr) is f]
                for holder in holders:
                    undo.append((holder, attr, f))
                    setattr(holder, attr, wrapped)
        yield totals
    finally:
        gc.callbacks.remove(collection)
        for holder, attr, f in reversed(undo):
            setattr(holder, attr, f)


def summary(totals: dict, cases: int, cpu_seconds: float) -> dict:
    """``totals`` of :func:`thread_times` over ``cases`` cases whose process took
    ``cpu_seconds`` of CPU: each function's exclusive and inclusive seconds, calls and
    exclusive milliseconds a case, the largest first, and the CPU outside them
    (``untimed_seconds``: the loops' threads between timed calls, and any other thread)."""
    rows = sorted(totals.items(), key=lambda kv: -kv[1][0])
    timed = sum(v[0] for _, v in rows)
    return {
        "cpu_seconds": cpu_seconds,
        "timed_seconds": timed,
        "untimed_seconds": cpu_seconds - timed,
        "functions": [
            {
                "function": label,
                "seconds": excl,
                "inclusive_seconds": incl,
                "calls": calls,
                "ms_per_case": 1e3 * excl / cases,
            }
            for label, (excl, incl, calls) in rows
        ],
    }
