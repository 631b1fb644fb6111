"""The paper's two-step characterization (docs/physics.md "Inverse problem", paper Sect. 4-5).

>>> from tawarp.fit.characterize import characterize
>>> from tawarp.measure.synthetic import make_paper_data
>>> ch = characterize(make_paper_data("mesh"), "mesh")
>>> ch.step1.value_dict(), ch.step2.values          # geometry; (h_s, h_h, h_a) per Q > 0

Step 1, Q = 0: fit the stack's geometry on the unheated data. For a stack made of the
same material as the hot exchanger (the ceramic run: same porosity, pore radius,
tortuosity and solid conductivity in the core file), the free parameters are
``stack.porosity`` and ``stack.pore_radius`` *tied* to ``hot_hx.porosity`` and
``hot_hx.pore_radius``, tortuosity fixed; otherwise ``stack.porosity``,
``stack.pore_radius``, ``stack.tortuosity`` (:func:`default_geometry`).

Bias correction (Eqs. 22-23): ``b_i = Y_i(Q=0; fitted) / Ybar_i(Q=0)`` per frequency
and coefficient; step 2 fits the corrected data ``Ybar_i(Q) b_i``.

Step 2, every Q > 0 in one batch: the heat-exchange coefficients of the thermal
segments (``stack.h``, ``hot_hx.h``, ``tbt.h``) with the geometry of step 1 fixed.

Weights: when the data carry ``sigma_*`` columns, ``w = 1/sigma`` of the dimensionless
value (re and im separately; in step 2 the sigma of ``Ybar(Q) b`` propagates the noise
of both ``Ybar(Q)`` and ``Ybar(0)``: ``|b| sqrt(s_Q^2 + |Ybar(Q)/Ybar(0)|^2 s_0^2)`` with
``s^2 = (s_re^2 + s_im^2)/2``, for both parts); else 1.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..model.coefficients import COEFFICIENTS, duct_impedance, normalize, rms_error
from ..model.fields import field as field_spec
from ..model.core import Core, load_core
from ..model import effects
from ..model.effects import same_material_ties
from .estimate import FitResult, fit, predict
from ..model.forward import ForwardSettings
from ..measure.files import TMatrixData
from ..rng import checked_seed


def stack_and_heater(core: Core) -> tuple[str, str]:
    """Names of the stack (the porous thermal segment that is not the heater) and of the
    hot exchanger (the heater): :func:`tawarp.model.effects.stack_and_heater`, raising
    where the core has none (a passive core, a core without a stack)."""
    heater = core.segments[core.heater_index].name  # (a CoreError for a passive core)
    stack, _ = effects.stack_and_heater(core)
    if stack is None:
        raise ValueError(f"{core.source}: no porous thermal segment besides the heater (the stack)")
    return stack, heater


def default_geometry(core: Core) -> tuple[list[str], dict[str, list[str]]]:
    """Step-1 free parameters and ties (module doc;
    :func:`tawarp.model.effects.same_material_ties`)."""
    stack, _ = stack_and_heater(core)
    ties = same_material_ties(core, ("porosity", "pore_radius"))  # (the tortuosity fixed)
    if ties:
        return list(ties), ties
    return [f"{stack}.porosity", f"{stack}.pore_radius", f"{stack}.tortuosity"], {}


def default_heat_names(core: Core) -> list[str]:
    """Step-2 free parameters: ``h`` of every thermal segment, in core order."""
    return [f"{s.name}.h" for s in core.segments if s.thermal]


def grid(data: TMatrixData, core: Core):
    """Heat inputs (nQ,), shared frequencies (m,), dimensionless Y (nQ, m, 4) and
    weights (nQ, m, 4, 2) or None, with rows sorted by frequency. One sort of all rows
    (linear in the file, whatever the number of heat inputs)."""
    Qs = data.heat_inputs
    order = np.lexsort((data.freq, data.heat_input))
    counts = np.unique(data.heat_input, return_counts=True)[1]
    nQ, m = len(Qs), int(counts[0])
    F = data.freq[order].reshape(nQ, m) if np.all(counts == m) else None
    bad = (
        np.flatnonzero(counts != m)
        if F is None
        else np.flatnonzero(~np.all(np.isclose(F, F[0], rtol=1e-9, atol=0.0), axis=1))
    )
    if bad.size:
        raise ValueError(
            f"{data.source}: the rows at Q = {Qs[bad[0]]:g} W have other frequencies than at "
            f"Q = {Qs[0]:g} W; every heat input must share one frequency grid"
        )
    zc = duct_impedance(core)
    Y = normalize(data.T[order], zc).reshape(nQ, m, 4)
    sig = None
    if data.sigma is not None:
        s = data.sigma[order]  # (rows, 2, 2, 2) raw
        sig = np.stack([s[:, 0, 0], s[:, 0, 1] / zc, s[:, 1, 0] * zc, s[:, 1, 1]], axis=1).reshape(nQ, m, 4, 2)
    return Qs, F[0], Y, sig


@dataclass
class Characterization:
    """Both steps of a characterization.

    ``core``: the core with the fitted geometry (step 1; ties applied); ``freqs`` (m,);
    ``step1`` (a one-problem :class:`FitResult`), ``Y0`` measured and ``Y0_fit`` fitted
    (m, 4) at Q = 0; ``bias`` (m, 4) the b_i of Eq. 23 (ones when not applied);
    ``heat_inputs`` (nQ,) Q > 0; ``step2`` (one problem per Q, or None), ``Y`` measured,
    ``Y_corr`` bias-corrected and ``Y_fit`` fitted (nQ, m, 4).
    """

    core: Core
    freqs: np.ndarray
    geometry_names: list[str]
    ties: dict
    step1: FitResult
    Y0: np.ndarray
    Y0_fit: np.ndarray
    bias: np.ndarray
    heat_inputs: np.ndarray
    heat_names: list[str]
    step2: FitResult | None
    Y: np.ndarray
    Y_corr: np.ndarray
    Y_fit: np.ndarray
    settings: ForwardSettings
    source: str = "<data>"

    def h_at(self, Q: float) -> dict[str, float]:
        """Fitted heat-exchange coefficients at heat input Q [W], linearly interpolated
        between the fitted heat inputs (held constant beyond them)."""
        if self.step2 is None or not len(self.heat_inputs):
            return {k: self.core.get(k) for k in self.heat_names}
        return {
            k: float(np.interp(Q, self.heat_inputs, self.step2.values[:, a])) for a, k in enumerate(self.heat_names)
        }

    def to_json(self) -> dict:
        """The fit.json structure (docs/formats.md): step 1 and one step-2 entry per Q."""
        s1 = {"heat_input_W": 0.0, **self.step1.problem(0)}
        out = {
            "data": self.source,
            "core": str(self.core.source),
            "freqs_Hz": self.freqs.tolist(),
            "procedure": "two-step (paper Sect. 4): geometry at Q = 0, then h at every Q > 0 on the "
            "bias-corrected data of Eqs. 22-23",
            "cells": self.settings.cells,
            "cell_density": self.settings.cell_density,
            "parameters": s1["parameters"],
            "correlation": s1["correlation"],
            "ties": self.ties,
            "step1": s1,
            "bias_correction": {
                "max_abs_b_minus_1": float(np.max(np.abs(self.bias - 1))) if self.bias.size else 0.0,
                "b": {
                    c: {"re": self.bias[:, k].real.tolist(), "im": self.bias[:, k].imag.tolist()}
                    for k, c in enumerate(COEFFICIENTS)
                },
            },
            "step2": [],
        }
        fits = [self.step1]
        if self.step2 is not None:
            for i, q in enumerate(self.heat_inputs):
                out["step2"].append({"heat_input_W": float(q), **self.step2.problem(i)})
            fits.append(self.step2)
        Ym = np.concatenate([self.Y0[None], self.Y_corr]) if self.step2 is not None else self.Y0[None]
        Yf = np.concatenate([self.Y0_fit[None], self.Y_fit]) if self.step2 is not None else self.Y0_fit[None]
        out["converged"] = bool(all(f.converged.all() for f in fits))
        out["iterations"] = int(sum(int(f.iterations.sum()) for f in fits))
        out["cost"] = float(sum(float(f.cost.sum()) for f in fits))
        out["rms_error"] = float(rms_error(Ym, Yf))
        out["warnings"] = [f"step 1: {w}" for w in self.step1.warnings] + (
            [f"step 2: {w}" for w in self.step2.warnings] if self.step2 is not None else []
        )
        return out


def _start(core, names, start, N):
    if isinstance(start, str) and start == "spread":
        return None
    if start is None:
        return {k: core.get(k) for k in names}
    return {k: start.get(k, core.get(k)) for k in names}


def _weights(sig):
    if sig is None:
        return None
    with np.errstate(divide="ignore"):
        return 1.0 / sig


def characterize(
    data: TMatrixData,
    core: Core | str,
    *,
    geometry: list[str] | None = None,
    ties=None,
    heat_names: list[str] | None = None,
    start1=None,
    start2=None,
    bias_correction: bool = True,
    settings: ForwardSettings | None = None,
    device: str | None = None,
    restarts: int = 2,
    n_starts: int = 8,
    damping: str = "nielsen",
    use_sigma: bool = True,
    seed: int = 0,
    progress: bool = False,
    warn: bool = True,
    propagate: bool = True,
) -> Characterization:
    """Run the two-step procedure on ``data`` (needs rows at Q = 0; every heat input on
    one frequency grid). ``geometry``/``ties`` default to :func:`default_geometry`,
    ``heat_names`` to :func:`default_heat_names`. ``start1``/``start2``: None (the core's
    values), ``"spread"`` (a Sobol spread of ``n_starts`` starts) or {name: value}.
    ``restarts`` extra runs from the solution ±20 % (paper). ``propagate``: add the
    step-1 geometry uncertainty to the step-2 covariance (:func:`geometry_propagation`;
    the statistical part stays in ``step2.std_statistical``). Returns a
    :class:`Characterization`."""
    seed = checked_seed(seed, "characterize")
    core = load_core(core) if isinstance(core, (str, Path)) else core
    settings = settings or ForwardSettings()
    if device is not None:
        settings = dataclasses.replace(settings, device=device)
    if geometry is None:
        geometry, dties = default_geometry(core)
        ties = dties if ties is None else ties
    ties = ties or {}
    heat_names = heat_names or default_heat_names(core)
    Qs, freqs, Y, sig = grid(data, core)
    if not use_sigma:
        sig = None
    if not np.any(Qs == 0):
        raise ValueError(f"{data.source}: no rows at Q = 0 W; step 1 (geometry) needs unheated data")
    i0 = int(np.flatnonzero(Qs == 0)[0])
    kw = dict(
        settings=settings,
        damping=damping,
        restarts=restarts,
        n_starts=n_starts,
        seed=seed,
        progress=progress,
        warn=warn,
    )
    s1 = fit(
        core,
        freqs,
        Y[i0],
        geometry,
        _start(core, geometry, start1, 1),
        heat_input=0.0,
        ties=ties,
        weights=None if sig is None else _weights(sig[i0])[None],
        **kw,
    )
    vals = s1.value_dict(0)
    for k, others in ties.items():
        for o in others:
            vals[o] = vals[k]
    core1 = core.replace(**vals)
    Y0_fit = predict(core1, freqs, settings=settings)[0]
    hot = Qs > 0
    Qh = Qs[hot]
    bias = Y0_fit / Y[i0] if bias_correction else np.ones_like(Y0_fit)
    Yh = Y[hot]
    Y_corr = Yh * bias[None]
    step2 = None
    Y_fit = np.zeros_like(Y_corr)
    if Qh.size:
        w2 = None
        if sig is not None:
            # Ybar(Q) b = Ybar(Q) Y0_fit / Ybar(0): first-order propagation of both noises
            s2q = 0.5 * (sig[hot][..., 0] ** 2 + sig[hot][..., 1] ** 2)
            s20 = 0.5 * (sig[i0][..., 0] ** 2 + sig[i0][..., 1] ** 2)
            s = (
                np.abs(bias)[None] * np.sqrt(s2q + np.abs(Yh / Y[i0][None]) ** 2 * s20[None])
                if bias_correction
                else np.sqrt(s2q)
            )
            w2 = _weights(np.stack([s, s], axis=-1))
        step2 = fit(
            core1,
            freqs,
            Y_corr,
            heat_names,
            _start(core1, heat_names, start2, Qh.size),
            heat_input=Qh,
            weights=w2,
            **kw,
        )
        Y_fit = predict(
            core1, freqs, {k: step2.values[:, a] for a, k in enumerate(heat_names)}, heat_input=Qh, settings=settings
        )
        if propagate and np.all(np.isfinite(s1.covariance[0])):
            step2.add_covariance(
                geometry_propagation(
                    core1,
                    freqs,
                    Qh,
                    heat_names,
                    step2.values,
                    list(geometry),
                    ties,
                    s1.covariance[0],
                    Yh,
                    Y[i0],
                    w2,
                    settings,
                    bias_correction,
                )
            )
    return Characterization(
        core1,
        freqs,
        list(geometry),
        ties,
        s1,
        Y[i0],
        Y0_fit,
        bias,
        Qh,
        heat_names,
        step2,
        Yh,
        Y_corr,
        Y_fit,
        settings,
        data.source,
    )


def geometry_propagation(
    core1: Core,
    freqs,
    Qh,
    heat_names,
    hvals,
    geometry,
    ties,
    Cg,
    Yh,
    Y0,
    w2,
    settings,
    bias_correction: bool = True,
    rel: float = 1e-6,
) -> np.ndarray:
    """Covariance (nQ, ph, ph) the step-1 geometry uncertainty ``Cg`` (pg, pg) adds to the
    step-2 estimates, by the implicit-function theorem: at the step-2 solution
    ``dh/dg = -(J_h^T J_h)^-1 J_h^T J_g`` with ``J_g`` the derivative of the step-2
    residual ``w (Y_Q(h, g) - Ybar_Q Y_0(g) / Ybar_0)`` (the bias correction depends on g
    too), so ``C_add = (dh/dg) Cg (dh/dg)^T``. Derivatives by forward differences of the
    forward model (relative step ``rel``); the geometry is held at its step-1 values.
    Problems share a cell count only with problems that need about as many
    (:func:`cell_groups`), so one outlying h does not size the whole batch."""
    from .estimate import smooth_settings

    nQ, ph = hvals.shape
    pg = len(geometry)
    m = len(freqs)
    g0 = np.array([core1.get(k) for k in geometry])
    k_sets = 1 + ph + pg
    params = {k: np.repeat(hvals[:, a], k_sets).reshape(nQ, k_sets).copy() for a, k in enumerate(heat_names)}
    params.update({k: np.full((nQ, k_sets), g0[b]) for b, k in enumerate(geometry)})
    # steps towards the interior: a porosity fitted at 1 must not be stepped past it
    g_step = np.array([-rel * g if g * (1 + rel) > field_spec(k).upper else rel * g for k, g in zip(geometry, g0)])
    steps = np.concatenate([hvals * rel, np.broadcast_to(g_step, (nQ, pg))], axis=1)  # (nQ, ph + pg)
    for a, k in enumerate(heat_names + geometry):
        params[k][:, 1 + a] += steps[:, a]
    Y = np.empty((nQ, k_sets, m, 4), dtype=complex)
    for idx, cells in cell_groups(core1, freqs, settings, {k: hvals[:, a] for a, k in enumerate(heat_names)}):
        Y[idx] = predict(
            core1,
            freqs,
            {k: v[idx].reshape(-1) for k, v in params.items()},
            heat_input=np.repeat(Qh[idx], k_sets),
            ties=ties,
            settings=cells,
        ).reshape(-1, k_sets, m, 4)
    dY = (Y[:, 1:] - Y[:, :1]) / steps[:, :, None, None]  # (nQ, ph+pg, m, 4)
    Jh, Jg = dY[:, :ph], dY[:, ph:]
    if bias_correction:
        p0 = {k: np.full(1 + pg, g0[b]) for b, k in enumerate(geometry)}
        for b, k in enumerate(geometry):
            p0[k][1 + b] += g_step[b]
        Y0m = predict(
            core1, freqs, p0, heat_input=0.0, ties=ties, settings=smooth_settings(core1, freqs, settings)
        )  # (1 + pg, m, 4)
        dY0 = (Y0m[1:] - Y0m[:1]) / g_step[:, None, None]
        Jg = Jg - (Yh / Y0[None])[:, None] * dY0[None]
    w = np.ones((nQ, m, 4, 2)) if w2 is None else np.broadcast_to(w2, (nQ, m, 4, 2))
    out = np.zeros((nQ, ph, ph))
    for i in range(nQ):

        def real(J):
            return np.concatenate(
                [(J.real * w[i, ..., 0]).reshape(J.shape[0], -1), (J.imag * w[i, ..., 1]).reshape(J.shape[0], -1)],
                axis=1,
            ).T

        A = -np.linalg.lstsq(real(Jh[i]), real(Jg[i]), rcond=None)[0]  # (ph, pg)
        out[i] = A @ Cg @ A.T
    return out


def cell_groups(core: Core, freqs, settings: ForwardSettings, values: dict):
    """Problems grouped by the Magnus cells a smooth model of each needs: yields
    (indices, settings with fixed cells). A problem's count per thermal segment is the
    fit's rule at its own ``values`` {name: (n,)} (:func:`tawarp.measure.kind.fit_cells`,
    room for k twice as large), rounded up to a power of sqrt(2): a handful of groups
    covers any spread of h, at most 42 % more cells than a problem needs, and every
    problem keeps one count across its difference steps. Fixed ``settings.cells``: one group."""
    from ..measure.kind import fit_cells

    n = len(next(iter(values.values())))
    if settings.cells is not None:
        yield np.arange(n), settings
        return
    thermal = [i for i, s in enumerate(core.segments) if s.thermal]
    need = fit_cells(core, float(np.max(freqs)), values, settings, k_factor=2.0).reshape(n, -1)[:, thermal]
    cells = np.ceil(np.sqrt(2.0) ** np.ceil(2 * np.log2(np.maximum(need, 1)) - 1e-9) - 1e-9).astype(int)
    keys, inverse = np.unique(cells, axis=0, return_inverse=True)
    for g, key in enumerate(keys):
        yield (
            np.flatnonzero(inverse.reshape(-1) == g),
            dataclasses.replace(settings, cells={core.segments[i].name: int(c) for i, c in zip(thermal, key)}),
        )


# -- figures -----------------------------------------------------------------------------
def plot_h_vs_Q(curves: dict[str, tuple], path, title: str = ""):
    """Fig. 5: fitted heat-exchange coefficients against Q with ±1 std error bars.
    ``curves``: label -> (Q (n,), values (n, 3), std (n, 3), names (3,))."""
    from ..plots import plt, save

    first = next(iter(curves.values()))
    k = len(first[3])
    fig, axes = plt.subplots(1, k, figsize=(4.2 * k, 3.6))
    axes = np.atleast_1d(axes)
    for label, (Q, v, s, _names) in curves.items():
        for a in range(k):
            axes[a].errorbar(
                Q, v[:, a], yerr=np.where(np.isfinite(s[:, a]), s[:, a], 0), marker="o", ms=4, capsize=3, label=label
            )
    for a, name in enumerate(first[3]):
        axes[a].set_title(name)
        axes[a].set_xlabel("Q [W]")
        axes[a].set_yscale("log")
    axes[0].set_ylabel("h [W/(m$^2$ K)]")
    axes[0].legend(fontsize=7)
    if title:
        fig.suptitle(title)
    return save(fig, path)


def plot_normalized_temperature(profiles: dict[str, tuple], path, title: str = ""):
    """Fig. 6: (T - T_cold)/(T_max - T_cold) along the core; ``profiles``: label -> (x, T)."""
    from ..plots import plt, save

    fig, ax = plt.subplots(figsize=(7, 4))
    for label, (x, T) in profiles.items():
        th = T - T.min()
        ax.plot(np.asarray(x) * 100, th / max(th.max(), 1e-300), label=label)
    ax.set_xlabel("x [cm]")
    ax.set_ylabel("(T - T$_c$) / (T$_{max}$ - T$_c$)")
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    return save(fig, path)


def temperature_profile(ch: Characterization, Q: float, n: int = 400):
    """(x [m], T(x) [K]) of the fitted core at heat input Q [W] (h interpolated in Q)."""
    from ..model.forward import steady_temperature

    x = np.linspace(0, ch.core.positions()[-1], n)
    T, _ = steady_temperature(ch.core, x, heat_input=Q, params=ch.h_at(Q), settings=ch.settings)
    return x, T[0]


#: Most heat inputs drawn in the step-2 figure (evenly spread, first and last included):
#: more curves make neither a readable figure nor a legend.
MAX_CURVES = 8


#: The figures of a characterization: ``STEM_NAME.png`` (:func:`write_figures`).
FIGURES = ("step1", "step2", "h", "temperature")


def figure_paths(stem: str | Path) -> list[Path]:
    """The files :func:`write_figures` may write for ``stem``."""
    return [Path(f"{stem}_{name}.png") for name in FIGURES]


def write_figures(ch: Characterization, stem: str | Path, label: str = "") -> list[Path]:
    """Figures of one characterization: ``STEM_step1.png`` (Fig. 3), ``STEM_step2.png``
    (Fig. 4; at most :data:`MAX_CURVES` heat inputs), ``STEM_h.png`` (Fig. 5),
    ``STEM_temperature.png`` (Fig. 6: the fitted profiles at the measured heat inputs of
    the step-2 figure, each with the h fitted there; no profile is drawn where no h was
    fitted)."""
    from ..plots import plot_coefficients, plot_temperature

    stem = Path(stem)
    label = label or Path(str(ch.core.source)).stem
    paths = [
        plot_coefficients(
            ch.freqs,
            {"fitted": ch.Y0_fit},
            f"{stem}_step1.png",
            markers={"measured": ch.Y0},
            title=f"{label}: Q = 0, measured vs fitted ({_fmt1(ch)})",
        )
    ]
    if ch.step2 is not None:
        nQ = len(ch.heat_inputs)
        shown = np.unique(np.linspace(0, nQ - 1, min(nQ, MAX_CURVES)).round().astype(int))
        some = f" ({shown.size} of {nQ} heat inputs)" if shown.size < nQ else ""
        paths.append(
            plot_coefficients(
                ch.freqs,
                {f"fit Q = {ch.heat_inputs[i]:g} W": ch.Y_fit[i] for i in shown},
                f"{stem}_step2.png",
                markers={f"Q = {ch.heat_inputs[i]:g} W": ch.Y_corr[i] for i in shown},
                title=f"{label}: heated, bias-corrected measured vs fitted{some}",
            )
        )
        paths.append(
            plot_h_vs_Q(
                {label: (ch.heat_inputs, ch.step2.values, ch.step2.std, ch.heat_names)},
                f"{stem}_h.png",
                title=f"{label}: fitted heat-exchange coefficients",
            )
        )
        profiles = {f"Q = {ch.heat_inputs[i]:g} W": temperature_profile(ch, ch.heat_inputs[i]) for i in shown}
        paths.append(
            plot_temperature(
                next(iter(profiles.values()))[0],
                {k: T for k, (x, T) in profiles.items()},
                f"{stem}_temperature.png",
                planes=ch.core.positions(),
                title=f"{label}: fitted temperature profiles at the measured heat inputs{some}",
            )
        )
    return paths


def _fmt1(ch):
    r = ch.step1
    return ", ".join(f"{k.split('.')[-1]} = {v:.4g} ± {s:.2g}" for k, v, s in zip(r.names, r.values[0], r.std[0]))


def fit_each_heat_input(
    data: TMatrixData,
    core: Core,
    names,
    *,
    settings=None,
    start=None,
    restarts=2,
    damping="nielsen",
    use_sigma=True,
    progress=False,
) -> dict:
    """Fit ``names`` at every heat input of ``data`` (one problem per Q, one batch, no
    bias correction); the fit.json structure with one entry per Q under ``fits``."""
    Qs, freqs, Y, sig = grid(data, core)
    st = None if start == "spread" else {k: core.get(k) for k in names}
    r = fit(
        core,
        freqs,
        Y,
        names,
        st,
        heat_input=Qs,
        weights=None if (sig is None or not use_sigma) else 1.0 / sig,
        settings=settings,
        restarts=restarts,
        damping=damping,
        progress=progress,
        warn=False,
    )
    fits = [{"heat_input_W": float(q), **r.problem(i)} for i, q in enumerate(Qs)]
    return {
        "data": data.source,
        "core": str(core.source),
        "freqs_Hz": freqs.tolist(),
        "fits": fits,
        "parameters": fits[0]["parameters"],
        "correlation": fits[0]["correlation"],
        "converged": bool(r.converged.all()),
        "iterations": int(r.iterations.sum()),
        "cost": float(r.cost.sum()),
        "rms_error": pooled_error(r.rms_error, Y),
        "warnings": r.warnings,
    }


def pooled_error(errors: np.ndarray, Y: np.ndarray) -> float:
    """docs/formats.md's error over all rows of N problems from each problem's own error
    ``errors`` (N,) and measured values ``Y`` (N, ...): rms|dY| / rms|Y| pooled over the
    rows, ``sqrt(sum e_i^2 |Y_i|^2 / sum |Y_i|^2)`` (not the mean of the per-problem ratios)."""
    y2 = np.sum(np.abs(Y.reshape(len(errors), -1)) ** 2, axis=1)
    return float(np.sqrt(np.sum(np.asarray(errors) ** 2 * y2) / np.sum(y2)))
