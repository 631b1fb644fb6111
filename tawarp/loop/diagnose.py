"""Closing the loop with measured data (issue #4): residual diagnosis, a library of
effects, the error before and after.

Steps of :func:`run_loop`:

1. **Base fit** of the given free parameters (scipy ``least_squares``, trust-region
   reflective, bounds; the Jacobian is one batched forward launch of 1 + p parameter sets:
   forward differences, step 1e-6 in the scaled variables of :class:`tawarp.effects.Param`).
   Data with ``sigma`` are weighted by it (chi^2); without, by 1/rms|Y| (the error measure).
2. **Residual structure**: the weighted residual per coefficient against frequency and
   heat input (or layer); ``structured_fraction`` is the part of it that a cubic in
   frequency per (coefficient, group, re/im) explains (white noise gives about
   ``n_poly / N``).
3. **Screening**: every candidate effect's sensitivity columns at the base solution, all
   in one batched launch (structural candidates: one launch each); its *score* is the
   fraction of the residual that a linearized step along those columns, orthogonalized
   against the base columns, explains: ``||P_(C perp B) r||^2 / ||r||^2``. Pure noise
   gives about ``k / (N - p)`` for k columns; the linearized F statistic gives a p-value.
4. **Augmented fits** of the promising candidates (linearized p < 0.01, best ``top`` by
   score), two starts each with the effect off (the base solution, the core's values), all
   in one batch (:func:`fit_batch`: :func:`tawarp.estimate.levenberg_marquardt` on all of
   them at once, one forward launch per iteration for every candidate's trial point and
   Jacobian); when none of them is
   accepted, the other candidates too (the screening is only linear).
5. **Choice.** An effect is accepted when all of:
   a. ``Delta BIC < -10`` (BIC = chi^2 + p ln N with known sigma, else N ln(RSS/N) + p ln N;
      "very strong" on Kass & Raftery's scale);
   b. F-test ``F = ((RSS0 - RSS1)/k) / (RSS1/(N - p - k))`` beyond the 99 % quantile of
      F(k, N - p - k): the cost drop exceeds what noise would give (p < 0.01);
   c. prediction: refitted without the held-out rows (the highest heat input, or every
      third frequency when there is one group), the augmented model predicts them better
      than the base model;
   d. with known sigma: the residual after is noise: its chi^2 lies below the 99.9 %
      quantile of chi^2(N - p - k), and the error after is within 1.5 times the noise floor
      (otherwise the effect explains only part of a structure it does not describe: no
      claim).
   Among accepted candidates the lowest BIC wins; none accepted: ``chosen_effect = None``.
6. **Drift**: with several heat inputs, the heat-exchange coefficients ``*.h`` are refitted
   at each heat input alone (everything else fixed) before and after; the paper's model
   says they should not drift with Q.

Measurement kinds: core T-matrices (:class:`TMatrixProblem`, :class:`TMatrixData`, also from
a scattering matrix via :func:`tawarp.measurements.read_scattering_csv`) and the surface
impedance of rigid-backed layers (:class:`ImpedanceProblem`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import stats
from scipy.optimize import least_squares

from ..model.coefficients import COEFFICIENTS, duct_impedance, normalize, rms_error
from ..model.core import Core, load_core
from ..model.fields import field as field_spec
from ..model.effects import Effect, Param, impedance_library, tmatrix_library
from ..fit.estimate import levenberg_marquardt, smooth_settings
from ..model.forward import Engine, ForwardSettings
from ..measure.files import ImpedanceData, TMatrixData

#: Acceptance thresholds (module docstring, step 5).
DELTA_BIC = -10.0
F_TEST_P = 0.01
NOISE_FACTOR = 1.5
CHI2_P = 1e-3
FD_STEP = 1e-6


# ======================================================================================
# Problems: data + batched model predictions on the same rows
# ======================================================================================
class Problem:
    """Measured complex values ``y`` (N,) with weights ``w`` (N, 2) for (re, im) and row
    labels ``freq``, ``group`` (heat input or layer), ``coef`` (index into ``coef_names``);
    :meth:`predict` maps parameter values to model values on the same rows."""

    kind = "problem"
    group_name = "group"
    coef_names: tuple[str, ...] = ()
    y: np.ndarray
    w: np.ndarray
    freq: np.ndarray
    group: np.ndarray
    coef: np.ndarray
    has_sigma: bool = False
    core: Core

    def predict(self, values: dict, n: int, effect: Effect | None = None) -> np.ndarray:
        raise NotImplementedError

    def noise_floor(self) -> float | None:
        """The FORMATS.md error of data that differ from the model by noise alone."""
        if not self.has_sigma:
            return None
        return float(np.sqrt(np.mean((1.0 / self.w ** 2).sum(-1)) / np.mean(np.abs(self.y) ** 2)))


class TMatrixProblem(Problem):
    """Core T-matrix data: rows (heat input, frequency) x the four dimensionless
    coefficients (Zc of the core as given, a constant even when ``gas.T_cold`` is fitted)."""

    kind = "tmatrix"
    group_name = "Q_W"
    coef_names = COEFFICIENTS

    def __init__(self, data: TMatrixData, core: Core, settings: ForwardSettings | None = None):
        self.data, self.core = data, core
        # fixed cells: finite-difference Jacobians need a model smooth in the parameters
        self.settings = smooth_settings(core, data.frequencies, settings)
        self.Zc = duct_impedance(core)
        self.freqs = data.frequencies
        self.Qs = data.heat_inputs
        Y = normalize(data.T, self.Zc)  # (rows, 4)
        nr = len(data)
        self.y = Y.reshape(-1)
        self.freq = np.repeat(data.freq, 4)
        self.group = np.repeat(data.heat_input, 4)
        self.coef = np.tile(np.arange(4), nr)
        self._qi = np.searchsorted(self.Qs, data.heat_input)
        self._fi = np.searchsorted(self.freqs, data.freq)
        if data.sigma is not None:
            s = np.asarray(data.sigma)  # (rows, 2, 2, 2) raw
            scale = np.array([[1.0, 1.0 / self.Zc], [self.Zc, 1.0]])
            s = s * scale[None, :, :, None]
            self.w = 1.0 / s.reshape(nr, 4, 2).reshape(-1, 2)
            self.has_sigma = True
        else:
            self.w = np.full((self.y.size, 2), 1.0 / np.sqrt(np.mean(np.abs(self.y) ** 2)))
        self._engines = {}

    def engine(self, names: tuple, effect: Effect | None) -> tuple[Engine, Core]:
        key = (names, effect.name if effect is not None and effect.transform else None)
        if key not in self._engines:
            core = effect.transform(self.core) if effect is not None and effect.transform else self.core
            self._engines[key] = (Engine(core, self.freqs, list(names), self.settings), core)
        return self._engines[key]

    def predict(self, values: dict, n: int, effect: Effect | None = None) -> np.ndarray:
        names = tuple(sorted(values))
        eng, core = self.engine(names, effect)
        nq = len(self.Qs)
        table = np.empty((1 + len(names), n * nq))
        table[0] = np.tile(self.Qs, n)
        for j, k in enumerate(names):
            table[1 + j] = np.repeat(np.broadcast_to(np.asarray(values[k], dtype=float), (n,)), nq)
        out, _, _ = eng.evaluate(table)
        T = out.numpy().view(np.complex128).reshape(n, nq, len(self.freqs), 2, 2)
        Y = normalize(T[:, self._qi, self._fi], self.Zc)  # (n, rows, 4)
        return Y.reshape(n, -1)


class ImpedanceProblem(Problem):
    """Surface impedance of layers of one material (several thicknesses) at one ambient
    state: rows (layer, frequency); group = layer thickness [m]."""

    kind = "impedance"
    group_name = "thickness_m"
    coef_names = ("Zs",)

    def __init__(self, data: list[ImpedanceData], settings: ForwardSettings | None = None, start: dict | None = None):
        from ..model.layer import layer_core

        self.data = list(data)
        self.settings = settings or ForwardSettings()
        d0 = self.data[0]
        self.core = layer_core(d0.thickness, T_ambient=d0.T_ambient or 293.15, p_ambient=d0.p_ambient or 101325.0)
        if start:
            self.core = self.core.replace(**start)
        self.y = np.concatenate([d.Zs for d in self.data])
        self.freq = np.concatenate([d.freq for d in self.data])
        self.group = np.concatenate([np.full(len(d), d.thickness) for d in self.data])
        self.coef = np.zeros(self.y.size, dtype=int)
        self.w = np.full((self.y.size, 2), 1.0 / np.sqrt(np.mean(np.abs(self.y) ** 2)))
        self._models = {}

    def predict(self, values: dict, n: int, effect: Effect | None = None) -> np.ndarray:
        from ..model.layer import LayerModel

        names = tuple(sorted(k for k in values if k != "layer.length_offset"))
        if names not in self._models:
            self._models[names] = LayerModel(self.data, names, self.settings,
                                             start={k: self.core.get(k) for k in ("layer.porosity", "layer.pore_radius",
                                                                                  "layer.tortuosity")})
        model = self._models[names]
        return np.concatenate(model.predict(values, n), axis=1)


# ======================================================================================
# Fitting
# ======================================================================================
@dataclass
class Fit:
    """One least-squares fit: ``params`` and their fitted ``values`` (physical units),
    ``std`` (from ``s^2 (J^T J)^-1``), ``rss`` (weighted), ``n`` residuals, ``error`` (FORMATS.md
    measure on the fitted rows), ``J`` (at the solution, scaled variables), ``x``."""

    params: list
    x: np.ndarray
    values: dict
    std: dict
    rss: float
    n: int
    error: float
    J: np.ndarray
    r: np.ndarray
    Y: np.ndarray
    converged: bool
    nfev: int
    effect: Effect | None = None

    def bic(self, has_sigma: bool) -> float:
        p = len(self.params)
        if has_sigma:
            return self.rss + p * math.log(self.n)
        return self.n * math.log(self.rss / self.n) + p * math.log(self.n)


def _values(params: list[Param], X: np.ndarray, fixed: dict) -> dict:
    """Model parameter values of parameter sets X (n, p)."""
    n = X.shape[0]
    out = {k: np.full(n, v) for k, v in fixed.items()}
    for j, par in enumerate(params):
        par.assign(par.value(X[:, j]), out)
    return out


def _residual(problem: Problem, Y: np.ndarray, rows: np.ndarray) -> np.ndarray:
    d = (Y - problem.y)[..., rows]
    w = problem.w[rows]
    return np.concatenate([d.real * w[:, 0], d.imag * w[:, 1]], axis=-1)


def fit(problem: Problem, params: list[Param], fixed: dict | None = None, effect: Effect | None = None,
        rows: np.ndarray | None = None, x0=None, max_nfev: int = 60) -> Fit:
    """Weighted least squares of ``params`` on the rows ``rows`` (default all)."""
    fixed = dict(fixed or {})
    rows = np.arange(problem.y.size) if rows is None else np.asarray(rows)
    p = len(params)
    lo = np.array([par.bounds_x()[0] for par in params])
    hi = np.array([par.bounds_x()[1] for par in params])
    x0 = np.zeros(p) if x0 is None else np.clip(np.asarray(x0, dtype=float), lo, hi)
    cache = {}

    def batch(X):
        return problem.predict(_values(params, X, fixed), X.shape[0], effect)

    def fun(x):
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = batch(x[None])[0]
        return _residual(problem, cache[key], rows)

    def steps(x):
        h = np.full(p, FD_STEP)
        h[x + h > hi] *= -1.0
        return h

    def jac(x):
        h = steps(x)
        X = np.vstack([x[None], x[None] + np.diag(h)])
        Y = batch(X)
        R = _residual(problem, Y, rows)
        return ((R[1:] - R[0]) / h[:, None]).T

    if p:
        sol = least_squares(fun, x0, jac=jac, bounds=(lo, hi), method="trf", x_scale=1.0, max_nfev=max_nfev,
                            xtol=1e-10, ftol=1e-12, gtol=1e-10)
        x, converged, nfev = sol.x, bool(sol.status > 0), int(sol.nfev)
        J = jac(x)
    else:
        x, converged, nfev, J = np.zeros(0), True, 1, np.zeros((2 * rows.size, 0))
    Y = batch(x[None])[0]
    return _finish(problem, params, x, J, Y, rows, effect, converged, nfev)


def _finish(problem, params, x, J, Y, rows, effect, converged, nfev) -> Fit:
    r = _residual(problem, Y, rows)
    rss = float(r @ r)
    N = r.size
    p = len(params)
    s2 = 1.0 if problem.has_sigma else rss / max(N - p, 1)
    try:
        cov = s2 * np.linalg.pinv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((p, p), np.nan)
    values, std = {}, {}
    for j, par in enumerate(params):
        v = float(par.value(x[j]))
        values[par.label] = v
        dv = abs(v) if par.log else par.scale
        std[par.label] = float(math.sqrt(max(cov[j, j], 0.0)) * dv)
    err = float(rms_error(problem.y[rows], Y[rows]))
    return Fit(list(params), np.array(x, dtype=float), values, std, rss, N, err, J, r, Y, converged, nfev, effect)


class LoopProblems:
    """The loop's fits ``specs`` = [(params, effect, x0), ...] as one batch for
    :func:`tawarp.estimate.levenberg_marquardt` (its :class:`~tawarp.estimate.LMProblems`).

    Problem c has the scaled variables x of its ``params`` (:class:`Param`: a unit step is
    a relative change of order one for log parameters, one ``scale`` for the others); z is
    x padded with zeros to the largest p of the batch, the padding pinned by the bounds
    ``zlo = zhi = 0`` (zero Jacobian columns: it never moves and adds nothing to the step
    and gradient tests; it does keep a fit whose own variables are all held at bounds from
    stopping as "bound", so such a fit ends as "stalled"). The residuals are :meth:`Problem.predict`'s on ``rows``,
    weighted by ``problem.w`` (dimensionless). :meth:`evaluate` forms the trial point and
    its forward-difference neighbours (step ``FD_STEP`` in x, towards the interior at an
    upper bound) of every problem asked for in one :meth:`Problem.predict` call per
    group: fits whose effects change no structure share one Engine (the union of their
    parameters, each fit's others at their "off" start values), a structural effect has
    its own.
    """

    def __init__(self, problem: Problem, specs: list, fixed: dict | None = None, rows: np.ndarray | None = None):
        self.problem, self.specs = problem, list(specs)
        self.rows = np.arange(problem.y.size) if rows is None else np.asarray(rows)
        fixed = dict(fixed or {})
        self.groups: dict = {}
        for c, (_, effect, _) in enumerate(self.specs):
            self.groups.setdefault(effect.name if effect is not None and effect.transform else None, []).append(c)
        self.base_vals = {}
        for key, members in self.groups.items():
            v = dict(fixed)
            for c in members:
                for par in self.specs[c][0]:
                    par.assign(par.start, v)
            self.base_vals[key] = v
        #: free parameters per fit; z is padded to the largest
        self.p = np.array([len(sp[0]) for sp in self.specs], dtype=int)
        P = int(self.p.max(initial=0))
        self.zlo, self.zhi = np.zeros((len(self.specs), P)), np.zeros((len(self.specs), P))
        for c, (params, _, _) in enumerate(self.specs):
            for j, par in enumerate(params):
                self.zlo[c, j], self.zhi[c, j] = par.bounds_x()
        #: per slot of the last :meth:`evaluate`: (J (2 len(rows), p_c) in x, model values (y.size,))
        self.last: list = []

    def start(self) -> np.ndarray:
        """The specs' x0, padded (K, P)."""
        z = np.zeros_like(self.zlo)
        for c, (_, _, x0) in enumerate(self.specs):
            z[c, :self.p[c]] = np.asarray(x0, dtype=float)
        return z

    def project(self, z, pid):
        return np.clip(z, self.zlo[pid], self.zhi[pid])

    def relative_change(self, dz, z):
        """|dz|: the scaled variables already measure relative change (:class:`Param`)."""
        return np.abs(dz)

    def predict(self, requests: list) -> list:
        """[(c, X (n, p_c)), ...] -> [model values (n, N_rows)], one launch per group."""
        out = [None] * len(requests)
        for key, members in self.groups.items():
            todo = [i for i, (c, _) in enumerate(requests) if c in members]
            if not todo:
                continue
            blocks = []
            for i in todo:
                c, X = requests[i]
                n = X.shape[0]
                arr = {k: np.full(n, float(v)) for k, v in self.base_vals[key].items()}
                for j, par in enumerate(self.specs[c][0]):
                    par.assign(par.value(X[:, j]), arr)
                blocks.append((i, n, arr))
            values = {k: np.concatenate([b[2][k] for b in blocks]) for k in blocks[0][2]}
            effect = self.specs[requests[todo[0]][0]][1] if key is not None else None
            Y = self.problem.predict(values, sum(b[1] for b in blocks), effect)
            k0 = 0
            for i, n, _ in blocks:
                out[i] = Y[k0:k0 + n]
                k0 += n
        return out

    def evaluate(self, pid, z, max_sets: int = 0):
        """(cost, raw, g, H) of problems ``pid`` at padded z (n, P): cost = r^T r of the
        weighted residuals, raw the unweighted sum |Y - y|^2 over the rows, g = J^T r,
        H = J^T J with the forward-difference J. All in one launch per group (``max_sets``
        is not used: the loop's batches are small)."""
        n, P = z.shape
        step = np.where(z + FD_STEP > self.zhi[pid], -FD_STEP, FD_STEP)
        requests = []
        for i, c in enumerate(pid):
            p = self.p[c]
            x, h = z[i, :p], step[i, :p]
            requests.append((c, np.vstack([x[None], x[None] + np.diag(h)])))
        got = self.predict(requests)
        cost, raw = np.empty(n), np.empty(n)
        g, H = np.zeros((n, P)), np.zeros((n, P, P))
        self.last = []
        for i, c in enumerate(pid):
            p = self.p[c]
            R = _residual(self.problem, got[i], self.rows)
            r = R[0]
            J = ((R[1:] - r) / step[i, :p, None]).T
            cost[i] = r @ r
            raw[i] = np.sum(np.abs(got[i][0, self.rows] - self.problem.y[self.rows]) ** 2)
            g[i, :p], H[i, :p, :p] = J.T @ r, J.T @ J
            self.last.append((J, got[i][0]))
        bad = ~(np.isfinite(cost) & np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(H), axis=(1, 2)))
        cost[bad] = np.inf
        return cost, raw, g, H


#: Stopping rule of the loop's fits (:func:`fit_batch`, tawarp.estimate's tests): an accepted
#: step below XTOL in the scaled variables, or the gradient cosine max |g_a| / sqrt(H_aa F)
#: below GTOL. Tighter than estimate's defaults: the fits' costs enter the F-test and BIC
#: comparisons, so they must sit at the minimum; GTOL is about what forward differences with
#: step 1e-6 resolve (below it the fits only stall, spending launches).
XTOL = 1e-10
GTOL = 1e-6


def fit_batch(problem: Problem, specs: list, fixed: dict | None = None, rows: np.ndarray | None = None,
              max_iter: int = 100) -> list[Fit]:
    """Several fits in lockstep, ``specs`` = [(params, effect, x0), ...]: every iteration
    evaluates every active fit's trial point and its forward-difference neighbours in one
    launch (one more per structural effect; :class:`LoopProblems`).

    The optimizer is :func:`tawarp.estimate.levenberg_marquardt` (Nielsen's damping
    ``mu I``: the variables are scaled by :class:`Param`, and Marquardt's diag(J^T J)
    would let weakly determined parameters take huge steps; steps projected onto the
    bounds) with the stopping rule :data:`XTOL`, :data:`GTOL`, ``max_iter``; the
    Jacobians and model values at the solutions take one more launch."""
    lm = LoopProblems(problem, specs, fixed, rows)
    K = len(lm.specs)
    if K == 0:
        return []
    pid = np.arange(K)
    if lm.zlo.shape[1]:
        st = levenberg_marquardt(lm, pid, lm.start(), xtol=XTOL, gtol=GTOL, max_iter=max_iter)
        z, converged, its = st.z, st.converged, st.iterations
    else:  # nothing free: the model at the fixed values
        z, converged, its = lm.start(), np.ones(K, dtype=bool), np.zeros(K, dtype=int)
    lm.evaluate(pid, z)
    # nfev: the start, one per iteration, the final launch
    return [_finish(problem, params, z[c, :lm.p[c]], lm.last[c][0], lm.last[c][1], lm.rows, effect,
                    bool(converged[c]), int(its[c]) + 2)
            for c, (params, effect, _) in enumerate(lm.specs)]


# ======================================================================================
# Residual structure and screening
# ======================================================================================
def residual_structure(problem: Problem, Y: np.ndarray) -> dict:
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


def screen(problem: Problem, base: Fit, fixed: dict, library: list[Effect]) -> list[dict]:
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
        x = np.concatenate([base.x, np.zeros(len(cols))])
        h = np.full(len(allp), FD_STEP)
        hi = np.array([par.bounds_x()[1] for par in allp])
        h[x + h > hi] *= -1
        X = np.vstack([x[None], x[None] + np.diag(h)[len(base.params):]])
        Y = problem.predict(_values(allp, X, fixed), X.shape[0])
        R = _residual(problem, Y, np.arange(problem.y.size))
        Jc = (R[1:] - R[0]) / h[len(base.params):, None]
        k = 0
        for e in field_effects:
            results[e.name] = Jc[k:k + len(e.params)].T
            k += len(e.params)
    for e in library:
        if e.transform is not None:
            allp = base.params + list(e.params)
            x = np.concatenate([base.x, np.zeros(len(e.params))])
            h = np.full(len(e.params), FD_STEP)
            X = np.vstack([x[None], x[None] + np.pad(np.diag(h), ((0, 0), (len(base.params), 0)))])
            Y = problem.predict(_values(allp, X, fixed), X.shape[0], e)
            R = _residual(problem, Y, np.arange(problem.y.size))
            results[e.name] = ((R[1:] - R[0]) / h[:, None]).T
    N, p = base.r.size, len(base.params)
    for e in library:
        C = results[e.name]
        k = C.shape[1]
        score = _explained(base.r, base.J, C)
        F = (score / k) / max((1 - score) / max(N - p - k, 1), 1e-300)
        out.append({"effect": e.name, "description": e.description, "parameters": [par.label for par in e.params],
                    "score": score, "score_if_noise": k / max(N - p, 1), "linearized_F": F,
                    "linearized_p": float(stats.f.sf(F, k, max(N - p - k, 1)))})
    return out


# ======================================================================================
# The loop
# ======================================================================================
def holdout_rows(problem: Problem) -> tuple[np.ndarray, np.ndarray, str]:
    """(train, test) row indices: the highest group (heat input / thickness) when there are
    three or more groups, else every third frequency."""
    groups = np.unique(problem.group)
    if problem.kind == "tmatrix" and len(groups) >= 3:
        test = problem.group == groups[-1]
        what = f"{problem.group_name} = {groups[-1]:g}"
    else:
        f = np.unique(problem.freq)
        held = f[1::3]
        test = np.isin(problem.freq, held)
        what = "every third frequency"
    return np.flatnonzero(~test), np.flatnonzero(test), what


def _param_report(f: Fit) -> dict:
    return {k: {"value": f.values[k], "std": f.std[k]} for k in f.values}


def drift(problem: Problem, base_params: list[Param], sol: Fit, fixed: dict, effect: Effect | None) -> dict | None:
    """h's refitted at each heat input > 0 alone, the rest fixed at ``sol``."""
    if problem.kind != "tmatrix":
        return None
    hp = [par for par in base_params if par.label.endswith(".h")]
    Qs = [q for q in np.unique(problem.group) if q > 0]
    if not hp or len(Qs) < 2:
        return None
    fx = dict(fixed)
    for par in sol.params:
        if par not in hp:
            par.assign(float(sol.values[par.label]), fx)
    hp_start = [par.with_start(sol.values[par.label]) for par in hp]
    out = {par.label: [] for par in hp}
    for q in Qs:
        rows = np.flatnonzero(problem.group == q)
        f = fit(problem, hp_start, fx, effect, rows)
        for par in hp:
            out[par.label].append(f.values[par.label])
    res = {"Q_W": [float(q) for q in Qs], "values": out}
    res["relative_spread"] = {k: float(np.ptp(v) / np.mean(v)) if np.mean(v) else None for k, v in out.items()}
    return res


def default_base_params(problem: Problem, names=None) -> list[Param]:
    """Fit parameters for ``names`` (default: the stack's porosity and pore radius and the
    thermal segments' h for T-matrix data; porosity, pore radius, tortuosity of a layer)."""
    core = problem.core
    if names is None:
        if problem.kind == "impedance":
            names = ["layer.porosity", "layer.pore_radius", "layer.tortuosity"]
        else:
            from ..model.effects import _stack_and_heater

            stack, heater = _stack_and_heater(core)
            names = [f"{stack}.porosity", f"{stack}.pore_radius"] if stack else []
            names += [f"{s.name}.h" for s in (core.segments[i] for i in core.thermal_indices) if s.h > 1.0]
    out = []
    for name in names:
        v = core.get(name)
        f = field_spec(name)
        lo, hi = f.fit_range
        if f.log and v > 0:
            out.append(Param(name, (name,), v, 1.0, max(lo, v * 1e-3), min(hi, v * 1e3), log=True))
        else:
            out.append(Param(name, (name,), v, f.scale, lo, hi))
    return out


def run_loop(problem: Problem, base_params: list[Param] | None = None, library: list[Effect] | None = None,
             top: int = 3, drift_h: bool = True, batched: bool = True) -> dict:
    """The loop of the module docstring; returns the report dict (report.json).
    ``batched``: the augmented fits run in lockstep (:func:`fit_batch`, one launch per
    iteration for all candidates); False fits them one by one with SciPy."""
    base_params = base_params or default_base_params(problem)
    if library is None:
        library = tmatrix_library(problem.core) if problem.kind == "tmatrix" else impedance_library(problem.core)
    fixed = {}
    base = fit(problem, base_params)
    N, p = base.n, len(base_params)
    floor = problem.noise_floor()
    has_sigma = problem.has_sigma
    structure_before = residual_structure(problem, base.Y)
    scores = screen(problem, base, fixed, library)
    promising = sorted([s for s in scores if s["linearized_p"] < F_TEST_P], key=lambda s: -s["score"])[:top]
    train, test, held = holdout_rows(problem)
    base_train = fit(problem, base_params, rows=train, x0=base.x)
    base_held_err = float(rms_error(problem.y[test], base_train.Y[test]))
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
            for x0 in (np.concatenate([base.x, np.zeros(k)]), np.zeros(p + k)):
                specs.append((base_params + list(e.params), e, x0))
        fits = fit_batch(problem, specs, fixed) if batched else [fit(problem, sp[0], fixed, sp[1], x0=sp[2])
                                                                 for sp in specs]
        augs = [min(fits[2 * i:2 * i + 2], key=lambda f: f.rss) for i in range(len(effects))]
        specs_t = [(base_params + list(e.params), e, a.x) for e, a in zip(effects, augs)]
        trains = (fit_batch(problem, specs_t, fixed, rows=train) if batched else
                  [fit(problem, sp[0], fixed, sp[1], rows=train, x0=sp[2]) for sp in specs_t])
        for e, aug, aug_train in zip(effects, augs, trains):
            k = len(e.params)
            F = ((base.rss - aug.rss) / k) / max(aug.rss / max(N - p - k, 1), 1e-300)
            pval = float(stats.f.sf(F, k, max(N - p - k, 1)))
            dbic = aug.bic(has_sigma) - base.bic(has_sigma)
            held_err = float(rms_error(problem.y[test], aug_train.Y[test]))
            checks = {"delta_bic": dbic < DELTA_BIC, "f_test": pval < F_TEST_P, "held_out": held_err < base_held_err}
            if floor is not None:
                checks["noise_floor"] = aug.error <= NOISE_FACTOR * floor
                checks["chi2"] = float(stats.chi2.sf(aug.rss, max(N - p - k, 1))) > CHI2_P
            candidates[e.name] = {"fit": aug, "error_after": aug.error, "delta_bic": dbic, "F": F, "p_value": pval,
                                  "explained_fraction": (base.rss - aug.rss) / base.rss if base.rss > 0 else 0.0,
                                  "held_out_error": held_err, "checks": checks, "accepted": all(checks.values())}

    refit([s["effect"] for s in promising])
    second_pass = False
    if not any(c["accepted"] for c in candidates.values()):
        # the screening is linear: when no promising candidate is accepted, refit the rest too
        second_pass = True
        rest = [s["effect"] for s in sorted(scores, key=lambda s: -s["score"]) if s["effect"] not in candidates]
        if rest:
            refit(rest)
    accepted = [name for name, c in candidates.items() if c["accepted"]]
    chosen = min(accepted, key=lambda n: candidates[n]["fit"].bic(has_sigma)) if accepted else None
    after = candidates[chosen]["fit"] if chosen else base
    report = {
        "kind": problem.kind,
        "n_residuals": N,
        "noise_floor": floor,
        "error_before": base.error,
        "error_after": after.error,
        "chosen_effect": chosen,
        "chosen_description": next((e.description for e in library if e.name == chosen), None),
        "acceptance_test": (f"accepted when Delta BIC < {DELTA_BIC:g}, F-test p < {F_TEST_P:g} (the cost drop exceeds "
                            f"what noise gives), the held-out rows ({held}) are predicted better than by the base "
                            f"model" + (f", and the residual after is noise (chi^2 p > {CHI2_P:g}, error after <= "
                                        f"{NOISE_FACTOR:g} x noise floor)" if floor else "")
                            + "; lowest BIC among accepted"),
        "held_out": held,
        "second_pass": second_pass,
        "note": (None if floor is not None else
                 "no sigma in the data: the noise floor is unknown, so an accepted effect may explain only part of the "
                 "residual (see explained_fraction and residual_structure_after)"),
        "held_out_error_base": base_held_err,
        "parameters_before": _param_report(base),
        "parameters_after": _param_report(after),
        "base_converged": base.converged,
        "candidates": [],
        "residual_structure_before": structure_before,
        "residual_structure_after": residual_structure(problem, after.Y),
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
                                 if chosen else report["drift_before"])
    report["_fits"] = {"before": base, "after": after}
    return report


def _effect_fixed(f: Fit, base_params: list[Param]) -> dict:
    out = {}
    for par in f.params:
        if par not in base_params:
            par.assign(float(f.values[par.label]), out)
    return out


# ======================================================================================
# Output: report.json, report.md, figures
# ======================================================================================
def _jsonable(report: dict) -> dict:
    return json.loads(json.dumps({k: v for k, v in report.items() if not k.startswith("_")},
                                 default=lambda o: o.tolist() if isinstance(o, np.ndarray) else
                                 (o.item() if isinstance(o, np.generic) else str(o))))


def residual_figure(problem: Problem, report: dict, path: Path) -> Path:
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
        d = np.abs(fits[key].Y - problem.y) * np.sqrt((problem.w ** 2).mean(-1))
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


def write_report(problem: Problem, report: dict, outdir: str | Path) -> dict:
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


# ======================================================================================
# Surface impedance of the Atalla & Panneton foams
# ======================================================================================
def impedance_loop(data: list[ImpedanceData], reference: dict | None = None, settings=None) -> tuple[Problem, dict]:
    """Fit the circular-pore model (porosity, pore radius, tortuosity) to all layers of one
    material together, then let the loop find what it lacks. ``reference``: the paper's
    values (``phi``, ``alpha_inf``, ``Lambda``, ``Lambda_prime``, ``sigma``) for the
    comparison table."""
    from ..model.layer import jca_equivalent

    start = {"layer.porosity": 0.95, "layer.pore_radius": 1.5e-4, "layer.tortuosity": 1.1}
    prob = ImpedanceProblem(data, settings or ForwardSettings(device="cpu"), start=start)
    base_params = [Param("layer.porosity", ("layer.porosity",), 0.95, 0.05, 0.3, 0.9999),
                   Param("layer.pore_radius", ("layer.pore_radius",), 1.5e-4, 1.0, 1e-6, 1e-2, log=True),
                   Param("layer.tortuosity", ("layer.tortuosity",), 1.1, 0.1, 1.0, 5.0)]
    rep = run_loop(prob, base_params, drift_h=False)
    if reference:
        before = jca_equivalent(rep["_fits"]["before"].values, prob.core)
        after = jca_equivalent(rep["_fits"]["after"].values, prob.core)
        rep["comparison"] = {k: {"before": before[k], "after": after[k], "reference": reference[k]}
                             for k in ("phi", "alpha_inf", "Lambda", "Lambda_prime", "sigma")}
        rep["comparison_note"] = ("circular pores: Lambda = Lambda' = r (Lambda' = ratio r with the thermal radius "
                                  "effect), alpha_inf = q^2, sigma = 8 mu q^2 / (phi r^2)")
    return prob, rep


# ======================================================================================
# Synthetic data with an undeclared effect (tests, demos)
# ======================================================================================
def synthetic_tmatrix(core: Core, truth: dict | None = None, freqs=None, heat_inputs=(0.0, 40.0, 80.0),
                      noise: float = 0.002, seed: int = 0, ambient_presence: float | None = None,
                      settings: ForwardSettings | None = None) -> TMatrixData:
    """Core T-matrices made by the forward model with parameters ``truth`` (any names,
    effects included) plus complex Gaussian noise of standard deviation ``noise`` times
    the rms of the dimensionless coefficients (per re/im part); sigma columns carry it.
    ``ambient_presence`` in (0, 1]: made with the ambient exchangers of the library."""
    from ..model.effects import ambient_presence as presence, with_ambient_exchangers, AMBIENT_HX
    from ..model.forward import transfer_matrices

    freqs = np.linspace(50.0, 500.0, 12) if freqs is None else np.asarray(freqs, dtype=float)
    truth = dict(truth or {})
    model = core
    if ambient_presence:
        model = with_ambient_exchangers(core, AMBIENT_HX["length"], 1.0, core.radius)
        truth.update({k: float(v) for k, v in presence(core, ambient_presence).items()})
    nq = len(heat_inputs)
    settings = settings or ForwardSettings(device="cpu", cells=8)
    res = transfer_matrices(model, freqs, list(heat_inputs), params={k: np.full(nq, v) for k, v in truth.items()},
                            settings=settings)
    T = res.T.reshape(-1, 2, 2)
    Zc = duct_impedance(core)
    s = noise * np.sqrt(np.mean(np.abs(normalize(T, Zc)) ** 2))
    scale = np.array([[1.0, Zc], [1.0 / Zc, 1.0]])
    rng = np.random.default_rng(seed)
    Tn = T + s * scale * (rng.standard_normal(T.shape) + 1j * rng.standard_normal(T.shape))
    sigma = np.broadcast_to(s * scale, T.shape).copy()
    meta = {"generator": "tawarp.loop.synthetic_tmatrix", "noise": str(noise), "seed": str(seed)}
    return TMatrixData(np.repeat(heat_inputs, len(freqs)), np.tile(freqs, nq), Tn, sigma, meta, "<synthetic>")
