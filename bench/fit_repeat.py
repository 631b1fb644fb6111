"""Side-by-side fit timing: the median of repeated complete fits in one process, for
comparing two checkouts (this one and an older one) on the same machine.

    python bench/fit_repeat.py --repeats 7 --n 10000 --out new.json
    (cd ../old-release && python /path/to/bench/fit_repeat.py --bench-dir bench --out old.json)

The workloads, data and timed call are those of ``bench/fit.py`` of the checkout named by
``--bench-dir`` (its ``make_data``, ``time_fits`` and ``WORKLOADS``), so an older release
runs its own code. A single fit of 1e4 problems takes 0.2-0.8 s on an H100 and separate
processes differ by up to 25 % (CPU placement): alternate the two checkouts' processes,
pin them to the same cores (``taskset -c 4-7``) and compare medians.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--bench-dir",
        default=str(Path(__file__).resolve().parent),
        help="bench/ folder of the checkout to time (default: this one)",
    )
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--n", type=float, default=1e4, help="problems per fit")
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--out", default=None, help="JSON output (default: print only)")
    args = ap.parse_args(argv)
    sys.path.insert(0, args.bench_dir)
    import warp as wp

    wp.config.quiet = True
    import fit as fb  # the checkout's own bench/fit.py

    n, dev = int(args.n), args.device
    settings = fb.ForwardSettings(device=dev)
    out = {"device": wp.get_device(dev).name, "bench_dir": str(Path(args.bench_dir).resolve()), "workloads": {}}
    for name, wl in fb.WORKLOADS.items():
        core = fb.load_core("mesh")
        Y, sd = fb.make_data(core, wl["names"], wl["Q"], n)
        fb.time_fits(core, wl, Y, sd, min(16, n), dev, settings)  # compile
        fb.time_fits(core, wl, Y, sd, n, dev, settings)  # allocations at full size
        rows = [fb.time_fits(core, wl, Y, sd, n, dev, settings) for _ in range(args.repeats)]
        ts = [r["seconds"] for r in rows]
        out["workloads"][name] = {
            "n": n,
            "seconds": ts,
            "median_fits_per_s": n / statistics.median(ts),
            "iterations_mean": rows[0]["iterations_mean"],
            "launches": rows[0]["launches"],
        }
        print(
            f"{name:9s} median {n / statistics.median(ts):.4g} fits/s (min/max {min(ts):.3f}/{max(ts):.3f} s, "
            f"{rows[0]['iterations_mean']:.1f} it)",
            flush=True,
        )
    if args.out:  # atomically, without tawarp.io: an older checkout may not have it
        tmp = Path(args.out).with_suffix(".tmp")
        tmp.write_text(json.dumps(out, indent=1))
        os.replace(tmp, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
