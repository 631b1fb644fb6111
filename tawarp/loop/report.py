"""The loop's report: report.json, report.md, residual and drift figures."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import GENERATOR, markdown_mark, write_json, write_text
from ..measure.kind import MeasurementKind
from .records import LoopReport


def _steps(report: dict) -> list[str]:
    """The claims' names (an effect, or "A+B" for a group the data cannot separate)."""
    return report["accepted_steps"]


def residual_figure(problem: MeasurementKind, report: LoopReport, path: Path) -> Path:
    """The residual per coefficient against frequency, one line per group (real part solid,
    imaginary part dashed), before (top row) and after (bottom row), in units of rms|y|
    with the noise floor shaded: a narrow feature such as a resonance dip stays visible."""
    from ..plots import plt, save

    fits = {"before": report.base.fit, "after": report.best.fit}
    nc = len(problem.coef_names)
    groups = np.unique(problem.group)
    scale = np.sqrt(np.mean(np.abs(problem.y) ** 2))
    floor = report.get("noise_floor")
    fig, axes = plt.subplots(
        2, nc, figsize=(max(3.2 * nc, 5.0), 5.6), squeeze=False, sharex=True, sharey="row", layout="constrained"
    )
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for row, key in enumerate(("before", "after")):
        d = (fits[key].model[0] - problem.y) / scale
        for c in range(nc):
            ax = axes[row, c]
            if floor:
                ax.axhspan(-floor / np.sqrt(2), floor / np.sqrt(2), color="0.88", lw=0)
            for k, g in enumerate(groups):
                m = np.flatnonzero((problem.coef == c) & (problem.group == g))
                m = m[np.argsort(problem.freq[m])]
                col = colors[k % len(colors)]
                ax.plot(
                    problem.freq[m],
                    d[m].real,
                    "-",
                    color=col,
                    lw=1.0,
                    label=f"{problem.group_name} = {g:.3g}" if len(groups) > 1 else None,
                )
                ax.plot(problem.freq[m], d[m].imag, "--", color=col, lw=1.0)
            ax.axhline(0.0, color="k", lw=0.5)
            ax.set_title(f"{problem.coef_names[c]} ({key})", fontsize=9)
            if row == 1:
                ax.set_xlabel("frequency [Hz]")
            if c == 0:
                ax.set_ylabel("(model - data) / rms|y|")
    if len(groups) > 1:
        axes[0, -1].legend(fontsize=7)
    fig.suptitle(
        f"error {report['error_before']:.3g} -> {report['error_after']:.3g}; verdict {report['verdict']}; "
        f"claimed: {'; '.join(_steps(report)) or 'none'} (re solid, im dashed; grey: noise)",
        fontsize=9,
    )
    return save(fig, path)


def drift_figure(report: dict, path: Path) -> Path | None:
    """The h's refitted per heat input with one standard deviation, before and after, each
    with its p of one value at every heat input (None without drift data)."""
    db, da = report.get("drift_before"), report.get("drift_after")
    if not db:
        return None
    from ..plots import plt, save

    names = list(db["values"])
    fig, axes = plt.subplots(1, len(names), figsize=(3.6 * len(names), 3.4), squeeze=False, layout="constrained")

    def p(d, k):  # the drift's score test of one value (docs/loop.md)
        return "" if d["consistency_p"][k] is None else f", p {d['consistency_p'][k]:.2g}"

    for ax, k in zip(axes[0], names):
        ax.errorbar(db["Q_W"], db["values"][k], db["std"][k], fmt="o-", capsize=3, label=f"before{p(db, k)}")
        if da:
            after = f"after ({'; '.join(_steps(report))}{p(da, k)})"
            ax.errorbar(da["Q_W"], da["values"][k], da["std"][k], fmt="s--", capsize=3, label=after)
        ax.set_xlabel("Q [W]")
        ax.set_ylabel(f"{k} [W/(m^2 K)]")
        ax.legend(fontsize=8)
    fig.suptitle(
        "heat-exchange coefficients refitted per heat input (p: each h one value at every heat input)", fontsize=10
    )
    return save(fig, path)


def plan_figure(problem: MeasurementKind, report: dict, path: Path) -> Path | None:
    """The best next measurement: each rival's prediction minus the best model's, in units of
    the data's noise, for the coefficient and group where they differ most, against
    frequency (real part solid, imaginary dashed; grey: one noise sd). None when no plan was
    made."""
    plans = report.get("next_measurement") or []
    if not plans:
        return None
    from ..plots import plt, save

    best = plans[0]
    pred, sd = best["_predictions"], best["_sd"]
    freq, group, coef = best["_rows"]
    a, b = best["separates"]
    k = int(np.argmax(np.abs(pred[b] - pred[a]) / sd.min(axis=1)))
    m = np.flatnonzero((coef == coef[k]) & (group == group[k]))
    m = m[np.argsort(freq[m])]
    fig, ax = plt.subplots(figsize=(7.0, 3.6), layout="constrained")
    ax.axhspan(-1.0, 1.0, color="0.88", lw=0)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for j, (label, y) in enumerate((lab, y) for lab, y in pred.items() if lab != a):
        d = y[m] - pred[a][m]
        ax.plot(freq[m], d.real / sd[m, 0], "-", color=colors[j % len(colors)], label=label)
        ax.plot(freq[m], d.imag / sd[m, 1], "--", color=colors[j % len(colors)])
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel(f"{problem.coef_names[coef[k]]}: rival - {a} [noise sd]")
    ax.legend(fontsize=7, title="rival", title_fontsize=7)
    fig.suptitle(
        f"next measurement: {best['description']}\n{problem.group_name} = {group[k]:.4g}; expected ln Bayes "
        f"factor {a} vs {b}: {best['expected_gain']:.3g}",
        fontsize=9,
    )
    return save(fig, path)


#: report.md names an h of the final model whose drift p (docs/loop.md) is below this: on
#: clean data one h in a thousand.
DRIFT_P = 1e-3


def drifting(drift: dict | None) -> dict[str, float]:
    """{h: p} of the h's of ``drift`` whose p of one value at every heat input is below
    :data:`DRIFT_P`."""
    return {k: p for k, p in ((drift or {}).get("consistency_p") or {}).items() if p is not None and p < DRIFT_P}


def report_markdown(report: dict) -> str:
    r = report
    g0, g1 = r["goodness_of_fit_before"], r["goodness_of_fit_after"]

    def gof(g):
        return (
            f"reduced chi^2 {g['reduced_chi2']:.3g} (p = {g['p_value']:.2g}), error {g['error']:.4g}, "
            f"adequate: {g['adequate']}, residual white: {g['white']} (smooth share "
            f"{g['structure']['fraction']:.3f}, white noise {g['structure']['if_white']:.3f}, "
            f"p = {g['structure']['p_value']:.2g})"
            + (f", at bounds: {', '.join(g['at_bounds'])}" if g["at_bounds"] else "")
        )

    lines = [
        "# tawarp loop report",
        markdown_mark(f"{GENERATOR} loop"),
        "",
        f"- verdict: **{r['verdict']}**",
        f"- measurement kind: {r['kind']}, {r['n_residuals']} real residuals",
        f"- base parameters: {', '.join(r['base_parameters'])}"
        + (f"; pinned: {', '.join(r['pinned'])}" if r["pinned"] else "")
        + (f"; tied: {', '.join(f'{t} to {k}' for k, ts in r['ties'].items() for t in ts)}" if r["ties"] else ""),
        f"- noise floor: {r['noise_floor']:.4g} ({r['noise_source']})",
        f"- base fit: {gof(g0)}",
        f"- final fit: {gof(g1)}",
        f"- claimed effects: **{'; '.join(_steps(r)) or 'none'}**"
        + (
            f" (the most probable model, {'+'.join(r['best_model']) or 'base'}, is not claimed: it fails a check below)"
            if not _steps(r) and r["best_model"] and r["verdict"] != "indistinguishable"
            else ""
        ),
        *(
            [
                f"- unexplained residual: {u['coefficient']}"
                + (f" at {u['group']:g}" if u["group"] is not None else "")
                + f", {u['band_Hz'][0]:g}-{u['band_Hz'][1]:g} Hz, error {u['error']:.4g} (noise floor "
                f"{u['noise_floor']:.4g})"
            ]
            if (u := r.get("unexplained_residual"))
            else []
        ),
        *(
            [
                "- changing with the heat input in the final model: "
                + ", ".join(f"{k} (p = {p:.2g})" for k, p in moving.items())
                + ": it misses something (section h refitted per heat input)"
            ]
            if (moving := drifting(r.get("drift_after")))
            else []
        ),
        f"- models compared: {r['models_compared']['subsets']} subsets of the library linearized, "
        f"{r['models_compared']['refitted']} refitted",
        f"- method: {r['method']}",
        f"- residual structure before: {r['residual_structure_before']['structured_fraction']:.3f} of the residual "
        f"is smooth in frequency (white noise: {r['residual_structure_before']['structured_fraction_if_white']:.3f})",
        "",
        "## Prior tension",
        "",
    ]
    lines += [f"- {t['message']}" for t in r["prior_tension"]] or ["none: every parameter within 3 prior sd"]
    lines += [
        "",
        "## Most probable models",
        "",
        "| model | probability | ln Z | error | chi^2 | parameters |",
        "|---|---|---|---|---|---|",
    ]
    for m in r["model_probabilities"][:10]:
        lines.append(
            f"| {m['label']} | {m['probability']:.3g} | {m['log_evidence']:.1f} | {m['error']:.4g} | "
            f"{m['chi2']:.1f} | {m['n_parameters']} |"
        )
    lines += ["", "## Inclusion probabilities", "", "| effect | P(in the model) |", "|---|---|"]
    for k, v in sorted(r["inclusion_probabilities"].items(), key=lambda kv: -kv[1]):
        lines.append(f"| {k} | {v:.3g} |")
    for k, v in r["group_probabilities"].items():
        lines.append(f"| at least one of {k} | {v:.3g} |")
    if r.get("next_measurement"):
        lines += ["", "## Next measurement", "", "| plan | separates | expected ln Bayes factor |", "|---|---|---|"]
        for p in r["next_measurement"]:
            lines.append(f"| {p['description']} | {' vs '.join(p['separates'])} | {p['expected_gain']:.3g} |")
    lines += ["", "## Parameters", "", "| parameter | before | after |", "|---|---|---|"]
    keys = list(dict.fromkeys(list(r["parameters_before"]) + list(r["parameters_after"])))
    for k in keys:

        def fmt(d):
            if k not in d:
                return ""
            std, z = d[k]["std"], d[k].get("prior_z")
            return (
                f"{d[k]['value']:.5g} ± "
                + (f"{std:.2g}" if std is not None else "undetermined")
                + (f" ({z:+.1f} prior sd)" if z is not None else "")
            )

        lines.append(f"| {k} | {fmt(r['parameters_before'])} | {fmt(r['parameters_after'])} |")
    for key in ("drift_before", "drift_after"):
        d = r.get(key)
        if d:
            lines += [
                "",
                f"## h refitted per heat input ({key.split('_')[1]})",
                "",
                "| parameter | " + " | ".join(f"Q = {q:g} W" for q in d["Q_W"]) + " | spread | p (one value) |",
                "|---|" + "---|" * (len(d["Q_W"]) + 2),
            ]
            for k, v in d["values"].items():
                p = d["consistency_p"][k]
                lines.append(
                    f"| {k} | "
                    + " | ".join(f"{x:.4g} ± {sd:.2g}" for x, sd in zip(v, d["std"][k]))
                    + f" | {d['relative_spread'][k]:.2%} | {'-' if p is None else f'{p:.2g}'} |"
                )
            lines += [
                "",
                "p: the score test of the h as one value at every heat input against one value per heat "
                "input, everything else refitted. Small: the model misses something, and would fit better "
                "with an h per heat input (several h's may share one cause, not always a thermal one).",
            ]
    if r.get("comparison"):
        lines += [
            "",
            "## Fitted values beside the reference",
            "",
            "| quantity | before | after | reference |",
            "|---|---|---|---|",
        ]
        for k, row in r["comparison"].items():
            lines.append(f"| {k} | {row['before']:.4g} | {row['after']:.4g} | {row['reference']:.4g} |")
    return "\n".join(lines) + "\n"


#: Every file :func:`write_report` may write in its folder (a command claims them first:
#: :func:`tawarp.io.claim_outputs`).
OUTPUTS = ("report.json", "report.md", "residuals.png", "drift.png", "next_measurement.png")


def write_report(problem: MeasurementKind, report: LoopReport, outdir: str | Path) -> dict:
    """OUTDIR/report.json, report.md, residuals.png (and drift.png, next_measurement.png);
    returns the JSON dict (:meth:`LoopReport.to_json` with the figures' names). report.json
    and report.md carry tawarp's mark (:func:`tawarp.io.written_by_tawarp`): ``generator``,
    and a :func:`tawarp.io.markdown_mark` line under the title."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    js = report.to_json()
    figs = [
        residual_figure(problem, report, outdir / "residuals.png"),
        drift_figure(report, outdir / "drift.png"),
        plan_figure(problem, report, outdir / "next_measurement.png"),
    ]
    js["figures"] = [f.name for f in figs if f is not None]
    write_json(outdir / "report.json", {"generator": f"{GENERATOR} loop", **js})
    write_text(outdir / "report.md", report_markdown(js) + "".join(f"\n![{f[:-4]}]({f})\n" for f in js["figures"]))
    return js
