"""Forward-model benchmark: throughput against batch size, accuracy of each cells
setting, and the CPU peers (the NumPy reference and openthermoacoustics) measured in
the same run on the same machine. Writes JSON.

    python bench/forward.py --device cuda --out bench/results/forward_cuda.json
    python bench/forward.py --device cpu --sizes 1e2,1e3,1e4 --out bench/results/forward_cpu.json
    python bench/forward.py --device cpu --sections threads --threads 1,2,4,8,16 --out bench/results/cpu_scaling.json

Accuracy: the max relative error (row-wise, on the four dimensionless coefficients)
of each ``cell_density`` (the bare rule, ``tolerance=None``) and of the default settings
(cells from the error estimate) against the adaptive NumPy reference at
80 W (RVC 18 W). ``estimate``: throughput with and without the error estimate on the
same batch, its cost fraction, and the mean cell density it chose; ``work``: what the
estimate's evaluation computes and asks of the host, counted without timing (a CPU gives the
GPU's counts). ``threads``: CPU
forward models/s against ``ForwardSettings.cpu_threads``, with the machine's load average
(a shared machine's numbers are only as good as its idle cores). ``heat``: the heat solve's
time a set for each kind of set a loop's fits ask for (linear, temperature-dependent, the
two-field wall, both), the launch's time on a GPU (where a launch lasts its slowest set).

A *forward model* is one (parameter set, frequency) pair: the heat solve of the set
(shared by its frequencies) and the T-matrix cascade at that frequency. Batches are m =
100 frequencies (30-500 Hz) times n parameter sets drawn around the paper-like ceramic
core (heat input 0-80 W, stack h, porosity and pore radius varied), kept on the device.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np
import warp as wp

from tawarp import reference
from tawarp.model.core import load_core, paper_cores
from tawarp.model import forward
from tawarp.model.forward import Engine, ForwardSettings, transfer_matrices
from _results import run, write_result

FREQS = np.linspace(30.0, 500.0, 100)
ACC_FREQS = np.array([30.0, 90.0, 170.0, 260.0, 380.0, 500.0])
ACC_HEAT = {"rvc_foam": 18.0}


def random_batch(n: int, rng) -> tuple[list[str], np.ndarray]:
    names = ["stack.h", "stack.porosity", "stack.pore_radius"]
    table = np.stack(
        [rng.uniform(0, 80, n), rng.uniform(50, 250, n), rng.uniform(0.85, 0.95, n), rng.uniform(0.3e-3, 0.6e-3, n)]
    )
    return names, table


def time_engine(engine: Engine, varying: wp.array, min_time: float) -> float:
    """Seconds per evaluate() of a device-resident batch (median of repeats)."""
    out, _, _ = engine.evaluate(varying)  # warm-up (compilation, allocation)
    wp.synchronize_device(engine.device)
    times = []
    t_total = time.perf_counter()
    while time.perf_counter() - t_total < min_time or len(times) < 3:
        t0 = time.perf_counter()
        engine.evaluate(varying, out=out)
        wp.synchronize_device(engine.device)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def relative_error(Y, Yref) -> float:
    return float((np.abs(Y - Yref).max(-1) / np.abs(Yref).max(-1)).max())


def accuracy_table(device: str, densities) -> dict:
    """Max relative error of each cell density against the adaptive NumPy reference,
    over the four bundled cores at their largest heat input (80 W, RVC 18 W)."""
    refs = {
        name: reference.dimensionless_transfer(load_core(name), ACC_FREQS, ACC_HEAT.get(name, 80.0))
        for name in paper_cores()
    }
    out = {}
    for d in densities:
        errs = {
            name: relative_error(
                transfer_matrices(
                    load_core(name), ACC_FREQS, ACC_HEAT.get(name, 80.0), device=device, cell_density=d, tolerance=None
                ).dimensionless()[0],
                refs[name],
            )
            for name in paper_cores()
        }
        out[str(d)] = {"max_relative_error": max(errs.values()), "per_core": errs}
    errs = {
        name: relative_error(
            transfer_matrices(load_core(name), ACC_FREQS, ACC_HEAT.get(name, 80.0), device=device).dimensionless()[0],
            refs[name],
        )
        for name in paper_cores()
    }
    out["estimate"] = {
        "max_relative_error": max(errs.values()),
        "per_core": errs,
        "settings": "default: cell_density 1.5, tolerance 1e-6",
    }
    return out


def estimate_cost(device: str, n: int, min_time: float, repeats: int = 7) -> dict:
    """Forward models/s of the default settings (error estimate) and of the bare rule on
    the same batch, timed alternately (best of ``repeats``: a shared machine's load
    drifts); ``cost_fraction``: the default's time over the rule's, less 1 (the estimate
    runs inside the main launch, so only the whole evaluation measures its cost);
    ``work``: :func:`cascade_work` of both, ``work_ratio`` the estimate's over the rule's;
    ``estimate_alone``: :meth:`Engine.cell_densities` (the sampled frequencies alone, for
    callers that need only the densities); the densities it chose; ``kernel_seconds``:
    :func:`kernel_seconds` of both (where the estimate's time goes)."""
    names, table = random_batch(n, np.random.default_rng(1))
    varying = wp.array(table, dtype=wp.float64, device=device)
    engines = estimate_engines(device, names)
    params, theta = engines["estimate"].heat(varying)
    best = {"rule": np.inf, "estimate": np.inf, "estimate_alone": np.inf}
    for _ in range(repeats):
        for label, engine in engines.items():
            best[label] = min(best[label], time_engine(engine, varying, 0.0))
        t0 = time.perf_counter()
        d = engines["estimate"].cell_densities(params, theta).numpy()
        wp.synchronize_device(device)
        best["estimate_alone"] = min(best["estimate_alone"], time.perf_counter() - t0)
    return {
        "kernel_seconds": {label: kernel_seconds(engine, varying) for label, engine in engines.items()},
        "models_per_s": {k: n * len(FREQS) / best[k] for k in ("rule", "estimate")},
        **estimate_work(device, n, engines),
        "seconds_best": best,
        "cost_fraction": best["estimate"] / best["rule"] - 1.0,
        "cpu_threads": 1,
        "density_mean": float(d.mean()),
        "density_max": float(d.max()),
        "sets_raised": float(np.mean(d > ForwardSettings().cell_density)),
        "sets": n,
    }


def estimate_engines(device: str, names: list[str]) -> dict:
    """The bare rule's and the default settings' (error estimate) engines of the bench's core."""
    return {
        label: Engine(load_core("ceramic"), FREQS, names, ForwardSettings(tolerance=tol, cpu_threads=1, device=device))
        for label, tol in (("rule", None), ("estimate", ForwardSettings().tolerance))
    }


def estimate_work(device: str, n: int, engines: dict | None = None) -> dict:
    """``work``: :func:`cascade_work` of the rule and of the estimate on the ``estimate``
    section's batch of n sets (no timing: the ``work`` section alone runs this on a CPU), and
    ``work_ratio`` the estimate's over the rule's."""
    names, table = random_batch(n, np.random.default_rng(1))
    engines = engines or estimate_engines(device, names)
    work = {label: cascade_work(engine, table) for label, engine in engines.items()}
    keys = ("cell_steps_per_model", "warp_cell_steps_per_model", "points_per_set", "idle_ops", "host_reads")
    return {"work": work, "work_ratio": {k: work["estimate"][k] / work["rule"][k] for k in keys}}


def cascade_work(engine: Engine, table: np.ndarray) -> dict:
    """What one evaluate() of ``table`` computes, counted on the host from each launch's
    inputs (a device-independent cost of the error estimate): Magnus cell steps per forward
    model (each cascade thread's cells, a part at uniform temperature one step; and as
    warps run them, :func:`warp_cell_steps`), points per
    set (:func:`tawarp.kernels.forward.make_point_kernel`), cascade threads per model and the
    cascade launches (the first, then one per round of reruns) with their sets; and what the
    host does, which a GPU waits for: ``host_reads`` (read-backs of device arrays, each a
    synchronization), ``device_ops`` (launches and radix sorts) and ``idle_ops``: the ops
    issued while the device has nothing long queued, from the call's start or a read-back up
    to the next cascade launch (the ops after a cascade launch run behind it). Warp's
    ``launch``, ``array.numpy`` and ``radix_sort_pairs`` are wrapped for the second of two
    calls, both with the reruns queued as a GPU queues them (``Engine.queue_ahead``)."""
    n_seg = len(engine.core.segments)
    work = {"cell_steps": 0, "warp_cell_steps": 0, "threads": 0, "points": 0, "launch_sets": []}
    host = {"host_reads": 0, "device_ops": 0, "idle_ops": 0, "idle": True}
    launch, numpy, sort = wp.launch, wp.array.numpy, wp.utils.radix_sort_pairs

    def op(long: bool = False):
        host["device_ops"] += 1
        host["idle_ops"] += host["idle"]
        host["idle"] = host["idle"] and not long

    def read(array):
        host["host_reads"] += 1
        host["idle"] = True
        return numpy(array)

    def sorted_pairs(*args, **kw):
        op()
        return sort(*args, **kw)

    def counted(kernel, dim=None, inputs=None, **kw):
        op(long=kernel is engine.transfer_kernel)
        if kernel is engine.transfer_kernel:
            cells, part, lo, order = numpy(inputs[2]), inputs[3], inputs[5], numpy(inputs[6])
            out, refined = inputs[8], inputs[9]
            steps = np.maximum(cells[lo : lo + part.shape[0]], 1)
            work["cell_steps"] += int(steps[:, :n_seg].sum()) * out.shape[1]
            work["cell_steps"] += int(steps[:, n_seg:].sum()) * refined.shape[1]
            work["warp_cell_steps"] += warp_cell_steps(steps, order, out.shape[1], refined.shape[1])
            work["threads"] += part.shape[0] * (out.shape[1] + refined.shape[1])
            work["launch_sets"].append(part.shape[0])
        elif kernel is engine.point_kernel:
            cells, lo, part = numpy(inputs[2]), inputs[6], inputs[7]
            work["points"] += int(
                np.where(cells[lo : lo + part.shape[0]] > 0, 3 * cells[lo : lo + part.shape[0]], 1).sum()
            )
        return launch(kernel, dim=dim, inputs=inputs, **kw)

    varying = wp.array(table, dtype=wp.float64, device=engine.device)  # device-resident, as timed
    ahead, engine.queue_ahead = engine.queue_ahead, True  # the GPU's reruns, on a CPU too
    try:
        engine.evaluate(varying)  # warm, as timed: the engine sizes its first rerun from its last evaluation
        wp.launch, wp.array.numpy, wp.utils.radix_sort_pairs = counted, read, sorted_pairs
        engine.evaluate(varying)
    finally:
        wp.launch, wp.array.numpy, wp.utils.radix_sort_pairs = launch, numpy, sort
        engine.queue_ahead = ahead
    models = table.shape[1] * len(engine.freqs)
    return {
        "cell_steps_per_model": work["cell_steps"] / models,
        "warp_cell_steps_per_model": work["warp_cell_steps"] / models,
        "threads_per_model": work["threads"] / models,
        "points_per_set": work["points"] / table.shape[1],
        "cascade_launch_sets": work["launch_sets"],
        **{k: host[k] for k in ("host_reads", "device_ops", "idle_ops")},
    }


def kernel_seconds(engine: Engine, varying: wp.array) -> dict:
    """Seconds of each kernel in one evaluate() of ``varying``, summed over its launches: on
    a GPU the device time between CUDA events recorded around every launch, on the CPU
    (whose launches return when done) the wall time of each; ``launches``: each launch's
    seconds (the first round's, then the reruns'); ``evaluate``: the whole call, whose rest
    is the host's work, the radix sort of the cascade order and the waits for read-backs.
    Warp's ``launch`` is wrapped for the call (run it warm: a first launch compiles)."""
    gpu = wp.get_device(engine.device).is_cuda
    marks = []
    launch = wp.launch

    def timed(kernel, dim=None, inputs=None, **kw):
        if gpu:
            start, end = wp.Event(engine.device, enable_timing=True), wp.Event(engine.device, enable_timing=True)
            wp.record_event(start)
            launch(kernel, dim=dim, inputs=inputs, **kw)
            wp.record_event(end)
        else:
            start = time.perf_counter()
            launch(kernel, dim=dim, inputs=inputs, **kw)
            end = time.perf_counter()
        marks.append((kernel.key.split("__")[-1], start, end))

    wp.launch = timed
    try:
        t0 = time.perf_counter()
        engine.evaluate(varying)
        wp.synchronize_device(engine.device)
        total = time.perf_counter() - t0
    finally:
        wp.launch = launch
    each = {}
    for name, start, end in marks:
        each.setdefault(name, []).append(wp.get_event_elapsed_time(start, end) / 1e3 if gpu else end - start)
    return {"evaluate": total, "kernels": {k: sum(v) for k, v in each.items()}, "launches": each}


def warp_cell_steps(steps: np.ndarray, order: np.ndarray, m: int, s: int, warp: int = 32) -> int:
    """Cell steps of a cascade launch counted as a GPU runs them: its threads in launch order
    (:func:`tawarp.kernels.forward.make_transfer_kernel`: the s refined ones of each set, then
    its m main ones, the sets in ``order`` or as they come), each warp of ``warp`` threads
    taking each segment's loop as long as its longest thread; ``steps`` (sets, columns) the
    launch's cells (a part at uniform temperature one step). Its excess over the threads' own
    steps (``cell_steps``) is the time lost to mixed cell counts within a warp."""
    n_seg = steps.shape[1] // (2 if s else 1)
    sets = order if order.size else np.arange(steps.shape[0])
    total = 0
    for grid, per_set in ((1, s), (0, m)):
        threads = steps[np.repeat(sets, per_set), grid * n_seg : (grid + 1) * n_seg]
        if threads.size:
            pad = np.zeros((-len(threads) % warp, n_seg), dtype=threads.dtype)
            total += warp * int(np.concatenate([threads, pad]).reshape(-1, warp, n_seg).max(1).sum())
    return total


#: The heat section's sets: (wall_conductance [W/(m K)], the buffer tube's h_convection
#: [W/(m^2 K^1.25)]) of each kind of set a loop's fits ask for
HEAT_SETS = {
    "linear": (0.0, 0.0),
    "temperature_dependent": (0.0, 2.0),
    "wall_field": (0.05, 0.0),
    "wall_field_and_temperature_dependent": (0.05, 2.0),
}


def heat_sets(device: str, n: int, min_time: float) -> dict:
    """Seconds of the heat solve (:meth:`Engine.heat`, with the copy of its excesses that
    waits for it) of n sets of one kind (:data:`HEAT_SETS`) on the mesh core at 40 W, in an
    engine whose names hold the wall and the convection (the loop's fits: 32 heat cells a
    thermal segment, the two-field wall's columns), cold starts; the median of repeats."""
    core = load_core("mesh")
    thermal = [core.segments[i].name for i in core.thermal_indices]
    names = [f"{s}.wall_conductance" for s in thermal] + [f"{thermal[0]}.wall_resistance", "tbt.h_convection"]
    engine = Engine(core, FREQS, names, ForwardSettings(device=device, cells=8, cpu_threads=1))
    out = {
        "core": "mesh",
        "heat_input_W": 40.0,
        "sets": n,
        "heat_nodes": engine.nodes,
        "cell_threads": engine.cell_threads,
    }
    for kind, (wall, convection) in HEAT_SETS.items():
        values = [
            wall if k.endswith("wall_conductance") else 1e-3 if k.endswith("wall_resistance") else convection
            for k in names
        ]
        table = np.vstack([np.full(n, 40.0)] + [np.full(n, v) for v in values])
        engine.heat(table)[1].numpy()  # compiles, allocates
        times, t_end = [], time.perf_counter() + min_time
        while time.perf_counter() < t_end or len(times) < 3:
            t0 = time.perf_counter()
            engine.heat(table)[1].numpy()
            times.append(time.perf_counter() - t0)
        out[kind] = {"seconds": float(np.median(times)), "us_per_set": float(np.median(times)) / n * 1e6}
        print(f"heat, {kind:38s} {out[kind]['us_per_set']:9.2f} us a set ({n} sets)", flush=True)
    return out


def cpu_scaling(threads, n: int, min_time: float) -> dict:
    """CPU forward models/s of one batch against ``cpu_threads`` (bit-identical results):
    per wall second, and per CPU second of this process (``time.process_time``). On a
    shared machine the wall rate only scales with the idle cores; the rate per CPU second
    staying flat shows the threads add no work, so on idle cores the speed-up is the
    thread count times the ratio of the two."""
    core = load_core("ceramic")
    names, table = random_batch(n, np.random.default_rng(2))
    rows = []
    for t in threads:
        engine = Engine(core, FREQS, names, ForwardSettings(cpu_threads=t, device="cpu"))
        engine.evaluate(table)  # warm-up
        load = os.getloadavg()[0]
        calls, wall0, cpu0 = 0, time.perf_counter(), time.process_time()
        while time.perf_counter() - wall0 < min_time or calls < 3:
            engine.evaluate(table)
            calls += 1
        wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
        rows.append(
            {
                "threads": t,
                "models_per_s": calls * n * len(FREQS) / wall,
                "models_per_cpu_s": calls * n * len(FREQS) / cpu,
                "cpu_s_per_wall_s": cpu / wall,
                "load_average_1min_before": load,
            }
        )
        print(
            f"threads={t:3d} models={n * len(FREQS):>9d}  {rows[-1]['models_per_s']:.3e} models/s, "
            f"{rows[-1]['models_per_cpu_s']:.3e} per CPU s, {cpu / wall:.2f} cores busy (load {load:.2f})",
            flush=True,
        )
    for r in rows:
        r["speedup"] = r["models_per_s"] / rows[0]["models_per_s"]
        r["work_efficiency"] = r["models_per_cpu_s"] / rows[0]["models_per_cpu_s"]
    return {
        "sets": n,
        "models": n * len(FREQS),
        "usable_cores": len(os.sched_getaffinity(0)),
        "rows": rows,
        "control_speedup": control_scaling(threads),
        "load_average_after": list(os.getloadavg()),
    }


def control_scaling(threads) -> dict:
    """Speed-up of a workload that is parallel by construction (SHA-256 of 64 MiB per
    thread; hashlib releases the GIL) at the same thread counts: what this machine grants
    a process now (a shared machine with autogroup scheduling grants a session its share
    of the cores whatever its thread count)."""
    import hashlib
    import threading

    data = b"\0" * (64 << 20)
    rates = {}
    for t in threads:
        t0 = time.perf_counter()
        workers = [threading.Thread(target=lambda: [hashlib.sha256(data).digest() for _ in range(3)]) for _ in range(t)]
        for w in workers:
            w.start()
        for w in workers:
            w.join()
        rates[t] = t / (time.perf_counter() - t0)
    return {str(t): rates[t] / rates[threads[0]] for t in threads}


def numpy_reference_rate(n_freqs: int = 8) -> float:
    """Forward models per second of the NumPy/SciPy reference (ceramic core, 40 W)."""
    core = load_core("ceramic")
    f = np.linspace(30, 500, n_freqs)
    t0 = time.perf_counter()
    reference.transfer_matrix(core, f, 40.0)
    return n_freqs / (time.perf_counter() - t0)


def openthermoacoustics_rate(n_freqs: int = 8) -> dict:
    """Per-frequency T-matrix of an equivalent duct-stack-duct (ceramic stack geometry,
    linear 293 -> 600 K profile) with openthermoacoustics: two propagations per frequency
    (unit p, unit U) give the two columns."""
    try:
        import openthermoacoustics as ota
        from openthermoacoustics.gas.air import Air
        from openthermoacoustics.geometry.circular import CircularPore
        from openthermoacoustics.segments.duct import Duct
        from openthermoacoustics.segments.stack import Stack
    except ImportError as e:
        return {"available": False, "reason": str(e)}
    R = 0.0167
    gas = Air(mean_pressure=101325.0)
    segs = [
        Duct(0.03, R),
        Stack(
            0.048,
            0.9,
            0.47e-3,
            area=np.pi * R**2,
            geometry=CircularPore(),
            solid_thermal_conductivity=3.0,
            T_hot=600.0,
            T_cold=293.15,
        ),
        Duct(0.03, R),
    ]
    f = np.linspace(30, 500, n_freqs)
    t0 = time.perf_counter()
    for fr in f:
        for p, U in ((1.0 + 0j, 0j), (0j, 1e-4 + 0j)):
            T_m = 293.15
            for s in segs:
                p, U, T_m = s.propagate(p, U, T_m, 2 * np.pi * fr, gas)
    dt = time.perf_counter() - t0
    return {
        "available": True,
        "version": getattr(ota, "__version__", "?"),
        "models_per_s": n_freqs / dt,
        "note": "duct-stack-duct, linear stack temperature, RK45 rtol 1e-8 (its default)",
    }


def _numbers(kind):
    """An argparse type: a comma list of numbers read by ``kind`` (int: "1e3" allowed)."""

    def parse(text: str) -> list:
        try:
            return [int(float(v)) if kind is int else kind(v) for v in text.split(",") if v.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: expected a comma list of numbers") from None

    return parse


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    ap.add_argument(
        "--sizes", type=_numbers(int), default=None, help="comma list of batch sizes in forward models (n * 100)"
    )
    ap.add_argument(
        "--densities",
        type=_numbers(float),
        default="0.5,0.75,1,1.5,2,3",
        help="cell_density settings (ForwardSettings)",
    )
    ap.add_argument(
        "--block-dims", type=_numbers(int), default="256", help="GPU block sizes to compare at the default density"
    )
    ap.add_argument(
        "--max-registers", type=_numbers(int), default="", help="register caps to compare (comma list; empty: none)"
    )
    ap.add_argument(
        "--point-registers",
        type=_numbers(int),
        default="128,80,64",
        help="the points section's register caps (comma list; 0: none)",
    )
    ap.add_argument("--min-time", type=float, default=0.5, help="seconds of repeats per timing")
    ap.add_argument(
        "--sections",
        default="accuracy,throughput,blocks,peers,estimate",
        help="comma list of accuracy, throughput, blocks, peers, estimate, work, threads, points, heat",
    )
    ap.add_argument("--threads", type=_numbers(int), default="1,2", help="CPU thread counts of the threads section")
    ap.add_argument("--heat-sets", type=int, default=256, help="sets of each kind in the heat section")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    wp.init()
    device = args.device or ("cuda" if wp.is_cuda_available() else "cpu")
    gpu = device.startswith("cuda")
    sizes = args.sizes or ([10**k for k in range(3, 8)] if gpu else [100, 1000, 10000])
    densities = args.densities
    rng = np.random.default_rng(0)
    core = load_core("ceramic")
    result = {
        "device": device,
        "device_name": wp.get_device(device).name,
        "warp": wp.config.version,
        "host": platform.processor() or platform.machine(),
        "python": sys.version.split()[0],
        "frequencies_per_set": len(FREQS),
        "core": "ceramic (paper-like), heated 0-80 W",
    }

    sections = set(args.sections.split(","))
    unknown = sections - {"accuracy", "throughput", "blocks", "peers", "estimate", "work", "threads", "points", "heat"}
    if unknown:
        ap.error(f"--sections: unknown {sorted(unknown)}")
    if args.heat_sets < 1:
        ap.error(f"--heat-sets: at least 1 set, got {args.heat_sets}")
    n = max(1, sizes[-1] // len(FREQS))
    if "accuracy" in sections:
        t0 = time.perf_counter()
        result["accuracy"] = accuracy_table(device, densities)
        result["accuracy_seconds"] = time.perf_counter() - t0

    throughput = {}
    if "throughput" in sections:
        for d in densities:
            rows = []
            for size in sizes if d == 1.5 else sizes[-1:]:
                m = max(1, size // len(FREQS))
                names, table = random_batch(m, rng)
                engine = Engine(core, FREQS, names, ForwardSettings(cell_density=d, tolerance=None, device=device))
                varying = wp.array(table, dtype=wp.float64, device=device)
                dt = time_engine(engine, varying, args.min_time)
                rows.append({"models": m * len(FREQS), "sets": m, "seconds": dt, "models_per_s": m * len(FREQS) / dt})
                print(f"density={d:4.2f} models={m * len(FREQS):>10d}  {m * len(FREQS) / dt:.3e} models/s", flush=True)
            throughput[str(d)] = rows
        result["throughput"] = throughput
    if "estimate" in sections:
        result["estimate"] = estimate_cost(device, n, args.min_time)
        print(f"error estimate: {result['estimate']}", flush=True)
    if "work" in sections:
        result["work"] = estimate_work(device, n)
        print(f"work: {result['work']}", flush=True)
    if "threads" in sections:
        result["cpu_scaling"] = cpu_scaling(args.threads, n, args.min_time)
    if "heat" in sections:
        result["heat_sets"] = heat_sets(device, args.heat_sets, args.min_time)
    if "blocks" in sections:
        names, table = random_batch(n, rng)
        varying = wp.array(table, dtype=wp.float64, device=device)
        blocks = {}
        for b in args.block_dims:
            for r in [None] + args.max_registers:
                engine = Engine(core, FREQS, names, ForwardSettings(block_dim=b, max_registers=r, device=device))
                try:
                    rate = n * len(FREQS) / time_engine(engine, varying, args.min_time)
                except Exception as e:  # a block too large for the register file fails to launch
                    print(f"block_dim={b} max_registers={r}: {e}", flush=True)
                    continue
                blocks[f"{b}/{r}"] = rate
                print(
                    f"block_dim={b:4d} max_registers={r} models={n * len(FREQS):>10d}  {rate:.3e} models/s", flush=True
                )
        result["block_dim/max_registers_models_per_s"] = blocks

    if "points" in sections:
        # the default settings (error estimate) with the point kernel under each register cap
        names, table = random_batch(n, rng)
        varying = wp.array(table, dtype=wp.float64, device=device)
        points = {}
        for r in args.point_registers:
            engine = Engine(core, FREQS, names, ForwardSettings(device=device))
            engine.point_kernel = forward._point_kernel(engine.nonlinear, r or None)
            points[str(r)] = rate = n * len(FREQS) / time_engine(engine, varying, args.min_time)
            print(f"point kernel max_registers={r} models={n * len(FREQS):>10d}  {rate:.3e} models/s", flush=True)
        result["point_registers_models_per_s"] = points
    if "peers" in sections and throughput:
        peers = {
            "numpy_reference_models_per_s": numpy_reference_rate(),
            "openthermoacoustics": openthermoacoustics_rate(),
        }
        best = {c: max(r["models_per_s"] for r in rows) for c, rows in throughput.items()}
        peers["speedup_vs_numpy_reference"] = {c: v / peers["numpy_reference_models_per_s"] for c, v in best.items()}
        if peers["openthermoacoustics"].get("available"):
            peers["speedup_vs_openthermoacoustics"] = {
                c: v / peers["openthermoacoustics"]["models_per_s"] for c, v in best.items()
            }
        result["peers"] = peers
        ok = [d for d in densities if result.get("accuracy", {}).get(str(d), {}).get("max_relative_error", 1) <= 1e-6]
        if ok:
            d = min(ok)
            result["operating_point"] = {
                "cell_density": d,
                "max_relative_error": result["accuracy"][str(d)]["max_relative_error"],
                "models_per_s": best[str(d)],
            }
    print(json.dumps(result, indent=2))
    if args.out:
        write_result(result, "", args.out)


if __name__ == "__main__":
    run(main)
