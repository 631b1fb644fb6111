"""Goodness of fit before effects: the noise level (given by sigma columns or estimated
from the data), reduced chi^2 and its p-value, parameters at bounds, and where a residual
that is not noise lives."""

from __future__ import annotations

import functools

import numpy as np
from scipy import stats

from ..fit.result import ADEQUATE_P, FitResult
from ..measure.kind import MeasurementKind

#: Without sigma, the fit is adequate when its reduced chi^2 against the estimated noise is
#: at most this (the error within sqrt(1.5) = 1.22 noise floors): the estimate itself is
#: uncertain by a few per cent and picks up some curvature, so a p-value would be too strict.
ADEQUATE_REDUCED_CHI2_ESTIMATED = 1.5
#: The noise estimate's rule, as the report states it.
NOISE_ESTIMATE = (
    "estimated: rms of the second differences d2 along frequency of the base fit's weighted "
    "residual, per coefficient (sigma = rms(d2) / sqrt(6): white noise gives var d2 = 6 sigma^2, a "
    "residual smooth over three frequencies cancels in d2)"
)


#: A fit that explains the data leaves a white residual: the share of it that cubics in
#: frequency explain (per coefficient, group and re/im part) is what white noise gives,
#: tested by an F-test at this level (the chi^2 test's level, ADEQUATE_P). A residual of the
#: noise's size can still be a smooth misfit spread thin (validation: another core's data
#: fitted at 1.04 noise floors, a calibration drift).
STRUCTURE_P = ADEQUATE_P


def smooth_fraction(problem: MeasurementKind, wr: np.ndarray) -> dict:
    """The share of the residual ``wr`` (n rows x (re, im), weighted: in units of the noise
    with sigma given, else of rms|y|) that a cubic in frequency explains, fitted per (coefficient,
    group, part): ``fraction``; what white noise gives on average, k / N (k coefficients of
    the cubics, N residuals): ``if_white``; the F statistic ``(S_smooth / k) / (S_rest / (N -
    k))`` and its p-value (F(k, N - k) under white noise; the fitted parameters take a few
    degrees of freedom, which makes the test slightly conservative; with noise that differs
    between coefficients it is approximate: the series of every coefficient have the same
    frequencies, so white noise still leaves k / N on average)."""
    smooth = total = 0.0
    k = 0
    labels = (
        np.asarray(problem.coef, dtype=np.int64),
        np.asarray(problem.group, float),
        np.asarray(problem.freq, float),
    )
    for rows, basis, columns in _cubic_bases(len(problem.coef_names), *(a.tobytes() for a in labels)):
        # the least-squares cubic's part of each series is its projection onto the basis
        r = wr[rows]
        smooth += float(((basis.T @ r) ** 2).sum())
        total += float((r**2).sum())
        k += 2 * columns
    N = wr.size
    F = (smooth / k) / max((total - smooth) / max(N - k, 1), 1e-300) if total > 0 else 0.0
    return {
        "fraction": smooth / total if total > 0 else 0.0,
        "if_white": k / N,
        "F": F,
        "p_value": float(stats.f.sf(F, k, max(N - k, 1))),
    }


@functools.lru_cache(maxsize=64)
def _cubic_bases(coefficients: int, coef: bytes, group: bytes, freq: bytes) -> tuple:
    """Per (coefficient, group) of the rows labelled ``coef`` (int64), ``group`` and
    ``freq`` (float64, as bytes: a problem's labels, the same for every residual of it):
    (its rows, an orthonormal basis of the Legendre polynomials up to the cubic in its
    frequency scaled to [-1, 1], their number). The basis spans what ``np.linalg.lstsq``
    fits: the left singular vectors above its cutoff (``rcond=None``)."""
    coef, group, freq = np.frombuffer(coef, dtype=np.int64), np.frombuffer(group), np.frombuffer(freq)
    out = []
    for c in range(coefficients):
        for g in np.unique(group):
            rows = np.flatnonzero((coef == c) & (group == g))
            if not rows.size:
                continue
            f = freq[rows]
            t = (f - f.min()) / max(np.ptp(f), 1e-30) * 2 - 1
            V = np.polynomial.legendre.legvander(t, min(3, rows.size - 1))
            U, sv, _ = np.linalg.svd(V, full_matrices=False)
            keep = sv > np.finfo(float).eps * max(V.shape) * sv[0]
            out.append((rows, U[:, keep], V.shape[1]))
    return tuple(out)


def noise_sigma(problem: MeasurementKind, residual: np.ndarray) -> np.ndarray:
    """Per real residual (the ``residual`` layout of :func:`tawarp.fit.problems.residual`,
    all rows: re parts, then im parts): the estimated noise sigma in weighted units, one
    value per coefficient (:data:`NOISE_ESTIMATE`) pooled over groups and re/im."""
    n = problem.y.size
    d2_all = {}
    for part in range(2):
        r = residual[part * n : (part + 1) * n]
        for c in range(len(problem.coef_names)):
            for g in np.unique(problem.group):
                m = np.flatnonzero((problem.coef == c) & (problem.group == g))
                if m.size < 3:
                    continue
                s = r[m[np.argsort(problem.freq[m])]]
                d2_all.setdefault(c, []).append(s[:-2] - 2 * s[1:-1] + s[2:])
    out = np.empty(2 * n)
    pooled = np.concatenate([np.concatenate(v) for v in d2_all.values()]) if d2_all else np.zeros(0)
    fallback = np.sqrt(np.mean(pooled**2) / 6.0) if pooled.size else float(np.sqrt(np.mean(residual**2)))
    for c in range(len(problem.coef_names)):
        d2 = np.concatenate(d2_all[c]) if c in d2_all else np.zeros(0)
        s = np.sqrt(np.mean(d2**2) / 6.0) if d2.size >= 5 else fallback
        m = problem.coef == c
        out[:n][m] = out[n:][m] = max(s, 1e-300)
    return out


def goodness_of_fit(problem: MeasurementKind, fit: FitResult, sigma: np.ndarray | None, source: str) -> dict:
    """Reduced chi^2 and p-value of ``fit`` (all rows) against noise ``sigma`` per real
    residual (None: the data's own sigma, weights 1/sigma), its noise floor, the parameters
    at a bound (flagged, not a failure: a tortuosity of 1 is a physical value on its bound),
    ``adequate`` (the misfit is of the noise's size): chi^2 p-value >= ADEQUATE_P with sigma
    given, reduced chi^2 <= :data:`ADEQUATE_REDUCED_CHI2_ESTIMATED` with estimated noise; the
    structure test of the fit's weighted residual (:func:`smooth_fraction`: ``structure``)
    and ``white``: its p-value >= :data:`STRUCTURE_P`."""
    r = fit.residuals[0]
    chi2 = float(np.sum(r**2)) if sigma is None else float(np.sum((r / sigma) ** 2))
    dof = max(r.size - len(fit.names), 1)
    p = float(stats.chi2.sf(chi2, dof))
    at = fit.at_bounds()
    n = problem.y.size
    # the residual as the fit weights it (1/sigma with sigma given): with estimated noise,
    # dividing by it would weight up the low-noise coefficients, where the estimate is least
    # sure and the forward model's own smooth error shows first (a validation case with no
    # visible effect gave p = 0.0009 so weighted, 0.6 with the fit's weights)
    structure = smooth_fraction(problem, np.stack([r[:n], r[n:]], -1))
    fits = p >= ADEQUATE_P if sigma is None else chi2 / dof <= ADEQUATE_REDUCED_CHI2_ESTIMATED
    floor = problem.noise_floor(sigma)
    return {
        "reduced_chi2": chi2 / dof,
        "p_value": p,
        "noise_floor": floor,
        "noise_source": source,
        "error": float(fit.rms_error[0]),
        "adequate": bool(fits),
        "structure": structure,
        "white": structure["p_value"] >= STRUCTURE_P,
        "at_bounds": at,
    }


def residual_location(problem: MeasurementKind, Y: np.ndarray, floor: float) -> dict:
    """Where the misfit of model values ``Y`` lives: the (coefficient, group) series with
    the largest rms residual, and in it the contiguous frequency band around its largest
    (3-point smoothed) |residual|^2 where that stays above half its peak. ``error``: the
    docs/formats.md error on those rows (the denominator rms|y| of all rows, so it compares
    with the noise floor)."""
    d2 = np.abs(Y - problem.y) ** 2
    norm = np.mean(np.abs(problem.y) ** 2)
    groups = np.unique(problem.group)
    best = None
    for c in range(len(problem.coef_names)):
        for g in groups:
            m = np.flatnonzero((problem.coef == c) & (problem.group == g))
            if m.size and (best is None or d2[m].mean() > best[0]):
                best = (d2[m].mean(), c, g, m[np.argsort(problem.freq[m])])
    _, c, g, m = best
    s = np.convolve(d2[m], np.ones(3) / 3, mode="same") if m.size >= 3 else d2[m]
    k = int(np.argmax(s))
    lo = k
    while lo > 0 and s[lo - 1] >= 0.5 * s[k]:
        lo -= 1
    hi = k
    while hi < m.size - 1 and s[hi + 1] >= 0.5 * s[k]:
        hi += 1
    band = m[lo : hi + 1]
    return {
        "band_Hz": [float(problem.freq[band].min()), float(problem.freq[band].max())],
        "group": float(g) if len(groups) > 1 else None,
        "coefficient": problem.coef_names[c],
        "error": float(np.sqrt(d2[band].mean() / norm)),
        "noise_floor": floor,
    }


def residual_structure(problem: MeasurementKind, Y: np.ndarray) -> dict:
    """Per coefficient: rms weighted residual against frequency and group; the fraction
    explained by a cubic in frequency per (coefficient, group, re/im)
    (:func:`smooth_fraction`)."""
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
