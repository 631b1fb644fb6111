"""The tangent cascade's register cap: complete fits/s of bench/fit.py's workloads with
tangent Jacobians under each cap of the tangent kernel, beside forward differences (the
plain cascade at its default cap of 64) in the same run. Writes JSON.

    python bench/tangent_registers.py --device cuda --sizes 1e4,1e5 --caps 64,128,none

``tawarp.model.forward.TANGENT_MAX_REGISTERS`` is set for each cap (None is the
package's default; the CPU ignores caps).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

import numpy as np
import warp as wp

from fit import FREQS, WORKLOADS, make_data
from tawarp.fit.estimate import FitWarning, fit
from tawarp.model import forward
from tawarp.model.core import load_core
from _results import write_result


def timed_fit(core, wl, Y, sd, n, device, jacobian) -> dict:
    """fits/s of one batch of n problems (after a warm-up batch of one)."""
    start = np.array([core.get(k) for k in wl["names"]]) * wl["start"]
    rows = {}
    for size in (1, n):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FitWarning)
            wp.synchronize_device(device)
            t0 = time.perf_counter()
            r = fit(core, FREQS, Y[:size], wl["names"], start, heat_input=wl["Q"], weights=1 / sd, device=device,
                    warn=False, jacobian=jacobian)
            wp.synchronize_device(device)
            rows = {"n": size, "seconds": time.perf_counter() - t0, "converged": float(r.converged.mean())}
    rows["fits_per_s"] = rows["n"] / rows["seconds"]
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None, help="cpu or cuda (default: cuda if present)")
    ap.add_argument("--sizes", default="1e4,1e5", help="comma list of batch sizes")
    ap.add_argument("--caps", default="64,128,none", help="comma list of register caps of the tangent kernel")
    ap.add_argument("--out", default=None, help="JSON output (default: bench/results/tangent_registers_<device>.json)")
    args = ap.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = args.device or ("cuda" if wp.is_cuda_available() else "cpu")
    sizes = [int(float(s)) for s in args.sizes.split(",")]
    try:
        caps = [None if c.strip().lower() == "none" else int(c) for c in args.caps.split(",")]
    except ValueError:
        ap.error(f"--caps: {args.caps!r}; expected a comma list of register counts or none")
    core = load_core("mesh")
    result = {"device": device, "device_name": wp.get_device(device).name, "warp": wp.config.version,
              "workloads": {}}
    for wname, wl in WORKLOADS.items():
        Y, sd = make_data(core, wl["names"], wl["Q"], max(sizes))
        rows = []
        for jacobian, cap in [("difference", None)] + [("tangent", c) for c in caps]:
            forward.TANGENT_MAX_REGISTERS = cap
            for n in sizes:
                row = dict(timed_fit(core, wl, Y, sd, n, device, jacobian), jacobian=jacobian,
                           tangent_max_registers=cap if jacobian == "tangent" else None)
                rows.append(row)
                label = "-" if jacobian == "difference" else str(cap)
                print(f"{wname:9s} {jacobian:10s} cap {label:5s} n = {n:7d}: "
                      f"{row['fits_per_s']:10.1f} fits/s", flush=True)
        result["workloads"][wname] = rows
    write_result(result, f"tangent_registers_{device.replace(':', '')}.json", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
