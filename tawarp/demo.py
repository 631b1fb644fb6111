"""``tawarp demo``: the main job on the bundled paper-like cores, end to end."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .core import bundled_cores, load_core
from .forward import DEFAULT_CELL_DENSITY, transfer_matrices
from .measurements import TMatrixData, write_tmatrix_csv
from .plots import plot_coefficients, plot_temperature

#: Heat inputs of the demo [W]; the RVC foam stops at 18 W as in the paper (combustion risk).
DEMO_HEAT = {"rvc_foam": [0.0, 9.0, 18.0]}
DEFAULT_HEAT = [0.0, 20.0, 40.0, 80.0]


def run_demo(args) -> int:
    from .cli import write_json

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    freqs = np.linspace(30.0, 500.0, 48)
    summary = {}
    rows = []
    for name in bundled_cores():
        core = load_core(name)
        Q = DEMO_HEAT.get(name, DEFAULT_HEAT)
        res = transfer_matrices(core, freqs, heat_input=Q, device=args.device, progress=not args.quiet)
        write_tmatrix_csv(out / f"{name}_T.csv", TMatrixData(np.repeat(Q, len(freqs)), np.tile(freqs, len(Q)),
                                                             res.T.reshape(-1, 2, 2), metadata={"core": name},
                                                             source=str(out / f"{name}_T.csv")))
        Y = res.dimensionless()
        plot_coefficients(freqs, {f"Q = {q:g} W": Y[k] for k, q in enumerate(Q)}, out / f"{name}_coefficients.png",
                          title=f"{name}: dimensionless T-matrix")
        x = np.linspace(0, core.positions()[-1], 400)
        T, _ = res.temperature(x)
        plot_temperature(x, {f"Q = {q:g} W": T[k] for k, q in enumerate(Q)}, out / f"{name}_temperature.png",
                         planes=core.positions(), title=f"{name}: steady temperature")
        det = np.linalg.det(res.T)
        summary[name] = {"heat_input_W": Q, "T_max_K": T.max(axis=1),
                         "det_T_minus_1_max": np.abs(det - 1).max(axis=1)}
        for k, q in enumerate(Q):
            rows.append((name, q, T[k].max(), np.abs(det[k] - 1).max()))
    write_json(out / "summary.json", {"cell_density": DEFAULT_CELL_DENSITY, "freqs_Hz": freqs, "cores": summary})
    if not args.quiet:
        print(f"{'core':<10} {'Q [W]':>6} {'T_max [K]':>10} {'max|det T - 1|':>15}")
        for name, q, tmax, d in rows:
            print(f"{name:<10} {q:6.1f} {tmax:10.1f} {d:15.3e}")
    from .characterize import demo_fit

    demo_fit(out / "fit", device=args.device, quiet=args.quiet)
    demo_loop(out / "loop", device=args.device, quiet=args.quiet)
    if not args.quiet:
        print(f"outputs in {out}/")
    return 0


#: Bundled measurement with an effect the paper's model lacks (studies/make_demo_data.py).
DEMO_MEASUREMENT = "ceramic_hidden_effect.csv"


def demo_loop(out: Path, device=None, quiet=False) -> dict:
    """Close the loop on the bundled measurement: fit, diagnose, choose an effect, and
    print the error and the parameters before and after, with the drift of h with Q."""
    from importlib import resources

    from .forward import ForwardSettings
    from .loop import TMatrixProblem, default_base_params, run_loop, write_report
    from .measurements import read_tmatrix_csv

    data = read_tmatrix_csv(resources.files("tawarp") / "data" / "measured" / DEMO_MEASUREMENT)
    problem = TMatrixProblem(data, load_core("ceramic"), ForwardSettings(device=device))
    report = write_report(problem, run_loop(problem, default_base_params(problem)), out)
    if not quiet:
        print(f"\nclosing the loop on {DEMO_MEASUREMENT} (ceramic core, Q = {data.heat_inputs.tolist()} W):")
        print(f"  error before {report['error_before']:.3e}, after {report['error_after']:.3e} "
              f"(noise floor {report['noise_floor']:.3e}); chosen effect: {report['chosen_effect']}")
        before, after = report["parameters_before"], report["parameters_after"]
        print(f"  {'parameter':<30} {'before':>22} {'after':>22}")
        for name in after:
            b = f"{before[name]['value']:.5g} +- {before[name]['std']:.2g}" if name in before else "-"
            a = f"{after[name]['value']:.5g} +- {after[name]['std']:.2g}"
            print(f"  {name:<30} {b:>22} {a:>22}")
        for tag in ("before", "after"):
            drift = report.get(f"drift_{tag}")
            if drift:
                spread = ", ".join(f"{k} {v:.1%}" for k, v in drift["relative_spread"].items())
                print(f"  spread of h refitted per Q, {tag}: {spread}")
        print(f"  report: {out / 'report.md'}")
    return report
