"""Residual diagnosis of a fit: its structure against frequency and group, and the
screening of candidate effects by their linearized share of the residual (steps 2 and 3
of :func:`tawarp.loop.run.run_loop`)."""

from __future__ import annotations

import numpy as np
from scipy import stats

from ..fit.problems import FD_STEP, param_values, residual
from ..fit.result import FitResult
from ..measure.kind import MeasurementKind
from ..model.effects import Effect
from .goodness import smooth_fraction


def residual_structure(problem: MeasurementKind, Y: np.ndarray) -> dict:
    """Per coefficient: rms weighted residual against frequency and group; the fraction
    explained by a cubic in frequency per (coefficient, group, re/im)
    (:func:`tawarp.loop.goodness.smooth_fraction`)."""
    d = Y - problem.y
    wr = np.stack([d.real * problem.w[:, 0], d.imag * problem.w[:, 1]], -1)
    smooth = smooth_fraction(problem, wr)
    per_coef = {}
    groups = np.unique(problem.group)
    for c, cname in enumerate(problem.coef_names):
        per_coef[cname] = {
            f"{g:g}": float(np.sqrt(np.mean((wr[m] ** 2).sum(-1))))
            for g in groups
            if (m := (problem.coef == c) & (problem.group == g)).any()
        }
    return {
        "rms_weighted_residual": {"per_coefficient_and_group": per_coef},
        "structured_fraction": smooth["fraction"],
        "structured_fraction_if_white": smooth["if_white"],
        "groups": [float(g) for g in groups],
        "group_name": problem.group_name,
    }


#: A candidate with a sensitivity column correlated with a base parameter's beyond this
#: (|cos| of the two columns; or two candidates whose linearized changes correlate so)
#: cannot be told apart from it on these data.
DEGENERATE_CORR = 0.99


def _linearized(r: np.ndarray, B: np.ndarray, C: np.ndarray, lo: np.ndarray, hi: np.ndarray, names: list[str]) -> dict:
    """The linearized step along the candidate columns C, orthogonalized against the base
    columns B, within the candidate's bounds [lo, hi] in x from its off value (a one-sided
    effect, e.g. a radiative conductivity >= 0, may only move one way: a gradient pointing
    outside its range explains nothing): ``score`` = ``(||r||^2 - min ||r + C_perp d||^2) /
    ||r||^2``, ``direction`` the change ``C_perp d`` (for candidate-candidate correlation),
    ``degenerate_with`` the base parameter (``names``) whose column correlates with one of
    C beyond :data:`DEGENERATE_CORR`, else None."""
    rr = float(r @ r)
    out = {"score": 0.0, "direction": np.zeros_like(r), "degenerate_with": None}
    if rr == 0 or C.shape[1] == 0:
        return out
    Cp = C.copy()
    cn = np.maximum(np.linalg.norm(C, axis=0), 1e-300)
    if B.shape[1]:
        s = np.linalg.norm(B, axis=0)
        s[s == 0] = 1.0
        U, sv, _ = np.linalg.svd(B / s, full_matrices=False)
        U = U[:, sv > 1e-6 * sv.max()]
        Cp = C - U @ (U.T @ C)
        cos = np.abs((B / s).T @ (C / cn))  # (p, k) correlations of base and candidate columns
        if cos.size and cos.max() > DEGENERATE_CORR:
            out["degenerate_with"] = f"base:{names[int(np.unravel_index(np.argmax(cos), cos.shape)[0])]}"
            return out
    change = _sign_constrained_step(Cp, r, lo >= 0, hi <= 0)
    out["score"] = float(max(rr - np.sum((r + change) ** 2), 0.0) / rr)
    out["direction"] = change
    return out


def _sign_constrained_step(C: np.ndarray, r: np.ndarray, nonneg: np.ndarray, nonpos: np.ndarray) -> np.ndarray:
    """The change ``C d`` minimizing ``||r + C d||`` with d_j >= 0 where ``nonneg``, <= 0
    where ``nonpos``: the exact solution by trying every set of columns held at zero (a
    candidate has one or two columns)."""
    k = C.shape[1]
    best, best_cost = np.zeros_like(r), float(r @ r)
    for mask in range(1 << k):
        free = np.array([(mask >> j) & 1 == 0 for j in range(k)])
        if not free.any():
            continue
        d, *_ = np.linalg.lstsq(C[:, free], -r, rcond=1e-10)
        if np.any(d[nonneg[free]] < 0) or np.any(d[nonpos[free]] > 0):
            continue
        change = C[:, free] @ d
        cost = float(np.sum((r + change) ** 2))
        if cost < best_cost:
            best, best_cost = change, cost
    return best


def screen(problem: MeasurementKind, base: FitResult, fixed: dict, library: list[Effect]) -> list[dict]:
    """Score every candidate from its sensitivity columns at the base solution ``base``
    (its effect, when structural, stays in): one batched launch for the field effects (all
    their columns), one per structural effect. Each row: the score, what noise would give
    (``k / (N - p)`` for k columns), the linearized F-test, and ``degenerate_with``."""
    out = []
    field_effects = [e for e in library if e.transform is None]
    cols = [(e, par) for e in field_effects for par in e.params]
    start_fixed = dict(fixed)
    for e in field_effects:
        for par in e.params:
            par.assign(par.start, start_fixed)
    results = {}
    if cols:
        allp = base.params + [par for _, par in cols]
        x = np.concatenate([base.x[0], np.zeros(len(cols))])
        h = np.full(len(allp), FD_STEP)
        hi = np.array([par.bounds_x()[1] for par in allp])
        h[x + h > hi] *= -1
        X = np.vstack([x[None], x[None] + np.diag(h)[len(base.params) :]])
        Y = problem.predict(param_values(allp, X, fixed), X.shape[0], base.effect)
        R = residual(problem, Y, np.arange(problem.y.size))
        Jc = (R[1:] - R[0]) / h[len(base.params) :, None]
        k = 0
        for e in field_effects:
            results[e.name] = Jc[k : k + len(e.params)].T
            k += len(e.params)
    for e in library:
        if e.transform is not None:
            allp = base.params + list(e.params)
            x = np.concatenate([base.x[0], np.zeros(len(e.params))])
            h = np.full(len(e.params), FD_STEP)
            X = np.vstack([x[None], x[None] + np.pad(np.diag(h), ((0, 0), (len(base.params), 0)))])
            Y = problem.predict(param_values(allp, X, fixed), X.shape[0], e)
            R = residual(problem, Y, np.arange(problem.y.size))
            results[e.name] = ((R[1:] - R[0]) / h[:, None]).T
    N, p = base.n, len(base.params)
    for e in library:
        C = results[e.name]
        k = C.shape[1]
        lo = np.array([min(par.bounds_x()[0], 0.0) for par in e.params])
        hi = np.array([max(par.bounds_x()[1], 0.0) for par in e.params])
        lin = _linearized(base.residuals[0], base.jacobian[0], C, lo, hi, base.names)
        score = lin["score"]
        F = (score / k) / max((1 - score) / max(N - p - k, 1), 1e-300)
        out.append(
            {
                "effect": e.name,
                "description": e.description,
                "parameters": [par.label for par in e.params],
                "score": score,
                "score_if_noise": k / max(N - p, 1),
                "linearized_F": F,
                "linearized_p": float(stats.f.sf(F, k, max(N - p - k, 1))),
                "degenerate_with": lin["degenerate_with"],
                "_direction": lin["direction"],
            }
        )
    return out
