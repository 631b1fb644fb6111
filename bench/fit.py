"""Fit benchmark: complete Levenberg-Marquardt fits per second against batch size, and
its peers in the same run: scipy.optimize.least_squares on the project's own CPU kernel
(the fair peer: what a user would write), on the NumPy reference model, and the batched
fit on the CPU. Writes JSON.

    python bench/fit.py --device cuda                       # sizes 1 ... 1e5, CPU batches 1,16,64
    python bench/fit.py --device cpu --sizes 1,4,16,64

A *fit* is one complete problem solved to the paper's stopping rule (relative step
below 0.1 %): 3 parameters, m = 100 frequencies (30-500 Hz), 4 complex coefficients
(800 real residuals), the mesh core of the paper. Two workloads:

* ``heat``: h_s, h_h, h_a at Q = 40 W (step 2 of the paper; heat solve + gradient
  cascade), starts 30 % off the truth;
* ``geometry``: porosity, pore radius, tortuosity at Q = 0 (step 1), starts 10-30 % off.

Every problem has its own noise draw (0.5 % complex, the synthetic generator's model,
data made with 48 Magnus cells), weights 1/sigma. The time of a batch is the whole
``tawarp.fit.estimate.fit`` call (upload, every launch, host-side LM logic, covariance),
after a warm-up fit that compiles the kernels; fits/s = batch size / time.

SciPy peers: ``least_squares(method="lm")`` (MINPACK) with ``xtol = 1e-3`` on similar
scaled variables (log h, log r; porosity and tortuosity divided by their start), 2-point
finite differences, the same data and weights, one fit at a time; the residual from

* ``scipy_kernel``: the project's Warp kernel on the CPU (``Engine.evaluate`` of one set
  at the 100 frequencies, the fixed cells the batched fit uses, ``smooth_settings``);
  time per fit is the mean over ``--kernel-fits`` problems;
* ``scipy``: ``tawarp.reference.dimensionless_transfer`` (closed form at Q = 0; DOP853 with
  ``rtol = 1e-8`` for the heated segments); mean over ``--scipy-fits`` problems.

``cpu_batches``: on a GPU run, the batched fit on the CPU too (``--cpu-sizes``).
``other_jacobians``: the same batches with other Jacobians (``--jacobians``: secant
updates between forward differences, forward differences, the tangent cascade), with how
far their values and std are from the headline's. Every row has the cascades (sets
evaluated) per fit and the forward launches of its batch, which do not depend on the device.

Heat fits on one GPU in about three minutes (the secant iteration, the default, against
forward differences; the kernels' first compilation included; 1e6 problems take about
55 GB of an 80 GB GPU's memory, 6.4 GB of it the data):

    python bench/fit.py --device cuda --workloads heat --sizes 10000,100000,1000000 \
        --jacobians broyden,difference --cpu-sizes "" --kernel-fits 0 --scipy-fits 0

``--pool-keep 0`` runs them with CUDA's own memory-pool threshold, for comparison
(:func:`tawarp.model.forward.keep_pool_memory`).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
import warnings

import numpy as np
import warp as wp

from tawarp import reference
from tawarp.fit.estimate import FitWarning, fit, is_log
from tawarp.measure.kind import smooth_settings
from tawarp.model.coefficients import duct_impedance, normalize
from tawarp.model.core import load_core
from tawarp.model import forward
from tawarp.model.forward import POOL_KEEP, Engine, ForwardSettings, transfer_matrices
from _results import run, write_result

FREQS = np.linspace(30.0, 500.0, 100)
WORKLOADS = {
    "heat": {"names": ["stack.h", "hot_hx.h", "tbt.h"], "Q": 40.0, "start": [1.3, 0.7, 1.3]},
    "geometry": {
        "names": ["stack.porosity", "stack.pore_radius", "stack.tortuosity"],
        "Q": 0.0,
        "start": [0.9, 1.3, 1.1],
    },
}


def make_data(core, names, Q, n, seed=0, noise=0.005):
    Y0 = transfer_matrices(core, FREQS, Q, cells=48, device="cpu").dimensionless()[0]
    sd = noise * np.abs(Y0) / np.sqrt(2)
    rng = np.random.default_rng(seed)
    Y = Y0 + sd * (rng.standard_normal((n,) + Y0.shape) + 1j * rng.standard_normal((n,) + Y0.shape))
    return Y, sd


def time_fits(core, wl, Y, sd, n, device, settings, jacobian="auto") -> dict:
    """One timed batch of n fits (``jacobian`` as :func:`tawarp.fit.estimate.fit`'s)."""
    names = wl["names"]
    start = np.array([core.get(k) for k in names]) * wl["start"]
    w = np.broadcast_to(1.0 / sd, (n,) + sd.shape)
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FitWarning)
        r = fit(
            core,
            FREQS,
            Y[:n],
            names,
            start,
            heat_input=wl["Q"],
            weights=w,
            settings=settings,
            device=device,
            warn=False,
            jacobian=jacobian,
        )
    wp.synchronize_device(device)
    dt = time.perf_counter() - t0
    truth = np.array([core.get(k) for k in names])
    z = (r.values - truth) / r.std
    return {
        "n": n,
        "jacobian": jacobian,
        "seconds": dt,
        "fits_per_s": n / dt,
        "converged": float(r.converged.mean()),
        "max_relative_error_vs_truth": float(np.max(np.abs(r.values / truth - 1))),
        "iterations_mean": float(r.iterations.mean()),
        "iterations_max": int(r.iterations.max()),
        "launches": r.launches,
        "evaluations": r.evaluations,
        "evaluations_per_fit": r.evaluations / n,
        "rms_z": float(np.sqrt(np.mean(z**2))),
        "values": r.values,
        "std": r.std,
    }


def reference_model(core, Q, rtol=1e-8):
    """Dimensionless coefficients (m, 4) of the NumPy reference at parameter ``values``."""
    return lambda vals: reference.dimensionless_transfer(core.replace(**vals), FREQS, Q, rtol=rtol)


def kernel_model(core, names, Q, start):
    """Dimensionless coefficients (m, 4) of one set on the project's CPU kernel, with the
    fixed cells the batched fit would use from ``start``."""
    settings = smooth_settings(core, FREQS, ForwardSettings(device="cpu"), dict(zip(names, start)), Q)
    engine = Engine(core, FREQS, names, settings)
    Zc = duct_impedance(core)

    def model(vals):
        out, _, _ = engine.evaluate(np.array([[Q]] + [[vals[k]] for k in names]))
        return normalize(out.numpy().view(np.complex128).reshape(len(FREQS), 2, 2), Zc)

    return model


def scipy_fit(model, names, Y, sd, start) -> dict:
    """least_squares(method="lm") on ``model(values) -> (m, 4)`` from ``start`` (module doc)."""
    from scipy.optimize import least_squares

    log = np.array([is_log(k) for k in names])
    s = np.asarray(start, dtype=float)

    def to_v(z):
        return np.where(log, s * np.exp(np.where(log, z, 0)), s * z)

    def resid(z):
        v = to_v(z)
        vals = {k: float(x) for k, x in zip(names, v)}
        if "stack.porosity" in vals:
            vals["stack.porosity"] = min(max(vals["stack.porosity"], 1e-3), 1.0)
        if "stack.tortuosity" in vals:
            vals["stack.tortuosity"] = max(vals["stack.tortuosity"], 1.0)
        d = (model(vals) - Y) / sd
        return np.concatenate([d.real.ravel(), d.imag.ravel()])

    z0 = np.where(log, 0.0, 1.0)
    t0 = time.perf_counter()
    res = least_squares(resid, z0, method="lm", xtol=1e-3)
    dt = time.perf_counter() - t0
    return {"seconds": dt, "nfev": int(res.nfev), "status": int(res.status), "values": to_v(res.x).tolist()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None, help="cpu or cuda (default: cuda if present)")
    ap.add_argument(
        "--sizes", default=None, help="comma list of batch sizes (default: 1..1e5 on a GPU, 1,4,16,64 on the CPU)"
    )
    ap.add_argument("--workloads", default="heat,geometry", help="comma list of %s" % ",".join(WORKLOADS))
    ap.add_argument(
        "--scipy-fits", type=int, default=None, help="SciPy fits per workload (default: 1 heat, 3 geometry; 0 skips)"
    )
    ap.add_argument(
        "--kernel-fits", type=int, default=16, help="SciPy fits on the project's CPU kernel per workload (0 skips)"
    )
    ap.add_argument("--cpu-sizes", default="1,16,64", help="batched CPU fits on a GPU run (empty: none)")
    ap.add_argument(
        "--cells", type=int, default=None, help="fixed Magnus cells (default: adaptive rule, fixed per fit)"
    )
    ap.add_argument(
        "--jacobians",
        default=None,
        help="comma list of the batched fits' Jacobians (auto, broyden, difference, tangent), the first "
        "the headline; the others are timed on the same batches (default: auto,difference: fit()'s "
        "default, the secant iteration for heat fits, and forward differences at every step)",
    )
    ap.add_argument(
        "--pool-keep",
        type=float,
        default=None,
        help="fraction of a GPU's memory its memory pool keeps in freed blocks (tawarp.model.forward.POOL_KEEP, "
        "default %g; 0: CUDA's own, which returns them to the driver at every synchronization)" % POOL_KEEP,
    )
    ap.add_argument("--out", default=None, help="JSON output (default: bench/results/fit_<device>.json)")
    args = ap.parse_args(argv)
    jacobians = (args.jacobians or "auto,difference").split(",")
    bad = [j for j in jacobians if j not in ("auto", "broyden", "tangent", "difference")]
    if bad:
        ap.error(f"--jacobians: {bad[0]!r} is not one of auto, broyden, tangent, difference")
    if args.pool_keep is not None:
        forward.POOL_KEEP = args.pool_keep
    wp.config.quiet = True
    wp.init()
    device = args.device or ("cuda" if wp.is_cuda_available() else "cpu")
    gpu = device.startswith("cuda")
    sizes = [int(float(s)) for s in (args.sizes or ("1,10,100,1000,10000,100000" if gpu else "1,4,16,64")).split(",")]
    settings = ForwardSettings(cells=args.cells, device=device)
    core = load_core("mesh")
    dev_name = wp.get_device(device).name
    result = {
        "device": device,
        "device_name": dev_name,
        "cpu": platform.processor() or platform.machine(),
        "load_average_at_start": list(os.getloadavg()),
        "cpu_count": os.cpu_count(),
        "warp": wp.config.version,
        "python": sys.version.split()[0],
        "freqs": {"min": FREQS[0], "max": FREQS[-1], "count": FREQS.size},
        "xtol": 1e-3,
        "cells": args.cells,
        "pool_keep": forward.POOL_KEEP,
        "workloads": {},
    }
    for wname in args.workloads.split(","):
        wl = WORKLOADS[wname]
        Y, sd = make_data(core, wl["names"], wl["Q"], max(sizes))
        rows, others = [], []
        for k, jac in enumerate(jacobians):
            # warm-up: compile the kernels; 64 problems, so that the shared start's second
            # derivatives (taken from 18 problems sharing a start) compile too
            time_fits(core, wl, Y, sd, min(64, max(sizes)), device, settings, jac)
            for n in sizes:
                row = time_fits(core, wl, Y, sd, n, device, settings, jac)
                (rows if k == 0 else others).append(row)
                print(
                    f"{wname:9s} {device:5s} {jac:10s} n = {n:7d}: {row['fits_per_s']:10.1f} fits/s  "
                    f"({row['seconds']:.3f} s, {row['iterations_mean']:.1f} it, {row['evaluations_per_fit']:.2f} "
                    f"cascades/fit, {row['launches']} launches, {row['converged']:.3f} converged)",
                    flush=True,
                )
        for row in others:  # the same problems as the headline's: how far apart their results are
            head = next(r for r in rows if r["n"] == row["n"])
            with np.errstate(divide="ignore", invalid="ignore"):
                row["max_values_difference_in_std"] = float(
                    np.nanmax(np.abs(row["values"] - head["values"]) / head["std"])
                )
                row["max_std_relative_difference"] = float(np.nanmax(np.abs(row["std"] / head["std"] - 1)))
        for row in rows + others:
            del row["values"], row["std"]
        entry = {
            "names": wl["names"],
            "heat_input_W": wl["Q"],
            "start_factor": wl["start"],
            "batches": rows,
            "other_jacobians": others,
        }
        best = max(r["fits_per_s"] for r in rows)
        if gpu and args.cpu_sizes:
            cpu = ForwardSettings(cells=args.cells, device="cpu")
            time_fits(core, wl, Y, sd, 1, "cpu", cpu)  # warm-up
            entry["cpu_batches"] = [
                time_fits(core, wl, Y, sd, int(float(n)), "cpu", cpu) for n in args.cpu_sizes.split(",")
            ]
            for row in entry["cpu_batches"]:
                del row["values"], row["std"]
            for row in entry["cpu_batches"]:
                print(f"{wname:9s} cpu   n = {row['n']:7d}: {row['fits_per_s']:10.1f} fits/s", flush=True)
        start = np.array([core.get(k) for k in wl["names"]]) * wl["start"]
        if args.kernel_fits:
            model = kernel_model(core, wl["names"], wl["Q"], start)
            model({k: float(v) for k, v in zip(wl["names"], start)})  # warm-up
            kf = [scipy_fit(model, wl["names"], Y[i], sd, start) for i in range(args.kernel_fits)]
            per = float(np.mean([s["seconds"] for s in kf]))
            truth = np.array([core.get(k) for k in wl["names"]])
            batched = fit(
                core,
                FREQS,
                Y[: args.kernel_fits],
                wl["names"],
                start,
                heat_input=wl["Q"],
                device="cpu",
                weights=np.broadcast_to(1.0 / sd, (args.kernel_fits,) + sd.shape),
                warn=False,
                settings=ForwardSettings(cells=args.cells, device="cpu"),
            )
            sv = np.array([s["values"] for s in kf])
            cpu_best = max(r["fits_per_s"] for r in entry.get("cpu_batches", rows if not gpu else []))
            entry["scipy_kernel"] = {
                "fits": kf,
                "seconds_per_fit": per,
                "fits_per_s": 1.0 / per,
                "method": "least_squares(method='lm', xtol=1e-3) on the project's CPU kernel (Engine.evaluate, "
                "one set x 100 frequencies, the batched fit's fixed cells), one fit at a time",
                "speedup_best_batch": best * per,
                "speedup_best_cpu_batch": cpu_best * per,
                "max_relative_error_vs_truth": float(np.max(np.abs(sv / truth - 1))),
                "max_difference_to_batched_fit_in_std": float(np.max(np.abs(sv - batched.values) / batched.std)),
            }
            print(
                f"{wname:9s} scipy on the CPU kernel: {per * 1e3:.1f} ms per fit "
                f"({np.mean([s['nfev'] for s in kf]):.1f} evaluations); best batch {best * per:.1f} x, "
                f"best CPU batch {cpu_best * per:.1f} x",
                flush=True,
            )
        nsp = args.scipy_fits if args.scipy_fits is not None else (1 if wname == "heat" else 3)
        sp = []
        for i in range(nsp):
            sp.append(scipy_fit(reference_model(core, wl["Q"]), wl["names"], Y[i], sd, start))
            print(f"{wname:9s} scipy fit {i}: {sp[-1]['seconds']:.2f} s ({sp[-1]['nfev']} evaluations)", flush=True)
        if sp:
            per = float(np.mean([s["seconds"] for s in sp]))
            entry["scipy"] = {
                "fits": sp,
                "seconds_per_fit": per,
                "fits_per_s": 1.0 / per,
                "method": "least_squares(method='lm', xtol=1e-3) on reference.dimensionless_transfer",
            }
            entry["speedup_best_batch_vs_scipy"] = best * per
            print(f"{wname:9s} best {best:.1f} fits/s = {best * per:.0f} x SciPy ({per:.3f} s per fit)", flush=True)
        result["workloads"][wname] = entry
    result["load_average_at_end"] = list(os.getloadavg())
    write_result(result, f"fit_{device.replace(':', '')}.json", args.out)
    return 0


if __name__ == "__main__":
    run(main)
