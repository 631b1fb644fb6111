"""``tawarp synth``: paper-like synthetic T-matrix measurements, or four-microphone
scattering measurements (and the empty tube's) of any core."""

from __future__ import annotations

import cmath
import math
from pathlib import Path

from ..measure.files import write_scattering_csv, write_tmatrix_csv
from ..measure.scattering import sample_length
from ..measure.synthetic import MATERIALS, make_paper_data, paper_frequencies, scattering_measurement
from ..model.core import load_core
from ..model.forward import transfer_matrices
from .common import _common, check_seed, parse_list


def add_synth_parser(subparsers):
    """Register ``tawarp synth MATERIAL -o data.csv --noise 0.005 --seed 0`` and
    ``tawarp synth CORE --scattering X_UP,X_DOWN -o S.csv``."""

    p = _common(
        subparsers.add_parser(
            "synth",
            help="paper-like synthetic T-matrix measurements of one of the four materials, or scattering "
            "measurements of any core (--scattering)",
        )
    )
    p.add_argument(
        "material",
        help=f"which material of the paper ({', '.join(MATERIALS)}); with --scattering any "
        "core (TOML or bundled name, e.g. foam_sample)",
    )
    p.add_argument("-o", "--output", default=None, help="output CSV (default: MATERIAL_synthetic.csv)")
    p.add_argument(
        "--noise",
        type=float,
        default=0.005,
        help="relative complex noise of the T-matrix coefficients; with --scattering the absolute "
        "complex noise of each S entry (default: %(default)s)",
    )
    p.add_argument(
        "--bias",
        type=float,
        default=None,
        help="systematic bias size b: factors 1 + b exp(i phase) per coefficient (default: none)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default: %(default)s)")
    p.add_argument("--freqs", type=parse_list, default=None, help="Hz, list or start:stop:count (default: the paper's)")
    p.add_argument(
        "--Q",
        type=parse_list,
        default=None,
        help="heat inputs [W] (default: the paper's; with --scattering one value, default 0)",
    )
    p.add_argument("--cells", type=int, default=48, help="Magnus cells of the generating model (default: %(default)s)")
    p.add_argument("--no-sigma", action="store_true", help="do not write sigma_* columns")
    p.add_argument(
        "--scattering",
        type=parse_list,
        default=None,
        metavar="X_UP,X_DOWN",
        help="write a four-microphone scattering CSV with reference planes at these signed positions "
        "[m] (from faces x1 and x6, positive downstream) and the empty tube's beside it "
        "(S.csv: S_empty.csv; docs/formats.md; write --scattering=-0.05,0.04 when X_UP is negative)",
    )
    p.add_argument(
        "--mic-gain",
        type=parse_list,
        default=None,
        metavar="ABS,PHASE_DEG",
        help="with --scattering: a calibration error, the downstream microphones' gain and phase (default: none)",
    )
    p.set_defaults(func=cmd_synth)
    return p


def cmd_synth(args) -> int:
    check_seed(args)
    if args.scattering is not None:
        return synth_scattering(args)
    if args.material not in MATERIALS:
        raise ValueError(f"{args.material!r}: expected one of {', '.join(MATERIALS)} (any core with --scattering)")
    data = make_paper_data(
        args.material,
        noise=args.noise,
        bias=args.bias,
        seed=args.seed,
        freqs=args.freqs,
        heat_inputs=args.Q,
        cells=args.cells,
        write_sigma=not args.no_sigma,
        device=args.device,
    )
    out = Path(args.output or f"{args.material}_synthetic.csv")
    out.parent.mkdir(parents=True, exist_ok=True)
    write_tmatrix_csv(out, data)
    if not args.quiet:
        print(
            f"wrote {out} ({data.heat_inputs.size} heat inputs x {data.frequencies.size} frequencies, "
            f"noise {args.noise:g}, seed {args.seed})"
        )
    return 0


def synth_scattering(args) -> int:
    """Scattering CSVs of the sample and of the empty tube (:func:`scattering_measurement`)
    from the forward model of the core ``args.material`` at its T_cold and p_mean."""
    if args.scattering.size != 2:
        raise ValueError("--scattering: expected two signed plane positions X_UP,X_DOWN [m]")
    Q = [0.0] if args.Q is None else args.Q.tolist()
    if len(Q) != 1:
        raise ValueError("--Q: a scattering file holds one heat input; give one value")
    if args.bias is not None:
        raise ValueError("--bias applies to T-matrix files; --mic-gain is the scattering rig's error")
    gain = None
    if args.mic_gain is not None:
        if args.mic_gain.size != 2:
            raise ValueError("--mic-gain: expected ABS,PHASE_DEG")
        gain = cmath.rect(float(args.mic_gain[0]), math.radians(float(args.mic_gain[1])))
    core = load_core(args.material)
    freqs = paper_frequencies(args.material) if args.freqs is None else args.freqs
    T = transfer_matrices(core, freqs, Q, cells=args.cells, device=args.device).T[0]
    out = Path(args.output or f"{Path(args.material).stem}_scattering.csv")
    empty_out = out.with_name(f"{out.stem}_empty{out.suffix}")
    sample, empty = scattering_measurement(
        T,
        freqs,
        tube_radius=core.radius,
        plane_upstream=float(args.scattering[0]),
        plane_downstream=float(args.scattering[1]),
        length=sample_length(core),
        T_ambient=core.gas.T_cold,
        p_ambient=core.gas.p_mean,
        gas=core.gas.name,
        gain=gain,
        noise=args.noise,
        seed=args.seed,
        write_sigma=not args.no_sigma,
        heat_input=Q[0],
        source=str(out),
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"core": args.material}
    write_scattering_csv(out, sample, meta)
    write_scattering_csv(empty_out, empty, meta)
    if not args.quiet:
        print(
            f"wrote {out} and {empty_out} ({len(freqs)} frequencies, Q = {Q[0]:g} W, noise {args.noise:g}, "
            f"seed {args.seed})"
        )
    return 0
