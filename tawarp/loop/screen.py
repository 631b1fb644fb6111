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


def residual_structure(problem: MeasurementKind, Y: np.ndarray) -> dict:
    """Per coefficient: rms weighted residual against frequency and group; the fraction
    explained by a cubic in frequency per (coefficient, group, re/im)."""
    d = Y - problem.y
    wr = np.stack([d.real * problem.w[:, 0], d.imag * problem.w[:, 1]], -1)
    total = float((wr ** 2).sum())
    smooth = 0.0
    n_poly = 0
    per_coef = {}
    groups = np.unique(problem.group)
    for c, cname in enumerate(problem.coef_names):
        per_group = {}
        for g in groups:
            m = (problem.coef == c) & (problem.group == g)
            if not m.any():
                continue
            f = problem.freq[m]
            t = (f - f.min()) / max(np.ptp(f), 1e-30) * 2 - 1
            deg = min(3, m.sum() - 1)
            V = np.polynomial.legendre.legvander(t, deg)
            for k in range(2):
                coef, *_ = np.linalg.lstsq(V, wr[m, k], rcond=None)
                smooth += float(((V @ coef) ** 2).sum())
                n_poly += deg + 1
            per_group[f"{g:g}"] = float(np.sqrt(np.mean((wr[m] ** 2).sum(-1))))
        per_coef[cname] = per_group
    N = wr.size
    return {"rms_weighted_residual": {"per_coefficient_and_group": per_coef},
            "structured_fraction": smooth / total if total > 0 else 0.0,
            "structured_fraction_if_white": n_poly / N,
            "groups": [float(g) for g in groups], "group_name": problem.group_name}


def _explained(r: np.ndarray, B: np.ndarray, C: np.ndarray, rcond: float = 1e-6) -> float:
    """||P_(C perp B) r||^2 / ||r||^2: the part of C orthogonal to the base columns B
    (columns that lie in span B to within ``rcond`` of their norm explain nothing: a
    direction the base parameters already have cannot be the effect)."""
    rr = float(r @ r)
    if rr == 0 or C.shape[1] == 0:
        return 0.0
    Cp = C.copy()
    if B.shape[1]:
        s = np.linalg.norm(B, axis=0)
        s[s == 0] = 1.0
        U, sv, _ = np.linalg.svd(B / s, full_matrices=False)
        U = U[:, sv > rcond * sv.max()]
        Cp = C - U @ (U.T @ C)
    keep = np.linalg.norm(Cp, axis=0) > rcond * np.maximum(np.linalg.norm(C, axis=0), 1e-300)
    if not keep.any():
        return 0.0
    Cp = Cp[:, keep]
    U2, sv2, _ = np.linalg.svd(Cp / np.linalg.norm(Cp, axis=0), full_matrices=False)
    U2 = U2[:, sv2 > rcond * sv2.max()]
    return float(np.sum((U2.T @ r) ** 2)) / rr


def screen(problem: MeasurementKind, base: FitResult, fixed: dict, library: list[Effect]) -> list[dict]:
    """Score every candidate from its sensitivity columns at the base solution: one batched
    launch for the field effects (all their columns), one per structural effect."""
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
        X = np.vstack([x[None], x[None] + np.diag(h)[len(base.params):]])
        Y = problem.predict(param_values(allp, X, fixed), X.shape[0])
        R = residual(problem, Y, np.arange(problem.y.size))
        Jc = (R[1:] - R[0]) / h[len(base.params):, None]
        k = 0
        for e in field_effects:
            results[e.name] = Jc[k:k + len(e.params)].T
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
        score = _explained(base.residuals[0], base.jacobian[0], C)
        F = (score / k) / max((1 - score) / max(N - p - k, 1), 1e-300)
        out.append({"effect": e.name, "description": e.description, "parameters": [par.label for par in e.params],
                    "score": score, "score_if_noise": k / max(N - p, 1), "linearized_F": F,
                    "linearized_p": float(stats.f.sf(F, k, max(N - p - k, 1)))})
    return out
