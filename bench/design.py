"""Benchmark of design search and sweeps: writes bench/results/design_<device>.json (cuda: design_cuda_<gpu>.json).

Search: a batched CMA-ES study (and an NSGA-II one) over material x stack length x
porosity x hot-exchanger length x heat input, stored as the command line does (a journal
file; every trial in its HDF5 trial store, the best copied into the study; committed once a
second, ``commit_seconds=1``); the samplers ask and tell on the device
(:mod:`tawarp.kernels.sampler`); reported: design evaluations per minute end to end (sampler, storage and
evaluation included), the share of wall time in the sampler, the storage and the
evaluation (device launches plus transfers), and the share of wall time the device is
busy with kernels (kernel time of one batch, measured on a device-resident batch, times
the number of batches, over the wall time), the trial store's share (part of the
storage's) and the trials the Optuna study holds. Optuna's own samplers (one ask per trial)
are timed on a smaller run for comparison.

Sweep: a Sobol sweep streamed to netCDF at two sizes, and the same sweep reduced on the
device (``--reduce`` of :data:`REDUCE`, no raw values: mode ``sobol_reduced``), each in its own process so that
its peak resident memory is its own: forward evaluations per hour and peak RSS (flat
memory: the two peaks should match). ``--sweep-only`` runs grid and Sobol sweeps (the
grid: the 4 materials times 2^k values of each continuous variable) at both sizes and
writes bench/results/design_sweep_<device>.json: per sweep the evaluations per hour, the
seconds waiting on the device (evaluation_s) and writing (write_s), the same sweep again over
the file it wrote (overwrite_*: ext4 writes the new file's data out at the rename), and the engine's own rate on one chunk (table, heat solve, metrics, to the
device's completion) for comparison: a chunk that is a whole coarser grid (every material,
each variable's full range), the sweep's own Sobol points, those with the reductions, and
the evaluation alone on those points as drawn, grouped by material and sorted by every
value (what a warp's differing designs cost).

    python bench/design.py --device cuda                # < 3 min on one H100
    python bench/design.py --device cuda --sweep-only   # sweeps alone
    python bench/design.py --device cpu --small         # < 2 min on a laptop CPU
    python bench/design.py --device cuda --cases sweep_reduced --sweep-points 67108864,268435456
    python bench/design.py --device cuda --cases cmaes,nsga2 --trials 4194304 --batch 32768 \
        --mo-trials 1048576 --mo-batch 8192             # the two batched searches alone

``--surrogate`` replaces the searches' design evaluation by an analytic stand-in computed
with NumPy (:func:`surrogate_metrics`; the tables, transfers and every other step as in a
real run): the wall time is then the host's own work, sampler and storage, which is what a
fast device leaves of a search; measured on a CPU it tells that work's cost without a GPU.

    python bench/design.py --device cpu --surrogate --cases nsga2 --mo-trials 1048576 --mo-batch 8192

``--cases`` picks the parts (cmaes, nsga2, optuna, sweep, sweep_reduced); the JSON file
is rewritten after each part (``"complete": false`` until the last), so a run stopped by
a time limit keeps what it measured.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from _results import run, write_result  # noqa: E402 (bench/ is the script's own folder)

VARS = [
    "material=ceramic,mesh,nicr_foam,rvc_foam",
    "stack.length=0.005:0.1",
    "stack.porosity=0.6:0.98",
    "hot_hx.length=0.005:0.03",
    "heat_input=1:30",
]


#: The parts of a run (--cases), in the order they run.
CASES = ("cmaes", "nsga2", "optuna", "sweep", "sweep_reduced")
#: The reductions of the reduced sweep (tawarp.design.reductions): all of them.
REDUCE = "best,quantiles,histogram,pareto,top=100"


def _space():
    from tawarp.model.core import load_core
    from tawarp.design.space import DesignSpace

    return DesignSpace(load_core("rvc_foam"), VARS)


def surrogate_metrics(table: np.ndarray) -> np.ndarray:
    """Stand-in kernel metrics (n, 4: gradient [K/m], T_max [K], heat_leak [W], T_hot [K])
    of a varying table (heat input, then :data:`VARS`' core parameters as
    ``DesignSpace.varying_table`` orders them): smooth, of the real metrics' magnitudes,
    gradient and heat leak in conflict (both grow with the heat input and the solid
    fraction, the leak falls with the stack's length) and the temperature limit active
    for some, so that NSGA-II's lineage front grows as on the real space."""
    Q, phi, k_s, length, hx = table[0], table[1], table[4], table[6], table[7]
    solid = 1.25 - phi
    gradient = 40.0 * Q * solid / (length + 0.003) / (1.0 + 0.05 * k_s)
    heat_leak = 0.2 * Q * (1.0 + phi) + 0.01 * k_s * solid / length + 20.0 * hx
    T_max = 300.0 + 12.0 * Q * (1.0 + 20.0 * hx) * solid
    return np.stack([gradient, T_max, heat_leak, T_max - 10.0], axis=1)


@contextlib.contextmanager
def surrogate_evaluation(on: bool):
    """Inside, every ``Evaluator.evaluate_device`` returns :func:`surrogate_metrics` (when ``on``)."""
    if not on:
        yield
        return
    import warp as wp

    from tawarp.design.evaluate import Evaluator

    real = Evaluator.evaluate_device

    def evaluate_device(self, varying, out=None):
        table = varying.numpy() if isinstance(varying, wp.array) else np.asarray(varying, dtype=np.float64)
        return wp.array(surrogate_metrics(table), dtype=wp.float64, device=self.device)

    Evaluator.evaluate_device = evaluate_device
    try:
        yield
    finally:
        Evaluator.evaluate_device = real


def bench_search(device, n_trials, batch, objectives, engine="batched", tmp=None, commit_seconds=1.0, surrogate=False):
    with surrogate_evaluation(surrogate):
        res = _bench_search(device, n_trials, batch, objectives, engine, tmp, commit_seconds)
    res["evaluation"] = "surrogate (NumPy on the host)" if surrogate else "the design kernels"
    return res


def _bench_search(device, n_trials, batch, objectives, engine, tmp, commit_seconds):
    import warp as wp

    from tawarp.design.evaluate import Evaluator
    from tawarp.design.search import search
    from tawarp.design.storage import study_summary
    from tawarp.model.forward import ForwardSettings

    space = _space()
    settings = ForwardSettings(device=device)
    storage = os.path.join(tmp, f"{engine}_{len(objectives)}.journal")
    # warm-up: kernels compiled and modules (h5py too) imported before timing
    search(
        space,
        objectives,
        n_trials=2 * min(batch, 64),
        batch=min(batch, 64),
        settings=settings,
        engine=engine,
        storage=os.path.join(tmp, f"warmup_{engine}_{len(objectives)}.journal"),
    )
    t, cpu, main = time.perf_counter(), time.process_time(), time.thread_time()
    res = search(
        space,
        objectives,
        n_trials=n_trials,
        batch=batch,
        storage=storage,
        settings=settings,
        engine=engine,
        commit_seconds=commit_seconds,
    )
    wall = time.perf_counter() - t
    cpu, main = time.process_time() - cpu, time.thread_time() - main
    # kernel time of one batch on a device-resident table
    ev = Evaluator(space, settings=settings)
    import numpy as np

    from tawarp.design.samplers import sobol_unit

    u = sobol_unit(batch, len(space.continuous), 1)
    vals = space.from_unit(u)
    vals["material"] = np.arange(batch) % 4
    table = wp.array(space.varying_table(vals), dtype=wp.float64, device=ev.device)
    ev.evaluate_device(table)
    wp.synchronize_device(ev.device)
    reps = 20
    t0 = time.perf_counter()
    for _ in range(reps):
        ev.evaluate_device(table)
    wp.synchronize_device(ev.device)
    kernel = (time.perf_counter() - t0) / reps
    n_batches = res.timing["evaluations"] / batch
    tm = res.timing
    summary = study_summary(res.study)
    return {
        "engine": engine,
        "objectives": list(objectives),
        "trials": tm["evaluations"],
        "batch": batch,
        "storage": "journal file" + (" + HDF5 trial store" if summary["store"] else ""),
        "commit_seconds": commit_seconds,
        "wall_s": wall,
        "evaluations_per_minute": 60.0 * tm["evaluations"] / wall,
        "sampler_s": tm["sampler"],
        "storage_s": tm["storage"],
        "evaluation_s": tm["evaluation"],
        "sampler_share": tm["sampler"] / wall,
        "storage_share": tm["storage"] / wall,
        "evaluation_share": tm["evaluation"] / wall,
        "trial_store_s": tm["trial_store"],
        # CPU time of the process (every thread) and of the search's own thread: on a
        # shared host the wall time varies with the other load, these much less
        "process_cpu_s": cpu,
        "main_thread_cpu_s": main,
        "trial_store_share": tm["trial_store"] / wall,
        "trials_in_study": summary["in_study"],
        "trials_queryable": summary["trials"],
        "kernel_s_per_batch": kernel,
        "device_busy_share": kernel * n_batches / wall,
        "best": res.best[0]["values"] if res.best else None,
    }


def _grid_space(n):
    """VARS as a grid of about n points: the 4 materials times 2^k values per continuous
    variable (k split as evenly as the power of two allows)."""
    from tawarp.model.core import load_core
    from tawarp.design.space import DesignSpace

    bits = max(0, int(n // 4).bit_length() - 1)
    counts = [2 ** (bits // 4 + (j < bits % 4)) for j in range(4)]
    spec = [VARS[0]] + [f"{v}:{c}" for v, c in zip(VARS[1:], counts)]
    return DesignSpace(load_core("rvc_foam"), spec)


def _engine_rate(space, device, chunk, mode="grid", reduce=None):
    """Points per second of the engine alone on one chunk: the table built on the device
    (``mode`` grid: from the point index; sobol: the sweep's Sobol points drawn there), the
    heat solve and the metrics kernel, timed to the device's completion (no transfers,
    no file): the rate a sweep would reach if nothing else cost. ``reduce``: with the
    reduced sweep's reductions of each chunk launched too (their device time; a Sobol
    chunk)."""
    import warp as wp

    from tawarp.design.evaluate import Evaluator
    from tawarp.design.objectives import kernel_metrics
    from tawarp.design.reductions import Reducer, parse_reduce
    from tawarp.design.space import DeviceTable
    from tawarp.model.forward import ForwardSettings

    ev = Evaluator(space, settings=ForwardSettings(device=device))
    tables = DeviceTable(space, ev.device)
    if mode == "grid":
        chunk = min(chunk, int(np.prod([len(v.grid()) for v in space.variables])))
    outputs = kernel_metrics()
    reducer = None
    if reduce:
        reducer = Reducer(parse_reduce(reduce), space, mode, outputs, ("gradient", "heat_leak"), ev.device, chunk)

    def one(k):
        table, values = (tables.grid(0, chunk), None) if mode == "grid" else tables.sobol(0, chunk, 0)
        f32 = ev.metric_columns(ev.evaluate_device(table), outputs)
        if reducer is not None:  # as the sweep: chunk k - 1's candidates merged while chunk k runs
            reducer.add(k, k * chunk, values, f32)
            if k > 0:
                reducer.collect(k - 1)

    one(0)
    wp.synchronize_device(ev.device)
    reps = 5
    t = time.perf_counter()
    for k in range(1, reps + 1):
        one(k)
    wp.synchronize_device(ev.device)
    return reps * chunk / (time.perf_counter() - t)


def _evaluation_rate(space, device, chunk, order=None):
    """Points per second of the evaluation alone (heat solve, metrics, their float32
    columns; no table made, no reduction) on one chunk of the sweep's Sobol points, whose
    table is made once and, with ``order``, its columns sorted on the host first:
    ``"material"`` grouped by material (stable: Sobol order within each), ``"values"`` by
    every design value (material first): the most coherent order the same points have.
    Against the unsorted rate: what a warp's 32 differing designs cost (divergent branches,
    the math functions' own value-dependent paths)."""
    import warp as wp

    from tawarp.design.evaluate import Evaluator
    from tawarp.design.objectives import kernel_metrics
    from tawarp.design.space import DeviceTable
    from tawarp.model.forward import ForwardSettings

    ev = Evaluator(space, settings=ForwardSettings(device=device))
    table, values = DeviceTable(space, ev.device).sobol(0, chunk, 0)
    if order is not None:
        v = values.numpy()  # rows: the continuous variables, then the material (lexsort's first key)
        perm = np.lexsort(v[-1:] if order == "material" else v)
        table = wp.array(table.numpy()[:, perm], dtype=wp.float64, device=ev.device)
    outputs = kernel_metrics()
    ev.metric_columns(ev.evaluate_device(table), outputs)
    wp.synchronize_device(ev.device)
    reps = 5
    t = time.perf_counter()
    for _ in range(reps):
        ev.metric_columns(ev.evaluate_device(table), outputs)
    wp.synchronize_device(ev.device)
    return reps * chunk / (time.perf_counter() - t)


def sweep_child(device, mode, n, chunk, path):
    """Run one sweep in this process and print its numbers (peak RSS of this process)."""
    from tawarp.model.forward import ForwardSettings
    from tawarp.design.sweep import sweep

    space = _grid_space(n) if mode == "grid" else _space()
    settings = ForwardSettings(device=device)
    kw = dict(reduce=REDUCE, raw=False) if mode == "sobol_reduced" else {}
    mode = "sobol" if mode == "sobol_reduced" else mode
    warm = _grid_space(min(n, 4 * chunk)) if mode == "grid" else space
    # the warm-up writes another file: the sweep measured writes a new one, as a first run does
    # (replacing an existing file costs ext4's flush of the new one's data at the rename)
    sweep(warm, path + ".warm", mode=mode, n_samples=min(n, 4 * chunk), chunk=chunk, settings=settings, **kw)
    os.remove(path + ".warm")
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    info = sweep(space, path, mode=mode, n_samples=n, chunk=chunk, settings=settings, **kw)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    again = sweep(space, path, mode=mode, n_samples=n, chunk=chunk, settings=settings, **kw)  # over the file
    # one chunk that is a whole (coarser) grid: every material, each variable's full range
    # (the sweep's own first chunk is one material and a quarter of the stack lengths)
    engine = _engine_rate(_grid_space(chunk), device, chunk)
    sobol_engine = reduced_engine = None
    evaluation = {}
    if mode == "sobol":
        sobol_engine = 3600.0 * _engine_rate(space, device, chunk, "sobol")
        reduced_engine = 3600.0 * _engine_rate(space, device, chunk, "sobol", REDUCE) if kw else None
        evaluation = {
            f"evaluation_{name}_evaluations_per_hour": 3600.0 * _evaluation_rate(space, device, chunk, order)
            for name, order in (("sobol", None), ("by_material", "material"), ("by_values", "values"))
        }
    print(
        json.dumps(
            {
                "mode": mode + (" reduced: " + REDUCE + ", no raw values" if kw else ""),
                "points": info.n_points,
                "chunk": chunk,
                "chunks": info.chunks,
                "seconds": info.seconds,
                "evaluations_per_hour": info.evaluations_per_hour,
                "evaluation_s": info.evaluation_seconds,
                "write_s": info.write_seconds,
                "engine_evaluations_per_hour": 3600.0 * engine,
                "share_of_engine_rate": info.evaluations_per_hour / (3600.0 * engine),
                # the same engine on the sweep's own Sobol points, then with the reductions:
                # what the device costs; the rest of ``seconds`` is the host's
                "engine_sobol_evaluations_per_hour": sobol_engine,
                "engine_reduced_evaluations_per_hour": reduced_engine,
                # the evaluation alone on one Sobol chunk: as drawn, grouped by material, sorted
                # by every value (a warp's designs alike: what their differences cost)
                **evaluation,
                # outside the chunks' loop: setup, the reductions' results and writing, the file's close
                "other_s": info.seconds - info.evaluation_seconds - info.write_seconds,
                "reduction_write_s": info.reduction_write_seconds,
                "overwrite_seconds": again.seconds,
                "overwrite_evaluations_per_hour": again.evaluations_per_hour,
                "peak_rss_MiB": rss / 1024.0,
                "peak_rss_after_warmup_MiB": rss0 / 1024.0,
                "file_MiB": os.path.getsize(path) / 2**20,
            }
        )
    )


def bench_sweep(device, mode, n, chunk, tmp):
    path = os.path.join(tmp, f"sweep_{mode}_{n}.nc")
    out = subprocess.run(
        [sys.executable, __file__, "--device", device, "--sweep-child", mode, str(n), str(chunk), path],
        capture_output=True,
        text=True,
        check=True,
    )
    os.remove(path)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _tag(device, name):
    """Result-file tag: cpu, or cuda_h100 / cuda_h200 as the other benches."""
    import re

    tag = device.split(":")[0]
    if tag == "cuda":
        m = re.search(r"\b([A-Z]\d{2,3}[A-Z]?)\b", name)
        tag = f"cuda_{m.group(1).lower()}" if m else tag
    return tag


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--small", action="store_true", help="CPU-sized run (< 2 min)")
    ap.add_argument(
        "--trials", type=int, default=None, help="trials of the CMA-ES search (default: 16384 --small, else 262144)"
    )
    ap.add_argument("--batch", type=int, default=None, help="its population (default: 1024 --small, else 8192)")
    ap.add_argument(
        "--mo-trials", type=int, default=None, help="trials of the NSGA-II search (default: 4096 --small, else 262144)"
    )
    ap.add_argument("--mo-batch", type=int, default=None, help="its population (default: 512 --small, else 8192)")
    ap.add_argument(
        "--cases",
        default=",".join(CASES),
        help=f"comma list of {', '.join(CASES)} (not with --sweep-only)",
    )
    ap.add_argument(
        "--sweep-only",
        action="store_true",
        help="only the sweeps (grid and Sobol, two sizes each): design_sweep_<device>.json",
    )
    ap.add_argument(
        "--surrogate",
        action="store_true",
        help="searches evaluate an analytic stand-in on the host: their wall time is the host's work",
    )
    ap.add_argument("--chunk", type=int, default=None, help="sweep chunk in points (default: 2^14 --small, else 2^22)")
    ap.add_argument(
        "--sweep-points",
        default=None,
        help="comma list of the sweeps' sizes in points (default: 2^16,2^18 --small, else 2^24,2^26)",
    )
    ap.add_argument("--sweep-child", nargs=4, metavar=("MODE", "N", "CHUNK", "PATH"), help=argparse.SUPPRESS)
    ap.add_argument("-o", "--output", default=None)
    args = ap.parse_args(argv)
    from tawarp.model.forward import resolve_device

    device = resolve_device(args.device)
    if args.sweep_child:
        mode, n, chunk, path = args.sweep_child
        sweep_child(device, mode, int(n), int(chunk), path)
        return 0
    import warp as wp

    if args.small:
        cfg = dict(
            trials=16384,
            batch=1024,
            mo_trials=4096,
            mo_batch=512,
            opt_trials=512,
            opt_batch=64,
            sweep=(1 << 16, 1 << 18),
            chunk=1 << 14,
        )
    else:
        cfg = dict(
            trials=262144,
            batch=8192,
            mo_trials=262144,
            mo_batch=8192,
            opt_trials=2048,
            opt_batch=256,
            sweep=(1 << 24, 1 << 26),
            chunk=1 << 22,
        )
    given = {"trials": args.trials, "batch": args.batch, "chunk": args.chunk}
    if args.sweep_points:
        given["sweep"] = tuple(int(float(v)) for v in args.sweep_points.split(","))
    given.update(mo_trials=args.mo_trials, mo_batch=args.mo_batch)
    cfg.update({k: v for k, v in given.items() if v is not None})
    cfg["surrogate"] = args.surrogate
    cases = [c for c in args.cases.split(",") if c]
    if not cases or set(cases) - set(CASES):
        ap.error(f"--cases {args.cases!r}: choose among {', '.join(CASES)}")
    t_all = time.perf_counter()
    out = {
        "device": device,
        "device_name": str(wp.get_device(device).name),
        "host": platform.node(),
        "python": platform.python_version(),
        "warp": wp.__version__,
        "config": cfg,
        "design_space": VARS,
    }
    tag = _tag(device, out["device_name"]) + ("_surrogate" if args.surrogate else "")
    if args.sweep_only:
        with tempfile.TemporaryDirectory(prefix="tawarp_bench_") as tmp:
            for mode in ("grid", "sobol", "sobol_reduced"):
                out[f"sweep_{mode}"] = [bench_sweep(device, mode, n, cfg["chunk"], tmp) for n in cfg["sweep"]]
                print(json.dumps(out[f"sweep_{mode}"]), flush=True)
        out["summary"] = {
            f"{mode}_evaluations_per_hour": out[f"sweep_{mode}"][-1]["evaluations_per_hour"]
            for mode in ("grid", "sobol", "sobol_reduced")
        }
        out["summary"].update(
            engine_evaluations_per_hour=out["sweep_grid"][-1]["engine_evaluations_per_hour"],
            target_per_hour=1e11,
            reduced_target_per_hour=1e12,
            bench_seconds=time.perf_counter() - t_all,
        )
        print(json.dumps(out["summary"], indent=2))
        write_result(out, f"design_sweep_{tag}.json", args.output)
        return 0
    out["command"] = "python bench/design.py " + " ".join(sys.argv[1:] if argv is None else argv)
    out["complete"] = False
    runs = {
        "search_cmaes": lambda tmp: bench_search(
            device, cfg["trials"], cfg["batch"], ("gradient",), tmp=tmp, surrogate=args.surrogate
        ),
        "search_nsga2": lambda tmp: bench_search(
            device, cfg["mo_trials"], cfg["mo_batch"], ("gradient", "heat_leak"), tmp=tmp, surrogate=args.surrogate
        ),
        "search_optuna_cmaes": lambda tmp: bench_search(
            device, cfg["opt_trials"], cfg["opt_batch"], ("gradient",), engine="optuna", tmp=tmp
        ),
        "sweep": lambda tmp: [bench_sweep(device, "sobol", n, cfg["chunk"], tmp) for n in cfg["sweep"]],
        "sweep_reduced": lambda tmp: [bench_sweep(device, "sobol_reduced", n, cfg["chunk"], tmp) for n in cfg["sweep"]],
    }
    with tempfile.TemporaryDirectory(prefix="tawarp_bench_") as tmp:
        for case, key in zip(CASES, runs):
            if case in cases:
                out[key] = runs[key](tmp)
                print(json.dumps(out[key]), flush=True)
                write_result(out, f"design_{tag}.json", args.output)  # what is measured so far
    summary = {
        "search_cmaes": {
            "search_evaluations_per_minute": "evaluations_per_minute",
            "search_sampler_share": "sampler_share",
            "search_storage_share": "storage_share",
            "search_trial_store_share": "trial_store_share",
            "search_trials_in_study": "trials_in_study",
            "search_evaluation_share": "evaluation_share",
            "search_device_busy_share": "device_busy_share",
        },
        "search_nsga2": {
            "nsga2_evaluations_per_minute": "evaluations_per_minute",
            "nsga2_sampler_share": "sampler_share",
        },
        "search_optuna_cmaes": {"optuna_samplers_evaluations_per_minute": "evaluations_per_minute"},
    }
    out["summary"] = {k: out[part][v] for part, keys in summary.items() if part in out for k, v in keys.items()}
    if "sweep" in out:
        out["summary"].update(
            sweep_evaluations_per_hour=out["sweep"][-1]["evaluations_per_hour"],
            sweep_peak_rss_MiB=[x["peak_rss_MiB"] for x in out["sweep"]],
            sweep_points=[x["points"] for x in out["sweep"]],
        )
    if "sweep_reduced" in out:
        out["summary"]["reduced_sweep_evaluations_per_hour"] = out["sweep_reduced"][-1]["evaluations_per_hour"]
    out["summary"]["targets"] = {
        "search_per_minute": 1e8,
        "search_sampler_share_at_most": 0.10,
        "nsga2_per_minute": 3e7,
        "sweep_per_hour": 1e9,
        "reduced_sweep_per_hour": 1e12,
    }
    out["summary"]["bench_seconds"] = time.perf_counter() - t_all
    out["complete"] = True
    print(json.dumps(out["summary"], indent=2))
    write_result(out, f"design_{tag}.json", args.output)
    return 0


if __name__ == "__main__":
    run(main)
