"""Accuracy per unit of compute of the forward model.

Makes studies/out/forward_accuracy.{json,png}: the max relative error of the four
dimensionless coefficients against the adaptive NumPy reference (DOP853, rtol 1e-12)
for fixed Magnus cells, for the adaptive cell density (the bare rule, ``tolerance=None``)
and for the default settings (cells from the error estimate), on the four bundled cores at
their largest heat input; and the error of the heat model's plain second-order scheme
against the exact solution, beside the exponentially fitted scheme on one cell.

    python studies/forward_accuracy.py [--device cpu]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from tawarp import reference
from tawarp.model.core import load_core, paper_cores
from tawarp.model.forward import transfer_matrices, steady_temperature
from tawarp.plots import plt, save

FREQS = np.array([30.0, 90.0, 170.0, 260.0, 380.0, 500.0])
HEAT = {"rvc_foam": 18.0}


def relative_error(Y, Yref) -> float:
    return float((np.abs(Y - Yref).max(-1) / np.abs(Yref).max(-1)).max())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=str(Path(__file__).parent / "out"))
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    result = {"fixed_cells": {}, "density": {}, "estimate": {}, "heat_plain": {}}
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for name in paper_cores():
        core, Q = load_core(name), HEAT.get(name, 80.0)
        ref = reference.dimensionless_transfer(core, FREQS, Q)
        cells = [2, 4, 8, 16, 32, 64]
        e = [
            relative_error(transfer_matrices(core, FREQS, Q, device=args.device, cells=c).dimensionless()[0], ref)
            for c in cells
        ]
        dens = [0.5, 0.75, 1.0, 1.5, 2.0, 3.0]
        ed = [
            relative_error(
                transfer_matrices(core, FREQS, Q, device=args.device, cell_density=d, tolerance=None).dimensionless()[
                    0
                ],
                ref,
            )
            for d in dens
        ]
        result["estimate"][name] = relative_error(
            transfer_matrices(core, FREQS, Q, device=args.device).dimensionless()[0], ref
        )
        result["fixed_cells"][name] = dict(zip(map(str, cells), e))
        result["density"][name] = dict(zip(map(str, dens), ed))
        ax1.loglog(np.array(cells) * 3, e, "o-", label=f"{name} fixed")
        x = np.array(core.positions()[1:5])
        exact = reference.heat_profile_exact(core, Q).temperature(x)
        hc = [4, 8, 16, 32, 64]
        eh = [
            float(
                np.abs(
                    steady_temperature(core, x, Q, device=args.device, heat_cells=c, fitted=False)[0][0] - exact
                ).max()
            )
            for c in hc
        ]
        fitted = float(np.abs(steady_temperature(core, x, Q, device=args.device, heat_cells=1)[0][0] - exact).max())
        result["heat_plain"][name] = {"cells": hc, "max_abs_error_K": eh, "fitted_1_cell_error_K": fitted}
        ax2.loglog(hc, eh, "s-", label=f"{name} plain (fitted, 1 cell: {fitted:.0e} K)")
    ax1.loglog(np.array([6, 192]), 1e-1 * (np.array([6, 192]) / 6.0) ** -6, "k--", lw=0.8, label="order 6")
    ax1.axhline(1e-6, color="0.6", lw=0.8)
    ax1.set_xlabel("Magnus cells in the three heated segments")
    ax1.set_ylabel("max relative error vs reference")
    ax1.legend(fontsize=7)
    ax2.loglog([4, 64], [10, 10 / 256], "k--", lw=0.8, label="order 2")
    ax2.set_xlabel("heat cells per segment")
    ax2.set_ylabel("max |T - T_exact| at the planes [K]")
    ax2.legend(fontsize=7)
    save(fig, out / "forward_accuracy.png")
    (out / "forward_accuracy.json").write_text(json.dumps(result, indent=2))
    print(json.dumps({k: result[k] for k in ("density", "estimate")}, indent=1))


if __name__ == "__main__":
    main()
