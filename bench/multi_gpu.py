"""Scaling over the GPUs of one machine through Dask distributed (tawarp.distributed):
batched fits, design evaluations, a reduced sweep and the island design search on 1, 2,
4 ... GPUs. One command per machine, one JSON:

    python bench/multi_gpu.py --gpus 1,2 --out bench/results/multi_gpu_h100x2.json
    python bench/multi_gpu.py --gpus 1,2,4 --out bench/results/multi_gpu_h100x4.json
    python bench/multi_gpu.py --devices cpu,cpu --gpus 1,2 --small   # CPU workers: a smoke check

For each k of ``--gpus`` a local cluster of one single-threaded Dask worker process on
each of the devices 0 .. k-1 (``--devices``: cuda:0, cuda:1, ... by default; each process
sees its GPU alone) is started (``start_seconds``, not in any rate), and every case warms
each worker up (its kernels loaded, compiled once beforehand in this process) before it
is timed:

* ``fits``: :func:`tawarp.distributed.fit_on_cluster`, the heat workload of bench/fit.py
  (mesh core, h_s, h_h, h_a at 40 W, 100 frequencies, starts 30 % off), ``--fits``
  problems in chunks of ``--fit-chunk``, dealt to the workers in turn (GPU memory bounds
  a chunk; the last round of results is what the client waits for). The data are made
  on the workers before
  the timing (``--fit-data workers``, as each worker would read its own files: problem i's
  noise is drawn from its block's stream, the same data whatever the chunks;
  ``fit_data_seconds``) and fitted once before the timed fits (``fit_first_seconds``), as
  a user fits them again (a GPU worker page-locks the data it fits a second time:
  ``tawarp.distributed.lock_for_uploads``), there in page-locked host memory (``--fit-data pinned``, as a
  loader reading into page-locked buffers: each chunk's upload to its GPU one DMA, no
  copy through the driver's staging buffer; pageable on CPU workers), or sent by the
  client (``--fit-data client``);
* ``evaluations``: :meth:`tawarp.distributed.ClusterEvaluator.evaluate_sobol` of
  ``--points`` Sobol points of the rvc_foam space: each worker draws its chunks' points
  and builds their tables on its device; the objectives come back through shared memory
  (worker processes of this host) or Dask. The first call (``evaluation_first_seconds``)
  writes fresh ``/dev/shm`` pages, the second (``evaluation_second_seconds``) maps and
  page-locks them in each worker; the timed calls after it write the files of the call
  before, let go (``tawarp.distributed.ChunkFiles``), as a caller evaluating batch after
  batch; ``evaluation_back_to_back_seconds``: :data:`BACK_TO_BACK` calls one right
  after the other (nothing between them, as such a caller's loop; the timed calls have
  the probes of the phases between them), ``evaluations_back_to_back_per_s`` at their
  median;
* ``sweep``: a Sobol sweep of ``--sweep-points`` points reduced on the workers
  (:data:`REDUCE`, no raw values: ``sweep(..., client=, reduce=, raw=False)``): each
  worker reduces its share of the chunks, only the reductions come back and merge;
* ``islands``: :func:`tawarp.design.islands.search_islands`, a batched CMA-ES island per
  worker (``--island-trials`` trials of ``--island-batch`` each, committed once a second;
  one journal study with its trial store, each island its own journal, their summaries
  merged into the study at the end); ``--repeats`` runs, each into a new study, the
  fastest kept (``island_call_seconds``: every run's).

Each case's ``*_phases`` say where its best call's wall time went (:func:`phases`, from
the scheduler's task stream): ``head`` (the client before the first task computes),
``tail`` (after the last one ends: the results' transfer and the client's merging, what
one client does for all workers), each worker's ``compute`` and ``tasks``, ``idle_share``
and ``imbalance``, and under ``workers`` each worker process's :func:`usage` in the call
(CPU seconds in user and kernel mode, page faults, context switches: per chunk, what
grows with the workers), under ``client`` the client's own (:class:`ClientClock`: its
round trips to the scheduler, its submission, its wait, the rest). A call's result is let go before the next is timed, and every
worker has fitted a chunk and evaluated one (its memory and host buffer grown) before.
Two probes run every worker at once before the timing: ``evaluation_probe`` times one
chunk's parts on each (``device``, ``copy`` to its host buffer, ``write`` into
``/dev/shm``, with the write's kernel time), ``fit_upload_probe`` each worker's upload of
a chunk of its fit data (GB/s): which part of a chunk slows when several run. Each row
has its workers' GPUs (``worker_gpus``, PCI bus ids), the JSON the host's
``threads_per_core`` and ``gpu_topology`` (``nvidia-smi topo -m``). The islands add ``island_client_seconds`` (opening the study, merging
the islands' summaries, the best: ``island_merge_seconds``, ``island_merged_trials``) and
the shares of the islands' own timing (``island_trial_store_share``: the trial store's
appends, on the disk of ``--study-dir``, default a temporary folder), and each island's
own seconds of each part (``island_sampler_seconds``, ``island_evaluation_seconds``,
``island_storage_seconds``, ``island_trial_store_seconds``; ``island_trial_store_thread_seconds``:
the appends' own time in the trial store's thread, beside the island's main thread).

Each row's ``worker_cpus`` says how many CPUs each worker may run on: those of its GPU's
NUMA node where the host says (:func:`tawarp.distributed.near_gpu`). Each case's
``<case>_gpu_clocks`` has, per GPU, its SM clock while busy, its highest power and
temperature and the clock event reasons that held it (``bench/_gpu_clocks.py``, sampled by
``nvidia-smi`` every 50 ms over the whole case, warm-up included): whether the GPUs of a
row run at one GPU's clocks.

``--cluster threads`` runs fits, evaluations and the sweep on worker threads of this
process instead (``local_cluster(processes=False)``: one GIL; the islands stay on
processes). Speed-up = rate on k GPUs / rate on the first k of ``--gpus`` (the targets:
>= 1.8 on 2 GPUs, >= 3.5 on 4). Each row also says whether its results equal those of
that first row (the evaluations and the sweep's reductions bit for bit, the fits' largest
relative difference, island0's best). The JSON is written after every row; a run that
passes ``--timeout`` seconds (a worker stuck) prints every thread's stack, stops the
worker processes, keeps the rows done and exits with status 3; a case that fails (a
worker killed) is recorded in its row (``errors``) and the run exits with status 1.
"""

from __future__ import annotations

import argparse
import dataclasses
import faulthandler
import hashlib
import json
import os
import platform
import signal
import sys
import tempfile
import threading
import time
import warnings

import numpy as np

from tawarp.design.evaluate import Evaluator
from tawarp.design.islands import search_islands
from tawarp.design.search import TIMED, search
from tawarp.design.space import DesignSpace, DeviceTable
from tawarp.design.sweep import sweep
from tawarp.distributed import ClusterEvaluator, fit_on_cluster, local_cluster, worker_addresses
from tawarp.fit.estimate import FitWarning
from tawarp.model.core import load_core
from tawarp.model.forward import ForwardSettings, resolve_device, transfer_matrices
from _gpu_clocks import GpuClocks
from _results import run, write_result

FREQS = np.linspace(30.0, 500.0, 100)
FIT_NAMES = ["stack.h", "hot_hx.h", "tbt.h"]
#: Problems per block of the fit data's noise (one seeded stream each).
FIT_BLOCK = 4096
#: The reductions of the sweep (tawarp.design.reductions): all of them.
REDUCE = "best,quantiles,histogram,pareto,top=100"
CASES = ("fits", "evaluations", "sweep", "islands")
#: Evaluation calls timed one after the other (``evaluation_back_to_back_seconds``).
BACK_TO_BACK = 8


def fit_model():
    """(core, noise-free data Y0 (m, 4), its noise sd (0.5 %), start 30 % off) of the
    mesh core at 40 W from 48 fixed cells."""
    core = load_core("mesh")
    Y0 = transfer_matrices(core, FREQS, 40.0, cells=48, device="cpu").dimensionless()[0]
    start = np.array([core.get(k) for k in FIT_NAMES]) * [1.3, 0.7, 1.3]
    return core, Y0, 0.005 * np.abs(Y0) / np.sqrt(2), start


def noisy_data(lo: int, hi: int, Y0, sd, seed: int = 0, pinned: bool = False) -> dict:
    """Problems lo .. hi - 1 of the fit data: Y0 plus noise of ``sd``, problem i's drawn
    from the stream (seed, i // FIT_BLOCK), so the data do not depend on the chunks;
    ``pinned``: in page-locked host memory where this process sees a GPU. Made block by
    block in place (no joined copies: this making is what a run's rows wait for)."""
    import warp as wp

    shape = (hi - lo,) + Y0.shape
    if pinned and wp.get_cuda_device_count():
        held = wp.empty(2 * int(np.prod(shape)), dtype=wp.float64, device="cpu", pinned=True).numpy()
        Y = held.view(np.complex128).reshape(shape)  # (its base holds the page-locked buffer)
    else:
        Y = np.empty(shape, dtype=np.complex128)
    for b in range(lo // FIT_BLOCK, -(-hi // FIT_BLOCK)):
        noise = np.random.default_rng([seed, b]).standard_normal((FIT_BLOCK, 2) + Y0.shape)
        i0, i1 = max(lo, b * FIT_BLOCK), min(hi, (b + 1) * FIT_BLOCK)
        noise, out = noise[i0 - b * FIT_BLOCK : i1 - b * FIT_BLOCK], Y[i0 - lo : i1 - lo]
        # Y0 + sd * (real + 1j * imaginary noise), a part at a time
        np.multiply(sd, noise[:, 0], out=out.real)
        out.real += Y0.real
        np.multiply(sd, noise[:, 1], out=out.imag)
        out.imag += Y0.imag
    return {"Y": Y}


def design_space() -> DesignSpace:
    return DesignSpace(
        load_core("rvc_foam"),
        [
            "material=ceramic,mesh,nicr_foam,rvc_foam",
            "stack.length=0.004:0.1",
            "heat_input=1:9",
            "hot_hx.length=0.005:0.03",
            "stack.porosity=0.6:0.98",
        ],
    )


def timed(fn, repeats: int, client=None, settle=None):
    """(best wall time of ``repeats`` calls [s], the last call's result, the CPU time of
    this process (client, scheduler, nannies: every thread; worker threads too, with
    ``--cluster threads``) in the best call [s], the best call's :func:`phases` with
    ``client``, with each worker's :func:`usage` and the client's :class:`ClientClock`
    in it, and under ``calls`` every call's wall, head, tail and submission time): with
    worker processes, a CPU time near the wall time says the client is the serial part.
    The result of a call is let go before the next starts (freeing 2 GB of
    objectives took 0.15 s of a call's tail). ``settle()``, after each call's timing and
    before its phases: waits until Dask has recorded the call's tasks as done (a call
    that returns on its workers' posts in shared memory, ``DoneBoard``, ends first)."""
    best, out, cpu, ph = np.inf, None, None, None
    calls = {"wall": [], "head": [], "tail": [], "submitted": []}
    for _ in range(repeats):
        out = None
        if client is not None:
            u0 = client.run(usage)
            # (tasks just before: the task stream's times carry the workers' clock offsets)
            done = {r["key"] for r in client.get_task_stream(start=time.time() - 60)}
        with ClientClock(client) as clock:
            t0, c0, w0 = time.perf_counter(), time.process_time(), time.time()
            out = fn()
            t, c, w1 = time.perf_counter() - t0, time.process_time() - c0, time.time()
        if client is None:
            if t < best:
                best, cpu = t, c
            continue
        if settle is not None:
            settle()
        u1 = client.run(usage)
        now = phases(client, w0, w1, done)
        for k, v in (("wall", t), ("head", now.get("head")), ("tail", now.get("tail")), ("submitted", clock.submitted)):
            calls[k].append(v)
        if t < best:
            best, cpu, ph = t, c, now
            ph["workers"] = {w: {k: u1[w][k] - v for k, v in u0[w].items()} for w in sorted(u0)}
            ph["client"] = clock.summary(t, ph.get("head"))
    if ph is not None:
        ph["calls"] = calls  # (every call's: on a busy host the best call's alone says little)
    return best, out, cpu, ph


class ClientClock:
    """The client's Dask calls timed while on (``with ClientClock(client) as clock:``):
    for each of :data:`CALLS` its count and seconds, and when the last task was handed to
    the scheduler. :meth:`summary` says where a call's wall went on the client's side:
    ``round_trips`` (``scheduler_info``, ``nthreads`` and ``run``, each a message to the
    scheduler and its answer), ``submit`` (the tasks sent), ``wait`` (``gather`` or ``wait``: until the
    results are in, the workers' time included), ``own`` (the rest: the client's own work
    before and after) and ``dispatch`` (from the last task sent to the first computing,
    with the phases' head: the scheduler's and the messages' part of the head). With
    ``client`` None it times nothing."""

    CALLS = ("scheduler_info", "nthreads", "run", "submit", "map", "gather", "compute")

    def __init__(self, client):
        self.client = client
        self.calls: dict = {}
        self.submitted = None

    def __enter__(self):
        import distributed

        self.t0 = time.perf_counter()
        if self.client is None:
            return self
        for name in self.CALLS:
            setattr(self.client, name, self._timed(name, getattr(self.client, name)))
        self._wait = distributed.wait
        distributed.wait = self._timed("wait", distributed.wait)
        return self

    def __exit__(self, *exc):
        import distributed

        if self.client is not None:
            for name in self.CALLS:
                delattr(self.client, name)  # (the class's method again)
            distributed.wait = self._wait

    def _timed(self, name, fn):
        def call(*args, **kwargs):
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                now = time.perf_counter()
                n, s = self.calls.get(name, (0, 0.0))
                self.calls[name] = (n + 1, s + now - t)
                if name in ("submit", "map", "compute"):
                    self.submitted = now - self.t0

        return call

    def summary(self, wall: float, head: float | None = None) -> dict:
        def part(*names):
            return [sum(self.calls.get(k, (0, 0.0))[i] for k in names) for i in (0, 1)]

        out = {
            "round_trips": part("scheduler_info", "nthreads", "run"),
            "submit": part("submit", "map", "compute"),
            "wait": part("gather", "wait"),
        }
        out["own"] = wall - sum(v[1] for v in out.values())
        out["submitted"] = self.submitted
        out["dispatch"] = None if head is None or self.submitted is None else head - self.submitted
        return out


def usage() -> dict:
    """This process's CPU seconds in user and kernel mode, page faults (``minflt``: a page
    made present without reading a disk) and context switches (``nivcsw``: taken off its
    CPU), summed over its threads: over a call, from each worker, the kernel's share of
    its host work (allocating and zeroing pages) and whether it waited for a CPU."""
    import resource

    r = resource.getrusage(resource.RUSAGE_SELF)
    return {
        "user": r.ru_utime,
        "sys": r.ru_stime,
        "minflt": r.ru_minflt,
        "majflt": r.ru_majflt,
        "nvcsw": r.ru_nvcsw,
        "nivcsw": r.ru_nivcsw,
    }


def phases(client, t0: float, t1: float, done=frozenset()) -> dict:
    """Where the wall time ``t0`` .. ``t1`` (``time.time()``) of a call went, from the
    scheduler's task stream (the tasks' compute intervals on the workers, clocks of this
    host): ``head`` [s] from the call to the first task computing (the client's work
    before, the dispatch), ``tail`` from the last task's end to the call's (the results'
    transfer and the client's work after: what one client does for all workers),
    ``compute`` each worker's computing time [s] and ``tasks`` its task count,
    ``transfer`` [s] between workers, ``idle_share`` of the workers within the call's
    wall, ``imbalance`` [s] the most computing of a worker less the least; the tasks of
    keys ``done`` (those before the call) left out. The workers run on this host's clock:
    the scheduler's estimate of their offset (tens of milliseconds on a busy host), which
    the stream adds to their times, is taken off."""
    records = [r for r in client.get_task_stream(start=t0 - 1.0) if r.get("startstops") and r["key"] not in done]
    offset = client.run(lambda dask_worker: dask_worker.scheduler_delay)
    compute, tasks, transfer, starts, stops = {}, {}, 0.0, [], []
    for r in records:
        for ss in r["startstops"]:
            shift = offset.get(ss.get("worker", r["worker"]), 0.0)
            ss = dict(ss, start=ss["start"] - shift, stop=ss["stop"] - shift)
            if ss["stop"] > t1 + 1.0:
                continue
            if ss["action"] == "compute":
                w = r["worker"]
                compute[w] = compute.get(w, 0.0) + ss["stop"] - ss["start"]
                tasks[w] = tasks.get(w, 0) + 1
                starts.append(ss["start"])
                stops.append(ss["stop"])
            elif ss["action"] == "transfer":
                transfer += ss["stop"] - ss["start"]
    if not starts:
        return {}
    workers = sorted(compute)
    busy = [compute[w] for w in workers]
    wall = t1 - t0
    return {
        "head": min(starts) - t0,
        "tail": max(0.0, t1 - max(stops)),
        "compute": busy,
        "tasks": [tasks[w] for w in workers],
        "transfer": transfer,
        "idle_share": 1.0 - sum(busy) / (len(worker_addresses(client, fresh=True)) * wall),
        "imbalance": max(busy) - min(busy),
    }


def evaluation_probe(ev: ClusterEvaluator, chunk: int) -> dict:
    """Each worker's parts of one chunk of ``ev.evaluate_sobol`` (``chunk`` points), every
    worker at once, as the timed calls run them: ``device`` [s] (its points drawn, the
    kernels, the objective columns made, to the device's end), ``copy`` (into the
    worker's host buffer), ``write`` (into a fresh shared-memory file of its own, as the
    first call) with the kernel's CPU time of the write (``write_sys``) and its page
    faults, ``remap`` (into that file again: the worker's mapping of it made, as a later
    call's first write of a pooled file), ``rewrite`` (once more, through the kept
    mapping), ``register`` and ``direct`` (the device's columns copied straight into the
    kept mapping, as a later call's chunks are: the first time a GPU's driver page-locks
    the mapping; None where it would not, and the chunks go through ``copy`` and
    ``rewrite``); the best of three. Their growth with the workers says which part of a
    chunk does not scale."""
    workers = worker_addresses(ev.client, fresh=True)
    futures = [ev.client.submit(_probe_chunk, ev.key, ev.spec, chunk, workers=[w], pure=False) for w in workers]
    return dict(zip(workers, ev.client.gather(futures)))


def _probe_chunk(key: str, spec: dict, chunk: int) -> dict:
    import resource

    import warp as wp

    from tawarp.distributed import ChunkFiles, SharedColumns, _on_host, _worker_evaluator, drop_unlinked_mappings

    ev, tables = _worker_evaluator(key, spec)
    best = {}
    for _ in range(3):
        t0 = time.perf_counter()
        table = tables.sobol(0, chunk, 0)[0]
        columns = ev.metric_columns(ev.evaluate_device(table), ev.columns, wp.float64)
        wp.synchronize_device(ev.device)
        t1 = time.perf_counter()
        host = dict(zip(ev.columns, _on_host(key, columns)))
        t2, r0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_THREAD)
        out = SharedColumns("", chunk, {k: (v.dtype.str, v.shape[1:]) for k, v in host.items()}, chunks=(0,))
        pool = ChunkFiles()
        files = pool.take(out.chunk_sizes())
        if files is None:  # (no room in /dev/shm: the timed calls send the objectives through Dask too)
            return {"device": t1 - t0, "copy": t2 - t1, "write": None}
        out = dataclasses.replace(out, files=files)
        try:
            out.write(0, host)
            t3, r1 = time.perf_counter(), resource.getrusage(resource.RUSAGE_THREAD)
            out.write(0, host)
            t4 = time.perf_counter()
            out.write(0, host)
            t5 = time.perf_counter()
            direct = out.write_device(0, ev.columns, columns)  # (a GPU's driver page-locks the mapping first)
            wp.synchronize_device(ev.device)  # (the copies are queued)
            t6 = time.perf_counter()
            direct = direct and out.write_device(0, ev.columns, columns)
            wp.synchronize_device(ev.device)
            t7 = time.perf_counter()
        finally:
            pool.close()
            drop_unlinked_mappings()
        now = {
            "device": t1 - t0,
            "copy": t2 - t1,
            "write": t3 - t2,
            "write_sys": r1.ru_stime - r0.ru_stime,
            "write_minflt": r1.ru_minflt - r0.ru_minflt,
            "remap": t4 - t3,
            "rewrite": t5 - t4,
            "register": t6 - t5 if direct else None,
            "direct": t7 - t6 if direct else None,
            "bytes": sum(v.nbytes for v in host.values()),
        }
        best = {k: min((x for x in (v, best.get(k)) if x is not None), default=None) for k, v in now.items()}
    return best


def upload_probe(client, futures: list) -> dict:
    """Each worker's upload of one chunk of its fit data (``Y``, as it lies: pageable, or
    page-locked with ``--fit-data pinned``) to its device, every worker at once: seconds
    and GB/s, the best of three. Its growth with the workers says whether the copies to
    the GPUs share a link or the host's copying."""
    where = client.who_has(futures)
    mine = {}
    for f in futures:
        for w in where.get(f.key, ()):
            mine.setdefault(w, f)
    tasks = [client.submit(_probe_upload, f, workers=[w], pure=False) for w, f in mine.items()]
    return dict(zip(mine, client.gather(tasks)))


def _probe_upload(chunk: dict) -> dict:
    import warp as wp

    from tawarp.distributed import worker_settings

    device = worker_settings(None).device
    Y = np.ascontiguousarray(chunk["Y"]).view(np.float64)
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        a = wp.array(Y, dtype=wp.float64, device=device)
        wp.synchronize_device(device)
        best = min(best, time.perf_counter() - t0)
        del a
    return {"seconds": best, "GB_per_s": Y.nbytes / best / 1e9}


def digest(arrays: dict) -> str:
    """A hash of named arrays' bytes: equal results, equal digests."""
    h = hashlib.sha256()
    for k in sorted(arrays):
        h.update(k.encode())
        h.update(np.ascontiguousarray(arrays[k]).tobytes())
    return h.hexdigest()


def closed(client) -> None:
    cluster = client.cluster
    client.close()
    cluster.close()


def even_ranges(n: int, parts: int) -> list[tuple[int, int]]:
    """``parts`` consecutive ranges covering 0 .. n - 1, their lengths within one."""
    edges = [n * i // parts for i in range(parts + 1)]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


class Bench:
    """The cases on a cluster of k workers (see the module docstring)."""

    def __init__(self, args, tmp):
        self.args, self.tmp = args, tmp
        self.space = design_space()
        self.core, self.Y0, self.sd, self.start = fit_model()
        self.client_data = None

    def _fit(self, client, Y, weights, chunk=None, sizes=None):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FitWarning)
            return fit_on_cluster(
                client,
                self.core,
                FREQS,
                Y,
                FIT_NAMES,
                self.start,
                heat_input=40.0,
                weights=weights,
                warn=False,
                chunk=chunk or 4096,
                sizes=sizes,
            )

    def _data_on_workers(self, client, n: int, workers: list, chunk: int) -> tuple[list, list]:
        """(futures of the chunks of n problems (``chunk`` each), dealt to the workers in
        turn and made there, their sizes)."""
        import distributed

        ranges = even_ranges(n, -(-n // chunk))
        futures = [
            client.submit(
                noisy_data,
                lo,
                hi,
                self.Y0,
                self.sd,
                pinned=self.args.fit_data == "pinned",
                workers=[workers[i % len(workers)]],
                pure=False,
            )
            for i, (lo, hi) in enumerate(ranges)
        ]
        distributed.wait(futures)
        for f in futures:
            f.result()  # (a worker's error raised here)
        return futures, [hi - lo for lo, hi in ranges]

    def fits(self, client, k: int) -> dict:
        n, chunk = self.args.fits, self.args.fit_chunk
        w = (1.0 / self.sd)[None]  # one row: every problem's
        workers = worker_addresses(client, fresh=True)
        # warm-up: every worker fits a few problems of its own (its fit kernels load)
        self._fit(client, *self._data_on_workers(client, 2 * len(workers), workers, 2)[:1], w)
        t0 = time.perf_counter()
        sizes = None
        if self.args.fit_data in ("workers", "pinned"):
            (data, sizes), weights = self._data_on_workers(client, n, workers, chunk), w
        else:
            if self.client_data is None:
                self.client_data = noisy_data(0, n, self.Y0, self.sd)["Y"]
            data, weights = self.client_data, np.broadcast_to(w, self.client_data.shape)
        t_data = time.perf_counter() - t0
        probe = upload_probe(client, data) if sizes else None
        # the data fitted once before the timing, as by a user who fits them again (a GPU
        # worker page-locks data it fits a second time: lock_for_uploads), and no timed
        # call grows a worker's memory for a chunk's size first
        t1 = time.perf_counter()
        self._fit(client, data, weights, chunk, sizes)
        t_once = time.perf_counter() - t1
        t, res, cpu, ph = timed(lambda: self._fit(client, data, weights, chunk, sizes), self.args.repeats, client)
        return {
            "fit_phases": ph,
            "fit_upload_probe": probe,
            "fits": n,
            "fit_data": self.args.fit_data,
            "fit_data_seconds": t_data,
            "fit_first_seconds": t_once,
            "fit_seconds": t,
            "fit_client_cpu_seconds": cpu,
            "fits_per_s": n / t,
            "fits_converged": float(res.converged.mean()),
            "_values": res.values,
        }

    def evaluations(self, client, k: int) -> dict:
        ev = ClusterEvaluator(client, self.space, chunk=self.args.eval_chunk)
        n = self.args.points
        ev.warm_up()
        ev.evaluate_sobol(64 * k)  # (and the objectives' layout, for shared memory)
        # (each worker's host buffer grown to a chunk before the timing, by the probe)
        probe = evaluation_probe(ev, min(n, self.args.eval_chunk)) if ev.shared else None

        # the first call writes fresh shared memory; the later ones, timed, write the files
        # of the call before, let go (ChunkFiles), as a caller evaluating batch after batch
        def settle():
            import distributed

            distributed.wait(ev._futures)

        first, out, _, first_ph = timed(lambda: ev.evaluate_sobol(n, seed=1), 1, client, settle)
        del out
        # the second maps and page-locks the first's files in each worker, which the calls
        # after it find kept (tawarp.distributed.mapping_budget): not timed either
        second, out, _, _ = timed(lambda: ev.evaluate_sobol(n, seed=1), 1, client, settle)
        del out
        t, out, cpu, ph = timed(lambda: ev.evaluate_sobol(n, seed=1), self.args.repeats, client, settle)
        del out
        # as a caller evaluating batch after batch: calls one after the other, nothing
        # between them but letting the result before go
        walls = []
        for _ in range(max(BACK_TO_BACK, self.args.repeats)):
            out = None
            t0 = time.perf_counter()
            out = ev.evaluate_sobol(n, seed=1)
            walls.append(time.perf_counter() - t0)
        row = {
            "evaluation_phases": ph,
            "evaluation_probe": probe,
            "evaluation_points": n,
            "evaluation_first_seconds": first,
            "evaluation_first_phases": first_ph,
            "evaluation_second_seconds": second,
            "evaluation_seconds": t,
            "evaluation_back_to_back_seconds": walls,
            "evaluations_back_to_back_per_s": n / float(np.median(walls)),
            "evaluation_client_cpu_seconds": cpu,
            "evaluations_per_s": n / t,
            "evaluations_first_call_per_s": n / first,
            "evaluations_shared_memory": ev.shared,
            "evaluations_digest": digest(out),
        }
        del out
        ev.close()
        return row

    def sweep(self, client, k: int) -> dict:
        a = self.args
        path = os.path.join(self.tmp, f"sweep{k}.nc")

        def run(n=a.sweep_points, chunk=a.sweep_chunk):
            return sweep(
                self.space, path, mode="sobol", n_samples=n, chunk=chunk, client=client, reduce=REDUCE, raw=False
            )

        run(64 * k, 64)  # warm-up
        t, info, cpu, ph = timed(run, self.args.repeats, client)
        os.remove(path)
        return {
            "sweep_phases": ph,
            "sweep_points": a.sweep_points,
            "sweep_chunk": a.sweep_chunk,
            "sweep_seconds": t,
            "sweep_client_cpu_seconds": cpu,
            "sweep_points_per_hour": 3600.0 * a.sweep_points / t,
            "sweep_reductions": info.reductions,
        }

    def islands(self, client, k: int) -> dict:
        a = self.args
        kw = dict(objectives=("gradient",), batch=a.island_batch, seed=0, commit_seconds=1.0)
        folder = a.study_dir or self.tmp
        warm = os.path.join(folder, f"warm{k}.journal")
        studies = [os.path.join(folder, f"islands{k}.{r}.journal") for r in range(a.repeats)]
        for f in [warm] + studies:
            _remove_study(f)  # (an earlier run's, which the search would resume)
        search_islands(client, self.space, storage=warm, n_trials=2 * a.island_batch, **kw)
        # each repeat a study of its own (the same one again would resume it), the fastest kept
        runs = [
            timed(lambda: search_islands(client, self.space, storage=s, n_trials=a.island_trials, **kw), 1, client)
            for s in studies
        ]
        walls = [t for t, *_ in runs]
        _, res, cpu, ph = min(runs, key=lambda run: run[0])
        if a.study_dir:  # (the temporary folder goes by itself)
            for f in [warm] + studies:
                _remove_study(f)
        tm = res.timing
        wall = tm["wall"]
        return {
            "island_phases": ph,
            "island_study_dir": folder,
            "island_client_seconds": tm["client"],
            "island_merge_seconds": tm["merge"],
            "island_merged_trials": tm["merged"],
            "island_trial_store_share": tm["trial_store"] / (k * wall),
            "island_trials": a.island_trials,
            "island_batch": a.island_batch,
            "islands": k,
            "island_seconds": wall,
            "island_client_cpu_seconds": cpu,
            "island_evaluations_per_minute": tm["evaluations_per_minute"],
            "island_sampler_share": tm["sampler"] / (k * wall),
            "island_storage_share": tm["storage"] / (k * wall),
            "island_evaluation_share": tm["evaluation"] / (k * wall),
            "island_walls": [i["wall"] for i in tm["islands"]],
            "island_call_seconds": walls,
            # each island's own split: which part spreads or grows with the islands
            **{f"island_{part}_seconds": [i.get(part) for i in tm["islands"]] for part in TIMED},
            "island0_best": tm["islands"][0]["best"],
            "best": res.best[0]["values"] if res.best else None,
        }


def _worker_gpus(client) -> dict:
    """Each worker's GPU, as its PCI bus id (None on a CPU worker): with the host's
    ``gpu_topology``, which workers' GPUs share a PCIe switch."""

    def bus():
        import warp as wp

        return wp.get_device("cuda:0").pci_bus_id if wp.get_cuda_device_count() else None

    return client.run(bus)


def host_topology() -> dict:
    """How many CPUs share a core (``threads_per_core``, from CPU 0's siblings), the
    GPUs' links (``nvidia-smi topo -m``, where there is one): what the workers share; and
    the kernel's transparent huge page settings (anonymous memory, tmpfs)."""
    import shutil
    import subprocess

    out = {"threads_per_core": None, "gpu_topology": None, "transparent_hugepage": {}}
    for name in ("enabled", "shmem_enabled"):  # (huge pages: a fault per 2 MB, not per 4 kB)
        try:
            with open(f"/sys/kernel/mm/transparent_hugepage/{name}") as f:
                out["transparent_hugepage"][name] = f.read().strip()
        except OSError:
            pass
    try:
        with open("/sys/devices/system/cpu/cpu0/topology/thread_siblings_list") as f:
            out["threads_per_core"] = sum(
                int(b or a) - int(a) + 1 for a, _, b in (p.partition("-") for p in f.read().strip().split(","))
            )
    except (OSError, ValueError):
        pass
    if smi := shutil.which("nvidia-smi"):
        try:
            out["gpu_topology"] = subprocess.run(
                [smi, "topo", "-m"], capture_output=True, text=True, timeout=20
            ).stdout.splitlines()
        except (OSError, subprocess.SubprocessError):
            pass
    return out


def _worker_cpus(client) -> list[int]:
    """How many CPUs each worker may run on (those of its GPU's NUMA node where the host
    says: :func:`tawarp.distributed.near_gpu`)."""
    return [len(c) for c in client.run(os.sched_getaffinity, 0).values()]


def _remove_study(journal: str) -> None:
    """A journal study and what lies beside it (its trial store, the islands' journals)."""
    import shutil

    for p in (journal, journal + ".lock"):
        if os.path.exists(p):
            os.remove(p)
    stem = os.path.splitext(journal)[0]
    for d in (stem + ".trials", stem + ".islands"):
        shutil.rmtree(d, ignore_errors=True)


def compile_here(bench: Bench, device: str) -> None:
    """Every kernel the cases use, compiled (or loaded) once in this process, so that the
    workers only load them from Warp's cache."""
    data = noisy_data(0, 2, bench.Y0, bench.sd)["Y"]
    settings = ForwardSettings(device=device)
    fit_on_cluster(
        None,
        bench.core,
        FREQS,
        data,
        FIT_NAMES,
        bench.start,
        heat_input=40.0,
        weights=(1.0 / bench.sd)[None],
        warn=False,
        settings=settings,
    )
    ev = Evaluator(bench.space, settings=settings)
    table = DeviceTable(bench.space, ev.device).sobol(0, 64, 0)[0]
    ev.objectives_of(ev.evaluate_device(table), table)
    path = os.path.join(bench.tmp, "compile.nc")
    sweep(bench.space, path, mode="sobol", n_samples=256, chunk=128, settings=settings, reduce=REDUCE, raw=False)
    search(bench.space, n_trials=64, batch=32, settings=settings, storage=os.path.join(bench.tmp, "compile.journal"))


class Watchdog:
    """After ``seconds``: every thread's stack to stderr, the worker processes killed (by
    their ids, as the clusters report them), the rows done written, exit status 3."""

    def __init__(self, seconds: float, save):
        self.pids: set[int] = set()
        self.save = save
        self.timer = threading.Timer(seconds, self.fire)
        self.timer.daemon = True
        self.timer.start()

    def watch(self, client) -> None:
        """Stop the worker processes of ``client`` (until :meth:`closed`) if time runs out."""
        self.pids = {pid for pid in client.run(os.getpid).values() if pid != os.getpid()}  # (not threads)

    def closed(self) -> None:
        self.pids = set()  # (their ids may be another process's by now)

    def fire(self) -> None:
        print("multi_gpu: --timeout passed; stacks follow, the worker processes are stopped", file=sys.stderr)
        faulthandler.dump_traceback(all_threads=True)
        for pid in self.pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        try:
            self.save(timed_out=True)
        finally:
            os._exit(3)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gpus", default="1,2", help="worker counts to measure, comma separated (default 1,2)")
    ap.add_argument("--devices", default=None, help="the devices in order (default cuda:0, cuda:1, ...)")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma list of {', '.join(CASES)}")
    ap.add_argument("--small", action="store_true", help="CPU-sized defaults (a smoke check)")
    ap.add_argument("--fits", type=int, default=None, help="fit problems (default 400000; --small 8)")
    ap.add_argument("--fit-chunk", type=int, default=None, help="fit problems per chunk (default 50000; --small 4)")
    ap.add_argument(
        "--fit-data",
        choices=("workers", "pinned", "client"),
        default="workers",
        help="where the fit data are made (default workers; pinned: there, in page-locked memory)",
    )
    ap.add_argument("--points", type=int, default=None, help="design evaluations (default 2^26; --small 2^14)")
    ap.add_argument("--eval-chunk", type=int, default=None, help="evaluation chunk (default 2^22; --small 2^11)")
    ap.add_argument("--sweep-points", type=int, default=None, help="reduced sweep points (default 2^30; --small 2^15)")
    ap.add_argument("--sweep-chunk", type=int, default=None, help="sweep chunk (default 2^22; --small 2^12)")
    ap.add_argument("--island-trials", type=int, default=None, help="trials per island (default 2^22; --small 2048)")
    ap.add_argument("--island-batch", type=int, default=None, help="island population (default 8192; --small 256)")
    ap.add_argument(
        "--study-dir",
        default=None,
        help="folder of the islands' study, journals and trial store (default: a temporary folder)",
    )
    ap.add_argument("--repeats", type=int, default=None, help="timings per case, the best kept (default 2; --small 1)")
    ap.add_argument(
        "--cluster",
        choices=("processes", "threads"),
        default="processes",
        help="workers of fits, evaluations and sweep (default processes; the islands always run on processes)",
    )
    ap.add_argument("--timeout", type=float, default=570.0, help="seconds before the run is stopped (default 570)")
    ap.add_argument("--out", default=None, help="JSON output (default: bench/results/multi_gpu.json)")
    args = ap.parse_args(argv)
    small = args.small
    for name, big, little in (
        ("fits", 400000, 8),
        ("fit_chunk", 50000, 4),
        ("points", 1 << 26, 1 << 14),
        ("eval_chunk", 1 << 22, 1 << 11),
        ("sweep_points", 1 << 30, 1 << 15),
        ("sweep_chunk", 1 << 22, 1 << 12),
        ("island_trials", 1 << 22, 2048),
        ("island_batch", 8192, 256),
        ("repeats", 2, 1),
    ):
        if getattr(args, name) is None:
            setattr(args, name, little if small else big)
    try:
        ks = sorted({int(g) for g in args.gpus.split(",")})
    except ValueError:
        ks = []
    if not ks or ks[0] < 1:
        ap.error(f"--gpus {args.gpus!r}: give worker counts >= 1, comma separated")
    cases = [c for c in args.cases.split(",") if c]
    if not cases or set(cases) - set(CASES):
        ap.error(f"--cases {args.cases!r}: choose among {', '.join(CASES)}")
    import warp as wp

    wp.config.quiet = True
    wp.init()
    devices = args.devices.split(",") if args.devices else [f"cuda:{i}" for i in range(ks[-1])]
    if len(devices) < ks[-1]:
        ap.error(f"--gpus {args.gpus}: {ks[-1]} workers but {len(devices)} devices ({','.join(devices)})")
    for d in devices:
        try:
            resolve_device(d)
        except ValueError as e:
            ap.error(f"--devices: {e}")
    import dask

    dask.config.set({"distributed.scheduler.allowed-failures": 0})  # a killed worker fails its case at once
    t_all = time.perf_counter()
    shm = os.statvfs("/dev/shm") if os.path.isdir("/dev/shm") else None
    result = {
        "command": "python bench/multi_gpu.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "devices": devices[: ks[-1]],
        "device_names": [wp.get_device(d).name for d in devices[: ks[-1]]],
        "host": platform.node(),
        "cpu_count": os.cpu_count(),
        "dev_shm_free_gb": None if shm is None else shm.f_bavail * shm.f_frsize / 2**30,
        "warp": wp.config.version,
        "python": sys.version.split()[0],
        "cluster": {"fits, evaluations, sweep": args.cluster, "islands": "processes"},
        **host_topology(),
        "sizes": {
            k: getattr(args, k)
            for k in (
                "fits",
                "fit_chunk",
                "fit_data",
                "points",
                "eval_chunk",
                "sweep_points",
                "sweep_chunk",
                "island_trials",
                "island_batch",
            )
        },
        "repeats": args.repeats,
        "rows": [],
    }

    def save(timed_out=False):
        out = dict(result, rows=[{k: v for k, v in r.items() if not k.startswith("_")} for r in result["rows"]])
        out["timed_out"] = timed_out
        out["bench_seconds"] = time.perf_counter() - t_all
        write_result(out, "multi_gpu.json", args.out)

    dog = Watchdog(args.timeout, save)
    failed = False
    with tempfile.TemporaryDirectory(prefix="tawarp_multi_gpu_") as tmp, GpuClocks() as clocks:
        bench = Bench(args, tmp)
        t = time.perf_counter()
        compile_here(bench, devices[0])
        result["compile_seconds"] = time.perf_counter() - t
        print(f"kernels ready in {result['compile_seconds']:.1f} s", flush=True)
        for k in ks:
            row = {"workers": k, "errors": {}}
            groups = [[c for c in cases if c != "islands"], [c for c in cases if c == "islands"]]
            if args.cluster == "processes":
                groups = [cases]
            for group in (g for g in groups if g):
                t = time.perf_counter()
                processes = args.cluster == "processes" or group == ["islands"]
                client = local_cluster(devices[:k], processes=processes, cpu_threads=1)
                row["start_seconds"] = row.get("start_seconds", 0.0) + time.perf_counter() - t
                try:
                    dog.watch(client)
                    row["worker_cpus"] = _worker_cpus(client)
                    row["worker_gpus"] = _worker_gpus(client)
                    client.get_task_stream()  # the scheduler records the tasks from now on (phases())
                    for c in group:
                        try:
                            w0 = time.time()
                            row.update(getattr(bench, c)(client, k))
                            row[f"{c}_gpu_clocks"] = clocks.between(w0, time.time())
                        except Exception as e:  # a worker killed, out of memory: recorded, the rest goes on
                            row["errors"][c] = f"{type(e).__name__}: {e}"
                            print(f"multi_gpu: {c} on {k} workers failed: {row['errors'][c]}", file=sys.stderr)
                            failed = True
                finally:
                    closed(client)
                    dog.closed()
            row["elapsed_s"] = time.perf_counter() - t_all
            print(json.dumps({key: v for key, v in row.items() if not key.startswith("_")}), flush=True)
            result["rows"].append(row)
            summarize(result, ks)
            save()
    dog.timer.cancel()
    print(json.dumps(result["summary"], indent=1))
    save()
    return 1 if failed else 0


def summarize(result: dict, ks: list) -> None:
    """Speed-ups over the first row and whether each row's results equal the first's."""
    base = result["rows"][0]
    v0 = base.get("_values")
    rates = (
        "fits_per_s",
        "evaluations_per_s",
        "evaluations_back_to_back_per_s",
        "sweep_points_per_hour",
        "island_evaluations_per_minute",
    )
    for r in result["rows"]:
        for key in rates:
            if key in r and key in base:
                r[f"speedup_{key}"] = r[key] / base[key]
        if "_values" in r and v0 is not None:
            r["fits_max_relative_difference_to_first_row"] = float(np.max(np.abs(r["_values"] - v0) / np.abs(v0)))
        if "evaluations_digest" in r:
            r["evaluations_equal_first_row"] = r["evaluations_digest"] == base.get("evaluations_digest")
        if "sweep_reductions" in r:
            r["sweep_reductions_equal_first_row"] = r["sweep_reductions"] == base.get("sweep_reductions")
        if "island0_best" in r:
            r["island0_equals_first_row"] = r["island0_best"] == base.get("island0_best")
    result["summary"] = {
        f"{k}_gpus": {key: r[f"speedup_{key}"] for key in rates if f"speedup_{key}" in r}
        for k, r in zip(ks, result["rows"])
    }
    result["summary"]["targets"] = {"2_gpus": 1.8, "4_gpus": 3.5}


if __name__ == "__main__":
    run(main)
