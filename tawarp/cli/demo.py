"""``tawarp demo``: the main job on the bundled paper-like cores, end to end."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import math
import warnings
from importlib import resources

from ..fit.characterize import characterize, default_geometry, default_heat_names, figure_paths, write_figures
from ..fit.estimate import FitWarning
from ..io import GENERATOR, claim_outputs, write_json
from ..loop import default_base_params, run_loop, write_report
from ..loop.report import OUTPUTS as LOOP_OUTPUTS
from ..measure.tmatrix import TMatrixKind
from ..measure.files import TMatrixData, read_tmatrix_csv, write_tmatrix_csv
from ..measure.synthetic import MATERIALS, make_paper_data, true_values
from ..model.core import load_core, paper_cores
from ..model.forward import DEFAULT_CELL_DENSITY, ForwardSettings, transfer_matrices
from ..plots import plot_coefficients, plot_temperature
from ..rng import checked_seed

#: Heat inputs of the demo [W]; the RVC foam stops at 18 W as in the paper (combustion risk).
DEMO_HEAT = {"rvc_foam": [0.0, 9.0, 18.0]}
DEFAULT_HEAT = [0.0, 20.0, 40.0, 80.0]

#: The mark of the demo's own files (:func:`tawarp.io.written_by_tawarp`): a later demo
#: into the same folder replaces them.
MARK = f"{GENERATOR} demo"


def demo_outputs(out: Path) -> list[Path]:
    """Every file ``tawarp demo -o OUT`` may write."""
    out = Path(out)
    files = [
        out / f"{name}{end}" for name in paper_cores() for end in ("_T.csv", "_coefficients.png", "_temperature.png")
    ]
    files += [out / "summary.json", *demo_fit_outputs(out / "fit"), out / "onset.json"]
    return files + [out / "loop" / name for name in LOOP_OUTPUTS]


def demo_fit_outputs(out_dir) -> list[Path]:
    """Every file :func:`demo_fit` may write in ``out_dir``."""
    stems = [Path(out_dir) / f"fit_{mat}" for mat in MATERIALS]
    files = [Path(f"{stem}{end}") for stem in stems for end in (".csv", ".json")]
    return files + [p for stem in stems for p in figure_paths(stem)] + [Path(out_dir) / "fit_summary.json"]


def run_demo(args) -> int:
    out = Path(args.output)
    # before the minute of work: a file of the user's in the folder is never replaced
    claim_outputs(*demo_outputs(out), why="the demo's outputs")
    out.mkdir(parents=True, exist_ok=True)
    freqs = np.linspace(30.0, 500.0, 48)
    summary = {}
    rows = []
    for name in paper_cores():
        core = load_core(name)
        Q = DEMO_HEAT.get(name, DEFAULT_HEAT)
        res = transfer_matrices(core, freqs, heat_input=Q, device=args.device, progress=not args.quiet)
        write_tmatrix_csv(
            out / f"{name}_T.csv",
            TMatrixData(
                np.repeat(Q, len(freqs)),
                np.tile(freqs, len(Q)),
                res.T.reshape(-1, 2, 2),
                metadata={"core": name, "generator": MARK},
                source=str(out / f"{name}_T.csv"),
            ),
        )
        Y = res.dimensionless()
        plot_coefficients(
            freqs,
            {f"Q = {q:g} W": Y[k] for k, q in enumerate(Q)},
            out / f"{name}_coefficients.png",
            title=f"{name}: dimensionless T-matrix",
        )
        x = np.linspace(0, core.positions()[-1], 400)
        T, _ = res.temperature(x)
        plot_temperature(
            x,
            {f"Q = {q:g} W": T[k] for k, q in enumerate(Q)},
            out / f"{name}_temperature.png",
            planes=core.positions(),
            title=f"{name}: steady temperature",
        )
        det = np.linalg.det(res.T)
        summary[name] = {"heat_input_W": Q, "T_max_K": T.max(axis=1), "det_T_minus_1_max": np.abs(det - 1).max(axis=1)}
        for k, q in enumerate(Q):
            rows.append((name, q, T[k].max(), np.abs(det[k] - 1).max()))
    write_json(
        out / "summary.json",
        {"generator": MARK, "cell_density": DEFAULT_CELL_DENSITY, "freqs_Hz": freqs, "cores": summary},
    )
    if not args.quiet:
        print(f"{'core':<10} {'Q [W]':>6} {'T_max [K]':>10} {'max|det T - 1|':>15}")
        for name, q, tmax, d in rows:
            print(f"{name:<10} {q:6.1f} {tmax:10.1f} {d:15.3e}")
    demo_fit(out / "fit", device=args.device, quiet=args.quiet)
    demo_loop(out / "loop", device=args.device, quiet=args.quiet)
    demo_onset(out / "onset.json", device=args.device, quiet=args.quiet)
    if not args.quiet:
        print(f"outputs in {out}/")
    return 0


def _value_std(d: dict) -> str:
    return f"{d['value']:.5g} +- " + (f"{d['std']:.2g}" if d["std"] is not None else "undetermined")


#: Bundled measurement with an effect the paper's model lacks (studies/make_demo_data.py).
DEMO_MEASUREMENT = "ceramic_hidden_effect.csv"


def _p(p: float | None) -> str:
    return "" if p is None else f" (p {p:.2g})"


def demo_loop(out: Path, device=None, quiet=False) -> dict:
    """Close the loop on the bundled measurement: fit, diagnose, choose an effect, and
    print the error and the parameters before and after, with the drift of h with Q."""
    data = read_tmatrix_csv(resources.files("tawarp") / "data" / "measured" / DEMO_MEASUREMENT)
    # the same core and loop as ``tawarp loop FILE --core ceramic``: one answer per file
    problem = TMatrixKind(data, load_core("ceramic"), ForwardSettings(device=device))
    report = write_report(problem, run_loop(problem, default_base_params(problem)), out)
    if not quiet:
        print(f"\nclosing the loop on {DEMO_MEASUREMENT} (ceramic core, Q = {data.heat_inputs.tolist()} W):")
        print(
            f"  error before {report['error_before']:.3e}, after {report['error_after']:.3e} "
            f"(noise floor {report['noise_floor']:.3e}); chosen effect: {report['chosen_effect']}"
        )
        before, after = report["parameters_before"], report["parameters_after"]
        print(f"  {'parameter':<30} {'before':>22} {'after':>22}")
        for name in after:
            b = _value_std(before[name]) if name in before else "-"
            a = _value_std(after[name])
            print(f"  {name:<30} {b:>22} {a:>22}")
        drifts = {tag: report.get(f"drift_{tag}") for tag in ("before", "after")}
        for tag, drift in drifts.items():
            if drift:
                spread = ", ".join(
                    f"{k} {v:.1%}" + _p(drift["consistency_p"][k]) for k, v in drift["relative_spread"].items()
                )
                print(f"  spread of h refitted per Q, {tag}: {spread}")
        if any(drifts.values()):
            print("  (p: of each h as one value at every Q, the rest refitted; small: the model misses something)")
        print(f"  report: {out / 'report.md'}")
    return report


def demo_fit(
    out_dir,
    device: str | None = None,
    quiet: bool = False,
    n_freqs: int = 40,
    noise: float = 0.005,
    seed: int = 0,
    cells: int | None = None,
    spread: bool = False,
) -> dict:
    """Fit every bundled core's synthetic data end to end (``tawarp demo``): writes
    ``OUT/fit_MATERIAL.csv`` (data), ``OUT/fit_MATERIAL.json`` and figures, and
    ``OUT/fit_summary.json``; returns the summary dict and prints a table (unless quiet).

    Starts: 20 % off the truth (geometry) and 50 % off (h), as a user's prior would be
    (default), or a Sobol spread with no prior in both steps (``spread=True``); 2 restarts
    at ±20 % either way. On the 2-core CPU the default takes about 10 s, ``spread=True``
    about 120 s (8 starts per problem)."""
    checked_seed(seed, "demo_fit")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    settings = ForwardSettings(cells=cells, device=device)
    summary = {
        "generator": MARK,
        "noise": noise,
        "seed": seed,
        "n_freqs": n_freqs,
        "cells": settings.cells,
        "starts": "spread" if spread else "offset from the truth",
        "materials": {},
    }
    rows = []
    for mat in MATERIALS:
        data = make_paper_data(mat, noise=noise, seed=seed, n_freqs=n_freqs, device=device)
        write_tmatrix_csv(out / f"fit_{mat}.csv", data)
        truth = true_values(data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FitWarning)
            if spread:
                s1 = s2 = "spread"
            else:
                s1 = {k: truth[k] * f for k, f in zip(default_geometry(load_core(mat))[0], (0.8, 1.2, 1.1))}
                s2 = {k: truth[k] * 1.5 for k in default_heat_names(load_core(mat))}
            ch = characterize(data, mat, start1=s1, start2=s2, settings=settings)
        obj = {"generator": MARK, **ch.to_json()}
        obj["figures"] = [str(p) for p in write_figures(ch, out / f"fit_{mat}", label=mat)]
        write_json(out / f"fit_{mat}.json", obj)
        ent = {"rms_error": obj["rms_error"], "converged": obj["converged"], "step1": {}, "step2": {}}
        for k, v in obj["parameters"].items():
            ent["step1"][k] = {"value": v["value"], "std": v["std"], "true": truth.get(k)}
            rows.append((mat, "0", k, v["value"], v["std"], truth.get(k)))
        for e in obj["step2"]:
            for k, v in e["parameters"].items():
                ent["step2"].setdefault(k, []).append(
                    {"Q_W": e["heat_input_W"], "value": v["value"], "std": v["std"], "true": truth.get(k)}
                )
        for k in ch.heat_names:
            # one row per h: the fit at the largest Q (best determined)
            e = obj["step2"][-1]
            rows.append(
                (mat, f"{e['heat_input_W']:g}", k, e["parameters"][k]["value"], e["parameters"][k]["std"], truth.get(k))
            )
        summary["materials"][mat] = ent
    write_json(out / "fit_summary.json", summary)
    if not quiet:
        print(f"{'material':<10} {'Q [W]':>6} {'parameter':<20} {'fitted':>11} {'std':>9} {'true':>11} {'z':>6}")
        for mat, q, k, v, s, t in rows:
            z = (v - t) / s if (t is not None and s and math.isfinite(s)) else float("nan")
            print(f"{mat:<10} {q:>6} {k:<20} {v:11.4g} {s:9.2g} {t if t is not None else float('nan'):11.4g} {z:6.2f}")
    return summary


def demo_onset(path: Path, device=None, quiet=False) -> dict:
    """One onset prediction: the bundled ``standing_wave`` engine (the ceramic core in a
    closed-closed resonator); writes the JSON ``path`` and prints Q_onset, f_onset, T_hot."""
    from ..model.onset import onset
    from ..model.resonator import load_engine

    res = onset(load_engine("standing_wave"), Q_max=100.0, n_bracket=9, curve=True, device=device)
    summary = {
        "generator": MARK,
        "engine": "standing_wave",
        "Q_onset_W": res.Q_onset[0],
        "f_onset_Hz": res.f_onset[0],
        "T_hot_K": res.T_hot[0],
        "Q_grid_W": res.Q_grid,
        "growth_rate_1_per_s": res.omega_grid[0].imag,
    }
    write_json(path, summary)
    if not quiet:
        print(
            f"\nonset of the standing-wave engine (ceramic core, closed-closed resonator): Q_onset "
            f"{res.Q_onset[0]:.2f} W, f_onset {res.f_onset[0]:.1f} Hz, T_hot {res.T_hot[0]:.0f} K"
        )
    return summary
