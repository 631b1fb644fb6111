"""Where the step-doubling error estimate is largest across a batch's frequencies.

The forward model's adaptive cells (``ForwardSettings.tolerance``) compare the cascade at
cell density d with 2d at the batch's highest frequency only. This study checks that
choice: on random cores (tests/test_cells.py's draws: every thermal field over its
documented range, 0-80 W) it computes the step-doubling difference |Y(d) - Y(2d)|
(row-relative, dimensionless coefficients) at 12 frequencies of two bands, d = 1.5 (the
default), and reports at which frequency it is largest and how the highest frequency's
compares. Makes studies/out/estimate_frequency.json.

    python studies/estimate_frequency.py
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from tawarp.io import write_json
from tawarp.model.core import load_core
from tawarp.model.forward import transfer_matrices

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from test_cells import random_sets  # noqa: E402 (the tests' draws of random cores)

CASES = {
    "30-500 Hz": (np.geomspace(30.0, 500.0, 12), [("ceramic", 0), ("mesh", 1), ("ceramic", 2), ("mesh", 3)], 3),
    "20-2000 Hz": (np.geomspace(20.0, 2000.0, 12), [("nicr_foam", 4), ("rvc_foam", 5), ("ceramic", 6), ("mesh", 7)], 4),
}


def difference(core, freqs, q, values) -> np.ndarray:
    """Row-relative |Y(1.5) - Y(3)| at each frequency (bare rule at both densities)."""
    params = {k: [v] for k, v in values.items()}
    Y = [
        transfer_matrices(core, freqs, q, params=params, device="cpu", tolerance=None, cell_density=d).dimensionless()[
            0
        ]
        for d in (1.5, 3.0)
    ]
    return np.abs(Y[0] - Y[1]).max(-1) / np.abs(Y[1]).max(-1)


def main():
    rows = []
    for band, (freqs, draws, per_core) in CASES.items():
        for name, seed in draws:
            core = load_core(name)
            for q, values in random_sets(core, per_core, seed):
                e = difference(core, freqs, q, values)
                rows.append(
                    {
                        "band": band,
                        "core": name,
                        "heat_input": q,
                        "largest": float(e.max()),
                        "at_hz": float(freqs[e.argmax()]),
                        "highest_over_largest": float(e[-1] / e.max()),
                    }
                )
                print(rows[-1], flush=True)
    elsewhere = [r for r in rows if r["highest_over_largest"] < 1.0]
    summary = {
        "sets": len(rows),
        "largest_at_highest_frequency": len(rows) - len(elsewhere),
        "elsewhere_largest_difference": max((r["largest"] for r in elsewhere), default=0.0),
        "elsewhere_smallest_ratio": min((r["highest_over_largest"] for r in elsewhere), default=1.0),
    }
    print(summary)
    out = Path(__file__).resolve().parent / "out" / "estimate_frequency.json"
    write_json(out, {"summary": summary, "sets": rows})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
