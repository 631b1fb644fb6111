"""``tawarp measure``: microphone signals of an impedance tube to the measurement CSV."""

from __future__ import annotations

from pathlib import Path

from ..io import CLAIM_HELP
from .common import _common, _say


def add_measure_parser(sub) -> None:
    """Register ``tawarp measure`` on an argparse sub-parsers object."""
    from ..model.core import bundled
    from ..tube.setup import METHODS

    p = sub.add_parser(
        "measure",
        help="impedance-tube signals to a T-matrix or surface-impedance CSV with sigma columns",
        description="Read a measurement description (docs/formats.md, 'Measurement description'), its "
        "signal and calibration files, and write the measured T-matrix (E2611 methods) or surface "
        "impedance (ISO 10534-2) in the CSV format that fit and loop read, with a figure beside it.",
    )
    p.add_argument(
        "setup", help=f"measurement description TOML, or a bundled one by name ({', '.join(bundled('tube'))})"
    )
    p.add_argument(
        "--data",
        default=None,
        metavar="DIR",
        help="read each file the description names from DIR, by its file name (default: the names are "
        "relative to the description's folder)",
    )
    p.add_argument(
        "-o",
        "--output",
        default=None,
        help="output CSV (default: the description's name with .csv); the figure STEM_measure.png beside it"
        + CLAIM_HELP,
    )
    p.add_argument(
        "--method",
        choices=sorted(METHODS),
        default=None,
        help="check that the description's measurement.method is this one",
    )
    p.add_argument(
        "--no-self-calibration",
        action="store_true",
        help="keep the description's microphone positions, temperature and Kirchhoff's wall losses",
    )
    p.add_argument("--no-plots", action="store_true", help="skip the figure")
    _common(p)
    p.set_defaults(func=cmd_measure)


def cmd_measure(args) -> int:
    from ..tube.measure import measure, write_measurement

    out = Path(args.output) if args.output else Path(Path(args.setup).name).with_suffix(".csv")
    m = measure(
        args.setup,
        data_dir=args.data,
        method=args.method,
        self_calibration=False if args.no_self_calibration else None,
        progress=not args.quiet,
    )
    write_measurement(m, out, figure=not args.no_plots)
    _say(
        args,
        f"wrote {out} ({len(m.data)} frequencies, {m.setup.method}; {len(m.left_out)} ill-conditioned left out; "
        f"calibration: {m.summary['calibration']})",
    )
    return 0
