"""Loop benchmark: the wall time of one :func:`tawarp.loop.run_loop` (base fit, the Bayesian
comparison of every model up to three effects, checks, next measurement, drift), warm (after
one loop that compiles the kernels), on two classes of data. Writes JSON: per case the wall
time ``seconds``, the process's CPU time ``cpu_seconds`` (all its threads) and the main
thread's ``main_thread_cpu_seconds`` (the host's work and its share of each CPU launch, which
:meth:`tawarp.model.forward.Engine.evaluate` splits over the cores: a lower bound of the wall
time on an idle machine), and the machine's ``load_average`` (1, 5, 15 min) before and after
the timed cases (on a shared machine the wall time grows with the others' load, the CPU times
less: on a 2-core VM shared with other jobs the main thread's CPU time of one loop varied by up
to 30 % from run to run), and ``forward_sets``, the parameter sets the kind predicted (every
stage of the loop predicts through it, the planned measurements too), and
``forward_columns``, the T-matrix columns the engines computed for them (a T-matrix set at one
heat input, a layer's set at one thickness): measures of the loop's work that no load changes.
Each case also records what the loop decided (:func:`decisions`: the verdict, the claims and
groups, the best model, ``error_after``, the inclusion probabilities), so that two runs of
different code can be checked to decide the same.

    python bench/loop.py --device cpu                 # on a 2-core machine: the CPU target
    taskset -c 0,1 python bench/loop.py --device cpu  # two cores of a larger host
    python bench/loop.py --device cuda
    python bench/loop.py --device cpu --cases impedance --out /tmp/loop.json   # one class of data

* ``tmatrix``: the validation study's core T-matrix cases (``studies/loop_validation.py``,
  the independent reference, core file 10-30 % off, 37 frequencies 40-400 Hz, Q = 0/20/40 W),
  one case per category in ``--seeds`` (default: clean, plane offsets, convection, a pair);
* ``impedance``: a rigid-backed layer's surface impedance at ``--impedance-freqs`` frequencies
  (default 2694): the measured foam2 layers (both thicknesses) interpolated onto that many
  frequencies over their measured band (200-1600 Hz; outside it ``np.interp`` would hold the
  end values, data no layer gives), with 0.5 % noise;
* ``study``: loop cases per second of a study on this machine, the T-matrix cases run in
  each of P processes for each P of ``--processes`` (``--repeats`` times each), spawned after
  the warm-up compiled the kernels (:func:`study`): how a study that runs many cases is
  best spread over a host's cores and its GPU; ``cases_per_second`` over the wall time,
  ``cases_per_second_after_start`` over the slowest process's own time (its start left out).
  With ``--together N`` each process runs its cases N at a time as loops together
  (:func:`tawarp.loop.run_loops`, ordered so that the kinds of one family come together),
  and the bench first runs them so in its own process from cold (``together_one_process``:
  the kernels the processes load, and one process's loops a second). With
  ``--blocking-waits`` each process's CUDA context waits for the GPU by blocking, not
  spinning (:func:`tawarp.distributed.wait_by_blocking`), so that more processes than cores
  share the host; with ``--read-waits`` each process's reads of GPU arrays and uploads are
  timed by the wall clock, by call site, with its context switches (``read_waits``,
  ``bench/_read_waits.py``: the waits that blocking takes off the CPU time);
* ``together``: the T-matrix cases in this process, ``--together`` at a time, warm (a first
  round, ``cold``, compiles or loads the kernels; the second, ``warm``, is timed): the host
  work a case costs when loops run together, without a study's processes sharing the host
  and the GPU (before and after a change, back to back in one lease); with ``--device-time``
  the warm round's kernels and copies are timed on the device (``device_time``: what the GPU
  itself spends a case, by kind and by kernel); with ``--host-time`` the warm round's host
  CPU time by function (``host_time``: each timed function's thread CPU time less that of the
  timed functions it calls, ``bench/_host_time.py``), with ``--read-waits`` its reads' and
  uploads' wall time, and with ``--blocking-waits`` this process waits for the GPU by
  blocking, so that its waits take no CPU time.

    python bench/loop.py --device cuda --cases study --processes 1,4,16
    python bench/loop.py --device cpu --cases study --processes 16
    python bench/loop.py --device cuda --cases study --processes 16 --together 64 \
        --seeds 1002-1103 --cache studies/out/loop_validation_heldout_drift/cache
    python bench/loop.py --device cuda --cases study --processes 24 --together 64 --blocking-waits \
        --seeds 1002-1103 --cache studies/out/loop_validation_heldout_drift/cache
    python bench/loop.py --device cuda --cases together --together 32 --seeds 1002-1039 \
        --cache studies/out/loop_validation_heldout_drift/cache --device-time
    python bench/loop.py --device cuda --cases together --together 64 --seeds 1002-1103 \
        --cache studies/out/loop_validation_heldout_drift/cache --host-time --blocking-waits
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import os
import platform
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "studies"))
import loop_validation as lv  # noqa: E402
from _host_time import summary, thread_times  # noqa: E402
from _read_waits import read_waits  # noqa: E402
from _read_waits import summary as read_waits_summary  # noqa: E402
from _results import run, write_result  # noqa: E402

from tawarp.distributed import (  # noqa: E402
    BLAS_THREAD_VARIABLES,
    context_waits,
    cores_shared,
    cuda_mps_running,
    require_blocking_waits,
)
from tawarp.loop import impedance_loop, run_loop, run_loops  # noqa: E402
from tawarp.measure import ImpedanceKind, TMatrixKind, load_atalla_panneton  # noqa: E402
from tawarp.measure.files import ImpedanceData  # noqa: E402
from tawarp.model.forward import Engine, ForwardSettings, cpu_share  # noqa: E402


def _clocks() -> tuple[float, float, float]:
    return time.perf_counter(), time.process_time(), time.thread_time()


def _elapsed(start: tuple[float, float, float]) -> dict:
    """The case's ``seconds``, ``cpu_seconds`` and ``main_thread_cpu_seconds`` since ``start``."""
    now = _clocks()
    keys = ("seconds", "cpu_seconds", "main_thread_cpu_seconds")
    return {k: b - a for k, a, b in zip(keys, start, now)}


@contextlib.contextmanager
def counting_sets(kind: type):
    """Count the parameter sets every instance of the measurement kind ``kind`` predicts
    while inside, and the columns the forward engines compute for them (:meth:`Engine.evaluate`
    and, under :meth:`Engine.distinct`, :meth:`Engine._computed`: the distinct ones,
    less those a CPU engine served from its memo): yields a dict whose ``sets`` and
    ``columns`` grow."""
    count = {"sets": 0, "columns": 0}
    predicting = {name: kind.__dict__.get(name) for name in ("predict", "predict_on_device")}
    engine = {name: getattr(Engine, name) for name in ("evaluate", "_computed")}
    inside = threading.local()  # a prediction on the device formed on the host counts once

    def counting(method):
        def counted(self, values, n, *args, **kw):
            outer = not getattr(inside, "on", False)
            count["sets"] += n if outer else 0
            inside.on = True
            try:
                return method(self, values, n, *args, **kw)
            finally:
                inside.on = not outer

        return counted

    def computing(method):
        def computed(self, varying, *args, **kw):
            count["columns"] += varying.shape[1]
            return method(self, varying, *args, **kw)

        return computed

    for name in predicting:
        setattr(kind, name, counting(getattr(kind, name)))
    for name, method in engine.items():
        setattr(Engine, name, computing(method))
    try:
        yield count
    finally:
        for name, method in predicting.items():
            if method is None:  # inherited: the class's own attribute goes again
                delattr(kind, name)
            else:
                setattr(kind, name, method)
        for name, method in engine.items():
            setattr(Engine, name, method)


def decisions(rep) -> dict:
    """What the loop decided, in report.json's keys: two runs of different code compare by
    these (the verdict, the claims, the groups and the best model the same, error_after and
    the inclusion probabilities within the fits' stopping rules)."""
    return {
        "verdict": rep["verdict"],
        "claimed": rep["accepted_steps"],
        "accepted_groups": rep["accepted_groups"],
        "best_model": rep["best_model"],
        "error_after": rep["error_after"],
        "inclusion_probabilities": rep["inclusion_probabilities"],
        "models": rep["models_compared"],
    }


def tmatrix_case(seed: int, device: str, cache: Path, cpu_threads: int | None = None) -> tuple:
    """(the study's case ``seed``, its T-matrix problem with the case's core file) on
    ``device`` (a CPU launch split over ``cpu_threads``, default every core), the reference
    data from ``cache``."""
    case = lv.make_case(seed)
    arrays = lv.load_or_generate(case, cache)
    core = lv.load_core(case.core_material).replace(**case.prior)
    settings = ForwardSettings(device=device, cpu_threads=cpu_threads)
    return case, lv.TMatrixKind(lv.measurement(case, arrays), core, settings)


def tmatrix_cases(seeds, device, cache: Path) -> list[dict]:
    out = []
    for seed in seeds:
        case, prob = tmatrix_case(seed, device, cache)
        with counting_sets(TMatrixKind) as count:
            clock = _clocks()
            rep = run_loop(prob)
            elapsed = _elapsed(clock)
        out.append(
            {
                "seed": seed,
                "category": case.category,
                "material": case.material,
                "rows": int(prob.y.size),
                **elapsed,
                "forward_sets": count["sets"],
                "forward_columns": count["columns"],
                **decisions(rep),
            }
        )
        print(f"tmatrix seed {seed} ({case.category}): {out[-1]['seconds']:.1f} s, {rep['verdict']}")
    return out


def by_family(items: list, kinds: list | None = None) -> list:
    """``items`` (default the kinds ``kinds`` themselves) ordered so that the kinds of one
    family (:meth:`tawarp.measure.MeasurementKind.family`), which share their launches in
    :func:`tawarp.loop.run_loops`, come together, in their first one's place."""
    kinds = items if kinds is None else kinds
    first: dict = {}
    keys = [first.setdefault(k.family(), len(first)) for k in kinds]
    return [items[i] for i in sorted(range(len(items)), key=lambda i: keys[i])]


def loops_in_groups(probs: list, together: int) -> list:
    """The loops' reports of ``probs``, ``together`` at a time (:func:`tawarp.loop.run_loops`;
    one: each alone, :func:`tawarp.loop.run_loop`), in their order."""
    if together == 1:
        return [run_loop(prob) for prob in probs]
    return [rep for k in range(0, len(probs), together) for rep in run_loops(probs[k : k + together])]


#: Warp's kinds of CUDA activity (:func:`warp.timing_begin`) by their names in the JSON.
ACTIVITIES = {
    "kernels": wp.TIMING_KERNEL,
    "builtin_kernels": wp.TIMING_KERNEL_BUILTIN,
    "copies": wp.TIMING_MEMCPY,
    "memsets": wp.TIMING_MEMSET,
    "graphs": wp.TIMING_GRAPH,
}


def device_time(activities: list, cases: int, top: int = 12) -> dict:
    """The device's own time of Warp's timed ``activities`` (:func:`warp.timing_end`) over
    ``cases`` cases: seconds of each kind, milliseconds a case, and the ``top`` activities
    by name (kernels by their module's function, copies by direction)."""
    kinds = {name: [a for a in activities if a.filter == flag] for name, flag in ACTIVITIES.items()}
    by_name: dict = {}
    for a in activities:
        seconds, count = by_name.get(a.name, (0.0, 0))
        by_name[a.name] = (seconds + a.elapsed / 1e3, count + 1)
    return {
        "activities_per_case": len(activities) / cases,
        "seconds": {name: sum(a.elapsed for a in got) / 1e3 for name, got in kinds.items()},
        "ms_per_case": {name: sum(a.elapsed for a in got) / cases for name, got in kinds.items()},
        "by_name": [
            {"name": name, "seconds": seconds, "count": count}
            for name, (seconds, count) in sorted(by_name.items(), key=lambda kv: -kv[1][0])[:top]
        ],
    }


def together_cases(
    seeds, device, cache: Path, together: int, timed: bool = False, host_time: bool = False, waits: bool = False
) -> dict:
    """The T-matrix cases ``seeds`` in this process, ``together`` loops at a time
    (:func:`tawarp.loop.run_loops`), from cold: the loops a second of one process, its first
    launches' compiles or cache loads included. ``timed``: the device's own time of every
    kernel and copy too (:func:`device_time`; CUDA events around each, which the wall time
    then includes). ``host_time``: the host's CPU time by function (``bench/_host_time.py``;
    a wrapper's few microseconds a call, which the CPU times then include). ``waits``: the
    wall time of the reads of GPU arrays and the uploads, by call site
    (``bench/_read_waits.py``)."""
    cases = [tmatrix_case(seed, device, cache) for seed in seeds]
    order = by_family(list(range(len(cases))), [prob for _, prob in cases])
    seeds, probs = [seeds[i] for i in order], [cases[i][1] for i in order]
    if timed:
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
    with (
        thread_times() if host_time else contextlib.nullcontext() as totals,
        read_waits() if waits else contextlib.nullcontext() as reads,
    ):
        clock = _clocks()
        reps = loops_in_groups(probs, together)
        out = {"cases": len(reps), "loops_together": together, **_elapsed(clock)}
    if waits:
        out["read_waits"] = read_waits_summary(reads, len(reps))
    if timed:
        out["device_time"] = device_time(wp.timing_end(), len(reps))
    if host_time:
        out["host_time"] = summary(totals, len(reps), out["cpu_seconds"])
    out["cases_per_second"] = len(reps) / out["seconds"]
    out["decisions"] = {str(seed): decisions(rep) for seed, rep in zip(seeds, reps)}
    print(f"{len(reps)} cases, {together} together, in this process: {out['seconds']:.1f} s")
    return out


@contextlib.contextmanager
def interrupts_ignored():
    """Ctrl-C ignored inside; processes started here keep ignoring it."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _study_worker(job: tuple) -> dict:
    """One process of :func:`study`: the T-matrix cases ``seeds``, ``repeats`` times each,
    ``together`` at a time (:func:`tawarp.loop.run_loops`); ``waits``: its reads' wall time
    (``bench/_read_waits.py``)."""
    seeds, device, cache, repeats, cpu_threads, together, waits = job
    wp.config.quiet = True
    verdicts = []
    with read_waits() if waits else contextlib.nullcontext() as reads:
        clock = _clocks()
        for _ in range(repeats):
            probs = by_family([tmatrix_case(seed, device, Path(cache), cpu_threads)[1] for seed in seeds])
            verdicts += [rep["verdict"] for rep in loops_in_groups(probs, together)]
        out = {**_elapsed(clock), "verdicts": verdicts, "cuda_waits": context_waits(device)}
    if waits:
        out["read_waits"] = read_waits_summary(reads, len(verdicts))
    return out


def _blocking_worker(device: str) -> None:
    """A loop process's start with ``--blocking-waits``: its CUDA context waits by blocking."""
    wp.config.quiet = True
    require_blocking_waits(device)


def study(
    seeds,
    device,
    cache: Path,
    processes: list[int],
    repeats: int,
    together: int = 1,
    blocking: bool = False,
    waits: bool = False,
) -> list[dict]:
    """Loop cases per second of a study on this machine: for each count P of ``processes``, P
    processes (each its own Warp context, on the CPU or sharing the GPU) each running the
    T-matrix cases ``seeds`` ``repeats`` times, ``together`` loops at a time in one batch
    (:func:`tawarp.loop.run_loops`), its linear algebra's threads limited to its share of
    the cores (:func:`tawarp.distributed.cores_shared`); on the CPU its launches split over
    that share too. ``blocking``: each process's CUDA contexts wait by blocking
    (:func:`tawarp.distributed.wait_by_blocking`). ``waits``: each process's reads of GPU
    arrays and uploads timed (``bench/_read_waits.py``)."""
    out = []
    for P in processes:
        threads = cpu_share(P) if device == "cpu" else None
        jobs = [(seeds, device, str(cache), repeats, threads, together, waits)] * P
        start = time.perf_counter()
        # spawned: this process has started CUDA, which a forked child cannot use; with
        # Ctrl-C ignored, which they inherit, so that an interrupt stops the study here once
        # and ends them (not a traceback from each)
        with interrupts_ignored(), cores_shared(P):
            pool = multiprocessing.get_context("spawn").Pool(
                P, initializer=_blocking_worker if blocking else None, initargs=(device,) if blocking else ()
            )
            started_with = {k: os.environ.get(k) for k in BLAS_THREAD_VARIABLES}
        try:
            runs = pool.map(_study_worker, jobs)
            pool.close()
        except BaseException:
            pool.terminate()
            raise
        finally:
            pool.join()
        wall = time.perf_counter() - start
        n = sum(len(r["verdicts"]) for r in runs)
        out.append(
            {
                "processes": P,
                "loops_together": together,
                "cpu_threads_per_process": threads,
                # the environment that sized each process's linear-algebra threads
                "blas_threads_environment": started_with,
                "cases": n,
                "seconds": wall,
                "cases_per_second": n / wall,
                # the wall holds the processes' start (spawn, imports, CUDA contexts, kernel
                # loads), which a study of more cases a process amortizes
                "cases_per_second_after_start": n / max(r["seconds"] for r in runs),
                "process_seconds": [r["seconds"] for r in runs],
                "process_cpu_seconds": [r["cpu_seconds"] for r in runs],
                # how each process's CUDA context waited for the GPU (None on the CPU)
                "cuda_waits": sorted({str(r["cuda_waits"]) for r in runs}),
                "verdicts": runs[0]["verdicts"][: len(seeds)],
            }
        )
        if waits:
            out[-1]["read_waits"] = [r["read_waits"] for r in runs]
        print(
            f"study, {P} processes on {device}, {together} loops together: {n} cases in {wall:.1f} s, "
            f"{n / wall:.3f} cases/s"
        )
    return out


def impedance_case(n: int, device: str) -> dict:
    rng = np.random.default_rng(0)
    layers = load_atalla_panneton("foam2")
    f = np.linspace(max(d.freq.min() for d in layers), min(d.freq.max() for d in layers), n)
    data = []
    for d in layers:
        Zs = np.interp(f, d.freq, d.Zs.real) + 1j * np.interp(f, d.freq, d.Zs.imag)
        Zs = Zs * (1 + 0.005 * (rng.standard_normal(n) + 1j * rng.standard_normal(n)))
        data.append(
            ImpedanceData(f, Zs, d.thickness, d.T_ambient, d.p_ambient, source=f"{d.source} on {n} frequencies")
        )
    with counting_sets(ImpedanceKind) as count:
        clock = _clocks()
        prob, rep = impedance_loop(data, settings=ForwardSettings(device=device))
        elapsed = _elapsed(clock)
    out = {
        "frequencies": n,
        "rows": int(prob.y.size),
        **elapsed,
        "forward_sets": count["sets"],
        "forward_columns": count["columns"],
        **decisions(rep),
    }
    print(f"impedance, {n} frequencies: {out['seconds']:.1f} s, best {'+'.join(rep['best_model']) or 'base'}")
    return out


def _seed_range(part: str) -> range:
    """ "A-B" as A..B, "A" as A alone."""
    a, dash, b = part.partition("-")
    return range(int(a), int(b) + 1) if dash else range(int(a), int(a) + 1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seeds", default="0,1,7,11", help="study seeds of the T-matrix cases (comma list; A-B: A to B)")
    ap.add_argument("--impedance-freqs", type=int, default=2694)
    ap.add_argument("--cases", default="tmatrix,impedance", help="which classes of data (comma list)")
    ap.add_argument(
        "--cache",
        default=str(Path(__file__).resolve().parents[1] / "studies" / "out" / "loop_bench" / "cache"),
        help="where the reference data of the cases are kept (git-ignored)",
    )
    ap.add_argument(
        "--processes",
        default="1,16",
        help="the study's process counts (comma list): each process runs the T-matrix cases --repeats times",
    )
    ap.add_argument("--repeats", type=int, default=1, help="times each study process runs the T-matrix cases")
    ap.add_argument(
        "--together",
        type=int,
        default=1,
        help="loops a study process runs together, their fits in one batch (tawarp.loop.run_loops)",
    )
    ap.add_argument(
        "--device-time",
        action="store_true",
        help="with --cases together on a GPU: the warm round's kernels and copies timed on the device",
    )
    ap.add_argument(
        "--host-time",
        action="store_true",
        help="with --cases together: the warm round's host CPU time by function (bench/_host_time.py)",
    )
    ap.add_argument(
        "--blocking-waits",
        action="store_true",
        help="with --cases study or together on a GPU: each process's CUDA context waits by blocking, not spinning",
    )
    ap.add_argument(
        "--read-waits",
        action="store_true",
        help="with --cases study or together on a GPU: each process's reads of GPU arrays and uploads timed "
        "by the wall clock, by call site, and its context switches (bench/_read_waits.py)",
    )
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    try:
        seeds = [k for part in args.seeds.split(",") for k in _seed_range(part)]
    except ValueError:
        ap.error(f"--seeds: {args.seeds!r}; expected integers, comma separated")
    cases = set(args.cases.split(","))
    if not cases or not cases <= {"tmatrix", "impedance", "study", "together"}:
        ap.error(f"--cases: {args.cases!r}; expected tmatrix, impedance, study, together or several, comma separated")
    try:
        processes = [int(p) for p in args.processes.split(",")]
    except ValueError:
        processes = []
    if not processes or min(processes) < 1:
        ap.error(f"--processes: {args.processes!r}; expected positive integers, comma separated")
    if args.repeats < 1:
        ap.error(f"--repeats: {args.repeats}; expected a positive integer")
    if args.together < 1:
        ap.error(f"--together: {args.together}; expected a positive integer")
    wp.config.quiet = True
    wp.init()
    try:
        device = wp.get_device(args.device)
    except (RuntimeError, ValueError) as e:
        ap.error(f"--device: {args.device!r}: {e}")
    if args.blocking_waits and (not cases & {"study", "together"} or device.is_cpu):
        ap.error(
            "--blocking-waits: sets how the loops' processes wait for a GPU; needs --cases study or together "
            "and a CUDA --device"
        )
    if args.host_time and "together" not in cases:
        ap.error("--host-time: times the warm round of loops together; needs --cases together")
    if args.read_waits and (not cases & {"study", "together"} or device.is_cpu):
        ap.error("--read-waits: times the waits for a GPU; needs --cases study or together and a CUDA --device")
    if args.device_time and ("together" not in cases or device.is_cpu):
        ap.error("--device-time: times a GPU's work; needs --cases together and a CUDA --device")
    cache = Path(args.cache)
    try:
        cache.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        ap.error(f"--cache: {e}")
    # warm-up: compiles the kernels
    together_warm = None
    if "study" in cases and args.together > 1:
        # the cases together in this process: their kernels, which the study's processes load
        # from Warp's cache, and the loops a second of one process
        together_warm = together_cases(seeds, args.device, cache, args.together)
    elif cases & {"tmatrix", "study"}:
        # a study's processes load the kernels every case compiles, from Warp's cache
        tmatrix_cases(seeds if "study" in cases else seeds[:1], args.device, cache)
    if "impedance" in cases:
        impedance_case(64, args.device)
    result = {
        "benchmark": "loop",
        "device": args.device,
        "device_name": wp.get_device(args.device).name if args.device != "cpu" else platform.processor(),
        "cpu_cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "host": platform.node(),
        "load_average": {"before": list(os.getloadavg())},
        # processes that share a GPU run side by side under NVIDIA's MPS daemon, else take turns
        "cuda_mps": cuda_mps_running(),
    }
    if "tmatrix" in cases:
        result["tmatrix"] = tmatrix_cases(seeds, args.device, cache)
        t = [c["seconds"] for c in result["tmatrix"]]
        result["tmatrix_seconds_mean_max"] = [float(np.mean(t)), float(np.max(t))]
    if "impedance" in cases:
        result["impedance"] = impedance_case(args.impedance_freqs, args.device)
    if "study" in cases:
        result["study"] = study(
            seeds, args.device, cache, processes, args.repeats, args.together, args.blocking_waits, args.read_waits
        )
        if together_warm is not None:
            result["together_one_process"] = together_warm
    if "together" in cases:
        if args.blocking_waits:
            _blocking_worker(args.device)
            result["cuda_waits"] = context_waits(args.device)
        result["together"] = {
            "cold": together_warm or together_cases(seeds, args.device, cache, args.together),
            "warm": together_cases(
                seeds, args.device, cache, args.together, args.device_time, args.host_time, args.read_waits
            ),
        }
    result["load_average"]["after"] = list(os.getloadavg())
    tag = "cpu" if args.device == "cpu" else wp.get_device(args.device).name.lower().replace(" ", "_")
    prefix = {frozenset({"study"}): "loop_study", frozenset({"together"}): "loop_together"}.get(
        frozenset(cases), "loop"
    )
    name = f"{prefix}_{tag}_{result['cpu_cores']}core" if args.device == "cpu" else f"{prefix}_{tag}"
    write_result(result, name + ".json", args.out)
    return 0


if __name__ == "__main__":
    run(main)
