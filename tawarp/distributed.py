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

Workers are processes by default (``processes=True``), each seeing its own GPU alone
(``CUDA_VISIBLE_DEVICES``) and running its host work (the fit's Levenberg-Marquardt
steps, a reducer's merges, a sampler) under its own GIL: what scales. What crosses
between processes is pickled and sent over TCP, which costs more than the device time of
a fit or a design point, so the work that scales makes its inputs where it runs and sends
back little: a sweep's and :meth:`ClusterEvaluator.evaluate_sobol`'s tasks are point
ranges (each worker draws its points and builds its tables on its device), a reduced
sweep returns its reductions, an island its best and summary, a fit of data already on
the workers (:func:`fit_on_cluster` of futures) its results, and the objectives of
``evaluate_sobol`` and a fit's per-problem arrays are written by the worker processes of
this host into shared memory (:class:`SharedColumns`; ``evaluate_sobol``'s files kept for
the next call once its result has gone, :class:`ChunkFiles`), and each worker process
keeps the memory it frees for its next chunk (:func:`keep_freed_memory`). The client's
part of a call is kept to a few messages: its tasks go to the scheduler in one
(:func:`submit_all`), results written to shared memory are waited for, not gathered
(:func:`wait_all`; ``evaluate_sobol``'s returns on its workers' posts in shared memory,
:class:`DoneBoard`), and the workers' list is asked at most once a second
(:func:`worker_addresses`); a GPU worker page-locks the fit data it keeps and fits again
(:func:`lock_for_uploads`). With ``local_cluster(devices, processes=False)`` the workers
are threads of this process, each driving its own device: Dask hands them contiguous
arrays by reference (pickle protocol 5 passes their buffers; a strided view is copied,
under the GIL, so what travels here is contiguous), which suits one GPU fed from this
process's arrays (a table, data in memory); their host work shares one GIL (Warp's
launches and copies release it; the first launches of a worker, which load Warp modules,
run one worker at a time: :func:`worker_state`).

Other clusters (several machines): start one ``dask worker --nthreads 1`` per GPU with
``CUDA_VISIBLE_DEVICES`` set (each then sees its GPU as ``cuda``), connect a
``distributed.Client`` to the scheduler and pass it to :func:`fit_on_cluster`,
:class:`ClusterEvaluator` (design search) or :func:`tawarp.design.sweep.sweep` (``client=``).

``dask[distributed]`` is an optional dependency (``pip install tawarp[distributed]``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import functools
import glob
import math
import mmap
import os
import pickle
import re
import sys
import threading
import time
import uuid
import weakref
from collections import deque

try:
    import fcntl
except ImportError:  # (Windows: no advisory locks; a killed process's files stay)
    fcntl = None

import numpy as np

from .model.forward import ForwardSettings, cpu_share
from .rng import checked_seed

#: Chunks in flight per worker: one running, one queued, so a worker never waits on the client.
CHUNKS_IN_FLIGHT = 2


def _distributed():
    try:
        import distributed
    except ImportError:  # pragma: no cover - the message is the point
        raise ImportError("tawarp.distributed needs Dask distributed: pip install 'dask[distributed]'") from None
    return distributed


class DevicePlugin:
    """Worker plugin giving worker ``name`` (an int, as :func:`local_cluster` names them)
    the device ``devices[name % len(devices)]`` and ``cpu_threads`` threads for CPU
    batches. Workers without an integer name keep the default device. ``pinned``: each
    worker a process of its own (:func:`local_cluster`), its GPU checked, its memory
    kept between chunks (:func:`keep_freed_memory`) and its :func:`housekeeping` done
    every :data:`HOUSEKEEPING_SECONDS` seconds."""

    def __init__(self, devices, cpu_threads: int = 1, pinned: bool = False):
        self.devices = list(devices)
        self.cpu_threads = int(cpu_threads)
        self.pinned = pinned

    def setup(self, worker):
        try:
            worker.tawarp_device = self.devices[int(worker.name) % len(self.devices)]
        except (TypeError, ValueError):
            worker.tawarp_device = None
        worker.tawarp_cpu_threads = self.cpu_threads
        if self.pinned:
            keep_freed_memory()
            # a pool's files unlinked while no task writes (the evaluator gone): their pages
            # go once this process drops its mappings of them
            from tornado.ioloop import PeriodicCallback

            check = PeriodicCallback(lambda: housekeeping(worker), 1000 * HOUSEKEEPING_SECONDS)
            worker.periodic_callbacks["tawarp-housekeeping"] = check
            check.start()
        if self.pinned and str(worker.tawarp_device).startswith("cuda"):
            # CUDA reads CUDA_VISIBLE_DEVICES once, when it starts: had something started it
            # before the variable was set, every worker would drive the first GPU
            import warp as wp

            wp.init()
            if wp.get_cuda_device_count() != 1:
                raise RuntimeError(
                    f"tawarp worker {worker.name}: sees {wp.get_cuda_device_count()} GPUs, not the one of "
                    f"CUDA_VISIBLE_DEVICES={os.environ.get('CUDA_VISIBLE_DEVICES')!r} (CUDA started before it was set)"
                )
            near_gpu(wp.get_device("cuda:0").pci_bus_id)


#: glibc's ``mallopt`` parameters (malloc.h) and the values a worker process sets:
#: blocks up to 32 MB (the most glibc allows) from its heap, the top of the heap
#: returned to the kernel only past 2 GB, and one heap for all its threads (a thread's
#: own arena gives its heaps back to the kernel whatever the trim threshold: the design
#: search's trial-store thread, which joins each commit's rows, faulted them in again at
#: every commit, 270k faults per island on four GPUs at once).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD, M_ARENA_MAX = -1, -3, -8
WORKER_MALLOC = {M_MMAP_THRESHOLD: 32 << 20, M_TRIM_THRESHOLD: (1 << 31) - 1, M_ARENA_MAX: 1}


def keep_freed_memory() -> bool:
    """This process's C heap keeps the memory it frees for the next allocations (glibc:
    :data:`WORKER_MALLOC`; False elsewhere). Dask's nanny starts a worker with
    ``MALLOC_TRIM_THRESHOLD_=65536``, which also fixes glibc's mmap threshold at 128 kB:
    every array above it is then a fresh mapping, its pages faulted in and zeroed again at
    every chunk, and the faults of several workers at once contend in the kernel (an
    island on each of four H100s: 115k faults and 0.5-0.7 s of kernel time in 2.4 s).
    A worker then holds its peak heap between chunks, as it needs it for the next, unless
    that nears its memory limit (:func:`housekeeping`)."""
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (AttributeError, OSError, TypeError):  # (not glibc; TypeError: Windows' CDLL(None))
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return all(mallopt(k, v) == 1 for k, v in WORKER_MALLOC.items())


#: Share of a worker's memory limit past which it gives its freed heap back to the kernel
#: (:func:`housekeeping`): below Dask's pause (0.8 of the limit by default), which a heap
#: kept whole could hold a worker in with no task running.
TRIM_SHARE = 0.6


def housekeeping(worker) -> bool:
    """What a worker process of :func:`local_cluster` does every :data:`HOUSEKEEPING_SECONDS`
    seconds: its mappings of unlinked shared files dropped (:func:`drop_unlinked_mappings`),
    and the heap it keeps (:func:`keep_freed_memory`) given back to the kernel where the
    process's memory passes :data:`TRIM_SHARE` of its limit. Returns whether it did so."""
    import ctypes

    drop_unlinked_mappings()
    limit = getattr(getattr(worker, "memory_manager", None), "memory_limit", None)
    if not limit or worker.monitor.get_process_memory() <= TRIM_SHARE * limit:
        return False
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (AttributeError, OSError, TypeError):  # (not glibc)
        return False
    return True


def gpu_cpus(pci_bus_id: str | None, devices: str = "/sys/bus/pci/devices") -> set[int] | None:
    """The CPUs of the NUMA node of the GPU ``pci_bus_id`` (Warp's ``Device.pci_bus_id``,
    ``domain:bus:device`` in hexadecimal), as the kernel lists them (``local_cpulist``
    under ``devices``); None where it does not say."""
    try:
        domain, bus, dev = pci_bus_id.split(":")
        with open(f"{devices}/{int(domain, 16):04x}:{int(bus, 16):02x}:{int(dev, 16):02x}.0/local_cpulist") as f:
            text = f.read().strip()
    except (AttributeError, ValueError, OSError):
        return None
    cpus = set()
    for part in filter(None, text.split(",")):
        lo, _, hi = part.partition("-")
        cpus.update(range(int(lo), int(hi or lo) + 1))
    return cpus or None


def cuda_mps_running() -> bool:
    """Whether NVIDIA's Multi-Process Service daemon runs (its control pipe, in
    ``CUDA_MPS_PIPE_DIRECTORY`` or the default folder): under it the kernels of processes
    that share a GPU run side by side, else the processes take turns on it, which small
    launches (a loop's fits) pay for (docs/loop.md, Speed)."""
    return os.path.exists(os.path.join(os.environ.get("CUDA_MPS_PIPE_DIRECTORY", "/tmp/nvidia-mps"), "control"))


#: The CUDA driver's flag (cuda.h ``CU_CTX_SCHED_BLOCKING_SYNC``) of a context whose host
#: threads wait for the device by blocking on a synchronization primitive, and the mask of
#: its scheduling flags.
CU_CTX_SCHED_BLOCKING_SYNC = 0x4
CU_CTX_SCHED_MASK = 0x7


@functools.cache
def _cuda_driver():
    """The CUDA driver library (ctypes), initialized, with the signatures of the calls that
    take pointers; None where there is none."""
    import ctypes

    try:
        cuda = ctypes.CDLL("nvcuda.dll" if sys.platform == "win32" else "libcuda.so.1")
    except OSError:
        return None
    cuda.cuMemHostRegister_v2.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint)
    cuda.cuMemHostUnregister.argtypes = (ctypes.c_void_p,)
    return cuda if cuda.cuInit(0) == 0 else None


def _context_flags(device) -> tuple | None:
    """(the CUDA driver, Warp's device ``device``, the flags of Warp's context there), read
    with that context current; None on the CPU, without a CUDA driver or where the driver
    will not say."""
    import ctypes

    import warp as wp

    device = wp.get_device(device)
    cuda = _cuda_driver()
    if not device.is_cuda or cuda is None:
        return None
    flags = ctypes.c_uint()
    with device.context_guard:
        if cuda.cuCtxGetFlags(ctypes.byref(flags)) != 0:
            return None
    return cuda, device, flags.value


def wait_by_blocking(device="cuda") -> bool:
    """Make the CUDA context Warp uses on ``device`` wait for the device by blocking its host
    thread (``CU_CTX_SCHED_BLOCKING_SYNC``) instead of CUDA's default, which spins on a core
    while there are fewer contexts than cores. A study runs one process per core or more,
    each waiting on the shared GPU at every read of its results: spinning, those waits take
    the cores the other processes' host work needs (docs/loop.md, Speed, "Blocking waits").
    The flag is set on the context itself (``cuCtxSetFlags``, CUDA 12.1 and later) after
    Warp has started it: Warp sets the primary context's flags as it starts a device, which
    would undo a flag set before. Returns whether the context waits by blocking now (False
    on the CPU, without a CUDA driver or where the driver has no ``cuCtxSetFlags``)."""
    got = _context_flags(device)
    if got is None or not hasattr(got[0], "cuCtxSetFlags"):
        return False
    cuda, device, flags = got
    with device.context_guard:
        if cuda.cuCtxSetFlags((flags & ~CU_CTX_SCHED_MASK) | CU_CTX_SCHED_BLOCKING_SYNC) != 0:
            return False
    return context_waits(device) == "blocking"


def require_blocking_waits(device="cuda") -> None:
    """:func:`wait_by_blocking`, or a :class:`RuntimeError` naming ``device`` where its
    context still does not wait by blocking: a study asked for blocking waits
    (``--blocking-waits``) is not run with spinning ones."""
    if not wait_by_blocking(device):
        raise RuntimeError(f"--blocking-waits: the CUDA driver did not take the flag on {device}")


def context_waits(device="cuda") -> str | None:
    """How the CUDA context Warp uses on ``device`` waits for the device: ``"blocking"``,
    ``"spin"``, ``"yield"`` or ``"auto"`` (CUDA's default); None on the CPU or without a
    CUDA driver."""
    got = _context_flags(device)
    if got is None:
        return None
    return {0: "auto", 1: "spin", 2: "yield", CU_CTX_SCHED_BLOCKING_SYNC: "blocking"}.get(
        got[2] & CU_CTX_SCHED_MASK, "auto"
    )


#: What sizes the thread pools of NumPy's and SciPy's linear algebra (OpenMP, OpenBLAS,
#: MKL) when a process loads it
BLAS_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def cores_shared(processes: int):
    """Processes spawned inside start with linear-algebra thread pools of their share of the
    cores (:func:`cpu_share` of ``processes``), set in the environment they inherit, as
    Dask's nanny starts its worker processes (one thread each); a variable set already is
    left as it is. Each pool is sized for the whole host otherwise: a study's 16 loop
    processes on 16 cores ran 16 pools of 16 threads, and gave 10-12 % fewer cases per
    second on a GPU under MPS (docs/loop.md, Speed; limiting the pools at run time, through
    threadpoolctl, gave no measurable gain). A forked process keeps its parent's pools:
    start the processes with the ``spawn`` method. Yields the share."""
    share = cpu_share(processes)
    unset = [k for k in BLAS_THREAD_VARIABLES if k not in os.environ]
    os.environ.update({k: str(share) for k in unset})
    try:
        yield share
    finally:
        for k in unset:
            os.environ.pop(k, None)


def near_gpu(pci_bus_id: str | None) -> None:
    """Every thread of this process (and those it starts later) on the CPUs of its GPU's
    NUMA node (:func:`gpu_cpus`), where that is fewer than it may use now: its host work,
    its pages (placed where they are first touched) and its copies to and from the GPU
    then stay on the GPU's side of the host, as dask-cuda's workers do; else unchanged."""
    if not hasattr(os, "sched_setaffinity"):
        return
    mine = os.sched_getaffinity(0)
    near = (gpu_cpus(pci_bus_id) or set()) & mine
    if not near or near == mine:
        return
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setaffinity(int(tid), near)
        except OSError:  # (a thread that ended meanwhile)
            pass


#: Seconds :func:`local_cluster` waits for its workers (a worker process imports Warp and
#: NumPy: seconds) before it stops them and raises.
START_TIMEOUT = 120.0


def local_cluster(devices=None, processes: bool = True, cpu_threads: int | None = None, timeout: float = START_TIMEOUT):
    """A :class:`distributed.Client` on a local cluster of one single-threaded worker per
    entry of ``devices`` (``"cuda:0"``, ``"cpu"``, ...; default: every GPU Warp sees,
    else two CPU workers). ``processes``: each worker a process of its own (its own GIL,
    so the host work of one worker never waits on another's), which sees its GPU alone
    (``CUDA_VISIBLE_DEVICES``, set as the process starts, before CUDA does: it makes no
    context on the other GPUs; checked as it joins), and CPU workers none; arrays sent to a process are pickled, so the work
    that scales keeps them where they are made (:func:`fit_on_cluster` of data on the
    workers, :meth:`ClusterEvaluator.evaluate_sobol`, reduced sweeps, islands). Else each
    worker is a thread of this process (arrays passed by reference, one GIL: see the
    module docstring). CPU workers split their batches over ``cpu_threads`` threads
    (default: an equal share of the cores this process may use). Raises
    :class:`TimeoutError` if the workers are not all up within ``timeout`` seconds."""
    import warp as wp

    distributed = _distributed()
    if devices is None:
        wp.init()
        n_gpu = wp.get_cuda_device_count()
        devices = [f"cuda:{i}" for i in range(n_gpu)] if n_gpu else ["cpu", "cpu"]
    devices = [_device_name(d) for d in devices]
    if not devices:
        raise ValueError("local_cluster: give at least one device")
    n_cpu = sum(d == "cpu" for d in devices)
    if processes:
        cluster = _process_cluster([_pinned_env(d) for d in devices])
        seen = ["cpu" if d == "cpu" else "cuda:0" for d in devices]  # each process sees its own GPU alone
    else:
        # the worker threads share this process's Warp runtime: started here, once, before
        # them (two threads starting it lazily at once can disturb a module load)
        wp.init()
        # (a free port for the scheduler's HTTP routes, as the process cluster's: two
        # clusters on one host asked for 8787 and one of them warned)
        cluster = distributed.LocalCluster(
            n_workers=len(devices),
            threads_per_worker=1,
            processes=False,
            dashboard_address=":0",
            scheduler_kwargs=dict(dashboard=False),
        )
        seen = devices
    try:
        client = distributed.Client(cluster, timeout=timeout)
        client.wait_for_workers(len(devices), timeout=timeout)
        threads = cpu_threads or cpu_share(n_cpu)
        client.register_plugin(_as_worker_plugin(DevicePlugin(seen, threads, pinned=processes)))
    except BaseException:
        cluster.close()
        raise
    return client


def _device_name(device: str) -> str:
    """``cpu`` or ``cuda:N`` (``cuda`` is ``cuda:0``); anything else raises."""
    if device == "cpu" or re.fullmatch(r"cuda:\d+", device):
        return device
    if device == "cuda":
        return "cuda:0"
    raise ValueError(f"local_cluster: device {device!r}: expected cpu, cuda or cuda:N")


def _pinned_env(device: str) -> dict:
    """The environment of the worker process of ``device``: ``CUDA_VISIBLE_DEVICES`` the
    one GPU it drives (the N-th of those this process sees), none for a CPU worker."""
    if device == "cpu":
        return {"CUDA_VISIBLE_DEVICES": ""}
    i = int(device.partition(":")[2])
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        ids = [v.strip() for v in visible.split(",") if v.strip()]
        if i >= len(ids):
            raise ValueError(f"local_cluster: {device} but CUDA_VISIBLE_DEVICES={visible!r} shows {len(ids)} GPUs")
        return {"CUDA_VISIBLE_DEVICES": ids[i]}
    return {"CUDA_VISIBLE_DEVICES": str(i)}


def _process_cluster(envs: list[dict]):
    """A local :class:`distributed.SpecCluster` of one single-threaded worker process per
    entry of ``envs``, worker i named i with the environment ``envs[i]`` (what
    :class:`distributed.LocalCluster` makes, less its one environment for all workers)."""
    import logging

    distributed = _distributed()
    from distributed.worker_memory import parse_memory_limit

    memory = parse_memory_limit("auto", 1, len(envs), logger=logging.getLogger("distributed"))
    common = dict(nthreads=1, host="127.0.0.1", protocol="tcp://", dashboard=False, silence_logs=logging.WARN)
    workers = {
        i: {"cls": distributed.Nanny, "options": dict(common, env=env, memory_limit=memory)}
        for i, env in enumerate(envs)
    }
    # the scheduler serves its HTTP routes (health, metrics) even without a dashboard: on a
    # free port (":0"), not on 8787 with a warning when another cluster of the host has it
    scheduler = {
        "cls": distributed.Scheduler,
        "options": dict(host="127.0.0.1", protocol="tcp://", dashboard=False, dashboard_address=":0"),
    }
    return distributed.SpecCluster(workers=workers, scheduler=scheduler, silence_logs=logging.WARN)


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
    window = window or CHUNKS_IN_FLIGHT * _workers(client)
    shared = [client.scatter(a, broadcast=True) if _is_large(a) else a for a in args]
    if isinstance(items, (list, tuple)) and len(items) <= window and not _holds_large(items):
        # all in flight at once, in one message (not one of arrays: the scheduler starts no
        # task before it has the whole message)
        for future in submit_all(client, func, items, *shared):
            yield future.result()
        return
    pending = deque()
    for item in items:
        pending.append(client.submit(func, item, *shared, pure=False))
        if len(pending) >= window:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()


def submit_all(client, func, items, *args, workers=None) -> list:
    """Futures of ``func(item, *args)`` for each of ``items``, sent to the scheduler in one
    message. The client sends its messages in batches, the first at once and the next no
    sooner than 10 ms after it (Dask's batched stream): tasks submitted one by one reach the
    scheduler as the first alone, then the others 10 ms later, so that one worker starts
    while the others wait (a fifth of a 4-GPU evaluation call). ``workers``: the worker each
    item goes to where it is there (else another takes it), for a worker that keeps
    something of that item's from a call before; None: the scheduler's choice (where the
    item's data lie)."""
    import dask

    items = list(items)
    if not items:
        return []
    keys = [f"{func.__name__}-{uuid.uuid4().hex}" for _ in items]
    columns = [items] + [[a] * len(items) for a in args]
    if workers is None:
        return client.map(func, *columns, key=keys, pure=False)
    # a worker per key: an annotation that maps each key to its worker (dask.annotate holds
    # it for this thread's submission alone)
    where = {k: [w] for k, w in zip(keys, workers)}
    with dask.annotate(workers=where.get, allow_other_workers=True):
        return client.map(func, *columns, key=keys, pure=False)


def wait_all(futures) -> None:
    """Return once every future of ``futures`` is done, raising the first one's error: for
    tasks whose results are not needed here (None; written where the client reads them),
    so none is gathered (a round trip to the scheduler and on to the workers)."""
    _distributed().wait(futures)
    for future in futures:
        if future.status != "finished":
            future.result()  # (its error, raised here)


#: Seconds a client's list of workers is kept (:func:`worker_addresses`) before it is
#: asked of the scheduler again.
WORKERS_SECONDS = 1.0


def worker_addresses(client, fresh: bool = False) -> list[str]:
    """The addresses of ``client``'s workers, sorted: asked of the scheduler at most every
    :data:`WORKERS_SECONDS` (a round trip, a millisecond or more, which two per call made
    a tenth of a 4-GPU evaluation call's head), for what a list a second old serves (the
    chunks' sizes, the workers they go to first: a task for a worker gone goes to
    another); ``fresh``: asked now, for tasks bound to each worker. Raises RuntimeError
    where the cluster has none.

    Asked with ``Client.nthreads``, whose answer is its own: ``Client.scheduler_info()``
    returns the client's copy of the scheduler's identity, which the client's periodic
    refresh (every 2 s, asking for no worker's) may overwrite between the answer and the
    return, so that it lists no workers (then :func:`tawarp.design.islands.search_islands`
    ran no island, and a reduced sweep reduced nothing)."""
    now = time.monotonic()
    held = getattr(client, "_tawarp_workers", None)
    if fresh or held is None or now - held[0] > WORKERS_SECONDS:
        workers = sorted(client.nthreads())
        if not workers:
            raise RuntimeError(
                "the Dask cluster has no workers: start some (client.wait_for_workers(n) waits for them)"
            )
        held = client._tawarp_workers = (now, workers)
    return held[1]


def _workers(client) -> int:
    return max(1, len(worker_addresses(client)))


def _is_large(a) -> bool:
    return isinstance(a, np.ndarray) and a.nbytes > 1 << 20


def _holds_large(a) -> bool:
    """Whether ``a`` (an array, or lists, tuples and dicts of them) holds a large array."""
    if isinstance(a, dict):
        return any(_holds_large(v) for v in a.values())
    if isinstance(a, (list, tuple)):
        return any(_holds_large(v) for v in a)
    return _is_large(a)


# -- batched fits ---------------------------------------------------------------------
def _fit_chunk(task: tuple, core, freqs, names, kw: dict, common: dict | None = None, out=None):
    """The fit of one chunk of problems, ``task`` = (chunk, its first problem, its problem
    count): ``chunk`` (``Y``, and ``weights``, ``start``, ``heat_input``, ``fixed`` where
    it has its own) over the entries of ``common``. With ``out`` (:class:`SharedColumns`,
    its layout unset) the per-problem numeric arrays are written to its rows and (the
    result without them, their layout) comes back, else (the result, None)."""
    from .fit.estimate import fit

    chunk, at, n = task
    if len(chunk["Y"]) != n:  # (its rows of a shared result would overlap another's)
        raise ValueError(
            f"fit_on_cluster: the chunk from problem {at} on holds {len(chunk['Y'])} problems, not {n}: "
            "give sizes the problems of each future, in order"
        )
    chunk = {"start": None, "heat_input": 0.0, "fixed": None, "weights": None, **(common or {}), **chunk}
    kw = dict(kw, settings=worker_settings(kw.get("settings")))
    if getattr(_worker(), "tawarp_device", None) is not None:
        kw["device"] = None  # the worker's device, in its settings
        if str(kw["settings"].device).startswith("cuda"):
            lock_for_uploads(chunk["Y"], kw["settings"].device)
    res = fit(
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
    return (res, None) if out is None else _shared_part(res, out, at)


#: Share of a worker's memory limit that the fit data it page-locks (:func:`lock_for_uploads`)
#: and its kept mappings of pooled result files (:func:`mapping_budget`) may take at most:
#: memory the kernel cannot swap.
LOCKED_SHARE = 0.5

_FITTED: dict = {}  # {id(owner): weak reference} of the data arrays fitted here once
_LOCKED: dict = {}  # {id(owner): bytes} of those page-locked (:func:`lock_for_uploads`)
_LOCKS = threading.Lock()


def fitted_again(a: np.ndarray) -> np.ndarray | None:
    """The array that owns the memory of ``a`` (its base, or ``a``) where this process
    has seen that memory here before (an earlier call), else None, and it is remembered
    (weakly: forgotten when the owner goes) for the next call. None for memory NumPy does
    not own (a mapping, another library's buffer)."""
    owner = a
    while isinstance(owner.base, np.ndarray):
        owner = owner.base
    if owner.base is not None or not owner.flags.owndata:
        return None
    key = id(owner)
    with _LOCKS:
        ref = _FITTED.get(key)
        if ref is not None and ref() is owner:
            return owner
        _FITTED[key] = weakref.ref(owner, lambda _, key=key: _forget(key))
    return None


def _forget(key: int) -> None:
    with _LOCKS:
        _FITTED.pop(key, None)


def lock_for_uploads(Y: np.ndarray, device) -> bool:
    """The memory of the fit data ``Y`` page-locked for the GPU ``device``'s driver
    (``cuMemHostRegister``) where this worker fits it a second time (:func:`fitted_again`),
    so that each of its later uploads is one DMA, not copies through the driver's staging
    buffer, which several workers' uploads at once slowed (4 H100s: fits 3.29x with
    pageable data, 3.67x with the data made page-locked: bench/README.md, section Several
    GPUs); unlocked as the array that owns the memory goes (its weak references are called
    before NumPy frees it). Data a worker keeps (:func:`fit_on_cluster` of futures) is
    fitted again so; data sent with each fit is new memory each time, never locked, and a
    fit done once pays nothing. Returns whether ``Y``'s memory is page-locked now: not for
    data the fit copies first (other than contiguous complex128), past :data:`LOCKED_SHARE`
    of the worker's memory limit (with the kept mappings of :func:`mapping_budget`), or
    where the driver refuses."""
    import ctypes

    import warp as wp

    if not (isinstance(Y, np.ndarray) and Y.dtype == np.complex128 and Y.flags.c_contiguous and Y.size):
        return False
    owner = fitted_again(Y)
    if owner is None:
        return False
    key = id(owner)
    limit = getattr(getattr(_worker(), "memory_manager", None), "memory_limit", None) or 0
    with _LOCKS:
        if key in _LOCKED:
            return True
        if sum(_LOCKED.values()) + _MAPPED_BYTES + owner.nbytes > LOCKED_SHARE * limit:
            return False
        name = str(wp.get_device(device))
        address = owner.ctypes.data
        try:
            with wp.get_device(name).context_guard:
                ok = _cuda_driver().cuMemHostRegister_v2(address, owner.nbytes, _CU_MEMHOSTREGISTER_PORTABLE) == 0
        except (OSError, AttributeError):
            ok = False
        if not ok:
            return False
        _LOCKED[key] = owner.nbytes
    # (not at exit: the driver unlocks a process's memory as it ends)
    weakref.finalize(owner, _unlock, key, name, ctypes.c_void_p(address)).atexit = False
    return True


def _unlock(key: int, device: str, address) -> None:
    import warp as wp

    with _LOCKS:
        _LOCKED.pop(key, None)
    with wp.get_device(device).context_guard:
        _cuda_driver().cuMemHostUnregister(address)


def _problem_arrays(res) -> dict[str, np.ndarray]:
    """The per-problem numeric arrays of a FitResult (problem axis first): what
    :func:`concatenate_results` joins, less the strings (whose width varies by chunk)."""
    return {
        f.name: v
        for f in dataclasses.fields(res)
        if isinstance(v := getattr(res, f.name), np.ndarray)
        and v.ndim >= 1
        and f.name not in ("lower", "upper")
        and v.dtype.kind in "biufc"
    }


def _shared_part(res, out: SharedColumns, at: int):
    """(``res`` less its per-problem numeric arrays, their layout), the arrays written to
    rows ``at`` .. of ``out``; (``res``, None) where ``out`` has not the room or is gone."""
    arrays = _problem_arrays(res)
    layout = {k: (v.dtype.str, v.shape[1:]) for k, v in arrays.items()}
    cols = out.sized(layout, len(res.values))
    if cols is None:
        return res, None
    try:
        cols.write(at, arrays)
    except OSError:  # the shared memory filled meanwhile: the arrays travel instead
        return res, None
    return dataclasses.replace(res, **dict.fromkeys(arrays)), layout


def _joined_parts(parts, n: int, starts: list, out: SharedColumns | None):
    """One FitResult of the (result, layout) ``parts`` of consecutive chunks of ``n``
    problems, the chunks' first problems ``starts``: the per-problem arrays that workers
    wrote to ``out`` mapped from it (those of a part that could not write them copied
    there), the rest joined by :func:`concatenate_results`."""
    if out is None:
        return concatenate_results((res for res, _ in parts), n)
    rest, travelled, layout = [], [], None
    for at, (res, lay) in zip(starts, parts):
        if lay is None:
            arrays = _problem_arrays(res)
            travelled.append((at, arrays))
            res = dataclasses.replace(res, **dict.fromkeys(arrays))
        elif layout is None:
            layout = lay
        elif lay != layout:
            raise ValueError(f"fit_on_cluster: the chunks' per-problem arrays differ: {lay} and {layout}")
        rest.append(res)
    if layout is None:  # no worker had the room: every part's arrays travelled
        return concatenate_results([dataclasses.replace(r, **a) for r, (_, a) in zip(rest, travelled)], n)
    cols = dataclasses.replace(out, layout=layout).columns()
    for at, arrays in travelled:
        for k, v in arrays.items():
            cols[k][at : at + len(v)] = v
    return dataclasses.replace(concatenate_results(rest, n), **cols)


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
    sizes=None,
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
    one call's with ``settings`` of these cells. Other keywords go to ``fit``.

    ``Y`` may also be data already on the workers: a list of Dask futures, each of a
    chunk's ``{"Y": (n, m, 4), "weights": ...}`` (made or read by a task on a worker:
    ``client.submit(load, ...)``), fitted in the list's order by the worker that holds it,
    so that no data travel and only the results come back; ``start``, ``heat_input``,
    ``fixed`` and ``weights`` given here then hold for every problem (the cells are sized
    on them), a chunk's own ``weights`` for its problems. ``sizes``: the problems of each
    future, where the caller knows them (else asked of the workers first: a round trip
    before any fit starts, tens of milliseconds); each chunk is checked against its size."""
    from .measure.kind import smooth_settings

    t0 = time.perf_counter()
    names = list(names)
    freqs = np.asarray(freqs, dtype=float)
    on_workers = isinstance(Y, (list, tuple)) and bool(Y) and all(_is_future(y) for y in Y)
    if on_workers:
        w = None if weights is None else np.asarray(weights)
        lead = () if w is None else w.shape[: -2 if w.shape[-1] == 4 else -3]
        if np.ndim(start) > 1 or np.ndim(heat_input) or int(np.prod(lead)) > 1:
            raise ValueError(
                "fit_on_cluster: with the data on the workers, start (p,), heat_input (a scalar) and "
                "weights (m, 4) hold for every problem: put per-problem values in the chunks' dicts"
            )
        if (
            isinstance(start, dict)
            and any(np.ndim(v) for v in start.values())
            or any(np.ndim(v) for v in (fixed or {}).values())
        ):
            raise ValueError("fit_on_cluster: with the data on the workers, start and fixed values are scalars")
        common = {"start": start, "heat_input": heat_input, "fixed": fixed, "weights": weights}
        settings = smooth_settings(
            core, freqs, settings, {**_sized_starts(core, names, start, kw), **(fixed or {})}, heat_input
        )
        if sizes is None:
            sizes = client.gather(submit_all(client, _problems, Y))  # (where each lies)
        elif len(sizes) != len(Y):
            raise ValueError(f"fit_on_cluster: {len(sizes)} sizes for {len(Y)} chunks of data")
        sizes = [int(m) for m in sizes]
        res = _fit_parts(client, Y, sizes, (core, freqs, names, dict(kw, settings=settings), common))
        res.seconds = time.perf_counter() - t0
        return res
    Y = np.asarray(Y)
    N = 1 if Y.ndim == 2 else Y.shape[0]
    settings = smooth_settings(
        core, freqs, settings, {**_sized_starts(core, names, start, kw), **(fixed or {})}, heat_input
    )

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

    slices = [slice(lo, min(N, lo + chunk)) for lo in range(0, N, chunk)]
    chunks = [
        {
            "Y": take(Y, sl, 3),
            "start": take(start, sl, 2),
            "heat_input": take(heat_input, sl, 1),
            "fixed": take(fixed, sl, 1),
            "weights": take_weights(sl),
        }
        for sl in slices
    ]
    sizes = [sl.stop - sl.start for sl in slices]
    res = _fit_parts(client, chunks, sizes, (core, freqs, names, dict(kw, settings=settings), None))
    res.seconds = time.perf_counter() - t0
    return res


def _fit_parts(client, chunks: list, sizes: list, args: tuple):
    """The FitResult of ``chunks`` (dicts or futures of them) of ``sizes`` problems, each
    fitted by :func:`_fit_chunk` with ``args`` on the cluster. Worker processes of this
    host write the per-problem arrays into one shared-memory file (:class:`SharedColumns`)
    that becomes the result's arrays: the client neither receives nor copies them, which
    for the last round of chunks, all arriving together, was the serial tail of a fit on
    several GPUs (a microsecond per problem)."""
    n = int(sum(sizes))
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int).tolist()
    out = None
    if client is not None and n and _local_processes(client):
        out = SharedColumns.create(n, None, writers=_workers(client))
    try:
        # chunks already on the workers all go at once: each worker then has its next one
        # queued whatever order the others finish in (a window would hold a worker's next
        # chunk until every chunk before it is fitted), and they hold no more memory
        window = len(chunks) if chunks and all(_is_future(c) for c in chunks) else None
        parts = ordered_map(client, _fit_chunk, list(zip(chunks, starts, sizes)), *args, out, window=window)
        return _joined_parts(parts, n, starts, out)
    finally:
        if out is not None:
            out.remove()  # (its pages stay mapped by the result)


def _problems(chunk: dict) -> int:
    return len(chunk["Y"])


def _sized_starts(core, names: list, start, kw: dict) -> dict:
    """The starts the cells are sized on: ``start`` as {name: values}, or the spread of
    starts ``fit`` draws (``n_starts``, ``seed``), with ``ties`` applied."""
    from .fit.estimate import spread_starts, with_ties

    if isinstance(start, dict):
        sized = {k: np.asarray(v, dtype=float) for k, v in start.items()}
    elif start is not None:
        sized = dict(zip(names, np.asarray(start, dtype=float).reshape(-1, len(names)).T))
    else:
        sized = dict(zip(names, spread_starts(core, names, kw.get("n_starts", 8), kw.get("seed", 0)).T))
    return with_ties(sized, kw.get("ties"))


def _is_future(a) -> bool:
    distributed = sys.modules.get("distributed")  # (a future means Dask is imported)
    return distributed is not None and isinstance(a, distributed.Future)


def _problem_count(part) -> int:
    """Problems of a FitResult: the length of its first per-problem array."""
    return next(
        len(v)
        for f in dataclasses.fields(part)
        if isinstance(v := getattr(part, f.name), np.ndarray) and v.ndim >= 1 and f.name not in ("lower", "upper")
    )


def concatenate_results(parts, n: int | None = None):
    """One :class:`~tawarp.fit.result.FitResult` from results of consecutive problem chunks:
    arrays with the problem axis first and per-problem lists are joined in order,
    ``evaluations`` and ``launches`` summed, batch ``warnings`` joined without repeats,
    everything else (names, dof, bounds, ...) taken from the first part. With ``n`` (the
    problems of all parts) ``parts`` may be an iterator: each part's arrays are copied into
    place as it comes (while the workers fit the next ones) and then dropped."""
    from .fit.result import ProblemWarnings

    if n is None:
        parts = list(parts)
        if len(parts) == 1:
            return parts[0]
        n = sum(_problem_count(p) for p in parts)
    joined, rest, at = {}, [], 0
    for part in parts:
        m = _problem_count(part)
        arrays = {}
        for f in dataclasses.fields(part):
            v = getattr(part, f.name)
            if isinstance(v, np.ndarray) and v.ndim >= 1 and f.name not in ("lower", "upper"):
                if not rest:
                    joined[f.name] = np.empty((n,) + v.shape[1:], dtype=v.dtype)
                if f.name in joined:
                    if (wider := np.result_type(joined[f.name], v)) != joined[f.name].dtype:
                        joined[f.name] = joined[f.name].astype(wider)  # (strings: a longer one came)
                    joined[f.name][at : at + m] = v
                    arrays[f.name] = None
        if arrays.keys() != joined.keys():
            raise ValueError(f"concatenate_results: per-problem arrays {sorted(joined)} not in every part")
        at += m
        rest.append(dataclasses.replace(part, **arrays))
    if at != n:
        raise ValueError(f"concatenate_results: the parts hold {at} problems, not {n}")
    first = rest[0]
    out = {}
    for f in dataclasses.fields(first):
        vals = [getattr(p, f.name) for p in rest]
        if f.name in joined:
            out[f.name] = joined[f.name]
        elif f.name in ("evaluations", "launches"):
            out[f.name] = sum(vals)
        elif f.name == "seconds":
            out[f.name] = max(vals)
        elif f.name == "warnings":
            out[f.name] = list(dict.fromkeys(w for v in vals for w in v))
        elif f.name == "problem_warnings":
            out[f.name] = ProblemWarnings.concatenate(vals)
        else:
            out[f.name] = vals[0]
    return type(first)(**out)


# -- design evaluations -----------------------------------------------------------------
def _worker_evaluator(key: str, spec: bytes):
    """This worker's (Evaluator, DeviceTable) of the evaluations ``key``, built by its first
    task (:func:`worker_state`) from ``spec`` (:class:`ClusterEvaluator`'s, pickled) with
    one Sobol point through every objective asked for (the modules load then)."""
    from .design.evaluate import Evaluator
    from .design.space import DeviceTable

    def build():
        job = pickle.loads(spec)
        ev = Evaluator(
            job["space"],
            extra=job["extra"],
            freqs=job["freqs"],
            settings=worker_settings(job["settings"]),
            onset=job["onset"],
        )
        tables = DeviceTable(job["space"], ev.device)
        table = tables.sobol(0, 1, 0)[0]
        ev.objectives_of(ev.evaluate_device(table), table)
        return ev, tables

    return worker_state(key, build)


def _warm_evaluator(key: str, spec: bytes) -> None:
    _worker_evaluator(key, spec)


def _objective_layout(key: str, spec: bytes) -> dict:
    """{objective: (dtype, shape of one point's value)} of the evaluations ``key``."""
    ev, tables = _worker_evaluator(key, spec)
    table = tables.sobol(0, 1, 0)[0]
    return {k: (v.dtype.str, v.shape[1:]) for k, v in ev.objectives_of(ev.evaluate_device(table), table).items()}


def _evaluate_chunk(table: np.ndarray, key: str, spec: bytes) -> dict:
    """Objectives of one chunk of a design table, on this worker's Evaluator for ``key``."""
    ev, _ = _worker_evaluator(key, spec)
    return ev.evaluate_table(table)


def _evaluate_sobol_chunk(task: tuple, key: str, spec: bytes, out: SharedColumns | None = None):
    """Objectives of the Sobol points ``task`` = (lo, hi, seed, at) of the design space,
    drawn on this worker's device (:meth:`tawarp.design.space.DeviceTable.sobol`);
    written to rows ``at`` .. of the shared ``out`` where given (and None returned:
    :func:`_evaluate_sobol_chunks`)."""
    if out is not None:
        return _evaluate_sobol_chunks(([task], None), key, spec, out)
    ev, tables = _worker_evaluator(key, spec)
    lo, hi, seed, _ = task
    table = tables.sobol(lo, hi, seed)[0]
    return ev.objectives_of(ev.evaluate_device(table), table)


def _evaluate_sobol_chunks(share: tuple, key: str, spec: bytes, out: SharedColumns) -> None:
    """The chunks ``tasks`` of ``share`` = (tasks, done) (each (lo, hi, seed, at):
    :func:`_evaluate_sobol_chunk`) of one call, written to the shared ``out``, in one
    task: a worker's share of a call. Each chunk's copies into its pooled file are queued
    behind its kernels (:meth:`SharedColumns.write_device`) and the device is waited for
    once, at the end, so the host launches chunk i + 1 while the device runs chunk i; and
    Dask's cost per task (its messages, the worker's bookkeeping: about a millisecond
    between two chunks of a 4-GPU call) is paid once per worker and call. ``done``:
    (board, slot) where the share, once written, says so (:class:`DoneBoard`), or None."""
    import warp as wp

    tasks, done = share
    ev, tables = _worker_evaluator(key, spec)
    queued = False
    try:
        for lo, hi, seed, at in tasks:
            table = tables.sobol(lo, hi, seed)[0]
            metrics = ev.evaluate_device(table)
            if ev.extra:  # (objectives computed on the host need the host table)
                out.write(at, ev.objectives_of(metrics, table))
                continue
            columns = ev.metric_columns(metrics, ev.columns, wp.float64)
            if out.write_device(at, ev.columns, columns):
                queued = True
            else:
                out.write(at, dict(zip(ev.columns, _on_host(key, columns))))
    finally:
        if queued:  # (also on an error: no copy left running into the files)
            wp.synchronize_device(ev.device)
    if done is not None:
        DoneBoard.post(*done)


def _on_host(key: str, columns):
    """The (k, n) device array ``columns`` copied into this worker's host buffer of the
    job ``key`` (page-locked beside a GPU, kept between its chunks, grown when a chunk is
    longer): one DMA, where a fresh host array would be paged in per chunk and filled
    through the driver's staging buffer, twice the host's memory traffic of the copy."""
    import warp as wp

    held = worker_state(key + ":host", dict)
    buf = held.get("buffer")
    if buf is None or buf.size < columns.size:
        cuda = wp.get_device(columns.device).is_cuda
        buf = held["buffer"] = wp.empty(columns.size, dtype=columns.dtype, device="cpu", pinned=cuda)
    wp.copy(buf, columns, count=columns.size)
    wp.synchronize_device(columns.device)
    return buf.numpy()[: columns.size].reshape(columns.shape)


#: ``madvise`` advice that makes a writable mapping's pages present, as a write fault each
#: would (Linux 5.14; Python names it from 3.13 on), failing with an error where a fault
#: would raise SIGBUS (a full tmpfs).
MADV_POPULATE_WRITE = getattr(mmap, "MADV_POPULATE_WRITE", 23)


def write_at(fd: int, data: np.ndarray, at: int, mapped: bool = False) -> None:
    """The bytes ``data`` (uint8, contiguous) at byte ``at`` of the tmpfs file ``fd``
    (its size already past them). ``mapped``: copied through a mapping of those bytes
    whose pages the kernel makes present in one call first, else with the write call.
    The write call costs a process least (the pages' allocation and one copy; a populated
    mapping zeroes each page before the copy and unmaps it after: 1.5x the CPU time), but
    tmpfs holds the file's inode lock through it, so processes writing one file take
    turns, while they fill populated mappings in parallel; a mapping left to fault page by
    page costs a fault per 4 kB (measured: bench/README.md, section Several GPUs). Where
    the kernel cannot populate (before Linux 5.14, or no room left: an OSError, not the
    SIGBUS of a fault) the write call does it."""
    if not data.size:
        return
    if mapped:
        lo = at - at % mmap.ALLOCATIONGRANULARITY
        try:
            m = mmap.mmap(fd, at + data.size - lo, offset=lo)
        except OSError:
            m = None
        if m is not None:
            try:
                m.madvise(MADV_POPULATE_WRITE)
            except OSError:
                pass
            else:
                m[at - lo :] = memoryview(data)
                return
            finally:
                m.close()
    view = memoryview(data)
    while view:  # (a call writes at most 2 GB)
        done = os.pwrite(fd, view, at)
        view, at = view[done:], at + done


class AddressRange:
    """A range of this process's addresses (Linux), reserved whole, into which pieces of
    files are mapped back to back (``MAP_FIXED``, which Python's :mod:`mmap` does not
    offer), and unmapped whole when the last array on it goes."""

    def __init__(self, size: int):
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.mmap.restype = ctypes.c_void_p
        libc.mmap.argtypes = (
            ctypes.c_void_p,
            ctypes.c_size_t,
            ctypes.c_int,
            ctypes.c_int,
            ctypes.c_int,
            ctypes.c_int64,
        )
        libc.munmap.argtypes = (ctypes.c_void_p, ctypes.c_size_t)
        self._libc, self.size = libc, max(size, mmap.PAGESIZE)
        self.addr = self._mmap(None, self.size, _PROT_NONE, mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | _MAP_NORESERVE)

    def _mmap(self, addr, size: int, prot: int, flags: int, fd: int = -1, offset: int = 0) -> int:
        import ctypes

        out = self._libc.mmap(addr, size, prot, flags, fd, offset)
        if out in (None, ctypes.c_void_p(-1).value):
            err = ctypes.get_errno()
            raise OSError(err, f"mmap of {size} bytes: {os.strerror(err)}")
        return out

    def map(self, at: int, fd: int, offset: int, size: int) -> None:
        """Bytes ``offset`` .. ``offset + size`` of the file ``fd`` (a page multiple each)
        at byte ``at`` of the range, shared with the file."""
        if at < 0 or at + size > self.size:
            raise ValueError(f"AddressRange.map: bytes {at} .. {at + size} outside the range's {self.size}")
        self._mmap(self.addr + at, size, mmap.PROT_READ | mmap.PROT_WRITE, mmap.MAP_SHARED | _MAP_FIXED, fd, offset)

    def array(self, at: int, dtype, shape: tuple) -> np.ndarray:
        """An array on the bytes from ``at`` on, which keeps the range mapped."""
        return np.asarray(_OnRange(self, at, np.dtype(dtype), shape))

    def __del__(self):
        if getattr(self, "addr", None):
            self._libc.munmap(self.addr, self.size)


class _OnRange:
    """What :meth:`AddressRange.array` hands NumPy: the array's base, which holds the range."""

    def __init__(self, space: AddressRange, at: int, dtype: np.dtype, shape: tuple):
        self.space = space
        self.__array_interface__ = {
            "data": (space.addr + at, False),
            "shape": tuple(shape),
            "typestr": dtype.str,
            "version": 3,
        }


def _row_bytes(dtype, shape) -> int:
    """Bytes of one row of a column of ``dtype`` whose rows are of ``shape``."""
    return np.dtype(dtype).itemsize * math.prod(shape)  # (np.prod: 5 us a call, 200 a call of 16 chunks)


#: Linux's mmap protection and flags that Python's mmap module does not name.
_PROT_NONE, _MAP_FIXED, _MAP_NORESERVE = 0, 0x10, 0x4000


@dataclasses.dataclass(frozen=True)
class SharedColumns:
    """Columns of ``n`` rows laid out in shared memory (``/dev/shm``, else the temporary
    folder), in the file ``path`` or in a file per chunk: each worker process of this host
    writes its rows in place, and the client maps the files and unlinks them, so that the
    results of a local process cluster cross no socket and are copied nowhere. ``layout``: {name: (dtype, shape of a
    row)}; the columns follow each other, each at an offset aligned to 64 bytes.
    ``writers``: the processes that write it at once (:func:`write_at`: with one, the
    write call, the cheapest; with several, populated mappings, which they fill in
    parallel). ``chunks``: where given, the first rows of chunks that each writer writes
    whole into a file of its own (``path.ROW``, its columns at page-aligned offsets), with
    the write call and no lock shared with another writer, which the reader maps back to
    back into one range of its addresses (:class:`AddressRange`: Linux): each chunk but the
    last a whole number of pages in every column (a multiple of the page size in rows).
    ``files``: the chunks' files where a :class:`ChunkFiles` pool lends them (made by the
    client, kept between calls: a writer finds the pages of one written before there and
    copies into them through a mapping it keeps, :func:`_written_mapping`)."""

    path: str
    n: int
    layout: dict
    writers: int = 1
    chunks: tuple = ()
    files: tuple = ()

    def offsets(self, align: int = 64) -> dict:
        out, at = {}, 0
        for k, (dtype, shape) in self.layout.items():
            out[k] = at
            at += -(-self.n * _row_bytes(dtype, shape) // align) * align
        out[None] = at
        return out

    def nbytes(self) -> int:
        return self.offsets()[None]

    def _chunk(self, at: int) -> SharedColumns:
        """The chunk of ``chunks`` that starts at row ``at``, as columns of its own file."""
        i = self.chunks.index(at)
        end = self.chunks[i + 1] if i + 1 < len(self.chunks) else self.n
        return SharedColumns(self.files[i] if self.files else f"{self.path}.{at}", end - at, self.layout)

    def chunk_sizes(self) -> list[int]:
        """Bytes of each chunk's file (``chunks``)."""
        return [self._chunk(at).offsets(mmap.PAGESIZE)[None] for at in self.chunks]

    def columns(self, mode: str = "r+", on_release=None) -> dict[str, np.ndarray]:
        """The columns, mapped from the file or the chunks' files; ``on_release()`` is
        called once the last array on the chunks' files has gone (their pool's cue that
        they may be written again)."""
        if self.chunks:
            return self._stitched(on_release)
        off = self.offsets()
        return {
            k: np.asarray(np.memmap(self.path, dtype=dtype, mode=mode, offset=off[k], shape=(self.n,) + tuple(shape)))
            for k, (dtype, shape) in self.layout.items()
            if self.n
        }

    def _stitched(self, on_release=None) -> dict[str, np.ndarray]:
        """The columns, each chunk file's part of a column mapped where its rows go."""
        page = mmap.PAGESIZE
        off = self.offsets(page)
        space = AddressRange(off[None])
        if on_release is not None:
            weakref.finalize(space, on_release)  # (after the range's unmapping: its __del__)
        for at in self.chunks:
            part = self._chunk(at)
            sections = part.offsets(page)
            fd = os.open(part.path, os.O_RDWR)
            try:
                for k, (dtype, shape) in self.layout.items():
                    row = _row_bytes(dtype, shape)
                    if size := -(-part.n * row // page) * page:  # (a row of no bytes maps nothing)
                        space.map(off[k] + at * row, fd, sections[k], size)
            finally:
                os.close(fd)
        return {k: space.array(off[k], dtype, (self.n,) + tuple(shape)) for k, (dtype, shape) in self.layout.items()}

    def write(self, at: int, res: dict) -> None:
        """Rows ``at`` .. of the columns ``res`` {name: array} (:func:`write_at`); with
        ``chunks``, the whole chunk that starts there, into its own file: a pooled file
        (``files``) written before through this process's mapping of it, one copy."""
        pieces = []
        for k, v in res.items():
            dtype, shape = self.layout[k]
            row = _row_bytes(dtype, shape)
            pieces.append((k, row, np.ascontiguousarray(v, dtype=dtype).reshape(-1).view(np.uint8)))
        if self.chunks:
            part = self._chunk(at)
            off, first = part.offsets(mmap.PAGESIZE), 0
            if self.files:
                with _WRITTEN_LOCK:  # (no mapping dropped under the copies)
                    if (held := _written_mapping(part.path, off[None])) is not None:
                        for k, _, data in pieces:
                            np.frombuffer(held, dtype=np.uint8, count=data.size, offset=off[k])[:] = data
                        return
            # a pooled file is the client's: one it dropped (its call failed) stays gone
            flags = os.O_RDWR if self.files else os.O_RDWR | os.O_CREAT | os.O_TRUNC
            fd = os.open(part.path, flags, 0o600)
        else:
            off, first = self.offsets(), at
            fd = os.open(self.path, os.O_RDWR)
        try:
            if self.chunks and os.fstat(fd).st_size != off[None]:
                os.ftruncate(fd, off[None])
            for k, row, data in pieces:
                write_at(fd, data, off[k] + first * row, mapped=self.writers > 1 and not self.chunks)
        finally:
            os.close(fd)

    def write_device(self, at: int, names: list, columns) -> bool:
        """The rows of the (len(names), m) float64 Warp array ``columns`` (on its device),
        one per column of ``names``, copied straight into the pooled file of the chunk
        that starts at row ``at``, where this process keeps its mapping and the device
        copies into it (:func:`_device_address`: one DMA per column from a GPU), queued on
        the device's stream: they are in the file once the caller has waited for the
        device (``wp.synchronize_device``; a kept mapping is dropped only after its device
        is waited for: :func:`_drop_mapping`); False where not (a fresh file, a driver
        that would not page-lock it: the caller copies through its host buffer and
        :meth:`write`)."""
        import warp as wp

        if not self.files or any(self.layout[k] != ("<f8", ()) for k in names):
            return False
        part = self._chunk(at)
        off, n = part.offsets(mmap.PAGESIZE), part.n
        if tuple(columns.shape) != (len(names), n) or not n:
            return False
        with _WRITTEN_LOCK:  # (held while the copies are queued: no mapping dropped under them)
            m = _written_mapping(part.path, off[None])
            address = None if m is None else _device_address(part.path, columns.device)
            if address is None:
                return False
            dest = wp.array(ptr=address, dtype=wp.float64, shape=(len(m) // 8,), device="cpu")
            for j, k in enumerate(names):
                wp.copy(dest, columns, dest_offset=off[k] // 8, src_offset=j * n, count=n)
        return True

    def remove(self) -> None:
        """The file and the chunks' files, those there are (their pages stay where
        mapped); not the pooled ``files``, which their :class:`ChunkFiles` keeps."""
        paths = [self.path] if self.path else []
        if not self.files:
            paths += [f"{self.path}.{at}" for at in self.chunks]
        for path in paths:
            unlink_owned(path)

    @classmethod
    def create(
        cls, n: int, layout: dict | None, folders=None, writers: int = 1, chunks: tuple = ()
    ) -> SharedColumns | None:
        """A new file of these columns in the first of ``folders`` (default ``/dev/shm``,
        then the temporary folder) with twice its size free, or None (a worker writing past
        the end of a full tmpfs would be killed). ``layout`` None: an empty file, which the
        writers size (:meth:`sized`) once they know the columns."""
        size = cls("", n, layout or {}).nbytes()
        folder = _shared_folder(size, folders)
        return None if folder is None else cls(_new_file(folder, size), n, layout, writers, tuple(chunks))

    def sized(self, layout: dict, rows: int) -> SharedColumns | None:
        """This file with the columns ``layout``, made its size by the first writer (the
        writers of one file give the same layout), or None where the file is gone (its
        reader gave up) or where writing ``rows`` more rows would leave less than their
        size free."""
        cols = dataclasses.replace(self, layout=layout)
        try:
            fd = os.open(self.path, os.O_RDWR)  # (no O_CREAT: a file its reader removed stays so)
        except FileNotFoundError:
            return None
        try:
            st = os.statvfs(self.path)
            need = rows * sum(_row_bytes(d, s) for d, s in layout.values())
            if st.f_bavail * st.f_frsize < 2 * need:
                return None
            if os.fstat(fd).st_size < cols.nbytes():
                os.ftruncate(fd, cols.nbytes())
        finally:
            os.close(fd)
        return cols


#: Where the shared-memory files go by default, the first with room (:func:`_shared_folder`),
#: then the temporary folder: Linux's tmpfs, whose pages the worker processes map.
SHARED_FOLDERS = ("/dev/shm",)


def _shared_folder(size: int, folders=None) -> str | None:
    """The first of ``folders`` (default :data:`SHARED_FOLDERS`, then the temporary folder)
    with twice ``size`` bytes free, or None (a worker writing past the end of a full tmpfs
    would be killed; the rest of the host keeps room)."""
    import tempfile

    for folder in folders or (*SHARED_FOLDERS, tempfile.gettempdir()):
        try:
            st = os.statvfs(folder)
        except OSError:
            continue
        if st.f_bavail * st.f_frsize >= 2 * size:
            return folder
    return None


#: Names of the shared-memory files this package makes (:func:`_new_file`): ``PREFIX*.columns``.
OWNED_PREFIX = "tawarp-held-"
#: A file whose owner has gone is swept (:func:`sweep_orphans`) only when unchanged for this
#: many seconds: a file another process has only just made may not hold its lock yet.
ORPHAN_SECONDS = 60.0
#: {path: descriptor} of the files this process made and keeps, each descriptor holding a
#: shared advisory lock (``flock``) on its file until :func:`unlink_owned`: the kernel
#: drops it when the process ends, however it ends, which tells :func:`sweep_orphans` so.
_OWNED: dict[str, int] = {}
_SWEPT: set[str] = set()  # the folders this process has swept
_OWNED_LOCK = threading.Lock()


def _new_file(folder: str, size: int) -> str:
    """A new file of ``size`` bytes (no pages yet) in ``folder``, locked as this process's
    until :func:`unlink_owned`: its path. The first file of a process in a folder sweeps
    that folder's orphans first (:func:`sweep_orphans`)."""
    import tempfile

    with _OWNED_LOCK:
        sweep = folder not in _SWEPT
        _SWEPT.add(folder)
    if sweep:
        sweep_orphans(folder)
    fd, path = tempfile.mkstemp(prefix=OWNED_PREFIX, suffix=".columns", dir=folder)
    try:
        if fcntl is not None:
            fcntl.flock(fd, fcntl.LOCK_SH)
        os.ftruncate(fd, size)
    except BaseException:
        os.close(fd)
        os.unlink(path)
        raise
    with _OWNED_LOCK:
        _OWNED[path] = fd
    return path


def unlink_owned(path: str) -> None:
    """Unlink ``path`` where it is there (its pages stay where mapped) and, where this
    process made it (:func:`_new_file`), let its lock go."""
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    with _OWNED_LOCK:
        fd = _OWNED.pop(path, None)
    if fd is not None:
        os.close(fd)


def sweep_orphans(folder: str, unchanged: float = ORPHAN_SECONDS) -> list[str]:
    """Unlink the files of ``folder`` that a process of this package made
    (:func:`_new_file`) and that no living process keeps: those whose owner was killed
    before it could unlink them (a client stopped by SIGKILL or the out-of-memory killer
    mid-call leaves up to a call's results in ``/dev/shm``, memory no one frees until the
    machine restarts). A file is an orphan when no process holds its lock (a lock, unlike a
    process id, means the same in every PID namespace that shares the folder) and it has
    not changed for ``unchanged`` seconds. Returns the paths unlinked."""
    if fcntl is None:
        return []
    gone = []
    for path in glob.glob(os.path.join(glob.escape(folder), OWNED_PREFIX + "*.columns")):
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            continue
        try:
            if time.time() - os.fstat(fd).st_mtime < unchanged:
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:  # its owner lives
                continue
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
                gone.append(path)
        finally:
            os.close(fd)
    return gone


#: Seconds between two looks of a client at its :class:`DoneBoard`.
DONE_POLL_SECONDS = 2e-4


class DoneBoard:
    """A small shared-memory file of ``slots`` bytes, made for one call, in which each of
    its tasks sets its slot once its results are in shared memory (:meth:`post`), and
    which the client reads through its mapping (:meth:`wait`): a call returns once its
    results are in place, without waiting for the messages that tell Dask a task is done
    (worker to scheduler to client, the scheduler sending the client a batch at most
    every 2 ms: 4.5 ms of the tail of a 4-GPU evaluation call, 2.6 ms on one GPU). The
    file lies in ``/dev/shm`` (``folders``) until :meth:`close`."""

    def __init__(self, slots: int, folders=None):
        folder = _shared_folder(slots, folders)
        if folder is None:
            raise OSError(errno.ENOSPC, "no room for a DoneBoard in shared memory")
        self.path = _new_file(folder, slots)
        with open(self.path, "r+b") as f:
            f.write(bytes(slots))  # (its page there: the writers' and this mapping's the same)
            f.flush()
            self._map = mmap.mmap(f.fileno(), slots)
        self.board = np.frombuffer(self._map, dtype=np.uint8)

    @staticmethod
    def post(path: str, slot: int) -> None:
        """Share ``slot`` of the call of the board ``path`` is written (by a worker process
        of this host); nothing where the call has ended without it (its board gone)."""
        try:
            fd = os.open(path, os.O_RDWR)
        except FileNotFoundError:
            return
        try:
            os.pwrite(fd, b"\x01", slot)
        finally:
            os.close(fd)

    def wait(self, futures) -> None:
        """Return once every slot of ``futures`` (share i in slot i) is set or every future
        is done, raising the first error of one."""
        board = self.board[: len(futures)]
        while not board.all():
            states = [f.status for f in futures]
            if "error" in states or "cancelled" in states or all(s == "finished" for s in states):
                wait_all(futures)  # (its error raised)
                return
            time.sleep(DONE_POLL_SECONDS)

    def close(self) -> None:
        if self.board is None:
            return
        self.board = None
        with contextlib.suppress(BufferError):  # (a view still alive: the mapping goes with it)
            self._map.close()
        unlink_owned(self.path)


class ChunkFiles:
    """Shared-memory files for the chunks of one caller's results (:class:`SharedColumns`
    ``files``), kept between its calls. A fresh tmpfs page costs its writer an allocation
    and a zeroing in the kernel, which several worker processes do no faster together than
    one alone (bench/README.md, section Several GPUs): a file written before has its pages,
    and a worker copies into them through the mapping it keeps (:func:`_written_mapping`).
    A file is lent with a result and comes back when the last array on it has gone
    (:meth:`SharedColumns.columns` ``on_release``), so a result still held is never
    written again; :meth:`take` keeps at most one call's files free beside those lent and
    unlinks the rest; :meth:`close` unlinks them all (the pages of a result still held
    stay with its mapping). The files lie in ``/dev/shm`` (``folders``) while kept, named
    ``tawarp-held-*.columns``: a process killed before :meth:`close` leaves them there,
    for the next process that makes such files to sweep (:func:`sweep_orphans`)."""

    def __init__(self, folders=None):
        self.folders = folders
        self._free: deque = deque()  # (size, path); appended by finalizers in any thread
        self._files: dict = {}  # {path: size} of every file kept, free or lent
        self.closed = False

    def take(self, sizes: list[int]) -> tuple | None:
        """Files of ``sizes`` bytes, free ones reused and the others made, or None where
        the new ones would not leave twice their size free; free files not taken go."""
        free: dict = {}
        while self._free:
            size, path = self._free.popleft()
            free.setdefault(size, []).append(path)
        # (in the order they were lent and given back: chunk i of a call gets the file of
        # chunk i of the call whose result went, which the same worker wrote)
        taken = [free[s].pop(0) if free.get(s) else None for s in sizes]
        folder = _shared_folder(sum(s for s, p in zip(sizes, taken) if p is None), self.folders)
        self._unlink([p for paths in free.values() for p in paths])
        if folder is None:
            self._unlink([p for p in taken if p is not None])
            return None
        taken = [p or _new_file(folder, s) for s, p in zip(sizes, taken)]
        self._files.update(zip(taken, sizes))
        return tuple(taken)

    def give_back(self, files) -> None:
        """``files`` free again (their result has gone): written by the next call."""
        if self.closed:
            return
        for path in files:
            if (size := self._files.get(path)) is not None:  # (else unlinked by a close meanwhile)
                self._free.append((size, path))

    def discard(self, files) -> None:
        """``files`` unlinked (a call that failed: a task may still write them)."""
        self._unlink(files)

    def close(self) -> None:
        self.closed = True
        self._unlink(list(self._files))
        self._free.clear()

    def _unlink(self, paths) -> None:
        for path in paths:
            self._files.pop(path, None)
            unlink_owned(path)


#: At most this many files' mappings kept per process (:func:`_written_mapping`): a bound
#: on its count of mappings, which the kernel limits (``vm.max_map_count``). Their bytes
#: are bounded by :func:`mapping_budget`.
MAPPED_FILES = 4096


@dataclasses.dataclass
class _Kept:
    """A pooled file's mapping kept by a writer: its descriptor, the mapping and, once a
    device has asked (:func:`_device_address`), that device and the mapping's address for
    its copies (None: a GPU's driver would not page-lock it)."""

    fd: int
    mapping: mmap.mmap
    device: str | None = None
    address: int | None = None


#: {path: _Kept} of the pooled files this process has written (:func:`_written_mapping`).
_WRITTEN: dict = {}
_WRITTEN_LOCK = threading.RLock()
_MAPPED_BYTES = 0  # the bytes of the mappings in _WRITTEN (read without the lock: an int)


def mapping_budget() -> float:
    """The bytes this process's kept mappings of pooled files may hold: on a GPU worker
    each is page-locked (:func:`_device_address`), memory the kernel cannot swap, so they
    share :data:`LOCKED_SHARE` of the worker's memory limit (of the machine's memory
    outside a worker) with the fit data locked for uploads (:func:`lock_for_uploads`).
    A worker's chunks of one call should all fit: where they do not, each call maps,
    page-locks, unlocks and unmaps a file per chunk again (with room for 64 files, a
    one-GPU call of 2^29 design points, 128 chunks and 17 GB, ran at half the rate of one
    of 2^28: bench/README.md, section Several GPUs)."""
    limit = getattr(getattr(_worker(), "memory_manager", None), "memory_limit", None)
    if not limit:
        limit = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    with _LOCKS:
        locked = sum(_LOCKED.values())
    return LOCKED_SHARE * limit - locked


def _written_mapping(path: str, size: int) -> mmap.mmap | None:
    """A writable mapping of the ``size`` bytes of the pooled file ``path`` with its pages
    present, where the file has all of them already (written by an earlier call: a copy
    into the mapping is then all a write costs, its mapping and page tables made once and
    kept), else None (a fresh file: the write call allocates its pages the cheapest way).
    Mappings of files their pool has unlinked are dropped here and every
    :data:`HOUSEKEEPING_SECONDS` seconds (:func:`drop_unlinked_mappings`); at most
    :data:`MAPPED_FILES` are kept, holding at most :func:`mapping_budget` bytes (the longest
    kept dropped first; None for a file larger than that)."""
    global _MAPPED_BYTES
    with _WRITTEN_LOCK:
        _drop_unlinked()
        held = _WRITTEN.get(path)
        if held is not None and len(held.mapping) != size:
            _drop_mapping(path)
            held = None
        if held is not None:
            return held.mapping
        budget = mapping_budget()
        if size > budget:
            return None
        while len(_WRITTEN) >= MAPPED_FILES or _MAPPED_BYTES + size > budget:
            _drop_mapping(next(iter(_WRITTEN)))  # (the longest kept)
        try:
            fd = os.open(path, os.O_RDWR)
        except FileNotFoundError:
            return None
        st = os.fstat(fd)
        if st.st_size != size or st.st_blocks * 512 < size:
            os.close(fd)
            return None
        try:
            m = mmap.mmap(fd, size)
        except OSError:  # (no address space or mappings left: the write call instead)
            os.close(fd)
            return None
        try:
            m.madvise(MADV_POPULATE_WRITE)  # (page tables in one call, not a fault per page)
        except OSError:
            pass
        _WRITTEN[path] = _Kept(fd, m)
        _MAPPED_BYTES += size
        return m


#: cuMemHostRegister's flag: the memory page-locked for every CUDA context.
_CU_MEMHOSTREGISTER_PORTABLE = 1


def _device_address(path: str, device) -> int | None:
    """The address of this process's kept mapping of ``path`` (:func:`_written_mapping`,
    held) into which ``device`` copies: a CPU's copy is a memcpy into it; a GPU's driver
    page-locks it once (``cuMemHostRegister``) so that a copy is one DMA into the file's
    pages, as into the worker's page-locked buffer, without the copy from there. None
    where the driver refuses (the caller copies through its buffer)."""
    import ctypes

    import warp as wp

    held = _WRITTEN[path]
    name = str(wp.get_device(device))
    if held.device != name:
        if held.device is not None:  # (another device: not here, one device per worker)
            return None
        held.device = name
        address = ctypes.addressof(ctypes.c_char.from_buffer(held.mapping))
        if name == "cpu":
            held.address = address
        else:
            try:
                with wp.get_device(name).context_guard:  # (its context current in this thread alone)
                    ok = _cuda_driver().cuMemHostRegister_v2(address, len(held.mapping), _CU_MEMHOSTREGISTER_PORTABLE)
            except (OSError, AttributeError):
                ok = -1
            held.address = address if ok == 0 else None
    return held.address


#: Seconds between a worker's :func:`housekeeping` (:class:`DevicePlugin`): the tmpfs pages
#: of an unlinked file stay while a mapping holds them.
HOUSEKEEPING_SECONDS = 2.0


def drop_unlinked_mappings() -> None:
    """The mappings :func:`_written_mapping` keeps of files since unlinked (their pool
    closed, or the files beyond one call's), dropped with their pages."""
    with _WRITTEN_LOCK:
        _drop_unlinked()


def _drop_unlinked() -> None:
    for p, held in list(_WRITTEN.items()):
        if os.fstat(held.fd).st_nlink == 0:
            _drop_mapping(p)


def _drop_mapping(path: str) -> None:
    global _MAPPED_BYTES
    held = _WRITTEN.pop(path)
    _MAPPED_BYTES -= len(held.mapping)
    if held.address is not None and held.device != "cpu":  # (page-locked: unlocked before it is unmapped)
        import warp as wp

        wp.synchronize_device(held.device)  # (copies queued into it by write_device done first)
        with wp.get_device(held.device).context_guard:
            _cuda_driver().cuMemHostUnregister(held.address)
    try:
        held.mapping.close()
    except BufferError:  # (an array on it still alive: the mapping goes with it)
        pass
    os.close(held.fd)


class ClusterEvaluator:
    """:class:`tawarp.design.evaluate.Evaluator`'s ``evaluate`` / ``evaluate_table`` over the
    cluster's workers: a table is cut into chunks of ``chunk`` points (default: the table
    in :data:`CHUNKS_IN_FLIGHT` chunks per worker), each evaluated by the worker's own
    Evaluator on its device. The chunks and the results (float64) travel through Dask:
    pickled between worker processes, by reference to worker threads
    (``local_cluster(..., processes=False)``); :meth:`evaluate_sobol` sends no table, and
    worker processes of this host write its results in shared memory (``shared``: None
    decides so for a cluster of such processes, False always sends them through Dask),
    into files kept for the next calls once a result has gone (:class:`ChunkFiles`:
    ``/dev/shm`` holds up to one call's results beside those held, until :meth:`close`
    or until the evaluator goes)."""

    def __init__(
        self,
        client,
        space,
        extra=(),
        freqs=None,
        settings: ForwardSettings | None = None,
        chunk: int | None = None,
        onset=None,
        shared: bool | None = None,
    ):
        from .design.evaluate import DEFAULT_FREQS

        self.client, self.space, self.chunk = client, space, chunk
        self.settings = settings or ForwardSettings()
        # what a worker builds its Evaluator from, pickled once here: each task carries its
        # bytes, which a worker unpickles only to build (:func:`_worker_evaluator`), where
        # the scheduler pickled and each worker unpickled the space and its core per chunk
        self.spec = pickle.dumps(
            {
                "space": space,
                "extra": list(extra),
                "settings": self.settings,
                "freqs": DEFAULT_FREQS if freqs is None else freqs,
                "onset": onset,
            },
            protocol=pickle.HIGHEST_PROTOCOL,
        )
        self.key = uuid.uuid4().hex
        self.shared = _local_processes(client) if shared is None else bool(shared)
        self._layout = None
        self._files = ChunkFiles()
        self._futures = []  # the last call's tasks (evaluate_sobol)
        weakref.finalize(self, self._files.close)

    def close(self) -> None:
        """The shared-memory files kept for later calls unlinked, and the workers' mappings
        of them dropped (a result still held keeps its pages)."""
        self._futures = []
        self._files.close()
        if self.shared:
            self.client.run(drop_unlinked_mappings)

    def warm_up(self) -> None:
        """Build every worker's Evaluator now (its kernels loaded, one point evaluated), so
        that the first evaluations do not wait for it."""
        workers = worker_addresses(self.client, fresh=True)
        self.client.gather(
            [self.client.submit(_warm_evaluator, self.key, self.spec, workers=[w], pure=False) for w in workers]
        )

    def _starts(self, n: int) -> range:
        """First points of the chunks of n points (by default a multiple of the page size
        where longer than a page: :func:`_chunk_files`)."""
        step = max(1, -(-n // (CHUNKS_IN_FLIGHT * _workers(self.client))))
        if step > mmap.PAGESIZE:
            step = -(-step // mmap.PAGESIZE) * mmap.PAGESIZE
        return range(0, max(n, 1), self.chunk or step)

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
        only the objectives come back, written by worker processes of this host into
        shared memory (:class:`SharedColumns`) where it has the room: the files of an
        earlier call's result that has gone are written again (their pages there, each
        worker copying into its kept mapping), never those of a result still held."""
        checked_seed(seed, "ClusterEvaluator.evaluate_sobol")
        starts = self._starts(n)
        tasks = [(first + lo, first + min(n, lo + starts.step), seed, lo) for lo in starts]
        out = None
        if self.shared and n:
            if self._layout is None:
                self._layout = self.client.submit(_objective_layout, self.key, self.spec, pure=False).result()
            if chunks := _chunk_files(starts, self._layout):
                # a file per chunk from the pool: those of an earlier call's result let go
                # are written again, their pages already there
                out = SharedColumns("", n, self._layout, chunks=chunks)
                files = self._files.take(out.chunk_sizes())
                out = None if files is None else dataclasses.replace(out, files=files)
            else:
                out = SharedColumns.create(n, self._layout, writers=_workers(self.client))
        if out is None:
            return self._gather(n, starts, ordered_map(self.client, _evaluate_sobol_chunk, tasks, self.key, self.spec))
        lent, board = False, None
        try:
            # one task per worker (its chunks' point ranges, its result None): chunks i,
            # i + k, ... to worker i (else another takes them), so each worker writes the
            # same pooled files call after call, through the mappings it keeps
            workers = worker_addresses(self.client)
            shares = [tasks[i :: len(workers)] for i in range(min(len(workers), len(tasks)))]
            board = DoneBoard(len(shares))  # (a call's own: no file left between calls)
            done = [(board.path, i) for i in range(len(shares))]
            futures = submit_all(
                self.client,
                _evaluate_sobol_chunks,
                list(zip(shares, done)),
                self.key,
                self.spec,
                out,
                workers=workers[: len(shares)],
            )
            # the last call's tasks let go only now: letting them go as that call returned
            # sent a message, which held this call's submission back until the client's next
            # send (10 ms: submit_all)
            self._futures = futures
            board.wait(futures)
            cols = out.columns(on_release=functools.partial(self._files.give_back, out.files))
            lent = True
            return cols
        finally:
            if board is not None:
                board.close()
            out.remove()  # (the one file goes; its pages stay mapped here)
            if out.files and not lent:
                self._files.discard(out.files)

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


#: At most this many pieces (chunks x columns) mapped into one range: a process has at
#: most ``vm.max_map_count`` (65530 by default) mappings.
MAPPED_PIECES = 4096


def _chunk_files(starts: range, layout: dict) -> tuple:
    """``starts`` where each chunk of evaluations may go into a file of its own
    (:class:`SharedColumns`: on Linux, chunks of a multiple of the page size in points,
    not too many pieces to map), else ()."""
    ok = sys.platform == "linux" and starts.step % mmap.PAGESIZE == 0 and len(starts) * len(layout) <= MAPPED_PIECES
    return tuple(starts) if ok else ()


def _local_processes(client) -> bool:
    """Whether every worker of ``client`` is another process of this host (asked once
    per set of workers: a round trip to each)."""
    import socket

    workers = frozenset(worker_addresses(client))
    known = getattr(client, "_tawarp_local_processes", None)
    if known is not None and known[0] == workers:
        return known[1]
    here = (socket.gethostname(), os.getpid())
    seen = client.run(lambda: (socket.gethostname(), os.getpid()))
    local = bool(seen) and all(host == here[0] and pid != here[1] for host, pid in seen.values())
    client._tawarp_local_processes = (workers, local)
    return local
