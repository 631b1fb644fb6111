"""One warm launch of the cascade kernel, for a profiler (ncu) to inspect (the bare cell
rule, ``tolerance=None``: the error estimate's own small launches of the same kernel
would otherwise be the ones ncu picks):

    ncu --clock-control none -k regex:transfer_kernel --launch-skip 1 --launch-count 1 \
        --section LaunchStats --section Occupancy --section SpeedOfLight python bench/profile_forward.py
"""

import argparse

import numpy as np
import warp as wp

from tawarp.model.core import load_core
from tawarp.model.forward import Engine, ForwardSettings


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", type=int, default=20000, help="parameter sets of the launch (100 frequencies each)")
    ap.add_argument("--device", default="cuda", help="a CUDA device (default cuda)")
    args = ap.parse_args(argv)
    wp.init()
    if not wp.is_cuda_available():
        ap.error("no CUDA device: this bench profiles a GPU launch")
    rng = np.random.default_rng(0)
    n = args.sets
    table = np.stack(
        [rng.uniform(0, 80, n), rng.uniform(50, 250, n), rng.uniform(0.85, 0.95, n), rng.uniform(0.3e-3, 0.6e-3, n)]
    )
    engine = Engine(
        load_core("ceramic"),
        np.linspace(30, 500, 100),
        ["stack.h", "stack.porosity", "stack.pore_radius"],
        ForwardSettings(tolerance=None, device=args.device),
    )
    varying = wp.array(table, dtype=wp.float64, device=args.device)
    for _ in range(2):
        engine.evaluate(varying)
    wp.synchronize()


if __name__ == "__main__":
    main()
