"""Scaling over the GPUs of one machine through Dask distributed (tawarp.distributed):
batched fits, design evaluations, a reduced sweep and the island design search on 1, 2,
... GPUs. One command per machine, one JSON:

    python bench/multi_gpu.py --gpus 1,2 --out bench/results/multi_gpu_h100x2.json
    python bench/multi_gpu.py --gpus 1,2,4 --out bench/results/multi_gpu_h100x4.json
    python bench/multi_gpu.py --devices cpu,cpu --gpus 1,2 --small   # CPU workers: a smoke check

For each k of ``--gpus`` a local cluster of one single-threaded Dask worker on each of
the devices 0 .. k-1 (``--devices``: cuda:0, cuda:1, ... by default) runs, after a
warm-up that loads the kernels on every worker (compiled once beforehand in this process):

* ``fits``: :func:`tawarp.distributed.fit_on_cluster`, the heat workload of bench/fit.py
  (mesh core, h_s, h_h, h_a at 40 W, 100 frequencies, starts 30 % off), ``--fits``
  problems in ``--fit-chunks`` chunks per worker; the data are the client's (they travel);
* ``evaluations``: :meth:`tawarp.distributed.ClusterEvaluator.evaluate_sobol` of
  ``--points`` Sobol points of the rvc_foam space: each worker draws its chunks' points
  and builds their tables on its device, the objectives come back;
* ``sweep``: a Sobol sweep of ``--sweep-points`` points reduced on the workers
  (:data:`REDUCE`, no raw values: ``sweep(..., client=, reduce=, raw=False)``): each
  worker reduces its share of the chunks, only the reductions come back and merge;
* ``islands``: :func:`tawarp.design.islands.search_islands`, a batched CMA-ES island per
  worker (``--island-trials`` trials of ``--island-batch`` each, one journal study with
  its trial store, committed once a second), worker processes (the search's host work
  per generation is Python: threads of one process would share the GIL).

Fits, evaluations and the sweep run on worker threads of this process
(``local_cluster(processes=False)``: arrays pass by reference; ``--cluster processes``
to compare), the islands on worker processes. Speed-up = rate on k GPUs / rate on the
first k of ``--gpus`` (the targets: >= 1.8 on 2 GPUs, >= 3.5 on 4). Each row also says
whether its results equal those of that first row (the evaluations and the sweep's
reductions bit for bit, the fits' largest relative difference, island0's best).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import sys
import tempfile
import time
import warnings

import numpy as np

from tawarp.design.search import search
from tawarp.design.space import DesignSpace
from tawarp.design.sweep import sweep
from tawarp.design.islands import search_islands
from tawarp.distributed import ClusterEvaluator, fit_on_cluster, local_cluster
from tawarp.fit.estimate import FitWarning
from tawarp.model.core import load_core
from tawarp.model.forward import ForwardSettings, resolve_device, transfer_matrices
from _results import write_result

FREQS = np.linspace(30.0, 500.0, 100)
FIT_NAMES = ["stack.h", "hot_hx.h", "tbt.h"]
#: The reductions of the sweep (tawarp.design.reductions): all of them.
REDUCE = "best,quantiles,histogram,pareto,top=100"
CASES = ("fits", "evaluations", "sweep", "islands")


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
        [
            "material=ceramic,mesh,nicr_foam,rvc_foam",
            "stack.length=0.004:0.1",
            "heat_input=1:9",
            "hot_hx.length=0.005:0.03",
            "stack.porosity=0.6:0.98",
        ],
    )


def timed(fn, repeats: int):
    """(best wall time of ``repeats`` calls [s], the last call's result)."""
    best, out = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


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


class Bench:
    """The cases on a cluster of k workers (see the module docstring)."""

    def __init__(self, args, tmp):
        self.args, self.tmp = args, tmp
        self.space = design_space()
        self.data = fit_data(args.fits)

    def fits(self, client, k: int) -> dict:
        core, Y, w, start = self.data
        chunks = self.args.fit_chunks

        def run(n=None):
            n = len(Y) if n is None else n
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", FitWarning)
                return fit_on_cluster(
                    client,
                    core,
                    FREQS,
                    Y[:n],
                    FIT_NAMES,
                    start,
                    heat_input=40.0,
                    weights=w[:n],
                    warn=False,
                    chunk=-(-n // (chunks * k)),
                )

        run(2 * k * chunks)  # warm-up: every worker loads the kernels
        t, res = timed(run, self.args.repeats)
        return {
            "fits": len(Y),
            "fit_seconds": t,
            "fits_per_s": len(Y) / t,
            "fits_converged": float(res.converged.mean()),
            "_values": res.values,
        }

    def evaluations(self, client, k: int) -> dict:
        ev = ClusterEvaluator(client, self.space)
        n = self.args.points
        ev.evaluate_sobol(64 * k)  # warm-up
        t, out = timed(lambda: ev.evaluate_sobol(n, seed=1), self.args.repeats)
        return {
            "evaluation_points": n,
            "evaluation_seconds": t,
            "evaluations_per_s": n / t,
            "evaluations_digest": digest(out),
        }

    def sweep(self, client, k: int) -> dict:
        a = self.args
        path = os.path.join(self.tmp, f"sweep{k}.nc")

        def run(n=a.sweep_points, chunk=a.sweep_chunk):
            return sweep(
                self.space, path, mode="sobol", n_samples=n, chunk=chunk, client=client, reduce=REDUCE, raw=False
            )

        run(64 * k, 64)  # warm-up
        t, info = timed(run, self.args.repeats)
        os.remove(path)
        return {
            "sweep_points": a.sweep_points,
            "sweep_chunk": a.sweep_chunk,
            "sweep_seconds": t,
            "sweep_points_per_hour": 3600.0 * a.sweep_points / t,
            "sweep_reductions": info.reductions,
        }

    def islands(self, client, k: int) -> dict:
        a = self.args
        kw = dict(objectives=("gradient",), batch=a.island_batch, seed=0, commit_seconds=1.0)
        warm = os.path.join(self.tmp, f"warm{k}.journal")
        search_islands(client, self.space, storage=warm, n_trials=2 * a.island_batch, **kw)
        res = search_islands(
            client, self.space, storage=os.path.join(self.tmp, f"islands{k}.journal"), n_trials=a.island_trials, **kw
        )
        tm = res.timing
        wall = tm["wall"]
        return {
            "island_trials": a.island_trials,
            "island_batch": a.island_batch,
            "islands": k,
            "island_seconds": wall,
            "island_evaluations_per_minute": tm["evaluations_per_minute"],
            "island_sampler_share": tm["sampler"] / (k * wall),
            "island_storage_share": tm["storage"] / (k * wall),
            "island_evaluation_share": tm["evaluation"] / (k * wall),
            "island_walls": [i["wall"] for i in tm["islands"]],
            "island0_best": tm["islands"][0]["best"],
            "best": res.best[0]["values"] if res.best else None,
        }


def compile_here(bench: Bench, device: str) -> None:
    """Every kernel the cases use, compiled (or loaded) once in this process, so that the
    workers only load them from Warp's cache."""
    core, Y, w, start = bench.data
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
        settings=ForwardSettings(device=device),
    )
    settings = ForwardSettings(device=device)
    path = os.path.join(bench.tmp, "compile.nc")
    sweep(bench.space, path, mode="sobol", n_samples=256, chunk=128, settings=settings, reduce=REDUCE, raw=False)
    search(bench.space, n_trials=64, batch=32, settings=settings, storage=os.path.join(bench.tmp, "compile.journal"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gpus", default="1,2", help="worker counts to measure, comma separated (default 1,2)")
    ap.add_argument("--devices", default=None, help="the devices in order (default cuda:0, cuda:1, ...)")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma list of {', '.join(CASES)}")
    ap.add_argument("--small", action="store_true", help="CPU-sized defaults (a smoke check)")
    ap.add_argument("--fits", type=int, default=None, help="fit problems (default 100000; --small 8)")
    ap.add_argument("--fit-chunks", type=int, default=2, help="fit chunks per worker")
    ap.add_argument("--points", type=int, default=None, help="design evaluations (default 2^24; --small 2^14)")
    ap.add_argument("--sweep-points", type=int, default=None, help="reduced sweep points (default 2^28; --small 2^15)")
    ap.add_argument("--sweep-chunk", type=int, default=None, help="sweep chunk (default 2^22; --small 2^12)")
    ap.add_argument("--island-trials", type=int, default=None, help="trials per island (default 2^21; --small 2048)")
    ap.add_argument("--island-batch", type=int, default=None, help="island population (default 8192; --small 256)")
    ap.add_argument("--repeats", type=int, default=None, help="timings per case, the best kept (default 2; --small 1)")
    ap.add_argument(
        "--cluster",
        choices=("threads", "processes"),
        default="threads",
        help="workers of fits, evaluations and sweep (the islands always run on processes)",
    )
    ap.add_argument("--out", default=None, help="JSON output (default: bench/results/multi_gpu.json)")
    args = ap.parse_args(argv)
    small = args.small
    for name, big, little in (
        ("fits", 100000, 8),
        ("points", 1 << 24, 1 << 14),
        ("sweep_points", 1 << 28, 1 << 15),
        ("sweep_chunk", 1 << 22, 1 << 12),
        ("island_trials", 1 << 21, 2048),
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
    t_all = time.perf_counter()
    result = {
        "command": "python bench/multi_gpu.py " + " ".join(sys.argv[1:] if argv is None else argv),
        "devices": devices[: ks[-1]],
        "device_names": [wp.get_device(d).name for d in devices[: ks[-1]]],
        "host": platform.node(),
        "cpu_count": os.cpu_count(),
        "warp": wp.config.version,
        "python": sys.version.split()[0],
        "cluster": {"fits, evaluations, sweep": args.cluster, "islands": "processes"},
        "sizes": {
            k: getattr(args, k)
            for k in ("fits", "fit_chunks", "points", "sweep_points", "sweep_chunk", "island_trials", "island_batch")
        },
        "repeats": args.repeats,
        "rows": [],
    }
    with tempfile.TemporaryDirectory(prefix="tawarp_multi_gpu_") as tmp:
        bench = Bench(args, tmp)
        t = time.perf_counter()
        compile_here(bench, devices[0])
        result["compile_seconds"] = time.perf_counter() - t
        print(f"kernels ready in {result['compile_seconds']:.1f} s", flush=True)
        for k in ks:
            row = {"workers": k}
            plain = [c for c in cases if c != "islands"]
            if plain:
                client = local_cluster(devices[:k], processes=args.cluster == "processes", cpu_threads=1)
                try:
                    for c in plain:
                        row.update(getattr(bench, c)(client, k))
                finally:
                    closed(client)
            if "islands" in cases:
                client = local_cluster(devices[:k], processes=True, cpu_threads=1)
                try:
                    row.update(bench.islands(client, k))
                finally:
                    closed(client)
            row["elapsed_s"] = time.perf_counter() - t_all
            print(json.dumps({key: v for key, v in row.items() if not key.startswith("_")}), flush=True)
            result["rows"].append(row)
    base = result["rows"][0]
    v0 = base.get("_values")
    rates = ("fits_per_s", "evaluations_per_s", "sweep_points_per_hour", "island_evaluations_per_minute")
    for r in result["rows"]:
        for key in rates:
            if key in r:
                r[f"speedup_{key}"] = r[key] / base[key]
        if "_values" in r:
            v = r.pop("_values")
            r["fits_max_relative_difference_to_first_row"] = float(np.max(np.abs(v - v0) / np.abs(v0)))
        if "evaluations_digest" in r:
            r["evaluations_equal_first_row"] = r["evaluations_digest"] == base["evaluations_digest"]
        if "sweep_reductions" in r:
            r["sweep_reductions_equal_first_row"] = r["sweep_reductions"] == base["sweep_reductions"]
        if "island0_best" in r:
            r["island0_equals_first_row"] = r["island0_best"] == base["island0_best"]
    result["summary"] = {
        f"{k}_gpus": {key: r[f"speedup_{key}"] for key in rates if f"speedup_{key}" in r}
        for k, r in zip(ks, result["rows"])
    }
    result["summary"]["targets"] = {"2_gpus": 1.8, "4_gpus": 3.5}
    result["bench_seconds"] = time.perf_counter() - t_all
    print(json.dumps(result["summary"], indent=1))
    write_result(result, "multi_gpu.json", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
