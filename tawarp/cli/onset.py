"""``tawarp onset ENGINE.toml``: onset heat input (or hot temperature), frequency and hot
temperature of engines."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np

from ..io import write_json
from .common import _common, _say, check_network_options, check_onset_search, check_option, parse_vars


def add_onset_parser(sub) -> None:
    """Register ``tawarp onset`` on an argparse sub-parsers object."""
    from ..model.core import bundled

    p = _common(
        sub.add_parser(
            "onset",
            help="onset heat input, frequency and hot temperature of an engine "
            "(complex eigenfrequency against heat input)",
        )
    )
    p.add_argument(
        "engine",
        help="engine TOML (a core file with an [engine] table, or a network with [[branch]] tables), "
        f"or a bundled engine: {', '.join(bundled('engines'))}",
    )
    p.add_argument(
        "--f-max", type=float, default=None, help="network: highest frequency searched for modes at T_cold [Hz]"
    )
    p.add_argument(
        "--amplitude", type=float, default=1e4, help="network: |p| [Pa] of the profiles at onset (default: %(default)s)"
    )
    p.add_argument(
        "--in",
        dest="search",
        choices=("heat_input", "T_hot"),
        default="heat_input",
        help="search the onset in the heat input, or in the hot temperature T_hot/T_cold of an engine "
        "whose temperatures are imposed (T_start, T_end on its segments) (default: %(default)s)",
    )
    p.add_argument("--Q-max", type=float, default=100.0, help="largest heat input searched [W] (default: %(default)s)")
    p.add_argument(
        "--T-ratio-max",
        type=float,
        default=4.0,
        help="largest T_hot/T_cold searched with --in T_hot, or for a network (default: %(default)s)",
    )
    p.add_argument("--mode", type=int, default=1, help="mode number, 1 = fundamental (default: %(default)s)")
    p.add_argument(
        "--bracket",
        type=int,
        default=21,
        help="points of the searched range (heat input on [0, Q-max], or T_hot/T_cold on [1, T-ratio-max], "
        "always so for a network) for the bracket and the growth-rate curve (default: %(default)s)",
    )
    p.add_argument(
        "--var",
        action="append",
        default=[],
        help="NAME=LIST: a parameter varied over a batch (SEGMENT.FIELD or engine.left_duct, "
        "engine.right_duct, ...); LIST is v1,v2 or start:stop:count; several --var form a grid",
    )
    p.add_argument("--cells", type=int, default=None, help="fixed Magnus cells per thermal segment (default adaptive)")
    p.add_argument("-o", "--output", default="tawarp-onset", help="output folder (default: %(default)s)")
    p.add_argument("--no-plots", action="store_true", help="skip the figures (growth_rate.png, root_locus.png)")
    p.set_defaults(func=cmd_onset)


def _finite(x: float):
    return float(x) if math.isfinite(x) else None


def _check_options(args) -> None:
    """Refuse impossible values of the numeric options, naming the option, before anything
    is read or written; whether or not the engine uses an option: no engine can use them."""
    check_option(args.mode >= 1, "--mode", args.mode, "expected a mode number >= 1 (1: the fundamental)")
    check_onset_search(args)
    check_network_options(args)


def cmd_onset(args) -> int:
    from ..model.core import read_toml
    from ..model.network import is_network_file
    from ..model.onset import onset
    from ..model.resonator import load_engine

    _check_options(args)
    if is_network_file(read_toml(args.engine, "engines")[1]):
        from .network import cmd_network_onset

        return cmd_network_onset(args)
    engine = load_engine(args.engine)
    axes = parse_vars(args.var)
    names = list(axes)
    combos = list(itertools.product(*axes.values())) if names else [()]
    params = {k: np.array([c[j] for c in combos]) for j, k in enumerate(names)}
    by_heat = args.search == "heat_input"
    bound = {"Q_max": args.Q_max} if by_heat else {"T_ratio_max": args.T_ratio_max}
    res = onset(
        engine,
        mode=args.mode,
        params=params,
        n_bracket=args.bracket,
        curve=True,
        cells=args.cells,
        device=args.device,
        **bound,
    )
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    sets = []
    first = f"{'Q_onset [W]':>14s}" if by_heat else f"{'T_hot/T_cold':>14s}"
    head = "".join(f"{k:>22s}" for k in names) + f"{first}{'f_onset [Hz]':>14s}{'T_hot [K]':>12s}"
    _say(args, head)
    for i, c in enumerate(combos):
        row = {
            "params": dict(zip(names, map(float, c))),
            "Q_onset_W": _finite(res.Q_onset[i]),
            "T_ratio_onset": _finite(res.ratio_onset[i]),
            "f_onset_Hz": _finite(res.f_onset[i]),
            "T_hot_K": _finite(res.T_hot[i]),
            "growth_rate_1_per_s": res.omega_grid[i].imag,
            "frequency_Hz": res.omega_grid[i].real / (2 * math.pi),
        }
        sets.append(row)
        onset_at = res.Q_onset[i] if by_heat else res.ratio_onset[i]
        _say(args, "".join(f"{v:22.6g}" for v in c) + f"{onset_at:14.6g}{res.f_onset[i]:14.6g}{res.T_hot[i]:12.6g}")
    grid = (
        {"Q_max_W": args.Q_max, "Q_grid_W": res.grid}
        if by_heat
        else {"T_ratio_max": args.T_ratio_max, "T_ratio_grid": res.grid}
    )
    write_json(
        out / "onset.json",
        {
            "engine": str(engine.source),
            "mode": args.mode,
            "searched": res.searched,
            **grid,
            "convention": "exp(-i omega t); growth_rate = Im omega > 0 grows; an onset null: none on the range",
            "sets": sets,
        },
    )
    if not args.no_plots:
        title = Path(str(engine.source)).stem
        _plot_growth(res, combos, names, out / "growth_rate.png", title)
        _plot_root_locus(res, combos, names, out / "root_locus.png", title)
    _say(args, f"wrote {out / 'onset.json'}")
    return 0


def _plot_growth(res, combos, names, path, title):
    import matplotlib.pyplot as plt

    from ..plots import save

    fig, ax = plt.subplots(figsize=(7, 4))
    for i, c in enumerate(combos):
        label = ", ".join(f"{k} = {v:g}" for k, v in zip(names, c)) or None
        ax.plot(res.grid, res.omega_grid[i].imag, "-o", ms=3, label=label)
        at = res.Q_onset[i] if res.searched == "heat_input" else res.ratio_onset[i]
        if math.isfinite(at):
            ax.plot([at], [0.0], "kx")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xlabel(_axis(res))
    ax.set_ylabel("growth rate Im omega [1/s]")
    ax.set_title(f"{title}: growth rate (x: onset)")
    if names and len(combos) <= 12:
        ax.legend(fontsize=7)
    save(fig, path)


def _plot_root_locus(res, combos, names, path, title):
    """Eigenfrequency in the complex plane (Re f [Hz], growth rate Im omega [1/s]) as the
    heat input goes from 0 to Q_max, points coloured by Q; the onset where a locus crosses
    the real axis (or as T_hot/T_cold rises, for a search in the hot temperature)."""
    import matplotlib.pyplot as plt

    from ..plots import save

    fig, ax = plt.subplots(figsize=(7, 4.5))
    f = res.omega_grid.real / (2 * math.pi)
    sc = None
    for i, c in enumerate(combos):
        label = ", ".join(f"{k} = {v:g}" for k, v in zip(names, c)) or None
        ax.plot(f[i], res.omega_grid[i].imag, "-", color=f"C{i % 10}", lw=1.0, label=label, zorder=1)
        sc = ax.scatter(f[i], res.omega_grid[i].imag, c=res.grid, cmap="viridis", s=14, zorder=2)
        if math.isfinite(res.Q_onset[i]):
            ax.plot([res.f_onset[i]], [0.0], "kx", ms=8, zorder=3)
    ax.axhline(0.0, color="k", lw=0.6)
    fig.colorbar(sc, ax=ax, label=_axis(res))
    ax.set_xlabel("frequency Re omega / 2 pi [Hz]")
    ax.set_ylabel("growth rate Im omega [1/s] (> 0 grows)")
    ax.set_title(f"{title}: root locus as {'Q' if res.searched == 'heat_input' else 'T_hot'} rises (x: onset)")
    if names and len(combos) <= 12:
        ax.legend(fontsize=7)
    save(fig, path)


def _axis(res) -> str:
    return "heat input Q [W]" if res.searched == "heat_input" else "hot temperature T_hot / T_cold"
