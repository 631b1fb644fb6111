"""``tawarp fit``: estimate parameters from measured T-matrices."""

from __future__ import annotations

import warnings
from pathlib import Path

from ..fit.characterize import characterize, fit_each_heat_input, write_figures
from ..fit.estimate import FitWarning
from ..io import write_json
from ..measure.files import read_tmatrix_csv
from ..model.core import load_core
from ..model.forward import ForwardSettings
from .common import _common


def add_fit_parser(subparsers):
    """Register ``tawarp fit DATA.csv --core CORE.toml [--fit a,b,c] -o fit.json``."""

    p = _common(subparsers.add_parser(
        "fit", help="estimate parameters from measured T-matrices (the paper's two-step procedure by default)"))
    p.add_argument("data", help="measured T-matrix CSV (FORMATS.md)")
    p.add_argument("--core", default=None,
                   help="core TOML or bundled core name (default: the data's '# core = ...' metadata)")
    p.add_argument("--fit", default=None,
                   help="comma list of parameters to fit at every heat input instead of the two-step procedure")
    p.add_argument("-o", "--output", default="fit.json", help="output JSON (default: %(default)s); figures beside it")
    p.add_argument("--start", default="core", choices=("core", "spread"),
                   help="start values: the core's ('core', default) or a Sobol spread of starts ('spread')")
    p.add_argument("--restarts", type=int, default=2, help="restarts from the solution ±20%% (default: %(default)s)")
    p.add_argument("--damping", default="nielsen", choices=("nielsen", "paper"), help="LM damping rule")
    p.add_argument("--cells", type=int, default=None,
                   help="fixed Magnus cells per thermal segment (default: sized by the adaptive rule, fixed per fit)")
    p.add_argument("--no-bias-correction", action="store_true", help="step 2 on the raw data (skip Eqs. 22-23)")
    p.add_argument("--no-sigma", action="store_true", help="ignore sigma_* columns (unit weights)")
    p.add_argument("--no-plots", action="store_true", help="skip the figures")
    p.set_defaults(func=cmd_fit)
    return p


def cmd_fit(args) -> int:
    from ..measure.files import read_tmatrix_csv

    data = read_tmatrix_csv(args.data)
    core_name = args.core or data.metadata.get("core")
    if core_name is None:
        raise ValueError(f"{args.data}: no --core given and no '# core = ...' metadata line")
    core = load_core(core_name)
    settings = ForwardSettings(cells=args.cells, device=args.device)
    start = "spread" if args.start == "spread" else None
    out = Path(args.output)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FitWarning)   # reported in fit.json and printed below
        if args.fit:
            names = [s.strip() for s in args.fit.split(",") if s.strip()]
            obj = fit_each_heat_input(data, core, names, settings=settings, start=start, restarts=args.restarts,
                                      damping=args.damping, use_sigma=not args.no_sigma, progress=not args.quiet)
        else:
            ch = characterize(data, core, start1=start, start2=start, restarts=args.restarts, damping=args.damping,
                              bias_correction=not args.no_bias_correction, use_sigma=not args.no_sigma,
                              settings=settings, progress=not args.quiet)
            obj = ch.to_json()
            if not args.no_plots:
                obj["figures"] = [str(p) for p in write_figures(ch, out.with_suffix(""))]
    write_json(out, obj)
    if not args.quiet:
        print(summary_text(obj))
        for w in obj.get("warnings", []):
            print(f"warning: {w}")
        print(f"wrote {out}")
    return 0


def summary_text(obj: dict) -> str:
    """A short table of a fit.json structure."""
    lines = []
    entries = [("Q = 0", obj["step1"])] if "step1" in obj else []
    entries += [(f"Q = {e['heat_input_W']:g}", e) for e in obj.get("step2", [])]
    entries += [(f"Q = {e['heat_input_W']:g}", e) for e in obj.get("fits", [])]
    for label, e in entries:
        pars = "  ".join(f"{k} = {v['value']:.4g} ± {v['std']:.2g}" for k, v in e["parameters"].items())
        lines.append(f"{label:>9} W  {pars}  (rms {e['rms_error']:.2e}, {e['iterations']} it, "
                     f"{'ok' if e['converged'] else e['reason']})")
    return "\n".join(lines)
