"""The loop's report: report.json, report.md, residual and drift figures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..measure.kind import MeasurementKind


def _jsonable(report: dict) -> dict:
    return json.loads(json.dumps({k: v for k, v in report.items() if not k.startswith("_")},
                                 default=lambda o: o.tolist() if isinstance(o, np.ndarray) else
                                 (o.item() if isinstance(o, np.generic) else str(o))))


def residual_figure(problem: MeasurementKind, report: dict, path: Path) -> Path:
    """Residual maps (frequency x group, one column per coefficient) before and after."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fits = report["_fits"]
    nc = len(problem.coef_names)
    groups = np.unique(problem.group)
    freqs = np.unique(problem.freq)
    fig, axes = plt.subplots(2, nc, figsize=(max(3.2 * nc, 5.0) + 1.5, 6.0), squeeze=False, layout="constrained")
    vmax = 0.0
    maps = []
    for row, key in enumerate(("before", "after")):
        d = np.abs(fits[key].model[0] - problem.y) * np.sqrt((problem.w ** 2).mean(-1))
        for c in range(nc):
            M = np.full((len(groups), len(freqs)), np.nan)
            m = problem.coef == c
            M[np.searchsorted(groups, problem.group[m]), np.searchsorted(freqs, problem.freq[m])] = d[m]
            maps.append((row, c, M))
            vmax = max(vmax, np.nanmax(M))
    for row, c, M in maps:
        ax = axes[row, c]
        im = ax.imshow(M, aspect="auto", origin="lower", vmin=0, vmax=vmax, cmap="magma",
                       extent=[freqs[0], freqs[-1], -0.5, len(groups) - 0.5])
        ax.set_yticks(range(len(groups)), [f"{g:.3g}" for g in groups])
        ax.set_title(f"{problem.coef_names[c]} ({'before' if row == 0 else 'after'})", fontsize=9)
        ax.set_xlabel("frequency [Hz]")
        if c == 0:
            ax.set_ylabel(problem.group_name)
    fig.colorbar(im, ax=axes, label="|weighted residual|")
    fig.suptitle(f"error {report['error_before']:.3g} -> {report['error_after']:.3g}; "
                 f"chosen: {report['chosen_effect']}", fontsize=10)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def drift_figure(report: dict, path: Path) -> Path | None:
    """The h's refitted per heat input, before and after (None without drift data)."""
    db, da = report.get("drift_before"), report.get("drift_after")
    if not db:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(db["values"])
    fig, axes = plt.subplots(1, len(names), figsize=(3.6 * len(names), 3.4), squeeze=False, layout="constrained")
    for ax, k in zip(axes[0], names):
        ax.plot(db["Q_W"], db["values"][k], "o-", label="before")
        if da:
            ax.plot(da["Q_W"], da["values"][k], "s--", label=f"after ({report['chosen_effect']})")
        ax.set_xlabel("Q [W]")
        ax.set_ylabel(f"{k} [W/(m^2 K)]")
        ax.legend(fontsize=8)
    fig.suptitle("heat-exchange coefficients refitted per heat input", fontsize=10)
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def report_markdown(report: dict) -> str:
    r = report
    lines = ["# tawarp loop report", "",
             f"- measurement kind: {r['kind']}, {r['n_residuals']} real residuals",
             f"- error before: {r['error_before']:.4g}; after: {r['error_after']:.4g}"
             + (f"; noise floor: {r['noise_floor']:.4g}" if r["noise_floor"] else ""),
             f"- chosen effect: **{r['chosen_effect']}**" + (f" ({r['chosen_description']})" if r["chosen_effect"] else ""),
             *([f"- indistinguishable on these data: **{', '.join(r['indistinguishable'])}** (BIC within "
                f"{r['indistinguishable_bic']:g}); 'after' shows {r['best_effect']}"] if r.get("indistinguishable") else []),
             f"- acceptance: {r['acceptance_test']}",
             f"- residual structure before: {r['residual_structure_before']['structured_fraction']:.3f} of the residual "
             f"is smooth in frequency (white noise: {r['residual_structure_before']['structured_fraction_if_white']:.3f})",
             "", "## Candidates", "",
             "| effect | score | if noise | lin. p | refit | error after | dBIC | p | held-out | accepted |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for c in r["candidates"]:
        if c["refit"]:
            extra = f"yes | {c['error_after']:.4g} | {c['delta_bic']:.1f} | {c['p_value']:.2g} | {c['held_out_error']:.4g}"
        else:
            extra = "no | | | | "
        lines.append(f"| {c['effect']} | {c['score']:.3g} | {c['score_if_noise']:.2g} | {c['linearized_p']:.2g} | "
                     f"{extra} | {c['accepted']} |")
    lines += ["", f"held-out rows: {r['held_out']}; base model's held-out error {r['held_out_error_base']:.4g}", "",
              "## Parameters", "", "| parameter | before | after |", "|---|---|---|"]
    keys = list(dict.fromkeys(list(r["parameters_before"]) + list(r["parameters_after"])))
    for k in keys:
        def fmt(d):
            return f"{d[k]['value']:.5g} ± {d[k]['std']:.2g}" if k in d else ""
        lines.append(f"| {k} | {fmt(r['parameters_before'])} | {fmt(r['parameters_after'])} |")
    for key in ("drift_before", "drift_after"):
        d = r.get(key)
        if d:
            lines += ["", f"## h refitted per heat input ({key.split('_')[1]})", "",
                      "| parameter | " + " | ".join(f"Q = {q:g} W" for q in d["Q_W"]) + " | spread |",
                      "|---|" + "---|" * (len(d["Q_W"]) + 1)]
            for k, v in d["values"].items():
                lines.append(f"| {k} | " + " | ".join(f"{x:.4g}" for x in v) + f" | {d['relative_spread'][k]:.2%} |")
    if r.get("comparison"):
        lines += ["", "## Fitted values beside the reference", "", "| quantity | before | after | reference |",
                  "|---|---|---|---|"]
        for k, row in r["comparison"].items():
            lines.append(f"| {k} | {row['before']:.4g} | {row['after']:.4g} | {row['reference']:.4g} |")
    return "\n".join(lines) + "\n"


def write_report(problem: MeasurementKind, report: dict, outdir: str | Path) -> dict:
    """OUTDIR/report.json, report.md, residuals.png (and drift.png); returns the JSON dict."""
    from ..io import write_json

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    js = _jsonable(report)
    figs = [residual_figure(problem, report, outdir / "residuals.png"), drift_figure(report, outdir / "drift.png")]
    js["figures"] = [f.name for f in figs if f is not None]
    write_json(outdir / "report.json", js)
    tmp = outdir / "report.md.tmp"
    tmp.write_text(report_markdown(js) + "".join(f"\n![{f[:-4]}]({f})\n" for f in js["figures"]))
    tmp.replace(outdir / "report.md")  # atomic: no half-written report
    return js
