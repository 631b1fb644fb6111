"""Rigid JCA vs Biot-Allard (elastic frame) on the Atalla & Panneton foam2 data.

    python studies/elastic_frame.py [--sample foam2] [--docs docs]

Fits the thin and thick rigid-backed layers of one sample together (one material) with
``scipy.optimize.least_squares`` (a study may use SciPy; the package's estimator is being
rebuilt):

* rigid JCA: phi, sigma, alpha_inf, Lambda, Lambda' (:func:`tawarp.model.biot.rigid_surface_impedance`);
* Biot: the same five plus the frame's E, eta and rho_1, nu fixed at 0.3 (at normal
  incidence only the P-wave modulus E (1-nu)/((1+nu)(1-2nu)) enters, so E and nu are not
  separately identifiable) (:func:`tawarp.model.biot.surface_impedance`).

Starts: the README's values (sigma, phi measured; alpha_inf, Lambda, Lambda' identified by
the paper) and 8 starts 30 % off them for the rigid fit; the Biot fit starts from the README
and the rigid fit, each with a grid of frame moduli and densities, and keeps the best. Parameters are fitted in log scale within physical bounds.
Error: docs/formats.md's measure, rms|Z_meas - Z_model| / rms|Z_meas| over the rows compared.
Writes ``DOCS/elastic_frame.md`` and ``DOCS/elastic_frame.png``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

from tawarp.measure import atalla_panneton_samples, load_atalla_panneton
from tawarp.model import biot

NU = 0.3
#: (name, lower bound, upper bound) of the fitted parameters
RIGID = (
    ("phi", 0.7, 0.999),
    ("sigma", 1e3, 1e5),
    ("alpha_inf", 1.0, 4.0),
    ("Lambda", 10e-6, 1e-3),
    ("Lambda_prime", 10e-6, 2e-3),
)
FRAME = (("E", 1e3, 1e8), ("eta", 1e-3, 1.0), ("rho_1", 2.0, 200.0))
BAND = (1100.0, 1400.0)  # Hz: the thick layer's frame-resonance feature


def error(Z, Zm) -> float:
    """docs/formats.md error measure: rms|Z - Zm| / rms|Z|."""
    return float(np.sqrt(np.mean(np.abs(Z - Zm) ** 2) / np.mean(np.abs(Z) ** 2)))


class Fit:
    """Least-squares fit of one model to the layers of one sample."""

    def __init__(self, data, spec, model, fixed):
        self.data, self.spec, self.model, self.fixed = data, spec, model, fixed
        self.lo = np.log([s[1] for s in spec])
        self.hi = np.log([s[2] for s in spec])
        self.scale = np.sqrt(np.mean(np.concatenate([np.abs(d.Zs) ** 2 for d in data])))

    def values(self, x) -> dict:
        return {s[0]: v for s, v in zip(self.spec, np.exp(x))}

    def predict(self, x) -> list[np.ndarray]:
        v = self.values(x)
        return [
            self.model(d.freq, thickness=d.thickness, T=d.T_ambient, P0=d.p_ambient, **v, **self.fixed)
            for d in self.data
        ]

    def residual(self, x) -> np.ndarray:
        r = np.concatenate([d.Zs - Z for d, Z in zip(self.data, self.predict(x))]) / self.scale
        return np.concatenate([r.real, r.imag]) / np.sqrt(r.size)

    def run(self, starts: list[dict]):
        best = None
        for start in starts:
            x0 = np.clip(np.log([start[s[0]] for s in self.spec]), self.lo + 1e-9, self.hi - 1e-9)
            res = least_squares(self.residual, x0, bounds=(self.lo, self.hi), x_scale=1.0, xtol=1e-10, ftol=1e-12)
            if best is None or res.cost < best.cost:
                best = res
        return best

    def log_std(self, res) -> tuple[np.ndarray, np.ndarray]:
        """Std of the log parameters (~ relative std) and their correlation matrix from
        s^2 (J^T J)^-1, s^2 = residual variance; the digitized data's errors are not
        independent, so these are indicative."""
        J = res.jac
        s2 = 2 * res.cost / (J.shape[0] - J.shape[1])
        cov = s2 * np.linalg.pinv(J.T @ J)
        std = np.sqrt(np.diag(cov))
        return std, cov / np.outer(std, std)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sample", default="foam2")
    ap.add_argument("--docs", default=str(Path(__file__).resolve().parents[1] / "docs"))
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    data = load_atalla_panneton(args.sample)
    readme = atalla_panneton_samples()[args.sample]
    start = {k: readme[k] for k in biot.JCA_PARAMETERS}

    rigid = Fit(data, RIGID, biot.rigid_surface_impedance, {})
    # README start and 8 starts 30 % off it on every parameter (seeded)
    rng = np.random.default_rng(0)
    r_starts = [start] + [
        {k: v * f for (k, v), f in zip(start.items(), rng.choice([0.7, 1.3], len(start)))} for _ in range(8)
    ]
    r_fit = rigid.run(r_starts)
    r_vals = rigid.values(r_fit.x)

    elastic = Fit(data, RIGID + FRAME, biot.surface_impedance, {"nu": NU})
    starts = [
        {**s, "E": E, "eta": 0.1, "rho_1": rho}
        for s in (start, r_vals)
        for E in (3e4, 1e5, 3e5, 1e6)
        for rho in (10.0, 40.0)
    ]
    e_fit = elastic.run(starts)
    e_vals = elastic.values(e_fit.x)
    seconds = time.perf_counter() - t0

    Zr, Ze = rigid.predict(r_fit.x), elastic.predict(e_fit.x)
    rows = []
    for name, sel in (("both layers", None), ("thin", 0), ("thick", 1), (f"thick, {BAND[0]:g}-{BAND[1]:g} Hz", "band")):
        if sel is None:
            Zm = np.concatenate([d.Zs for d in data])
            a, b = np.concatenate(Zr), np.concatenate(Ze)
        elif sel == "band":
            m = (data[1].freq >= BAND[0]) & (data[1].freq <= BAND[1])
            Zm, a, b = data[1].Zs[m], Zr[1][m], Ze[1][m]
        else:
            Zm, a, b = data[sel].Zs, Zr[sel], Ze[sel]
        rows.append((name, error(Zm, a), error(Zm, b)))

    docs = Path(args.docs)
    docs.mkdir(parents=True, exist_ok=True)
    _figure(data, Zr, Ze, docs / "elastic_frame.png", args.sample)
    c_frame = np.sqrt(e_vals["E"] * (1 - NU) / ((1 + NU) * (1 - 2 * NU) * e_vals["rho_1"]))
    _write_md(
        docs / "elastic_frame.md",
        args.sample,
        data,
        readme,
        r_vals,
        e_vals,
        rows,
        c_frame,
        seconds,
        r_fit,
        e_fit,
        elastic.log_std(e_fit),
    )
    for name, a, b in rows:
        print(f"{name:>24}: rigid JCA {a:.4f}  Biot {b:.4f}")
    print(f"E = {e_vals['E']:.3g} Pa, eta = {e_vals['eta']:.3g}, rho_1 = {e_vals['rho_1']:.3g} kg/m^3; {seconds:.1f} s")
    return 0


def _figure(data, Zr, Ze, path, sample):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(data), figsize=(5 * len(data), 6.5), sharex=True, squeeze=False)
    for k, d in enumerate(data):
        for row, part, label in ((0, np.real, "Re Zs/(rho0 c0)"), (1, np.imag, "Im Zs/(rho0 c0)")):
            ax = axes[row, k]
            ax.plot(d.freq, part(d.Zs), "k.", ms=4, label="data (exp(-iwt))")
            ax.plot(d.freq, part(Zr[k]), "C0-", label="rigid JCA")
            ax.plot(d.freq, part(Ze[k]), "C3-", label="Biot (elastic frame)")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        axes[0, k].set_title(f"{sample}, d = {d.thickness * 1e3:.2f} mm")
        axes[1, k].set_xlabel("frequency [Hz]")
    axes[0, 0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _write_md(path, sample, data, readme, rv, ev, rows, c_frame, seconds, r_fit, e_fit, e_std):
    units = {k: biot.BIOT_PARAMETERS[k][0] for k in biot.BIOT_PARAMETERS}
    lines = [
        "# Elastic frame (Biot-Allard)",
        "",
        "## Model (`tawarp.model.biot`)",
        "",
        "Biot-Allard porous layer at normal incidence (Allard & Atalla, *Propagation of Sound in Porous",
        "Media*, 2nd ed., ch. 5, 6, 11), NumPy, complex128, batched: parameters broadcast to a batch shape B,",
        "frequencies (m,), results B + (m,). Convention exp(-iwt): Allard's exp(+jwt) formulas with j -> -i;",
        "frame modulus E (1 - i eta); a rigid-backed equivalent-fluid layer has Zs = +i Zc cot(kd)",
        "(Allard's -j Zc cot(kd) conjugated; Im Zs > 0 at low frequency).",
        "",
        "- `jca_fluid(freq, phi, sigma, alpha_inf, Lambda, Lambda_prime, T, P0)`: JCA rho_eq, K_eq;",
        "  `rigid_surface_impedance(...)`: the rigid-frame layer; `flow_resistivity(pore_radius, ...)`.",
        "- `biot_waves(freq, ..., E, eta, nu, rho_1)`: P, Q, R, rho11, rho12, rho22, the compressional",
        "  waves delta_1, delta_2 with mu_1, mu_2, the shear wave delta_3, mu_3 (not excited here).",
        "- `surface_impedance(freq, thickness, ...)`: Zs/(rho0 c0) of a rigid-backed layer, frame bonded",
        "  to the backing (v^s = v^f = 0 there); at the air face sigma^s = -(1-phi) p, sigma^f = -phi p,",
        "  v = (1-phi) v^s + phi v^f.",
        "- `transfer_matrix(freq, thickness, ..., area)`: 2-port (p, U)(d) = T (p, U)(0), air on both faces,",
        "  **frame free to slide at the tube wall** (exactly 1-D). A frame clamped at its edge is not 1-D",
        "  and is not modelled. With free edges an infinitely stiff frame of finite mass moves as a rigid",
        "  body, so the 2-port's E -> inf limit is the mobile-rigid frame, not the immobile equivalent",
        "  fluid (that needs rho_1 -> inf as well); the rigid-backed layer's E -> inf limit is rigid JCA.",
        "- Both geometries solve the 4x4 normal-incidence system of the four waves (+-delta_1, +-delta_2),",
        "  each written as decaying from the face where it starts: no overflow for thick or soft frames.",
        "- Only the P-wave modulus E (1-nu)/((1+nu)(1-2nu)) enters at normal incidence: fix nu when fitting.",
        "",
        "Tested (`tests/test_biot.py`): E = 1e12 Pa gives rigid JCA (rigid-backed, 1e-6) and, with",
        "rho_1 = 1e12, the equivalent-fluid 2-port (1e-6); with a real rho_1 the mobile-rigid-frame closed",
        "form (1e-6); E = 1e-6 Pa gives Panneton's limp frame (both, 1e-6); det T = 1 (1e-10); passivity;",
        "the frame-resonance dip within 15 % of c_frame / (4 d); ValueError naming bad parameters.",
        "",
        "## Measured foam",
        "",
        f"Generated by `python studies/elastic_frame.py --sample {sample}` ({seconds:.0f} s on the CPU).",
        "",
        f"Data: Atalla & Panneton (2005) `{sample}`, thin ({data[0].thickness * 1e3:.2f} mm) and thick "
        f"({data[1].thickness * 1e3:.2f} mm) layers,",
        f"{data[0].freq.min():g}-{data[0].freq.max():g} Hz, fitted together (one material) with",
        "`scipy.optimize.least_squares` (log parameters within bounds). Error: rms|Z_meas - Z_model| /",
        "rms|Z_meas| (docs/formats.md). Poisson ratio fixed at 0.3 (not identifiable at normal incidence).",
        "",
        "| rows | rigid JCA | Biot (elastic frame) |",
        "| --- | --- | --- |",
    ]
    lines += [f"| {n} | {a:.4f} | {b:.4f} |" for n, a, b in rows]
    lines += [
        "",
        "Fitted parameters (README: the paper's values):",
        "",
        "| parameter | unit | README | rigid JCA | Biot |",
        "| --- | --- | --- | --- | --- |",
    ]
    for k in biot.JCA_PARAMETERS:
        lines.append(f"| {k} | {units[k]} | {readme[k]:.4g} | {rv[k]:.4g} | {ev[k]:.4g} |")
    for k in ("E", "eta", "rho_1"):
        lines.append(f"| {k} | {units[k]} | | | {ev[k]:.4g} |")
    names = [s[0] for s in RIGID + FRAME]
    std, corr = e_std
    iE, ir = names.index("E"), names.index("rho_1")
    lines += [
        "",
        "Relative std (from the Jacobian, indicative: digitized data) of the Biot fit: "
        + ", ".join(f"{n} {v:.2g}" for n, v in zip(names, std))
        + f"; correlation(E, rho_1) = {corr[iE, ir]:.3f}: what the data fix is the frame wave speed",
        "(the resonance frequency), less so E and rho_1 apart.",
    ]
    r_bound = [s[0] for s, m in zip(RIGID, r_fit.active_mask) if m != 0]
    e_bound = [s[0] for s, m in zip(RIGID + FRAME, e_fit.active_mask) if m != 0]
    lines += [
        "",
        f"In-vacuo frame wave speed of the Biot fit: c_frame = sqrt(E (1-nu)/((1+nu)(1-2nu) rho_1)) = "
        f"{c_frame:.1f} m/s;",
        f"quarter-wavelength frame resonance c_frame / (4 d): thin {c_frame / (4 * data[0].thickness):.0f} Hz, "
        f"thick {c_frame / (4 * data[1].thickness):.0f} Hz.",
        f"Parameters at a bound: rigid JCA {', '.join(r_bound) or 'none'}; Biot {', '.join(e_bound) or 'none'}.",
        "",
        "![impedance: data, rigid JCA, Biot](elastic_frame.png)",
        "",
    ]
    if "Lambda" in r_bound:
        lines[-3:-3] = [
            "(The rigid fit runs Lambda to its bound, flattening the viscous dispersion in place of the",
            "missing frame; for foam2, raising the bound to 10 mm left its error at 0.0581.)",
        ]
    Path(path).write_text("\n".join(lines))


if __name__ == "__main__":
    raise SystemExit(main())
