"""The ``tawarp`` command line (docs/formats.md, "Command line").

Every subcommand has ``--help``, ``--device cpu|cuda|cuda:N`` (default: a GPU if there
is one), ``--quiet`` and ``--verbose`` (Warp's own banner and module-load lines, silent
otherwise); outputs are machine readable (CSV/JSON/netCDF) with figures beside them.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import sys
import time
from pathlib import Path

import numpy as np

from ..io import CLAIM_HELP, claim_outputs
from ..model.core import bundled_cores
from .common import _common, _say, init_warp, interrupts_honoured, parse_list
from .design import add_design_parser, add_rank_parser, add_sweep_parser
from .fit import add_fit_parser
from .loop import add_loop_parser
from .measure import add_measure_parser
from .onset import add_onset_parser
from .synth import add_synth_parser


# -- forward -----------------------------------------------------------------------------
def cmd_forward(args) -> int:
    from ..model.core import load_core
    from ..model.forward import transfer_matrices
    from ..measure.files import TMatrixData, write_tmatrix_csv
    from ..plots import plot_coefficients, plot_temperature

    stem = Path(args.output).with_suffix("")
    if not args.no_plots:
        claim_outputs(f"{stem}_coefficients.png", f"{stem}_temperature.png", why="a figure")
    core = load_core(args.core)
    Q = args.Q
    res = transfer_matrices(
        core, args.freqs, heat_input=Q, cells=args.cells, device=args.device, progress=not args.quiet
    )
    m = len(args.freqs)
    data = TMatrixData(
        np.repeat(Q, m),
        np.tile(args.freqs, len(Q)),
        res.T.reshape(-1, 2, 2),
        # the core as the user named it: a bundled name stays one, not this installation's path
        metadata={
            "core": args.core,
            "generator": "tawarp forward",
            "cells": "adaptive" if args.cells is None else str(args.cells),
        },
        source=str(args.output),
    )
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    write_tmatrix_csv(args.output, data)
    Y = res.dimensionless()
    if not args.no_plots:
        plot_coefficients(
            args.freqs,
            {f"Q = {q:g} W": Y[k] for k, q in enumerate(Q)},
            f"{stem}_coefficients.png",
            title=f"{Path(core.source).name}: dimensionless T-matrix",
        )
        x = np.linspace(0, core.positions()[-1], 400)
        T, _ = res.temperature(x)
        plot_temperature(
            x,
            {f"Q = {q:g} W": T[k] for k, q in enumerate(Q)},
            f"{stem}_temperature.png",
            planes=core.positions(),
            title=f"{Path(core.source).name}: temperature",
        )
    _say(args, f"wrote {args.output} ({len(Q)} heat inputs x {m} frequencies)")
    return 0


# -- demo --------------------------------------------------------------------------------
def cmd_demo(args) -> int:
    from .demo import run_demo

    return run_demo(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tawarp", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"tawarp {importlib.metadata.version('tawarp')}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = _common(sub.add_parser("demo", help="the main job on the bundled paper-like data, end to end"))
    p.add_argument("-o", "--output", default="tawarp-demo", help="output folder (default: %(default)s)" + CLAIM_HELP)
    p.set_defaults(func=cmd_demo)

    p = _common(sub.add_parser("forward", help="T-matrices of a core (CSV as the measurement format) and plots"))
    p.add_argument("core", help=f"core TOML file, or a bundled core: {', '.join(bundled_cores())}")
    p.add_argument(
        "--freqs", type=parse_list, default="30:500:100", help="Hz, list or start:stop:count (default: %(default)s)"
    )
    p.add_argument(
        "--Q", type=parse_list, default="0", help="heat inputs [W], list or start:stop:count (default: %(default)s)"
    )
    p.add_argument("--cells", type=int, default=None, help="fixed Magnus cells per thermal segment (default: adaptive)")
    p.add_argument(
        "-o",
        "--output",
        default="T.csv",
        help="output CSV (default: %(default)s); figures STEM_coefficients.png and STEM_temperature.png "
        "beside it" + CLAIM_HELP,
    )
    p.add_argument("--no-plots", action="store_true", help="skip the figures")
    p.set_defaults(func=cmd_forward)

    add_fit_parser(sub)
    add_synth_parser(sub)
    add_design_parser(sub)
    add_rank_parser(sub)
    add_sweep_parser(sub)
    add_loop_parser(sub)
    add_onset_parser(sub)
    add_measure_parser(sub)
    return parser


def error_text(e: Exception) -> str:
    """One line for an error: an OSError without its ``[Errno N]`` prefix (its text names
    the file), a KeyError without its quotes."""
    if isinstance(e, OSError) and e.strerror:
        return f"{e.filename}: {e.strerror}" if e.filename else e.strerror
    if isinstance(e, KeyError) and e.args:
        return str(e.args[0])
    return str(e)


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand; bad input, a missing device or an interruption end with a
    one-line message on stderr and exit code 2 (130 when interrupted), never a traceback."""
    parser = build_parser()
    args = parser.parse_args(argv)
    from ..measure.files import MeasurementError
    from ..model.core import CoreError
    from ..model.forward import resolve_device

    t0 = time.perf_counter()
    try:
        with interrupts_honoured():
            init_warp(args.verbose, args.quiet)
            if args.device is not None:
                resolve_device(args.device)
            rc = args.func(args)
    except (CoreError, MeasurementError, OSError, KeyError, ValueError) as e:
        print(f"tawarp {args.command}: error: {error_text(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(
            f"tawarp {args.command}: interrupted; finished outputs are complete, none is half-written", file=sys.stderr
        )
        return 130
    _say(args, f"done in {time.perf_counter() - t0:.1f} s")
    return rc


if __name__ == "__main__":
    sys.exit(main())
