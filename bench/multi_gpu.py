"""Scaling over several devices through Dask distributed (tawarp.distributed): batched
fits, design evaluations and a sweep on 1, 2, ... workers (one per device). Writes JSON.

    python bench/multi_gpu.py --devices cuda:0,cuda:1 --out bench/results/multi_gpu_h200x2.json
    python bench/multi_gpu.py --devices cpu,cpu --fits 8 --points 16384 --sweep-points 65536 \
        --sweep-chunk 16384 --repeats 1   # CPU workers: a smoke check

For each kind of local cluster (``--cluster``: worker processes, worker threads of this
process, or both) and k = 1 .. len(devices), a cluster of the first k devices (one
single-threaded worker each) runs, after a warm-up that compiles and loads the kernels
on every worker:

* ``fits``: :func:`tawarp.distributed.fit_on_cluster`, the heat workload of bench/fit.py
  (mesh core, h_s, h_h, h_a at 40 W, 100 frequencies, starts 30 % off), ``--fits`` problems
  in ``--fit-chunks`` chunks per worker;
* ``evaluations``: :class:`tawarp.distributed.ClusterEvaluator` on ``--points`` design
  points of the rvc_foam space of bench/design.py (kernel metrics);
* ``sweep``: :func:`tawarp.design.sweep.sweep` of ``--sweep-points`` Sobol points to
  netCDF with ``client=``, tasks of ``--sweep-chunk`` points: the outputs sent back and
  written by this process (one file), then written by the workers to part files that the
  file maps (``parts=True``: ``sweep_parts_*``).

Speed-up = rate on k workers / rate on 1 worker of the same kind of cluster (the target:
>= 1.8 on 2 GPUs). Each row also says whether its evaluations and its sweep
file equal those of one process on the first device (bit for bit: same device kind, same
code), which checks Warp driving several devices from threads; ``one_process`` holds
that process's sweep rate (no Dask).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
import warnings

import h5py
import numpy as np

from tawarp.design.evaluate import Evaluator
from tawarp.design.space import DesignSpace
from tawarp.design.sweep import parts_path, sweep
from tawarp.distributed import ClusterEvaluator, fit_on_cluster, local_cluster
from tawarp.fit.estimate import FitWarning
from tawarp.model.core import load_core
from tawarp.model.forward import ForwardSettings, resolve_device, transfer_matrices
from _results import write_result

FREQS = np.linspace(30.0, 500.0, 100)
FIT_NAMES = ["stack.h", "hot_hx.h", "tbt.h"]


def fit_data(n: int, seed: int = 0):
    """Noisy data (0.5 %) of the mesh core at 40 W from 48 fixed cells, starts 30 % off."""
    core = load_core("mesh")
    Y0 = transfer_matrices(core, FREQS, 40.0, cells=48, device="cpu").dimensionless()[0]
    sd = 0.005 * np.abs(Y0) / np.sqrt(2)
    rng = np.random.default_rng(seed)
    Y = Y0 + sd * (rng.standard_normal((n,) + Y0.shape) + 1j * rng.standard_normal((n,) + Y0.shape))
    start = np.array([core.get(k) for k in FIT_NAMES]) * [1.3, 0.7, 1.3]
    return core, Y, np.broadcast_to(1.0 / sd, Y.shape), start


def design_space() -> DesignSpace:
    return DesignSpace(
        load_core("rvc_foam"),
        ["stack.length=0.004:0.1", "heat_input=1:9", "hot_hx.length=0.005:0.03", "stack.porosity=0.6:0.98"],
    )


def timed(fn, repeats: int = 2) -> float:
    """Best wall time of ``repeats`` calls [s]."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def same_file(a: str, b: str) -> bool:
    """Whether the netCDF files ``a`` and ``b`` hold the same variables, value for value."""
    with h5py.File(a, "r") as x, h5py.File(b, "r") as y:
        names = [k for k in x if isinstance(x[k], h5py.Dataset)]
        return sorted(names) == sorted(k for k in y if isinstance(y[k], h5py.Dataset)) and all(
            np.array_equal(x[k][()], y[k][()], equal_nan=True) for k in names
        )


def measure(client, k: int, args, data, table, reference: dict, tmp) -> dict:
    core, Y, w, start = data
    space = design_space()
    ev = ClusterEvaluator(client, space)
    path = os.path.join(tmp, f"sweep{k}.nc")

    def fits(per_worker=args.fit_chunks[0]):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FitWarning)
            return fit_on_cluster(
                client,
                core,
                FREQS,
                Y,
                FIT_NAMES,
                start,
                heat_input=40.0,
                weights=w,
                warn=False,
                chunk=-(-len(Y) // (per_worker * k)),
            )

    def sweep_once(n=args.sweep_points, chunk=args.sweep_chunk, parts=False):
        return sweep(space, path, mode="sobol", n_samples=n, chunk=chunk, client=client, parts=parts)

    # warm-up on every worker: compile/load the kernels (one small chunk per worker)
    fit_on_cluster(
        client, core, FREQS, Y[: 2 * k], FIT_NAMES, start, heat_input=40.0, weights=w[: 2 * k], warn=False, chunk=1
    )
    ev.evaluate_table(table[:, : 64 * k])
    sweep_once(64 * k, 64)
    sweep_once(64 * k, 64, parts=True)
    res = fits()
    t_fits = {c: timed(lambda: fits(c), args.repeats) for c in args.fit_chunks}
    t_fit = t_fits[args.fit_chunks[0]]
    t_ev = timed(lambda: ev.evaluate_table(table), args.repeats)
    values = ev.evaluate_table(table)
    t_sw = timed(sweep_once, 1)
    sweep_same = same_file(path, reference["sweep_path"])
    t_parts = timed(lambda: sweep_once(parts=True), 1)
    row = {
        "workers": k,
        "fits": len(Y),
        "fit_seconds": t_fit,
        "fits_per_s": len(Y) / t_fit,
        "fits_converged": float(res.converged.mean()),
        "fits_per_s_by_chunks_per_worker": {c: len(Y) / t for c, t in t_fits.items()},
        "evaluation_points": table.shape[1],
        "evaluation_seconds": t_ev,
        "evaluations_per_s": table.shape[1] / t_ev,
        "evaluations_equal_one_process": all(
            np.array_equal(values[key], v, equal_nan=True) for key, v in reference["evaluations"].items()
        ),
        "sweep_points": args.sweep_points,
        "sweep_seconds": t_sw,
        "sweep_points_per_hour": 3600.0 * args.sweep_points / t_sw,
        "sweep_equals_one_process": sweep_same,
        "sweep_parts_seconds": t_parts,
        "sweep_parts_points_per_hour": 3600.0 * args.sweep_points / t_parts,
        "sweep_parts_equals_one_process": same_file(path, reference["sweep_path"]),
    }
    os.remove(path)
    shutil.rmtree(parts_path(path))
    return row


def one_process(args, space, table, tmp, device: str) -> dict:
    """Evaluations of ``table`` and a sweep in this process on ``device``, no Dask: the
    reference of every row's results, and the one-process sweep rate."""
    settings = ForwardSettings(device=device)
    path = os.path.join(tmp, "one_process.nc")
    evaluations = Evaluator(space, settings=settings).evaluate_table(table)
    info = sweep(space, path, mode="sobol", n_samples=args.sweep_points, chunk=args.sweep_chunk, settings=settings)
    return {
        "evaluations": evaluations,
        "sweep_path": path,
        "summary": {
            "device": device,
            "sweep_points": args.sweep_points,
            "sweep_seconds": info.seconds,
            "sweep_points_per_hour": info.evaluations_per_hour,
        },
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", default="cuda:0,cuda:1", help="comma list, one worker each (cuda:N or cpu)")
    ap.add_argument("--fits", type=int, default=20000, help="fit problems per timing")
    ap.add_argument("--points", type=int, default=1 << 22, help="design points per evaluation timing")
    ap.add_argument("--sweep-points", type=int, default=1 << 24, help="Sobol points of the sweep")
    ap.add_argument("--sweep-chunk", type=int, default=1 << 21, help="sweep points per task")
    ap.add_argument(
        "--fit-chunks",
        default="2",
        help="fit chunks per worker (comma list: each timed; the first is the row's fits_per_s)",
    )
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument(
        "--cluster",
        choices=("processes", "threads", "both"),
        default="both",
        help="workers as processes, as threads of this process (local_cluster(processes=False)), or both",
    )
    ap.add_argument("--out", default=None, help="JSON output (default: bench/results/multi_gpu.json)")
    args = ap.parse_args(argv)
    try:
        fit_chunks = [int(c) for c in args.fit_chunks.split(",")]
    except ValueError:
        fit_chunks = []
    if not fit_chunks or min(fit_chunks) < 1:
        ap.error(f"--fit-chunks: {args.fit_chunks!r}; expected positive integers, comma separated")
    args.fit_chunks = fit_chunks
    devices = args.devices.split(",")
    for d in devices:
        try:
            resolve_device(d)
        except ValueError as e:
            ap.error(f"--devices: {e}")
    kinds = ("processes", "threads") if args.cluster == "both" else (args.cluster,)
    import warp as wp

    wp.config.quiet = True
    wp.init()
    data = fit_data(args.fits)
    space = design_space()
    rng = np.random.default_rng(0)
    table = space.varying_table(space.from_unit(rng.random((args.points, len(space.continuous)))))
    result = {
        "devices": devices,
        "device_names": [wp.get_device(d).name for d in devices],
        "host": platform.node(),
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "warp": wp.config.version,
        "python": sys.version.split()[0],
        "load_average_at_start": list(os.getloadavg()),
        "sweep_chunk": args.sweep_chunk,
        "rows": [],
    }
    # compile the kernels once here, so the workers only load them from Warp's cache
    core, Y, w, start = data
    fit_on_cluster(
        None,
        core,
        FREQS,
        Y[:2],
        FIT_NAMES,
        start,
        heat_input=40.0,
        weights=w[:2],
        warn=False,
        settings=ForwardSettings(device=devices[0]),
    )
    with tempfile.TemporaryDirectory() as tmp:
        reference = one_process(args, space, table, tmp, devices[0])
        result["one_process"] = reference["summary"]
        print(
            f"one process on {devices[0]}: {reference['summary']['sweep_points_per_hour']:.3e} sweep points/h",
            flush=True,
        )
        for kind in kinds:
            for k in range(1, len(devices) + 1):
                client = local_cluster(devices[:k], processes=kind == "processes", cpu_threads=1)  # CPU: a core each
                try:
                    row = {"cluster": kind, **measure(client, k, args, data, table, reference, tmp)}
                finally:
                    cluster = client.cluster
                    client.close()
                    cluster.close()
                print(
                    f"{kind}, {k} workers: {row['fits_per_s']:.3e} fits/s, {row['evaluations_per_s']:.3e} "
                    f"evaluations/s, {row['sweep_points_per_hour']:.3e} sweep points/h ({row['sweep_parts_points_per_hour']:.3e} "
                    f"with parts); equal to one process: evaluations {row['evaluations_equal_one_process']}, "
                    f"sweep {row['sweep_equals_one_process']}, parts {row['sweep_parts_equals_one_process']}",
                    flush=True,
                )
                result["rows"].append(row)
    for r in result["rows"]:
        base = next(b for b in result["rows"] if b["cluster"] == r["cluster"])
        for key in ("fits_per_s", "evaluations_per_s", "sweep_points_per_hour", "sweep_parts_points_per_hour"):
            r[f"speedup_{key}"] = r[key] / base[key]
    result["load_average_at_end"] = list(os.getloadavg())
    print(json.dumps(result["rows"], indent=1))
    write_result(result, "multi_gpu.json", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
