"""Looped-engine onset benchmark: onsets of the traveling-wave engine network per minute,
one thread per design (:class:`tawarp.model.network_batch.NetworkBatch`), and the time for
one onset of the peers: the NumPy reference and openthermoacoustics' segments
(studies/network_peer.py). Writes JSON.

    python bench/network_onset.py --device cuda --sizes 1e4,1e5,1e6 --out bench/results/network_onset_cuda_h100.json
    python bench/network_onset.py --device cpu --sizes 100,1000 --out bench/results/network_onset_cpu.json

Designs: the bundled ``traveling_wave`` network with the regenerator's pore radius
(60-110 um), porosity (0.65-0.78) and length (5-9 cm) and the resonator's length
(4.6-5.3 m) drawn at random. An *onset* is one design's (omega, T_hot) where the network's
determinant vanishes with omega real, to 1e-10 relative, found two ways: Newton's method from
the nominal design's onset (found once on the host by following the mode from T_cold, timed
separately; :meth:`NetworkBatch.onset`), and each design's mode followed from T_cold on 12
hot temperatures up to 700 K, Muller at each, the first crossing refined by Newton
(:meth:`NetworkBatch.followed_onset`: no start needed). Every determinant walks 8 Magnus
cells in the regenerator, the buffer tube and each cone. Timed: building the tables, the
launch and the transfers, after a warm-up call; the designs without an onset are counted.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

from tawarp.model import network_reference as nr
from tawarp.model.network import load_network
from tawarp.model.network_batch import NetworkBatch
from _results import run, write_result

ENGINE = "traveling_wave"


def random_designs(n: int, rng) -> dict:
    return {
        "regenerator.pore_radius": rng.uniform(60e-6, 110e-6, n),
        "regenerator.porosity": rng.uniform(0.65, 0.78, n),
        "regenerator.length": rng.uniform(0.05, 0.09, n),
        "resonator.length": rng.uniform(4.6, 5.3, n),
    }


def time_onsets(net, start, n: int, device: str, rng, repeats: int, followed: bool = False) -> dict:
    """Newton from the nominal onset, or (``followed``) each design's mode followed from
    T_cold on 12 hot temperatures up to 700 K (no start near the onset)."""
    params = random_designs(n, rng)

    def run(p):
        b = NetworkBatch(net, p, device=device)
        if followed:
            r = b.followed_onset(start[0] * (1 + 0j), 700.0, n=12)
            return r.T_hot, r.status == 1, None
        r = b.onset(*start)
        return r.T_hot, r.iterations > 0, r.iterations

    run({k: v[: min(n, 64)] for k, v in params.items()})  # warm-up: compilation, allocation
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        T, ok, its = run(params)
        times.append(time.perf_counter() - t0)
    dt = float(np.median(times))
    return {
        "method": "followed from T_cold" if followed else "Newton from the nominal onset",
        "designs": n,
        "seconds": dt,
        "onsets_per_minute": 60.0 * n / dt,
        "converged": int(ok.sum()),
        "mean_newton_steps": float(its[ok].mean()) if its is not None and ok.any() else None,
        "T_ratio_range": [float(T[ok].min() / net.gas.T_cold), float(T[ok].max() / net.gas.T_cold)]
        if ok.any()
        else None,
    }


def peers(net, start, rng, n: int = 3) -> dict:
    """Seconds per onset of the NumPy reference and of openthermoacoustics' segments, both by
    the same Newton iteration from the nominal onset, on ``n`` designs; and one full onset
    (mode followed from T_cold) of each."""
    params = random_designs(4 * n, rng)
    batch = NetworkBatch(net, params, device="cpu").onset(*start)
    keep = np.flatnonzero(batch.iterations > 0)[:n]  # designs the batch finds: the same iteration's
    designs = [net.replace(**{k: float(v[j]) for k, v in params.items()}) for j in keep]
    out = {}
    t0 = time.perf_counter()
    ref = [nr.onset_newton(d, *start) for d in designs]
    out["numpy_reference"] = {"seconds_one_onset_newton": (time.perf_counter() - t0) / n}
    t0 = time.perf_counter()
    full = nr.onset(net, start[0], T_max=700.0, n=8)
    out["numpy_reference"]["seconds_one_onset_followed"] = time.perf_counter() - t0
    out["numpy_reference"]["max_relative_difference_T_onset"] = float(
        max(abs(batch.T_hot[j] / r[1] - 1) for j, r in zip(keep, ref, strict=True))
    )
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
    try:
        from network_peer import peer_determinant

        t0 = time.perf_counter()
        peer = [nr.onset_newton(d, *start, det=lambda w, T, d=d: peer_determinant(d, w, T)) for d in designs]
        out["openthermoacoustics"] = {
            "seconds_one_onset_newton": (time.perf_counter() - t0) / n,
            "max_relative_difference_T_onset": float(max(abs(peer[j][1] / ref[j][1] - 1) for j in range(n))),
            "note": "its segment classes inside tawarp's junction and end rows (studies/network_peer.py); "
            "its own loop onset is a gain proxy",
        }
        t0 = time.perf_counter()
        nr.onset(net, start[0], T_max=700.0, n=8, det=lambda w, T: peer_determinant(net, w, T))
        out["openthermoacoustics"]["seconds_one_onset_followed"] = time.perf_counter() - t0
    except ImportError as e:
        out["openthermoacoustics"] = {"available": False, "reason": str(e)}
    out["followed_onset_T_ratio"] = full.ratio
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--sizes", default=None, help="comma list of designs per launch")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-peers", action="store_true", help="skip the reference and openthermoacoustics timings")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    wp.init()
    device = args.device or ("cuda" if wp.is_cuda_available() else "cpu")
    gpu = device.startswith("cuda")
    sizes = [int(float(s)) for s in (args.sizes or ("1e4,1e5,1e6" if gpu else "100,1000")).split(",")]
    net = load_network(ENGINE)
    t0 = time.perf_counter()
    (w0, *_) = nr.real_axis_modes(net, 40.0, 130.0, 90, T_hot=net.gas.T_cold)
    nominal = nr.onset(net, w0, T_max=700.0, n=8)
    start = (nominal.omega.real, nominal.T_onset)
    result = {
        "device": device,
        "device_name": wp.get_device(device).name,
        "warp": wp.config.version,
        "host": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": sys.version.split()[0],
        "engine": ENGINE,
        "definition": "one design's onset (real omega, T_hot) with det = 0 by Newton's method from the nominal "
        "design's onset, to 1e-10 relative; tables, launch and transfers timed",
        "nominal": {
            "T_ratio": nominal.ratio,
            "f_Hz": nominal.frequency,
            "seconds_host_followed_onset": time.perf_counter() - t0,
        },
    }
    rng = np.random.default_rng(0)
    rows = []
    for followed in (False, True):
        for n in sizes:
            r = time_onsets(net, start, n, device, rng, args.repeats, followed)
            rows.append(r)
            print(f"{r['method']:<32s} designs={n:>9d}  {r['seconds']:.3f} s  {r['onsets_per_minute']:.3e} onsets/min")
    result["throughput"] = rows
    best = max(r["onsets_per_minute"] for r in rows if r["method"].startswith("Newton"))
    result["best_onsets_per_minute"] = best
    result["best_followed_onsets_per_minute"] = max(r["onsets_per_minute"] for r in rows if r["method"].startswith("f"))
    if not args.no_peers:
        p = peers(net, start, rng)
        for v in p.values():
            if isinstance(v, dict) and "seconds_one_onset_newton" in v:
                v["speedup_of_tawarp"] = best / 60.0 * v["seconds_one_onset_newton"]
                v["speedup_of_tawarp_followed"] = (
                    result["best_followed_onsets_per_minute"] / 60.0 * v["seconds_one_onset_followed"]
                )
        result["peers"] = p
    print(json.dumps(result, indent=2, default=float))
    if args.out:
        write_result(result, "", args.out)


if __name__ == "__main__":
    run(main)
