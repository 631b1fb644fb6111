"""``tawarp synth``: paper-like synthetic T-matrix measurements."""

from __future__ import annotations

from pathlib import Path

from ..measure.files import write_tmatrix_csv
from ..measure.synthetic import MATERIALS, make_paper_data
from .common import _common, parse_list


def add_synth_parser(subparsers):
    """Register ``tawarp synth MATERIAL -o data.csv --noise 0.005 --seed 0``."""

    p = _common(subparsers.add_parser(
        "synth", help="paper-like synthetic T-matrix measurements of one of the four materials"))
    p.add_argument("material", choices=MATERIALS, help="which material of the paper")
    p.add_argument("-o", "--output", default=None, help="output CSV (default: MATERIAL_synthetic.csv)")
    p.add_argument("--noise", type=float, default=0.005, help="relative complex noise (default: %(default)s)")
    p.add_argument("--bias", type=float, default=None,
                   help="systematic bias size b: factors 1 + b exp(i phase) per coefficient (default: none)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: %(default)s)")
    p.add_argument("--freqs", type=parse_list, default=None, help="Hz, list or start:stop:count (default: the paper's)")
    p.add_argument("--Q", type=parse_list, default=None, help="heat inputs [W] (default: the paper's)")
    p.add_argument("--cells", type=int, default=48, help="Magnus cells of the generating model (default: %(default)s)")
    p.add_argument("--no-sigma", action="store_true", help="do not write sigma_* columns")
    p.set_defaults(func=cmd_synth)
    return p


def cmd_synth(args) -> int:
    data = make_paper_data(args.material, noise=args.noise, bias=args.bias, seed=args.seed, freqs=args.freqs,
                           heat_inputs=args.Q, cells=args.cells, write_sigma=not args.no_sigma, device=args.device)
    out = Path(args.output or f"{args.material}_synthetic.csv")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_tmatrix_csv(out, data)
    if not args.quiet:
        print(f"wrote {out} ({data.heat_inputs.size} heat inputs x {data.frequencies.size} frequencies, "
              f"noise {args.noise:g}, seed {args.seed})")
    return 0
