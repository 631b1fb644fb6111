"""Figures of design searches: optimization history, Pareto front, temperature profiles
of the best designs (as the paper's Fig. 6). Written atomically with :func:`tawarp.plots.save`."""

from __future__ import annotations

import numpy as np

from ..plots import plt, save


def plot_history(study, objectives, path, T_limit=None, title: str = ""):
    """Objective value of every complete trial (:func:`tawarp.design.storage.trials_table`)
    against its place in evaluation order, with the running best (first objective for
    several)."""
    from .objectives import objective
    from .storage import trials_table

    ds = trials_table(study)
    ok = ds.state.values == "COMPLETE"
    fig, ax = plt.subplots(figsize=(7, 4))
    if ok.any():
        num = np.flatnonzero(ok)
        val = ds[objectives[0]].values[ok]
        feas = np.nan_to_num(ds.constraint.values[ok], nan=0.0) <= 0 if T_limit is not None else np.ones(len(num), bool)
        ax.plot(num[feas], val[feas], ".", ms=2, alpha=0.4, label="feasible trials")
        if np.any(~feas):
            ax.plot(num[~feas], val[~feas], "x", ms=2, alpha=0.4, color="0.6", label="T_max above limit")
        maximize = objective(objectives[0]).direction == "maximize"
        v = np.where(feas, val, -np.inf if maximize else np.inf)
        best = np.maximum.accumulate(v) if maximize else np.minimum.accumulate(v)
        ax.plot(num, best, "-", color="C3", lw=1.5, label="best so far")
    unit = objective(objectives[0]).unit
    ax.set_xlabel("trial (evaluation order)")
    ax.set_ylabel(f"{objectives[0]} [{unit}]")
    ax.legend(fontsize=8)
    ax.set_title(title or "optimization history")
    return save(fig, path)


def plot_pareto(study, objectives, front: list[dict], path, title: str = ""):
    """All complete trials (:func:`tawarp.design.storage.trials_table`) in the plane of
    the first two objectives, the front highlighted."""
    from .objectives import objective
    from .storage import trials_table

    ds = trials_table(study)
    ok = ds.state.values == "COMPLETE"
    fig, ax = plt.subplots(figsize=(6, 4.5))
    if ok.any():
        ax.plot(ds[objectives[0]].values[ok], ds[objectives[1]].values[ok], ".", ms=2, color="0.7", label="trials")
    if front:
        P = np.array([[b["values"][objectives[0]], b["values"][objectives[1]]] for b in front])
        o = np.argsort(P[:, 0])
        ax.plot(P[o, 0], P[o, 1], "o-", ms=3, color="C3", label="Pareto front (feasible)")
    ax.set_xlabel(f"{objectives[0]} [{objective(objectives[0]).unit}]")
    ax.set_ylabel(f"{objectives[1]} [{objective(objectives[1]).unit}]")
    ax.legend(fontsize=8)
    ax.set_title(title or "Pareto front")
    return save(fig, path)


def plot_best_profiles(space, designs: list[dict], path, n: int = 5, device=None, title: str = ""):
    """Temperature along the core T(x) of up to ``n`` designs (paper Fig. 6), with the
    stack planes of each marked."""
    from ..model.forward import steady_temperature

    fig, ax = plt.subplots(figsize=(7, 4))
    for d in designs[:n]:
        core, q = space.core_for(d["params"])
        pos = core.positions()
        x = np.linspace(0.0, pos[-1], 600)
        T, _ = steady_temperature(core, x, heat_input=q, device=device)
        label = ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}" for k, v in d["params"].items())
        (line,) = ax.plot(x * 100, T[0], lw=1.3, label=label)
        i = space.stack_index
        for xp in (pos[i], pos[i + 1]):
            ax.axvline(xp * 100, color=line.get_color(), lw=0.6, ls=":")
    ax.set_xlabel("x [cm]")
    ax.set_ylabel("T [K]")
    ax.legend(fontsize=6)
    ax.set_title(title or "temperature profiles of the best designs")
    return save(fig, path)


def plot_ranking(result, path, title: str = ""):
    """Gradient distributions of each material at each heat input (mean ± 2 std, 95 % interval)."""
    fig, ax = plt.subplots(figsize=(7, 4))
    qs = result.heat_inputs
    width = 0.8 / max(len(result.materials), 1)
    for i, m in enumerate(result.materials):
        rows = [next(r for r in result.table if r["material"] == m and r["Q_W"] == q) for q in qs]
        xs = np.arange(len(qs)) + (i - (len(result.materials) - 1) / 2) * width
        mean = np.array([r["gradient_mean_K_per_m"] for r in rows])
        lo = mean - np.array([r["gradient_p025_K_per_m"] for r in rows])
        hi = np.array([r["gradient_p975_K_per_m"] for r in rows]) - mean
        ax.bar(xs, mean, width, yerr=[lo, hi], capsize=3, label=m)
    ax.set_xticks(np.arange(len(qs)), [f"Q = {q:g} W" for q in qs])
    ax.set_ylabel("gradient across the stack [K/m]")
    ax.legend(fontsize=8)
    ax.set_title(title or "material ranking (95 % intervals)")
    return save(fig, path)
