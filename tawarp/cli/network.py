"""``tawarp onset NETWORK.toml``: onset temperature ratio of an engine network, its mode
followed as T_hot rises, and the profiles along the network at onset (p, U, T, Edot, Htot)
with the figures DeltaEC users read."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..io import write_json, write_text
from .common import _say, parse_vars


def _finite(x: float):
    return float(x) if math.isfinite(x) else None


def _start(net, mode: int, f_max: float | None) -> complex:
    """Mode ``mode`` (1: the lowest) at T_hot = T_cold: the roots near the minima of |det| on
    the real axis up to ``f_max`` [Hz] (default: 4 lossless half-waves of the longest branch)."""
    from ..model.network_reference import real_axis_modes
    from ..reference import gas_properties

    if f_max is None:
        c = float(gas_properties(net.gas.name, net.gas.T_cold, net.gas.p_mean).c)
        f_max = 2.0 * c / max(br.length() for br in net.branches)
    modes = real_axis_modes(net, f_max / 400, f_max, 400, T_hot=net.gas.T_cold)
    if len(modes) < mode:
        raise ValueError(
            f"{net.source}: found {len(modes)} mode(s) below {f_max:g} Hz at T_hot = T_cold; raise --f-max"
        )
    return modes[mode - 1]


def cmd_network_onset(args) -> int:
    from ..model.network import load_network
    from ..model.network_reference import onset, profiles

    net = load_network(args.engine)
    T_max = args.T_ratio_max * net.gas.T_cold
    w0 = _start(net, args.mode, args.f_max)
    if not net.uses_T_hot():
        return _passive(args, net, w0)
    res = onset(net, w0, T_max=T_max, n=args.bracket)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    jumps = [
        {
            "T_before_K": j.T_before,
            "T_after_K": j.T_after,
            "f_before_Hz": j.omega_before.real / (2 * math.pi),
            "f_after_Hz": j.omega_after.real / (2 * math.pi),
        }
        for j in res.path.jumps
    ]
    doc = {
        "engine": str(net.source),
        "mode": args.mode,
        "T_cold_K": net.gas.T_cold,
        "T_onset_K": _finite(res.T_onset),
        "T_ratio": _finite(res.ratio),
        "f_onset_Hz": _finite(res.frequency),
        "path": {
            "T_hot_K": res.path.T,
            "frequency_Hz": res.path.omega.real / (2 * math.pi),
            "growth_rate_1_per_s": res.path.omega.imag,
        },
        "mode_jumps": jumps,
        "convention": "exp(-i omega t); growth_rate = Im omega > 0 grows; T_onset null: no onset up to T_max",
    }
    _say(args, f"{'T_onset [K]':>14s}{'T_hot/T_cold':>14s}{'f_onset [Hz]':>14s}")
    _say(args, f"{res.T_onset:14.6g}{res.ratio:14.6g}{res.frequency:14.6g}")
    for j in jumps:
        _say(args, f"mode jump between T_hot = {j['T_before_K']:.6g} K and {j['T_after_K']:.6g} K")
    if math.isfinite(res.T_onset):
        prof = profiles(net, res.omega, res.T_onset, amplitude=args.amplitude)
        doc["profiles_amplitude_Pa"] = args.amplitude
        write_text(out / "profiles.csv", _profiles_csv(prof, args.amplitude))
        if not args.no_plots:
            plot_profiles(
                prof, out / "profiles.png", f"{Path(str(net.source)).stem}: onset, |p| = {args.amplitude:g} Pa"
            )
    if args.var:
        doc["sets"] = _batched_sets(args, net, w0, T_max)
    write_json(out / "onset.json", doc)
    if not args.no_plots:
        _plot_locus(res, out / "root_locus.png", Path(str(net.source)).stem)
    _say(args, f"wrote {out / 'onset.json'}")
    return 0


def _passive(args, net, w0: complex) -> int:
    """A network that names no T_hot (a refrigerator, a resonator) has no onset to search:
    its mode ``--mode`` at the file's temperatures, and the profiles of that mode (powers
    evaluated with Re omega, :func:`tawarp.model.network_reference.profiles`)."""
    from ..model.network_reference import profiles

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    f, g = w0.real / (2 * math.pi), w0.imag
    _say(args, f"{net.source}: names no T_hot; mode {args.mode}: f = {f:.6g} Hz, growth rate Im omega = {g:.6g} 1/s")
    prof = profiles(net, w0, net.T_hot, amplitude=args.amplitude)
    write_text(out / "profiles.csv", _profiles_csv(prof, args.amplitude))
    if not args.no_plots:
        plot_profiles(prof, out / "profiles.png", f"{Path(str(net.source)).stem}: mode {args.mode}, {f:.4g} Hz")
    doc = {
        "engine": str(net.source),
        "mode": args.mode,
        "f_Hz": f,
        "growth_rate_1_per_s": g,
        "T_onset_K": None,
        "profiles_amplitude_Pa": args.amplitude,
        "convention": "exp(-i omega t); growth_rate = Im omega > 0 grows; no segment names T_hot: no onset search",
    }
    write_json(out / "onset.json", doc)
    _say(args, f"wrote {out / 'onset.json'}")
    return 0


def _batched_sets(args, net, w0: complex, T_max: float) -> list[dict]:
    """The onset of every design of the --var grid on the device, each design's mode followed
    from T_cold (the file's mode at T_cold as the start, the same grid of --bracket hot
    temperatures; :meth:`tawarp.model.network_batch.NetworkBatch.followed_onset`)."""
    import itertools

    from ..model.network_batch import NetworkBatch

    axes = parse_vars(args.var)
    names = list(axes)
    combos = list(itertools.product(*axes.values()))
    params = {k: np.array([c[j] for c in combos]) for j, k in enumerate(names)}
    on = NetworkBatch(net, params, device=args.device).followed_onset(w0, T_max, n=args.bracket)
    head = "".join(f"{k:>26s}" for k in names) + f"{'T_hot/T_cold':>14s}{'f_onset [Hz]':>14s}"
    _say(args, head)
    sets = []
    for i, c in enumerate(combos):
        ok = bool(on.status[i] == 1)
        ratio = on.T_hot[i] / net.gas.T_cold if ok else math.nan
        f = on.omega[i] / (2 * math.pi) if ok else math.nan
        sets.append(
            {
                "params": dict(zip(names, map(float, c), strict=True)),
                "T_ratio": _finite(ratio),
                "f_onset_Hz": _finite(f),
                "mode_jumps": int(on.jumps[i]),
            }
        )
        _say(args, "".join(f"{v:26.6g}" for v in c) + f"{ratio:14.6g}{f:14.6g}")
    return sets


def _profiles_csv(prof, amplitude: float) -> str:
    lines = [
        f"# profiles at onset, |p| = {amplitude:g} Pa at the first branch's start; convention = exp(-iwt)",
        "branch,segment,x_m,p_abs_Pa,p_phase_deg,U_abs_m3_per_s,U_phase_deg,T_K,Edot_W,Htot_W",
    ]
    for b in prof:
        for k in range(len(b.x)):
            lines.append(
                f"{b.branch},{b.segment[k]},{b.x[k]:.9g},{abs(b.p[k]):.9g},{np.degrees(np.angle(b.p[k])):.6f},"
                f"{abs(b.U[k]):.9g},{np.degrees(np.angle(b.U[k])):.6f},{b.T[k]:.6f},{b.Edot[k]:.9g},{b.Htot[k]:.9g}"
            )
    return "\n".join(lines) + "\n"


def plot_profiles(prof, path, title: str = ""):
    """|p|, |U|, Edot and Htot, and T along x, one line per branch (DeltaEC's usual plots)."""
    import matplotlib.pyplot as plt

    from ..plots import save

    fig, axes = plt.subplots(4, 1, figsize=(8, 10), sharex=True)
    for i, b in enumerate(prof):
        c = f"C{i % 10}"
        axes[0].plot(b.x, np.abs(b.p) / 1e3, color=c, label=b.branch)
        axes[1].plot(b.x, np.abs(b.U) * 1e3, color=c)
        axes[2].plot(b.x, b.Edot, color=c)
        axes[2].plot(b.x, b.Htot, color=c, ls="--")
        axes[3].plot(b.x, b.T, color=c)
    axes[0].set_ylabel("|p| [kPa]")
    axes[1].set_ylabel("|U| [L/s]")
    axes[2].set_ylabel("Edot (solid), Htot (dashed) [W]")
    axes[3].set_ylabel("T [K]")
    axes[3].set_xlabel("x along each branch [m]")
    axes[0].legend(fontsize=8)
    axes[0].set_title(title)
    for ax in axes:
        ax.grid(alpha=0.3)
    save(fig, path)


def _plot_locus(res, path, title: str):
    import matplotlib.pyplot as plt

    from ..plots import save

    fig, ax = plt.subplots(figsize=(7, 4.5))
    f = res.path.omega.real / (2 * math.pi)
    ax.plot(f, res.path.omega.imag, "-", color="C0", lw=1.0, zorder=1)
    sc = ax.scatter(f, res.path.omega.imag, c=res.path.T, cmap="viridis", s=14, zorder=2)
    if math.isfinite(res.T_onset):
        ax.plot([res.frequency], [0.0], "kx", ms=8, zorder=3)
    for j in res.path.jumps:
        ax.annotate(
            "",
            xy=(j.omega_after.real / (2 * math.pi), j.omega_after.imag),
            xytext=(j.omega_before.real / (2 * math.pi), j.omega_before.imag),
            arrowprops={"arrowstyle": "->", "color": "r"},
        )
    ax.axhline(0.0, color="k", lw=0.6)
    fig.colorbar(sc, ax=ax, label="T_hot [K]")
    ax.set_xlabel("frequency Re omega / 2 pi [Hz]")
    ax.set_ylabel("growth rate Im omega [1/s] (> 0 grows)")
    ax.set_title(f"{title}: root locus as T_hot rises (x: onset, red: mode jump)")
    save(fig, path)
