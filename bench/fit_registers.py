"""The cascades' register caps in fits: complete fits/s of bench/fit.py's workloads with
forward-difference Jacobians under each cap of the plain cascade (``--plain-caps``,
``ForwardSettings.max_registers``) and with tangent Jacobians under each cap of the
tangent cascade (``--tangent-caps``, ``tawarp.model.forward.TANGENT_MAX_REGISTERS``), in
one run. Writes JSON; the CPU ignores caps.

    python bench/fit_registers.py --device cuda --sizes 1e4,1e5 --plain-caps 64,128 --tangent-caps 64,128,none
"""

from __future__ import annotations

import argparse

import warp as wp

from fit import WORKLOADS, make_data, time_fits
from tawarp.model import forward
from tawarp.model.core import load_core
from tawarp.model.forward import ForwardSettings
from _results import run, write_result


def timed_fit(core, wl, Y, sd, n, device, jacobian, settings) -> dict:
    """:func:`fit.time_fits` of a batch of n problems after a warm-up batch of one, without
    the per-problem values."""
    time_fits(core, wl, Y, sd, 1, device, settings, jacobian)
    row = time_fits(core, wl, Y, sd, n, device, settings, jacobian)
    del row["values"], row["std"]
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default=None, help="cpu or cuda (default: cuda if present)")
    ap.add_argument("--sizes", default="1e4,1e5", help="comma list of batch sizes")
    ap.add_argument("--plain-caps", default="64,128", help="register caps of the plain cascade (difference Jacobians)")
    ap.add_argument("--tangent-caps", default="64,128,none", help="register caps of the tangent cascade")
    ap.add_argument("--out", default=None, help="JSON output (default: bench/results/fit_registers_<device>.json)")
    args = ap.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    device = args.device or ("cuda" if wp.is_cuda_available() else "cpu")
    sizes = [int(float(s)) for s in args.sizes.split(",")]

    def caps(text, option):
        try:
            return [None if c.strip().lower() == "none" else int(c) for c in text.split(",") if c.strip()]
        except ValueError:
            ap.error(f"{option}: {text!r}; expected a comma list of register counts or none")

    runs = [("difference", c) for c in caps(args.plain_caps, "--plain-caps")] + [
        ("tangent", c) for c in caps(args.tangent_caps, "--tangent-caps")
    ]
    core = load_core("mesh")
    result = {"device": device, "device_name": wp.get_device(device).name, "warp": wp.config.version, "workloads": {}}
    for wname, wl in WORKLOADS.items():
        Y, sd = make_data(core, wl["names"], wl["Q"], max(sizes))
        rows = []
        for jacobian, cap in runs:
            forward.TANGENT_MAX_REGISTERS = cap if jacobian == "tangent" else None
            settings = ForwardSettings(max_registers=cap) if jacobian == "difference" else ForwardSettings()
            for n in sizes:
                row = dict(timed_fit(core, wl, Y, sd, n, device, jacobian, settings), max_registers=cap)
                rows.append(row)
                print(
                    f"{wname:9s} {jacobian:10s} cap {str(cap):5s} n = {n:7d}: {row['fits_per_s']:10.1f} fits/s",
                    flush=True,
                )
        result["workloads"][wname] = rows
    forward.TANGENT_MAX_REGISTERS = None
    write_result(result, f"fit_registers_{device.replace(':', '')}.json", args.out)
    return 0


if __name__ == "__main__":
    run(main)
