"""Batched work spread over several workers (GPUs, machines, or CPU processes) with Dask
distributed.

One Dask worker per device, one thread each: a worker runs one chunk at a time on its
device, so each GPU holds one batch and a CPU worker one core's share. The client splits
the work into chunks, keeps a window of chunks in flight, and gathers the results in
order; every chunk is the same batched code a single process runs, so the results are
those of one process (the tests check 1e-12 on a local CPU cluster).

>>> from tawarp.distributed import local_cluster, fit_on_cluster
>>> client = local_cluster(["cuda:0", "cuda:1"])          # or ["cpu", "cpu"]
>>> res = fit_on_cluster(client, core, freqs, Y, names, start)  # doctest: +SKIP

Workers are processes by default (``processes=True``): a chunk's arrays are pickled and
sent over TCP, which costs more than the device time of a design point. With
``local_cluster(devices, processes=False)`` the workers are threads of this process, each
driving its own device: Dask hands them contiguous arrays by reference (pickle protocol
5 passes their buffers; a strided view is copied, under the GIL, so what travels here is
contiguous) and nothing crosses between processes (Warp's launches and copies release the
GIL; the first launches of a worker, which load Warp modules, run one worker at a time:
:func:`worker_state`).
A sweep sends no table either way (each worker makes its chunks' tables on its device,
:func:`tawarp.design.sweep.sweep`).

Other clusters (several machines): start one ``dask worker --nthreads 1`` per GPU with
``CUDA_VISIBLE_DEVICES`` set (each then sees its GPU as ``cuda``), connect a
``distributed.Client`` to the scheduler and pass it to :func:`fit_on_cluster`,
:class:`ClusterEvaluator` (design search) or :func:`tawarp.design.sweep.sweep` (``client=``).

``dask[distributed]`` is an optional dependency (``pip install tawarp[distributed]``).
"""

from __future__ import annotations

import dataclasses
import os
import threading
import uuid
from collections import deque

import numpy as np

from .model.forward import ForwardSettings

#: Chunks in flight per worker: one running, one queued, so a worker never waits on the client.
CHUNKS_IN_FLIGHT = 2


def _distributed():
    try:
        import distributed
    except ImportError:  # pragma: no cover - the message is the point
        raise ImportError("tawarp.distributed needs Dask distributed: pip install 'dask[distributed]'") from None
    return distributed


class DevicePlugin:
    """Worker plugin giving worker ``name`` (an int, as LocalCluster names them) the device
    ``devices[name % len(devices)]`` and ``cpu_threads`` threads for CPU batches. Workers
    without an integer name keep the default device."""

    def __init__(self, devices, cpu_threads: int = 1):
        self.devices = list(devices)
        self.cpu_threads = int(cpu_threads)

    def setup(self, worker):
        try:
            worker.tawarp_device = self.devices[int(worker.name) % len(self.devices)]
        except (TypeError, ValueError):
            worker.tawarp_device = None
        worker.tawarp_cpu_threads = self.cpu_threads


def local_cluster(devices=None, processes: bool = True, cpu_threads: int | None = None):
    """A :class:`distributed.Client` on a local cluster of one single-threaded worker per
    entry of ``devices`` (``"cuda:0"``, ``"cpu"``, ...; default: every GPU Warp sees,
    else two CPU workers). ``processes``: each worker a process (arrays pickled and sent
    over TCP), else a thread of this process (arrays passed by reference: what design
    evaluations need, see the module docstring). CPU workers split their batches over
    ``cpu_threads`` threads (default: an equal share of the cores this process may use)."""
    import warp as wp

    distributed = _distributed()
    if devices is None:
        wp.init()
        n_gpu = wp.get_cuda_device_count()
        devices = [f"cuda:{i}" for i in range(n_gpu)] if n_gpu else ["cpu", "cpu"]
    devices = list(devices)
    if not devices:
        raise ValueError("local_cluster: give at least one device")
    n_cpu = sum(d == "cpu" for d in devices)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    cluster = distributed.LocalCluster(
        n_workers=len(devices), threads_per_worker=1, processes=processes, dashboard_address=None
    )
    client = distributed.Client(cluster)
    client.register_plugin(_as_worker_plugin(DevicePlugin(devices, cpu_threads or max(1, cores // max(1, n_cpu)))))
    return client


def _as_worker_plugin(plugin: DevicePlugin):
    """``plugin`` as a :class:`distributed.WorkerPlugin` (built here: Dask is optional)."""
    distributed = _distributed()

    class _Plugin(distributed.WorkerPlugin):
        name = "tawarp-devices"

        def setup(self, worker):
            plugin.setup(worker)

    return _Plugin()


def worker_settings(settings: ForwardSettings | None) -> ForwardSettings:
    """``settings`` on this worker's device (:class:`DevicePlugin`); unchanged outside a
    worker or on a worker without an assigned device."""
    settings = settings or ForwardSettings()
    worker = _worker()
    device = getattr(worker, "tawarp_device", None)
    if device is None:
        return settings
    kw = {"device": device}
    if device == "cpu":
        kw["cpu_threads"] = getattr(worker, "tawarp_cpu_threads", 1)
    return dataclasses.replace(settings, **kw)


def _worker():
    """The Dask worker running this task, or None outside one."""
    try:
        return _distributed().get_worker()
    except ValueError:
        return None


#: Objects a worker keeps between the chunks of one job, per key (:func:`worker_state`);
#: those built outside a worker (``client=None``) are kept here.
_STATE: dict = {}
#: At most this many jobs' objects kept per worker (a job's key is new per job).
STATE_KEYS = 8
_BUILD = threading.Lock()


def worker_state(key: str, build):
    """The object ``build()`` made for ``key`` on this worker: built by the worker's first
    task of the job ``key`` and kept for its next tasks (an Evaluator, a device table).
    Kept per worker, not per process: worker threads of one process (``processes=False``)
    each have their own, on their own device. ``build`` runs under a process-wide lock and
    should end with a first launch: Warp modules then load one worker at a time (concurrent
    first loads of a CPU module can lose it: NVIDIA/warp#1705), and each worker compiles
    nothing another is compiling."""
    worker = _worker()
    if worker is None:
        cache = _STATE
    elif (cache := getattr(worker, "tawarp_state", None)) is None:
        cache = worker.tawarp_state = {}
    obj = cache.get(key)
    if obj is None:
        with _BUILD:
            obj = cache.get(key)  # (a worker of several threads may have built it meanwhile)
            if obj is None:
                obj = build()
                if len(cache) >= STATE_KEYS:
                    cache.clear()
                cache[key] = obj
    return obj


def ordered_map(client, func, items, *args, window: int | None = None):
    """``func(item, *args)`` for each item on the cluster, yielded in the items' order,
    with at most ``window`` (default: workers x :data:`CHUNKS_IN_FLIGHT`) in flight;
    ``client=None`` runs them here, one after the other."""
    if client is None:
        for item in items:
            yield func(item, *args)
        return
    window = window or CHUNKS_IN_FLIGHT * max(1, len(client.scheduler_info()["workers"]))
    shared = [client.scatter(a, broadcast=True) if _is_large(a) else a for a in args]
    pending = deque()
    for item in items:
        pending.append(client.submit(func, item, *shared, pure=False))
        if len(pending) >= window:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


def _is_large(a) -> bool:
    return isinstance(a, np.ndarray) and a.nbytes > 1 << 20


# -- batched fits ---------------------------------------------------------------------
def _fit_chunk(chunk: dict, core, freqs, names, kw: dict):
    from .fit.estimate import fit

    kw = dict(kw, settings=worker_settings(kw.get("settings")))
    if getattr(_worker(), "tawarp_device", None) is not None:
        kw["device"] = None  # the worker's device, in its settings
    return fit(
        core,
        freqs,
        chunk["Y"],
        names,
        chunk["start"],
        heat_input=chunk["heat_input"],
        fixed=chunk["fixed"],
        weights=chunk["weights"],
        **kw,
    )


def fit_on_cluster(
    client,
    core,
    freqs,
    Y,
    names,
    start=None,
    *,
    chunk: int = 4096,
    heat_input=0.0,
    fixed=None,
    weights=None,
    settings: ForwardSettings | None = None,
    **kw,
):
    """:func:`tawarp.fit.estimate.fit` of N problems split into chunks of ``chunk``
    problems over the cluster's workers; the same :class:`~tawarp.fit.result.FitResult`
    as one call (per-problem arrays concatenated in order; counts summed; ``seconds`` the
    wall time here). The adaptive cells are fixed once for the whole batch
    (:func:`tawarp.measure.kind.smooth_settings` on every problem's start), so no chunk
    fits a different model; with the margin of 2 on the heat model's k (h up to 4x), as
    the chunks cannot re-size at their solutions together the way one call does
    (:data:`tawarp.fit.estimate.FIT_K_FACTOR`): where cells are sized the results equal
    one call's with ``settings`` of these cells. Other keywords go to ``fit``."""
    import time

    from .fit.estimate import spread_starts, with_ties
    from .measure.kind import smooth_settings

    t0 = time.perf_counter()
    names = list(names)
    freqs = np.asarray(freqs, dtype=float)
    Y = np.asarray(Y)
    N = 1 if Y.ndim == 2 else Y.shape[0]
    if isinstance(start, dict):
        sized = {k: np.asarray(v, dtype=float) for k, v in start.items()}
    elif start is not None:
        sized = dict(zip(names, np.asarray(start, dtype=float).reshape(-1, len(names)).T))
    else:
        sized = dict(zip(names, spread_starts(core, names, kw.get("n_starts", 8), kw.get("seed", 0)).T))
    sized = with_ties(sized, kw.get("ties"))
    settings = smooth_settings(core, freqs, settings, {**sized, **(fixed or {})}, heat_input)

    def take(a, sl, ndim):
        """Problems ``sl`` of ``a`` where it has a problem axis (``ndim`` dimensions)."""
        if isinstance(a, dict):
            return {k: take(v, sl, 1) for k, v in a.items()}
        return np.asarray(a)[sl] if a is not None and np.ndim(a) >= ndim else a

    def take_weights(sl):
        # weights broadcast along the problems (np.broadcast_to: the same for all) travel as
        # their one row, which fit() broadcasts again: a slice of the broadcast would be sent
        # whole (Dask copies a strided array) and fitted as per-problem weights
        w = np.asarray(weights) if weights is not None and np.ndim(weights) >= 3 else None
        return w[:1] if w is not None and w.strides[0] == 0 else take(weights, sl, 3)

    chunks = [
        {
            "Y": take(Y, sl, 3),
            "start": take(start, sl, 2),
            "heat_input": take(heat_input, sl, 1),
            "fixed": take(fixed, sl, 1),
            "weights": take_weights(sl),
        }
        for sl in (slice(lo, min(N, lo + chunk)) for lo in range(0, N, chunk))
    ]
    parts = list(ordered_map(client, _fit_chunk, chunks, core, freqs, names, dict(kw, settings=settings)))
    res = concatenate_results(parts)
    res.seconds = time.perf_counter() - t0
    return res


def concatenate_results(parts):
    """One :class:`~tawarp.fit.result.FitResult` from results of consecutive problem chunks:
    arrays with the problem axis first and per-problem lists are joined in order,
    ``evaluations`` and ``launches`` summed, batch ``warnings`` joined without repeats,
    everything else (names, dof, bounds, ...) taken from the first part."""
    from .fit.result import ProblemWarnings

    first = parts[0]
    out = {}
    for f in dataclasses.fields(first):
        vals = [getattr(p, f.name) for p in parts]
        if f.name in ("evaluations", "launches"):
            out[f.name] = sum(vals)
        elif f.name == "seconds":
            out[f.name] = max(vals)
        elif f.name == "warnings":
            out[f.name] = list(dict.fromkeys(w for v in vals for w in v))
        elif f.name == "problem_warnings":
            out[f.name] = ProblemWarnings.concatenate(vals)
        elif (
            isinstance(vals[0], np.ndarray)
            and vals[0].ndim >= 1
            and f.name not in ("lower", "upper")
            and all(isinstance(v, np.ndarray) for v in vals)
            and len(parts) > 1
        ):
            out[f.name] = np.concatenate(vals)
        else:
            out[f.name] = vals[0]
    return type(first)(**out)


# -- design evaluations -----------------------------------------------------------------
def _evaluate_chunk(table: np.ndarray, key: str, spec: dict) -> dict:
    """Objectives of one chunk of a design table, on this worker's Evaluator for ``key``."""
    from .design.evaluate import Evaluator

    def build():
        ev = Evaluator(
            spec["space"],
            extra=spec["extra"],
            freqs=spec["freqs"],
            settings=worker_settings(spec["settings"]),
            onset=spec["onset"],
        )
        ev.evaluate_table(table[:, :1])  # loads the modules of every objective asked for
        return ev

    return worker_state(key, build).evaluate_table(table)


def _evaluate_sobol_chunk(task: tuple, key: str, spec: dict) -> dict:
    """Objectives of the Sobol points ``task`` = (lo, hi, seed) of the design space, drawn
    on this worker's device (:meth:`tawarp.design.space.DeviceTable.sobol`)."""
    from .design.evaluate import Evaluator
    from .design.space import DeviceTable

    def build():
        ev = Evaluator(
            spec["space"],
            extra=spec["extra"],
            freqs=spec["freqs"],
            settings=worker_settings(spec["settings"]),
            onset=spec["onset"],
        )
        tables = DeviceTable(spec["space"], ev.device)
        table = tables.sobol(0, 1, task[2])[0]
        ev.objectives_of(ev.evaluate_device(table), table)  # loads the modules (worker_state)
        return ev, tables

    ev, tables = worker_state(key, build)
    lo, hi, seed = task
    table = tables.sobol(lo, hi, seed)[0]
    return ev.objectives_of(ev.evaluate_device(table), table)


class ClusterEvaluator:
    """:class:`tawarp.design.evaluate.Evaluator`'s ``evaluate`` / ``evaluate_table`` over the
    cluster's workers: a table is cut into chunks of ``chunk`` points (default: the table
    in :data:`CHUNKS_IN_FLIGHT` chunks per worker), each evaluated by the worker's own
    Evaluator on its device. The chunks and the results (float64) travel through Dask:
    pickled between worker processes, by reference to worker threads
    (``local_cluster(..., processes=False)``)."""

    def __init__(
        self,
        client,
        space,
        extra=(),
        freqs=None,
        settings: ForwardSettings | None = None,
        chunk: int | None = None,
        onset=None,
    ):
        from .design.evaluate import DEFAULT_FREQS

        self.client, self.space, self.chunk = client, space, chunk
        self.settings = settings or ForwardSettings()
        self.spec = {
            "space": space,
            "extra": list(extra),
            "settings": self.settings,
            "freqs": DEFAULT_FREQS if freqs is None else freqs,
            "onset": onset,
        }
        self.key = uuid.uuid4().hex

    def _starts(self, n: int) -> range:
        """First points of the chunks of n points."""
        workers = max(1, len(self.client.scheduler_info()["workers"]))
        return range(0, max(n, 1), self.chunk or max(1, -(-n // (CHUNKS_IN_FLIGHT * workers))))

    def _gather(self, n: int, starts: range, parts) -> dict[str, np.ndarray]:
        """The chunks' objectives ``parts`` (in order) as (n,) arrays, each copied into
        place while the workers evaluate the next ones."""
        out = {}
        for lo, part in zip(starts, parts):
            for k, v in part.items():
                if k not in out:
                    out[k] = np.empty((n,) + v.shape[1:], dtype=v.dtype)
                out[k][lo : lo + len(v)] = v
        return out

    def evaluate_sobol(self, n: int, seed: int = 0, first: int = 0) -> dict[str, np.ndarray]:
        """Objectives of the points ``first`` .. ``first + n - 1`` of the space's scrambled
        Sobol sequence (``seed``; the points of a Sobol sweep and of
        :meth:`tawarp.design.space.DeviceTable.sobol`): a task is a chunk's point range,
        its points drawn and its table built on the worker's device, so no table travels;
        only the objectives come back."""
        starts = self._starts(n)
        tasks = ((first + lo, first + min(n, lo + starts.step), seed) for lo in starts)
        return self._gather(
            n, starts, ordered_map(self.client, _evaluate_sobol_chunk, tasks, self.key + "-sobol", self.spec)
        )

    def evaluate_table(self, varying) -> dict[str, np.ndarray]:
        """Objectives of a (1 + len(names), n) table (NumPy, or Warp on any device)."""
        table = varying.numpy() if hasattr(varying, "numpy") else np.asarray(varying, dtype=np.float64)
        n = table.shape[1]
        starts = self._starts(n)
        # the client thread copies each chunk out of the table (Dask pickles a column block,
        # which is not contiguous, element by element: seconds for 1e7 points) and each result
        # into place while the workers evaluate the others: only the first copy and the last
        # result's are not hidden
        chunks = (np.ascontiguousarray(table[:, lo : lo + starts.step]) for lo in starts)
        return self._gather(n, starts, ordered_map(self.client, _evaluate_chunk, chunks, self.key, self.spec))

    def evaluate(self, values: dict) -> dict[str, np.ndarray]:
        """Objectives of design points ``{variable: (n,) array}``."""
        return self.evaluate_table(self.space.varying_table(values))
