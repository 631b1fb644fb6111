"""Accuracy and cost of the temperature-dependent conductivity effects.

Core ``ceramic``, Q = 40 W, stack.conductivity_exponent = 0.5 and, separately,
stack.radiative_conductivity = 0.3 W/(m K) (and, for information, tbt.h_convection = 3,
whose h the kernels take per heat cell: second order); 30-500 Hz. The kernels' T-matrix is compared
with the independent reference (:func:`tawarp.reference.transfer_matrix`: the nonlinear
heat BVP by scipy's solve_bvp at residual tolerance 1e-8, about 1e-11 in theta, and
DOP853 at rtol 1e-12 on its profile), at the default settings and with the heat grid and
the Magnus cells refined 2x and 4x. Also the heat profile's error (max |theta - theta_ref|
/ max theta_ref on a fine grid) and the forward throughput on the CPU, nonlinear and
linear.

    python studies/nonlinear_effects_accuracy.py [--out studies/out/nonlinear_effects_accuracy.json]

Before the Kirchhoff cells (commit 17b707e: conductivity constant per heat cell, dT/dx
jumping at the nodes), the same run gave T-matrix errors 1.1e-3 / 4.5e-4 / 1.3e-4
(exponent) and 1.4e-3 / 5.7e-4 / 1.3e-4 (radiative) at 1x / 2x / 4x, theta errors
6.8e-4 / 2.0e-4 / 5.2e-5 and 6.1e-4 / 1.6e-4 / 4.2e-5.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from tawarp import reference
from tawarp.model.core import load_core
from tawarp.model.forward import DEFAULT_CELL_DENSITY, ForwardSettings, steady_temperature, transfer_matrices

FREQS = np.geomspace(30.0, 500.0, 9)
Q = 40.0
EFFECTS = {"stack.conductivity_exponent": 0.5, "stack.radiative_conductivity": 0.3, "tbt.h_convection": 3.0}


def relative_error(Y, Yref) -> float:
    """Max over frequencies of max_c |Y - Yref| / max_c |Yref| (dimensionless coefficients)."""
    return float((np.abs(Y - Yref).max(-1) / np.abs(Yref).max(-1)).max())


def with_value(core, name: str, value: float):
    """The core with field ``SEGMENT.FIELD`` = value."""
    seg, _, field = name.partition(".")
    return dataclasses.replace(
        core, segments=tuple(dataclasses.replace(s, **{field: value}) if s.name == seg else s for s in core.segments)
    )


def settings(level: int) -> ForwardSettings:
    """Default settings refined by 2^level (heat grid and Magnus cell density; the rule
    alone, without the error estimate that would raise the coarse levels' cells)."""
    base = ForwardSettings()
    return ForwardSettings(
        nonlinear_heat_cells=base.nonlinear_heat_cells * 2**level,
        cell_density=DEFAULT_CELL_DENSITY * 2**level,
        tolerance=None,
        device="cpu",
    )


def throughput(core, params: dict, n: int = 64, repeats: int = 3) -> float:
    """Forward models (set x frequency) per second on the CPU, best of ``repeats``."""
    transfer_matrices(core, FREQS, Q, params=params, device="cpu")  # compile
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        transfer_matrices(core, FREQS, np.full(n, Q), params=params, device="cpu")
        best = min(best, time.perf_counter() - t)
    return n * len(FREQS) / best


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="studies/out/nonlinear_effects_accuracy.json")
    ap.add_argument("--no-timing", action="store_true")
    args = ap.parse_args(argv)
    core = load_core("ceramic")
    pos = core.positions()
    x = np.linspace(pos[1], pos[4], 2001)
    result = {"freqs_hz": FREQS.tolist(), "heat_input_w": Q, "effects": {}}
    for field, value in EFFECTS.items():
        c = with_value(core, field, value)
        t = time.perf_counter()
        Yref = reference.dimensionless_transfer(c, FREQS, Q)
        t_ref = time.perf_counter() - t
        href = reference.heat_profile(c, Q)
        th_ref = href.theta(x)
        Ylin = reference.dimensionless_transfer(core, FREQS, Q)
        row = {"value": value, "effect_size": relative_error(Ylin, Yref), "reference_s": t_ref, "levels": []}
        for level in range(3):
            s = settings(level)
            Y = transfer_matrices(core, FREQS, Q, params={field: value}, settings=s).dimensionless()[0]
            th = steady_temperature(core, x, Q, params={field: value}, settings=s)[0][0] - core.gas.T_cold
            row["levels"].append(
                {
                    "nonlinear_heat_cells": s.nonlinear_heat_cells,
                    "cell_density": s.cell_density,
                    "tmatrix_error": relative_error(Y, Yref),
                    "theta_error": float(np.abs(th - th_ref).max() / th_ref.max()),
                }
            )
            print(field, row["levels"][-1], flush=True)
        print(field, "effect size", row["effect_size"])
        if not args.no_timing:
            row["models_per_s_cpu"] = throughput(core, {field: value})
        result["effects"][field] = row
    if not args.no_timing:
        result["linear_models_per_s_cpu"] = throughput(core, {})
        print(
            "linear models/s",
            result["linear_models_per_s_cpu"],
            {k: v["models_per_s_cpu"] for k, v in result["effects"].items()},
        )
    from tawarp.io import write_json

    write_json(args.out, result)


if __name__ == "__main__":
    main()
