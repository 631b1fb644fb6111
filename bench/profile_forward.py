"""One warm launch of the cascade kernel, for a profiler (ncu) to inspect (the bare cell
rule, ``tolerance=None``: the error estimate's own small launches of the same kernel
would otherwise be the ones ncu picks):

    ncu --clock-control none -k regex:transfer_kernel --launch-skip 1 --launch-count 1 \
        --section LaunchStats --section Occupancy --section SpeedOfLight python bench/profile_forward.py
"""

import numpy as np
import warp as wp

from tawarp.model.core import load_core
from tawarp.model.forward import Engine, ForwardSettings

wp.init()
rng = np.random.default_rng(0)
n = 20000
table = np.stack(
    [rng.uniform(0, 80, n), rng.uniform(50, 250, n), rng.uniform(0.85, 0.95, n), rng.uniform(0.3e-3, 0.6e-3, n)]
)
engine = Engine(
    load_core("ceramic"),
    np.linspace(30, 500, 100),
    ["stack.h", "stack.porosity", "stack.pore_radius"],
    ForwardSettings(tolerance=None, device="cuda"),
)
varying = wp.array(table, dtype=wp.float64, device="cuda")
for _ in range(2):
    engine.evaluate(varying)
wp.synchronize()
