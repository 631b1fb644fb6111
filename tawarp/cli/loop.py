"""``tawarp loop``: close the loop on measured data."""

from __future__ import annotations

from pathlib import Path

from ..io import CLAIM_HELP, claim_outputs
from ..loop import default_base_params, impedance_loop, run_loop, write_report
from ..loop.report import OUTPUTS, drifting
from ..measure import atalla_panneton_samples, load_atalla_panneton
from ..model.forward import ForwardSettings
from .common import _common, add_measurement_options, load_data


def add_loop_parser(sub) -> None:
    """Register ``tawarp loop`` on an argparse sub-parsers object."""
    p = sub.add_parser("loop", help="close the loop: fit, diagnose the residual, choose an effect, report")
    p.add_argument(
        "data",
        help="T-matrix CSV (docs/formats.md), scattering-matrix CSV (freq_Hz,S11_re,...), "
        "surface impedance CSV (freq_Hz,Zs_re,Zs_im), "
        f"or atalla:NAME ({', '.join(sorted(atalla_panneton_samples()))}) for the bundled Atalla & Panneton data",
    )
    p.add_argument(
        "--core",
        default=None,
        help="core TOML (or bundled name) for T-matrix and scattering data "
        "(default: the file's '# core = ...' metadata); for surface impedance, a passive core "
        "of one porous segment whose values start the layer (as tawarp fit takes it)",
    )
    p.add_argument(
        "--fit",
        default=None,
        help="comma list of base parameters (default: the paper's full method: every "
        "porous segment's porosity, pore radius, tortuosity and every thermal "
        "segment's h, less the core file's [fit] pinned list; a layer's "
        "porosity, pore radius, tortuosity)",
    )
    p.add_argument("--cells", type=int, default=None, help="fixed Magnus cells per thermal segment (default adaptive)")
    p.add_argument(
        "-o",
        "--output",
        default="tawarp-loop",
        help="output folder (default: %(default)s): report.json, report.md and figures residuals.png, "
        "drift.png, next_measurement.png" + CLAIM_HELP,
    )
    _common(p)
    add_measurement_options(p)
    p.set_defaults(func=cmd_loop)


def cmd_loop(args) -> int:
    # before the fits, which take a while: a file of the user's there is never replaced
    claim_outputs(*(Path(args.output) / name for name in OUTPUTS), why="the loop's report")
    settings = ForwardSettings(device=args.device, cells=args.cells)
    names = [s.strip() for s in args.fit.split(",")] if args.fit else None
    if args.data.startswith("atalla:"):
        if args.core:
            raise ValueError("--core does not apply to atalla:NAME (layers use the circular-pore layer model)")
        name = args.data.split(":", 1)[1]
        data = load_atalla_panneton(name)
        ref = atalla_panneton_samples()[name]
        ref = {
            "phi": ref["phi"],
            "alpha_inf": ref["alpha_inf"],
            "Lambda": ref["Lambda"],
            "Lambda_prime": ref["Lambda_prime"],
            "sigma": ref["sigma"],
        }
        data = [d for d in data if d.thickness is not None]
        prob, rep = impedance_loop(data, ref, settings, names)
    else:
        prob = load_data(args, settings)
        rep = run_loop(prob, default_base_params(prob, names), progress=not args.quiet)
    js = write_report(prob, rep, args.output)
    if not args.quiet:
        print(
            f"verdict {js['verdict']}: error before {js['error_before']:.4g}, after {js['error_after']:.4g} "
            f"(noise floor {js['noise_floor']:.4g}); accepted: {'; '.join(js['accepted_steps']) or 'none'}; "
            + "".join(
                f"{k} drifts with the heat input (p {p:.2g}); " for k, p in drifting(js.get("drift_after")).items()
            )
            + f"wrote {Path(args.output) / 'report.json'}"
        )
    return 0
