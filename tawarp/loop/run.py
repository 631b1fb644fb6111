"""The loop (steps of the package doc :mod:`tawarp.loop`): base fit, screening,
augmented fits in lockstep, the acceptance tests, held-out rows and the drift of h."""

from __future__ import annotations

import numpy as np
from scipy import stats

from ..fit.problems import fit_batch, fit_one
from ..fit.result import FitResult
from ..measure.impedance import ImpedanceKind
from ..measure.kind import MeasurementKind
from ..measure.tmatrix import TMatrixKind
from ..model.coefficients import rms_error
from ..model.effects import Effect, Param, base_params, impedance_library, tmatrix_library
from ..model.forward import ForwardSettings
from ..model.layer import jca_equivalent
from ..progress import progress_bar
from .screen import residual_structure, screen

#: Acceptance thresholds (package docstring, step 5).
DELTA_BIC = -10.0
F_TEST_P = 0.01
NOISE_FACTOR = 1.5
CHI2_P = 1e-3
#: Two effects whose BIC differ by less than this are indistinguishable ("not worth more
#: than a bare mention" on Kass & Raftery's scale).
INDISTINGUISHABLE_BIC = 2.0


def library_for(problem: MeasurementKind) -> list[Effect]:
    """The candidate effects of a kind: :func:`tmatrix_library` for core T-matrices (and
    scattering), :func:`impedance_library` for layers, none for other kinds."""
    if isinstance(problem, TMatrixKind):
        return tmatrix_library(problem.core)
    if isinstance(problem, ImpedanceKind):
        return impedance_library(problem.core)
    return []


def holdout_rows(problem: MeasurementKind) -> tuple[np.ndarray, np.ndarray, str]:
    """(train, test) row indices: the highest group (heat input / thickness) when there are
    three or more groups, else every third frequency."""
    groups = np.unique(problem.group)
    if isinstance(problem, TMatrixKind) and len(groups) >= 3:
        test = problem.group == groups[-1]
        what = f"{problem.group_name} = {groups[-1]:g}"
    else:
        f = np.unique(problem.freq)
        held = f[1::3]
        test = np.isin(problem.freq, held)
        what = "every third frequency"
    return np.flatnonzero(~test), np.flatnonzero(test), what


def _param_report(f: FitResult) -> dict:
    return {k: {"value": v, "std": s} for (k, v), s in zip(f.value_dict().items(), f.std[0])}


def drift(problem: MeasurementKind, base_params: list[Param], sol: FitResult, fixed: dict, effect: Effect | None) -> dict | None:
    """h's refitted at each heat input > 0 alone, the rest fixed at ``sol``."""
    if not isinstance(problem, TMatrixKind):
        return None
    hp = [par for par in base_params if par.label.endswith(".h")]
    Qs = [q for q in np.unique(problem.group) if q > 0]
    if not hp or len(Qs) < 2:
        return None
    fx = dict(fixed)
    for par in sol.params:
        if par not in hp:
            par.assign(float(sol.value_dict()[par.label]), fx)
    hp_start = [par.with_start(sol.value_dict()[par.label]) for par in hp]
    out = {par.label: [] for par in hp}
    for q in Qs:
        rows = np.flatnonzero(problem.group == q)
        f = fit_one(problem, hp_start, fx, effect, rows)
        for par in hp:
            out[par.label].append(f.value_dict()[par.label])
    res = {"Q_W": [float(q) for q in Qs], "values": out}
    res["relative_spread"] = {k: float(np.ptp(v) / np.mean(v)) if np.mean(v) else None for k, v in out.items()}
    return res


def default_base_params(problem: MeasurementKind, names=None) -> list[Param]:
    """Fit parameters for ``names`` (default: the kind's ``default_names()``: the stack's
    porosity and pore radius and the thermal segments' h for T-matrix data; porosity, pore
    radius, tortuosity of a layer), scaling and bounds from :mod:`tawarp.model.fields`."""
    return base_params(problem.core, names if names is not None else problem.default_names())


#: The loop's stages, in order, as its progress bar names them.
STAGES = ("base fit", "screening", "held-out base fit", "refits", "second pass", "drift")


def run_loop(problem: MeasurementKind, base_params: list[Param] | None = None, library: list[Effect] | None = None,
             top: int = 3, drift_h: bool = True, progress: bool = False) -> dict:
    """The loop of the module docstring; returns the report dict (report.json).
    ``library``: candidate effects (default :func:`library_for` the kind); ``progress``: a
    bar over the :data:`STAGES` (on a terminal only).
    """
    bar = progress_bar(len(STAGES), "closing the loop", progress, unit="stage")

    def stage(name: str) -> None:
        bar.set_postfix_str(name)
        bar.update(1)

    base_params = base_params or default_base_params(problem)
    if library is None:
        library = library_for(problem)
    fixed = {}
    base = fit_one(problem, base_params)
    stage("base fit")
    N, p = base.n, len(base_params)
    rss0 = float(base.cost[0])
    floor = problem.noise_floor()
    has_sigma = problem.has_sigma
    structure_before = residual_structure(problem, base.model[0])
    scores = screen(problem, base, fixed, library)
    stage("screening")
    promising = sorted([s for s in scores if s["linearized_p"] < F_TEST_P], key=lambda s: -s["score"])[:top]
    train, test, held = holdout_rows(problem)
    base_train = fit_one(problem, base_params, rows=train, x0=base.x[0])
    base_held_err = float(rms_error(problem.y[test], base_train.model[0, test]))
    stage("held-out base fit")
    candidates = {}

    def refit(names: list[str]):
        """Augmented fits of the candidates ``names``, all in one batched fit: two starts
        each, effect off (the base solution and the core's own values: a strong effect can
        pull the base fit far from where the augmented optimum lies), then the held-out
        refits, again in one batch."""
        effects = [next(x for x in library if x.name == name) for name in names]
        specs = []
        for e in effects:
            k = len(e.params)
            for x0 in (np.concatenate([base.x[0], np.zeros(k)]), np.zeros(p + k)):
                specs.append((base_params + list(e.params), e, x0))
        fits = fit_batch(problem, specs, fixed)
        augs = [min(fits[2 * i:2 * i + 2], key=lambda f: float(f.cost[0])) for i in range(len(effects))]
        specs_t = [(base_params + list(e.params), e, a.x[0]) for e, a in zip(effects, augs)]
        trains = fit_batch(problem, specs_t, fixed, rows=train)
        for e, aug, aug_train in zip(effects, augs, trains):
            k = len(e.params)
            F = ((rss0 - float(aug.cost[0])) / k) / max(float(aug.cost[0]) / max(N - p - k, 1), 1e-300)
            pval = float(stats.f.sf(F, k, max(N - p - k, 1)))
            dbic = aug.bic(has_sigma) - base.bic(has_sigma)
            held_err = float(rms_error(problem.y[test], aug_train.model[0, test]))
            checks = {"delta_bic": dbic < DELTA_BIC, "f_test": pval < F_TEST_P, "held_out": held_err < base_held_err}
            if floor is not None:
                checks["noise_floor"] = float(aug.rms_error[0]) <= NOISE_FACTOR * floor
                checks["chi2"] = float(stats.chi2.sf(float(aug.cost[0]), max(N - p - k, 1))) > CHI2_P
            candidates[e.name] = {"fit": aug, "error_after": float(aug.rms_error[0]), "delta_bic": dbic, "F": F, "p_value": pval,
                                  "explained_fraction": (rss0 - float(aug.cost[0])) / rss0 if rss0 > 0 else 0.0,
                                  "held_out_error": held_err, "checks": checks, "accepted": all(checks.values())}

    refit([s["effect"] for s in promising])
    stage("refits")
    second_pass = False
    if not any(c["accepted"] for c in candidates.values()):
        # the screening is linear: when no promising candidate is accepted, refit the rest too
        second_pass = True
        rest = [s["effect"] for s in sorted(scores, key=lambda s: -s["score"]) if s["effect"] not in candidates]
        if rest:
            refit(rest)
    stage("second pass")
    bic = {name: c["fit"].bic(has_sigma) for name, c in candidates.items()}
    accepted = [name for name, c in candidates.items() if c["accepted"]]
    best = min(accepted, key=bic.get) if accepted else None
    # a rival that the data support as strongly (Delta BIC and F-test passed, BIC within
    # INDISTINGUISHABLE_BIC of the best) cannot be told apart from it: name both, choose neither
    rivals = [name for name, c in candidates.items() if best and name != best and c["checks"]["delta_bic"]
              and c["checks"]["f_test"] and abs(bic[name] - bic[best]) < INDISTINGUISHABLE_BIC]
    chosen = None if rivals else best
    indistinguishable = sorted([best] + rivals) if rivals else []
    after = candidates[best]["fit"] if best else base
    report = {
        "kind": problem.name,
        "n_residuals": N,
        "noise_floor": floor,
        "error_before": float(base.rms_error[0]),
        "error_after": float(after.rms_error[0]),
        "chosen_effect": chosen,
        "chosen_description": next((e.description for e in library if e.name == chosen), None),
        "indistinguishable": indistinguishable,
        "indistinguishable_bic": INDISTINGUISHABLE_BIC,
        "best_effect": best,
        "acceptance_test": (f"accepted when Delta BIC < {DELTA_BIC:g}, F-test p < {F_TEST_P:g} (the cost drop exceeds "
                            f"what noise gives), the held-out rows ({held}) are predicted better than by the base "
                            f"model" + (f", and the residual after is noise (chi^2 p > {CHI2_P:g}, error after <= "
                                        f"{NOISE_FACTOR:g} x noise floor)" if floor else "")
                            + f"; lowest BIC among accepted; candidates within {INDISTINGUISHABLE_BIC:g} of it in BIC that "
                              "also pass the BIC and F tests are reported as indistinguishable, none chosen"),
        "held_out": held,
        "second_pass": second_pass,
        "note": (None if floor is not None else
                 "no sigma in the data: the noise floor is unknown, so an accepted effect may explain only part of the "
                 "residual (see explained_fraction and residual_structure_after)"),
        "held_out_error_base": base_held_err,
        "parameters_before": _param_report(base),
        "parameters_after": _param_report(after),
        "base_converged": bool(base.converged[0]),
        "candidates": [],
        "residual_structure_before": structure_before,
        "residual_structure_after": residual_structure(problem, after.model[0]),
    }
    for s in scores:
        c = candidates.get(s["effect"])
        row = dict(s)
        if c is not None:
            row.update({"refit": True, "error_after": c["error_after"], "explained_fraction": c["explained_fraction"],
                        "delta_bic": c["delta_bic"], "F": c["F"],
                        "p_value": c["p_value"], "held_out_error": c["held_out_error"], "checks": c["checks"],
                        "accepted": c["accepted"], "fitted": _param_report(c["fit"])})
        else:
            row.update({"refit": False, "accepted": False})
        report["candidates"].append(row)
    if drift_h:
        report["drift_before"] = drift(problem, base_params, base, fixed, None)
        report["drift_after"] = (drift(problem, base_params, after, _effect_fixed(after, base_params), after.effect)
                                 if best else report["drift_before"])
    stage("drift")
    bar.close()
    report["_fits"] = {"before": base, "after": after}
    return report


def _effect_fixed(f: FitResult, base_params: list[Param]) -> dict:
    out = {}
    for par in f.params:
        if par not in base_params:
            par.assign(float(f.value_dict()[par.label]), out)
    return out




def impedance_loop(data: list, reference: dict | None = None, settings=None) -> tuple[MeasurementKind, dict]:
    """Fit the circular-pore model (porosity, pore radius, tortuosity) to all layers of one
    material together, then let the loop find what it lacks. ``reference``: the paper's
    values (``phi``, ``alpha_inf``, ``Lambda``, ``Lambda_prime``, ``sigma``) for the
    comparison table."""
    prob = ImpedanceKind(data, settings or ForwardSettings(device="cpu"))
    rep = run_loop(prob, default_base_params(prob), drift_h=False)
    if reference:
        before = jca_equivalent(rep["_fits"]["before"].value_dict(), prob.core)
        after = jca_equivalent(rep["_fits"]["after"].value_dict(), prob.core)
        rep["comparison"] = {k: {"before": before[k], "after": after[k], "reference": reference[k]}
                             for k in ("phi", "alpha_inf", "Lambda", "Lambda_prime", "sigma")}
        rep["comparison_note"] = ("circular pores: Lambda = Lambda' = r (Lambda' = ratio r with the thermal radius "
                                  "effect), alpha_inf = q^2, sigma = 8 mu q^2 / (phi r^2)")
    return prob, rep
