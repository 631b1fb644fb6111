"""Rank the four bundled materials by the onset heat input of a reference engine, with the
uncertainty of their fits to synthetic measurements (docs/design.md, "Ranking by onset").

    python studies/onset_rank.py [--samples 400] [--out studies/out]

For each material: ``tawarp synth MAT`` (paper-like T-matrix data, 0.5 % noise, seed 0)
and ``tawarp fit`` (the paper's two-step estimation) give a fit.json; the material is read
from it with its covariance (porosity, pore radius, tortuosity; solid conductivity exact).
``stack.h`` comes from the second step: the fit at the largest heat input (the best
determined), its std added to the material (it is fitted per Q, so the fit.json's top-level
covariance does not hold it). Each material then goes into the stack of the bundled
``standing_wave`` engine (the ceramic core in a closed-closed resonator; the hot exchanger
stays ceramic), at 1 atm and at 10 bar (``gas.p_mean = 1e6``), and ``--samples`` parameter
sets drawn from each fit's covariance are searched for onset in one batched call. The
10 bar case is repeated with the catalogue's standard deviations (paper Table 1, tawarp's
choices for h_s), an uncertainty much larger than that of a synthetic fit.
Writes ``onset_rank.json`` and the Markdown table ``onset_rank.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
from pathlib import Path

from tawarp.cli import main as tawarp
from tawarp.design.catalogue import Material
from tawarp.design.rank import rank_by_onset
from tawarp.io import write_json, write_text
from tawarp.model.resonator import load_engine

MATERIALS = ("ceramic", "mesh", "nicr_foam", "rvc_foam")
Q_MAX = 200.0


def fitted_material(name: str, work: Path) -> Material:
    """The material of ``tawarp synth NAME`` + ``tawarp fit``, stack.h from the last Q."""
    csv, fit = work / f"{name}.csv", work / f"{name}_fit.json"
    if tawarp(["synth", name, "-o", str(csv), "--device", "cpu", "--quiet"]) != 0:
        raise RuntimeError(f"tawarp synth {name} failed")
    if tawarp(["fit", str(csv), "--core", name, "-o", str(fit), "--device", "cpu", "--quiet"]) != 0:
        raise RuntimeError(f"tawarp fit {name} failed")
    m = Material.from_fit_json(fit, name=name)
    h = json.loads(fit.read_text())["step2"][-1]["parameters"]["stack.h"]
    return dataclasses.replace(m, h_s=h["value"], std={**m.std, "h_s": h["std"]})


def table(res, mats, label: str) -> str:
    def q(v):
        return f"{v:.2f}" if v is not None else f"> {Q_MAX:g}"

    lines = [
        f"**{label}** ({res.n_samples} draws per material, Q_max {Q_MAX:g} W)",
        "",
        "| rank | material | Q_onset nominal [W] | median [W] | 5-95 % [W] | p90 [W] | f_onset [Hz] | "
        "T_hot/T_cold | P(no onset) | P(best) |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in res.table:
        f = f"{r['f_onset_median_Hz']:.1f}" if r["f_onset_median_Hz"] is not None else "-"
        t = f"{r['T_ratio_median']:.3f}" if r["T_ratio_median"] is not None else "-"
        lines.append(
            f"| {r['rank']} | {r['material']} | {q(r['Q_onset_nominal_W'])} | {q(r['Q_onset_median_W'])} | "
            f"{q(r['Q_onset_p05_W'])} - {q(r['Q_onset_p95_W'])} | {q(r['Q_onset_p90_W'])} | {f} | {t} | "
            f"{r['p_no_onset']:.2f} | {r['p_best']:.2f} |"
        )
    pairs = [
        f"P({a} < {b}) = {r['p_beats'][b]:.2f}"
        for r in res.table
        for a in [r["material"]]
        for b in r["p_beats"]
        if r["rank"] < next(x["rank"] for x in res.table if x["material"] == b) and r["p_no_onset"] < 1
    ]
    return "\n".join(lines + ["", "Pairwise: " + "; ".join(pairs) + "." if pairs else ""])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=400)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="studies/out")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as work:  # the synthetic data and fits are not kept
        mats = [fitted_material(m, Path(work)) for m in MATERIALS]
    base = load_engine("standing_wave")
    report, md = {"materials": {m.name: m.to_dict() for m in mats}}, []
    for label, p_mean in (("standing_wave, air at 1 atm", 101325.0), ("standing_wave, air at 10 bar", 1e6)):
        eng = dataclasses.replace(base, core=base.core.replace(**{"gas.p_mean": p_mean}))
        res = rank_by_onset(mats, eng, n_samples=args.samples, seed=args.seed, Q_max=Q_MAX)
        report[label] = res.to_dict()
        md.append(table(res, mats, label))
    # the same at 10 bar with the paper's Table 1 standard deviations (much wider than a fit's)
    label = "standing_wave, air at 10 bar, paper Table 1 standard deviations (tawarp/design/catalogue.py)"
    res = rank_by_onset(list(MATERIALS), eng, n_samples=args.samples, seed=args.seed, Q_max=Q_MAX)
    report[label] = res.to_dict()
    md.append(table(res, None, label))
    write_json(out / "onset_rank.json", report)
    write_text(out / "onset_rank.md", "\n\n".join(md) + "\n")
    print("\n\n".join(md))


if __name__ == "__main__":
    main()
