"""``tawarp fit``: estimate parameters from a measurement of any registered kind
(T-matrix, scattering, surface impedance: :mod:`tawarp.measure`)."""

from __future__ import annotations

import warnings
from pathlib import Path

from ..fit.characterize import characterize, figure_paths, fit_each_heat_input, write_figures
from ..fit.estimate import FitWarning
from ..fit.problems import fit_kind
from ..io import CLAIM_HELP, GENERATOR, claim_outputs, write_json
from ..measure import ImpedanceKind, MeasurementKind, TMatrixKind
from ..model.core import CoreError
from ..model.forward import ForwardSettings
from ..model.layer import LAYER_BASE
from .common import _common, add_measurement_options, check_option, load_data

#: The mark of fit.json (:func:`tawarp.io.written_by_tawarp`), as the loop's and the demo's JSON carry theirs.
MARK = f"{GENERATOR} fit"


def add_fit_parser(subparsers):
    """Register ``tawarp fit DATA.csv --core CORE.toml [--fit a,b,c] -o fit.json``."""

    p = _common(
        subparsers.add_parser(
            "fit",
            help="estimate parameters from a measurement: T-matrices (the paper's two-step procedure by default), "
            "a scattering matrix or a surface impedance",
        )
    )
    p.add_argument("data", help="measured T-matrix, scattering-matrix or surface-impedance CSV (docs/formats.md)")
    p.add_argument(
        "--core",
        default=None,
        help="core TOML or bundled core name for T-matrix and scattering data (default: the data's "
        "'# core = ...' metadata); for surface impedance a passive core of one porous segment "
        "gives the layer's start values (default: a typical foam), its parameters named layer.*",
    )
    p.add_argument(
        "--fit",
        default=None,
        help="comma list of parameters: fitted at every heat input instead of the two-step procedure "
        "(T-matrices), or the layer's parameters (default porosity, pore radius, tortuosity)",
    )
    add_measurement_options(p)
    p.add_argument(
        "-o",
        "--output",
        default="fit.json",
        help="output JSON (default: %(default)s); figures STEM_step1.png, STEM_step2.png, STEM_h.png and "
        "STEM_temperature.png beside it" + CLAIM_HELP,
    )
    p.add_argument(
        "--start",
        default="core",
        choices=("core", "spread"),
        help="start values: the core's ('core', default) or a Sobol spread of starts ('spread')",
    )
    p.add_argument("--restarts", type=int, default=2, help="restarts from the solution ±20%% (default: %(default)s)")
    p.add_argument("--damping", default="nielsen", choices=("nielsen", "paper"), help="LM damping rule")
    p.add_argument(
        "--cells",
        type=int,
        default=None,
        help="fixed Magnus cells per thermal segment (default: sized by the adaptive rule, fixed per fit)",
    )
    p.add_argument("--no-bias-correction", action="store_true", help="step 2 on the raw data (skip Eqs. 22-23)")
    p.add_argument("--no-sigma", action="store_true", help="ignore sigma_* columns (unit weights)")
    p.add_argument("--no-plots", action="store_true", help="skip the figures")
    p.set_defaults(func=cmd_fit)
    return p


def cmd_fit(args) -> int:
    check_option(args.restarts >= 0, "--restarts", args.restarts, "expected a number of restarts >= 0")
    settings = ForwardSettings(cells=args.cells, device=args.device)
    kind = load_data(args, settings)
    names = [s.strip() for s in args.fit.split(",") if s.strip()] if args.fit else None
    check_fit_names(kind, names)
    if args.no_sigma and kind.has_sigma:
        kind.w, kind.has_sigma = kind.unit_weights(), False
    data, core = getattr(kind, "data", None), kind.core
    start = "spread" if args.start == "spread" else None
    out = Path(args.output)
    two_step = isinstance(kind, TMatrixKind) and core.thermal_indices and not names  # the one with figures
    if two_step and not args.no_plots:
        claim_outputs(*figure_paths(out.with_suffix("")), why="a figure of the fit")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FitWarning)  # reported in fit.json and printed below
        if not isinstance(kind, TMatrixKind) or not core.thermal_indices:  # other kinds, passive cores
            for option, value, default in (("--start", args.start, "core"), ("--damping", args.damping, "nielsen")):
                if value != default:
                    raise CoreError(
                        f"{option} {value}: applies to T-matrix data of a thermoacoustic core; "
                        f"{kind.name} data on core {core.source} take the kind fit from the core's values"
                    )
            res = fit_kind(kind, names)
            obj = {
                "kind": kind.name,
                "source": str(args.data),
                "core": str(core.source),
                "fits": [{**res.problem(0), "heat_input_W": None}],
            }
        elif names:
            obj = fit_each_heat_input(
                data,
                core,
                names,
                settings=settings,
                start=start,
                restarts=args.restarts,
                damping=args.damping,
                use_sigma=not args.no_sigma,
                progress=not args.quiet,
            )
        else:
            ch = characterize(
                data,
                core,
                start1=start,
                start2=start,
                restarts=args.restarts,
                damping=args.damping,
                bias_correction=not args.no_bias_correction,
                use_sigma=not args.no_sigma,
                settings=settings,
                progress=not args.quiet,
            )
            obj = ch.to_json()
            if not args.no_plots:
                obj["figures"] = [str(p) for p in write_figures(ch, out.with_suffix(""))]
    calibration = {k: v for k, v in getattr(data, "metadata", {}).items() if k.startswith("empty_tube")}
    if calibration:
        obj["empty_tube"] = calibration
    write_json(out, {"generator": MARK, **obj})
    if not args.quiet:
        print(summary_text(obj))
        for w in obj.get("warnings", []):
            print(f"warning: {w}")
        print(f"wrote {out}")
    return 0


def check_fit_names(kind: MeasurementKind, names) -> None:
    """Refuse a ``--fit`` name the kind's model does not have, naming it and the choices."""
    if names is None:
        return
    fixed = {"layer.length"} if isinstance(kind, ImpedanceKind) else set()  # the file's thickness
    allowed = [n for n in kind.core.parameter_names() if n not in fixed]
    for name in names:
        if name not in allowed:
            why = "the layer thickness is the file's" if name in fixed else "unknown parameter"
            hint = (
                f"e.g. {', '.join(LAYER_BASE)}" if isinstance(kind, ImpedanceKind) else f"one of {', '.join(allowed)}"
            )
            raise CoreError(f"--fit {name}: {why} for {kind.name} data on core {kind.core.source}; {hint}")


def summary_text(obj: dict) -> str:
    """A short table of a fit.json structure."""
    lines = []
    entries = [("Q = 0 W", obj["step1"])] if "step1" in obj else []
    entries += [(f"Q = {e['heat_input_W']:g} W", e) for e in obj.get("step2", [])]
    entries += [
        (f"Q = {e['heat_input_W']:g} W" if e["heat_input_W"] is not None else obj.get("kind", ""), e)
        for e in obj.get("fits", [])
    ]
    for label, e in entries:
        pars = "  ".join(
            f"{k} = {v['value']:.4g} ± " + (f"{v['std']:.2g}" if v["std"] is not None else "undetermined")
            for k, v in e["parameters"].items()
        )
        lines.append(
            f"{label:>11}  {pars}  (rms {e['rms_error']:.2e}, {e['iterations']} it, "
            f"{'ok' if e['converged'] else e['reason']})"
        )
        gof = e.get("goodness_of_fit") or {}
        if gof.get("adequate") is False:
            why = [
                f"reduced chi^2 = {gof['reduced_chi2']:.3g} (p = {gof['chi2_p_value']:.2g})"
                if gof.get("reduced_chi2") is not None
                else "",
                f"at a bound: {', '.join(gof['parameters_at_bounds'])}" if gof["parameters_at_bounds"] else "",
            ]
            lines.append(
                f"{'':>11}  INADEQUATE FIT: {'; '.join(w for w in why if w)}: the model does not describe "
                f"these data within their noise"
            )
    return "\n".join(lines)
