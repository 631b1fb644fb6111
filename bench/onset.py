"""Onset benchmark: complete onset predictions per minute (designs x Q-bracketing), and the
time for one prediction of the peers: the NumPy reference driven by SciPy root finders and
openthermoacoustics (studies/onset_peer.py). Writes JSON.

    python bench/onset.py --device cuda --sizes 1e4,1e5,1e6 --out bench/results/onset_cuda_h100.json
    python bench/onset.py --device cpu --sizes 50,200 --out bench/results/onset_cpu.json

A *complete onset prediction* is one design's :func:`tawarp.model.onset.onset`: the
unheated eigenfrequency, Im omega on ``--bracket`` heat inputs on [0, Q_max] up to the first
crossing (each a Muller search), Newton on (Re omega, Q) to 1e-10 relative (the Illinois
secant as its fallback), and the hot temperature at onset. Reported with the throughput:
the residual (cascade) evaluations per onset, mean over the designs (the work per onset).
Designs: the bundled ``standing_wave`` engine with the left resonator duct (0.5-0.9 m), the
stack length (3-7 cm), porosity (0.85-0.93) and h_s (100-200 W/(m^2 K)) drawn at random.
Timed: the whole onset() call, host loop and transfers included, after a warm-up call.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import scipy.optimize as so
import warp as wp

from tawarp import reference
from tawarp.model.onset import onset
from tawarp.model.resonator import load_engine
from _results import run, write_result

Q_MAX = 100.0


def random_designs(n: int, rng) -> dict:
    return {
        "engine.left_duct": rng.uniform(0.5, 0.9, n),
        "stack.length": rng.uniform(0.03, 0.07, n),
        "stack.porosity": rng.uniform(0.85, 0.93, n),
        "stack.h": rng.uniform(100, 200, n),
    }


def time_onsets(eng, n: int, bracket: int, device: str, rng, repeats: int) -> dict:
    params = random_designs(n, rng)
    onset(
        eng, Q_max=Q_MAX, params={k: v[: min(n, 64)] for k, v in params.items()}, n_bracket=bracket, device=device
    )  # warm-up: compilation, allocation
    times, res = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = onset(eng, Q_max=Q_MAX, params=params, n_bracket=bracket, device=device)
        times.append(time.perf_counter() - t0)
    dt = float(np.median(times))
    return {
        "designs": n,
        "bracket": bracket,
        "seconds": dt,
        "onsets_per_minute": 60.0 * n / dt,
        "evaluations_per_onset": res.mean_evaluations,
        "refine_steps": res.refine_steps,
        "secant_fallbacks": int(res.fallback.size),
        "with_onset": int(np.isfinite(res.Q_onset).sum()),
    }


def reference_onset(eng, rtol: float = 1e-10) -> dict:
    """One onset by the independent NumPy reference (closed-form ducts, DOP853 at complex
    omega, exact heat profile), driven by SciPy: the secant on omega for Tup = 0 (closed-closed)
    and Brent's method on Q; seconds, and Q_onset to compare with tawarp's."""
    core = eng.core
    row = eng.resonator_row()
    gas = core.gas

    def residual(w, Q):
        Ml = reference.duct_matrix_omega(gas.name, gas.p_mean, row[2], row[1], row[0], w)[0]
        Mr = reference.duct_matrix_omega(gas.name, gas.p_mean, row[5], row[4], row[3], w)[0]
        return (Mr @ reference.transfer_matrix_omega(core, w, Q, rtol=rtol)[0] @ Ml)[1, 0]

    guess = [2 * math.pi * 150.0 + 0j]

    def growth(Q):
        guess[0] = so.newton(lambda w: residual(w, Q), guess[0], tol=1e-11, maxiter=60)
        return guess[0].imag

    t0 = time.perf_counter()
    Q = so.brentq(growth, 0.0, Q_MAX / 2, xtol=1e-9, rtol=1e-10)
    return {
        "seconds_one_prediction": time.perf_counter() - t0,
        "Q_onset_W": Q,
        "rtol": rtol,
        "method": "scipy.optimize.newton (secant) on omega, brentq on Q in [0, 50] W",
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--sizes", default=None, help="comma list of designs per onset() call")
    ap.add_argument("--bracket", type=int, default=9, help="heat inputs of the bracketing grid (default 9)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-peers", action="store_true", help="skip the reference and openthermoacoustics timings")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    wp.init()
    device = args.device or ("cuda" if wp.is_cuda_available() else "cpu")
    gpu = device.startswith("cuda")
    sizes = [int(float(s)) for s in (args.sizes or ("1e4,1e5,1e6" if gpu else "50,200")).split(",")]
    eng = load_engine("standing_wave")
    rng = np.random.default_rng(0)
    result = {
        "device": device,
        "device_name": wp.get_device(device).name,
        "warp": wp.config.version,
        "host": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": sys.version.split()[0],
        "engine": "standing_wave",
        "Q_max_W": Q_MAX,
        "definition": "one design's onset(): unheated eigenfrequency, bracket grid to the first crossing, "
        "Newton on (Re omega, Q) to 1e-10 (Illinois secant fallback), T_hot at onset",
    }
    rows = []
    for n in sizes:
        r = time_onsets(eng, n, args.bracket, device, rng, args.repeats)
        rows.append(r)
        print(
            f"designs={n:>9d}  {r['seconds']:.3f} s  {r['onsets_per_minute']:.3e} onsets/min  "
            f"{r['evaluations_per_onset']:.1f} evaluations/onset",
            flush=True,
        )
    result["throughput"] = rows
    best = max(r["onsets_per_minute"] for r in rows)
    result["best_onsets_per_minute"] = best
    if not args.no_peers:
        ours = onset(eng, Q_max=Q_MAX, device=device).Q_onset[0]
        ref = reference_onset(eng)
        ref["relative_difference_to_tawarp"] = ref["Q_onset_W"] / ours - 1
        peers = {"numpy_reference_scipy": ref}
        sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
        try:
            from onset_peer import peer_onset

            t0 = time.perf_counter()
            p = peer_onset(eng)
            peers["openthermoacoustics"] = {
                "seconds_one_prediction": time.perf_counter() - t0,
                **p,
                "note": "imposed linear stack profile; 9-point T-ratio grid, brentq (studies/onset_peer.py)",
            }
        except ImportError as e:
            peers["openthermoacoustics"] = {"available": False, "reason": str(e)}
        for v in peers.values():
            if "seconds_one_prediction" in v:
                v["speedup_of_tawarp"] = best / 60.0 * v["seconds_one_prediction"]
        result["peers"] = peers
    print(json.dumps(result, indent=2, default=float))
    if args.out:
        write_result(result, "", args.out)


if __name__ == "__main__":
    run(main)
