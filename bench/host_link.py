"""Copy bandwidth between page-locked host memory and the GPUs, one GPU alone and several at
once: what the host link gives a multi-GPU fit's data uploads and an evaluation's result
copies (bench/multi_gpu.py) when every GPU copies together.

Each GPU has a page-locked host buffer and a device buffer of ``--mb`` MB; a thread per GPU
copies one into the other ``--repeats`` times (host to device, ``h2d``, and back, ``d2h``),
the GPUs of a group all at once. ``gb_per_s``: each GPU's best copy; ``aggregate``: the
group's bytes over the wall time of all its copies.

    python bench/host_link.py [--mb 512] [--repeats 5] [--out bench/results/NAME.json]
"""

from __future__ import annotations

import argparse
import sys
import threading
import time

import warp as wp

from _results import run, write_result


def copies(pairs: dict, device: str, way: str, repeats: int, best: dict) -> None:
    """``repeats`` copies ``way`` on ``device``, its best time [s] into ``best``."""
    host, dev = pairs[device]
    fastest = float("inf")
    for _ in range(repeats):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        if way == "h2d":
            wp.copy(dev, host)
        else:
            wp.copy(host, dev)
        wp.synchronize_device(device)
        fastest = min(fastest, time.perf_counter() - t0)
    best[device] = fastest


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mb", type=int, default=512, help="MB per GPU (default 512)")
    ap.add_argument("--repeats", type=int, default=5, help="copies per GPU and case (default 5)")
    ap.add_argument("--out", default=None, help="JSON output (default: print it only)")
    args = ap.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    devices = [f"cuda:{i}" for i in range(wp.get_cuda_device_count())]
    if not devices:
        ap.error("no CUDA device: the host link is measured on a GPU machine")
    nbytes = args.mb << 20
    pairs = {
        d: (
            wp.empty(nbytes // 8, dtype=wp.float64, device="cpu", pinned=True),
            wp.empty(nbytes // 8, dtype=wp.float64, device=d),
        )
        for d in devices
    }
    groups = sorted({1, 2, len(devices)} & set(range(1, len(devices) + 1)))
    rows = []
    for way in ("h2d", "d2h"):
        for k in groups:
            group = devices[:k]
            for _ in range(2):  # (the second round timed: the first warms the copies up)
                best = {}
                threads = [threading.Thread(target=copies, args=(pairs, d, way, args.repeats, best)) for d in group]
                t0 = time.perf_counter()
                for t in threads:
                    t.start()
                for t in threads:
                    t.join()
                wall = time.perf_counter() - t0
            row = {
                "way": way,
                "gpus": k,
                "gb_per_s": [nbytes / best[d] / 1e9 for d in group],
                "aggregate_gb_per_s": args.repeats * nbytes * k / wall / 1e9,
            }
            rows.append(row)
            print(way, k, [round(v, 1) for v in row["gb_per_s"]], round(row["aggregate_gb_per_s"], 1), flush=True)
    out = {
        "mb_per_gpu": args.mb,
        "repeats": args.repeats,
        "devices": [wp.get_device(d).name for d in devices],
        "rows": rows,
    }
    if args.out:
        write_result(dict(out, command="python bench/host_link.py " + " ".join(sys.argv[1:])), "", args.out)
    return 0


if __name__ == "__main__":
    run(main)
