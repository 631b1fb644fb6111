"""Accuracy and cost of the tabulated circular-pore functions.

Makes studies/out/pore_table_accuracy.json: the largest error, relative to |f| and to
|g| separately, of the kernels' tabulated f, g (tawarp.kernels.pore.pore_circular_tabulated)
and of the recurrence/Hankel functions it is built from (pore_circular), against mpmath
at 40 digits, per decade of s = r / delta over [1e-4, 1e5] (log-spaced random points
plus both sides of every piece boundary); and the time per evaluation of each on the
device, at s spread over [0.1, 30] (the stacks' range).

    python studies/pore_table_accuracy.py [--points 5000] [--device cpu]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import mpmath
import numpy as np
import warp as wp

from tawarp.io import write_json
from tawarp.kernels.pore import (
    PIECES,
    PIECES_PER_OCTAVE,
    S_MAX,
    S_MIN,
    PoreTable,
    pore_circular,
    pore_circular_tabulated,
)
from tawarp.kernels.pore_table import circular_table


@wp.kernel
def _evaluate(
    s: wp.array(dtype=wp.float64),
    table: PoreTable,
    tabulated: int,
    f: wp.array(dtype=wp.vec2d),
    g: wp.array(dtype=wp.vec2d),
):
    i = wp.tid()
    if tabulated != 0:
        fi, gi = pore_circular_tabulated(table, wp.log(s[i]))
    else:
        fi, gi = pore_circular(s[i])
    f[i] = fi
    g[i] = gi


def evaluate(s: np.ndarray, tabulated: bool, device: str):
    """f, g at s (complex arrays) and the seconds of the launch (median of 5)."""
    s_wp = wp.array(s, dtype=wp.float64, device=device)
    f = wp.empty(len(s), dtype=wp.vec2d, device=device)
    g = wp.empty(len(s), dtype=wp.vec2d, device=device)
    args = [s_wp, circular_table(device), int(tabulated), f, g]
    times = []
    for _ in range(5):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        wp.launch(_evaluate, dim=len(s), inputs=args, device=device)
        wp.synchronize_device(device)
        times.append(time.perf_counter() - t0)
    as_complex = lambda a: a.numpy().view(np.complex128).ravel()  # noqa: E731
    return as_complex(f), as_complex(g), float(np.median(times))


def reference(s: float):
    """f, g of the circular pore at 40 digits, exp(-i w t) convention."""
    with mpmath.workdps(40):
        z = mpmath.mpc(1, 1) * mpmath.mpf(float(s))
        j0 = mpmath.besselj(0, z)
        return complex(2 * mpmath.besselj(1, z) / (z * j0)), complex(-mpmath.besselj(2, z) / j0)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=5000, help="random log-spaced points")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=str(Path(__file__).parent / "out"))
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    edges = S_MIN * 2.0 ** (np.arange(PIECES + 1) / PIECES_PER_OCTAVE)
    s = np.sort(
        np.concatenate(
            [
                np.exp(rng.uniform(np.log(1e-4), np.log(1e5), args.points)),
                np.nextafter(edges, 0.0),
                edges,
                np.nextafter(edges, np.inf),
            ]
        )
    )
    ref = np.array([reference(si) for si in s])
    result = {
        "s_range": [1e-4, 1e5],
        "table_range": [S_MIN, S_MAX],
        "pieces": PIECES,
        "points": len(s),
        "device": args.device,
        "max_rel_error": {},
        "seconds_per_evaluation": {},
    }
    decades = np.floor(np.log10(s)).astype(int)
    for name, tabulated in (("table", True), ("recurrence", False)):
        f, g, _ = evaluate(s, tabulated, args.device)
        ef = np.abs(f - ref[:, 0]) / np.abs(ref[:, 0])
        eg = np.abs(g - ref[:, 1]) / np.abs(ref[:, 1])
        per_decade = {
            f"1e{d}": [float(ef[decades == d].max()), float(eg[decades == d].max())] for d in np.unique(decades)
        }
        result["max_rel_error"][name] = {"f": float(ef.max()), "g": float(eg.max()), "per_decade_f_g": per_decade}
        print(f"{name}: max relative error f {ef.max():.2e}, g {eg.max():.2e}")
    s_cost = np.exp(rng.uniform(np.log(0.1), np.log(30.0), 1 << 20))
    for name, tabulated in (("table", True), ("recurrence", False)):
        evaluate(s_cost[:16], tabulated, args.device)  # compile and load first
        seconds = evaluate(s_cost, tabulated, args.device)[2] / len(s_cost)
        result["seconds_per_evaluation"][name] = seconds
        print(f"{name}: {seconds * 1e9:.1f} ns per evaluation of f, g on {args.device} (s in [0.1, 30])")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "pore_table_accuracy.json", result)


if __name__ == "__main__":
    main()
