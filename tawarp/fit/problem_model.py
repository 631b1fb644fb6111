"""The problem a fit solves, one description for every fit of the package: the T-matrix
estimator (:class:`tawarp.fit.estimate.Problems`) and the fits of any measurement kind
(:class:`tawarp.fit.problems.KindProblems`, the loop's maximum a posteriori fits).

:class:`ProblemModel` holds the parameters' scaling (the fit variables x and the values v),
their fit ranges, their Gaussian priors as (centre, sd) pairs in x, and whether the noise is
estimated; :meth:`ProblemModel.covariance` is the one covariance of a fit's result
(:class:`tawarp.fit.result.FitResult`), meaning the same wherever it is computed.

**Scaling.** ``v = ref exp(x)`` for log parameters (positive quantities), ``v = ref + step x``
for the others: x = 0 is the start ``ref``, and a unit step in x is a relative change of
order one or one typical ``step`` of the field (:mod:`tawarp.model.fields`).

**Covariance.** At the solution x*, with ``H = J^T W J`` the Gauss-Newton matrix of the
weighted residuals (J their Jacobian in x, W the weights squared) and ``Lambda =
diag(1/sd^2)`` the priors' precision (0 for a parameter without prior), the covariance of x
is the posterior one of the linearized model,

    C_x = s^2 (H + s^2 Lambda)^-1 = (H / s^2 + Lambda)^-1,

with s^2 = 1 when the weights are 1/sigma of the noise (``noise_estimated`` False: the
``absolute_sigma`` of :func:`tawarp.fit.estimate.fit`) and s^2 = cost / (n - p), the
reduced chi^2 of the data's residuals, where the noise level is estimated from the fit. In
values, by the delta method, ``C_v = D C_x D``, ``D = diag(dv/dx)`` (v for log parameters,
``step`` otherwise). Without priors it is ``s^2 H^-1``, the least-squares covariance.
The correlation is that of ``(H + s^2 Lambda)^-1`` (defined for exact data, s^2 = 0).

**Undetermined directions.** The columns of ``A = H + s^2 Lambda`` are scaled to unit
diagonal; directions whose eigenvalue is at most :data:`RCOND` times the largest are
undetermined (the forward-difference Jacobians, step 1e-6 in x, resolve J to about 1e-6
relative, so such directions are set by the differencing error, not by the data). The
covariance is the pseudo-inverse on the determined directions, and a parameter on which an
undetermined direction has a component above :data:`UNDETERMINED_SHARE` is reported
undetermined: std NaN (None in JSON), never a tiny number. A parameter with a prior is never
undetermined: its prior bounds it.

The T-matrix estimator computes the same C on the device for many problems
(:func:`tawarp.fit.estimate.covariance`, :mod:`tawarp.kernels.covariance`), with its own
cut for undetermined directions (eigenvalues of the unscaled matrix at most 1e-14 of the
largest mark every entry they touch infinite); ``tests/test_fit_kinds.py`` checks that a
T-matrix fit through :func:`tawarp.fit.problems.fit_kind` and through
:func:`tawarp.fit.estimate.fit` give the same covariance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Eigenvalues of the column-scaled ``H + s^2 Lambda`` at or below this fraction of the
#: largest are undetermined directions: singular values of the scaled Jacobian below 1e-6 of
#: the largest, what forward differences with step 1e-6 resolve.
RCOND = 1e-12
#: A parameter on which an undetermined direction has a component above this is undetermined.
UNDETERMINED_SHARE = 0.1


def noise_variance(cost, dof: int, estimated: bool):
    """s^2 of the covariance: 1 where the weights are 1/sigma, else the reduced chi^2
    ``cost / dof`` (``cost`` scalar or array)."""
    cost = np.asarray(cost, dtype=float)
    return cost / dof if estimated else np.ones_like(cost)


#: Rows per block of :func:`r_factor`.
QR_BLOCK = 256


def r_factor(A: np.ndarray) -> np.ndarray:
    """The triangular factor R of ``A`` = Q R (..., n, k), n >> k, up to the signs of its
    rows: the factors of blocks of :data:`QR_BLOCK` rows stacked and factored again (Q is
    never formed; the same R to rounding, as every step is orthogonal). LAPACK's QR of the
    whole tall matrix runs threaded and was 10-100x slower on a loaded 2-core machine."""
    n = A.shape[-2]
    if n <= QR_BLOCK:
        return np.linalg.qr(A, mode="r")
    blocks = [np.linalg.qr(A[..., i : i + QR_BLOCK, :], mode="r") for i in range(0, n, QR_BLOCK)]
    return np.linalg.qr(np.concatenate(blocks, axis=-2), mode="r")


def determined_inverse(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A^-1 on the determined directions, undetermined) of symmetric positive
    semi-definite matrices ``A`` (..., p, p), each scaled to unit diagonal first (module doc):
    the covariance's inverse from the Gauss-Newton matrix, of one fit or of a stack of them
    (the Laplace evidence of many models at once, :func:`tawarp.loop.evidence.laplace_log_evidences`)."""
    A = np.asarray(A, dtype=float)
    norm = np.sqrt(np.abs(np.diagonal(A, axis1=-2, axis2=-1))).copy()
    norm[norm == 0] = 1.0
    ev, V = np.linalg.eigh(A / norm[..., :, None] / norm[..., None, :])
    return _pseudo_inverse(ev, V, norm)


def _pseudo_inverse(ev: np.ndarray, V: np.ndarray, norm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(inverse on the determined directions, undetermined (..., p)) of the matrices with
    eigenvalues ``ev`` (..., p) and eigenvectors the columns of ``V`` (..., p, p) after their
    scaling by ``norm`` (..., p): directions at most :data:`RCOND` of the largest eigenvalue
    (every one where none is positive) are left out, and a parameter with a component above
    :data:`UNDETERMINED_SHARE` on one of them is undetermined."""
    top = ev.max(axis=-1, keepdims=True)
    null = np.where(top > 0, ev <= RCOND * top, True)
    w = np.where(null, 0.0, 1.0 / np.where(null, 1.0, ev))
    unit_x = (V * w[..., None, :]) @ np.swapaxes(V, -1, -2) / norm[..., :, None] / norm[..., None, :]
    undetermined = np.any((np.abs(V) > UNDETERMINED_SHARE) & null[..., None, :], axis=-1)
    return unit_x, undetermined


@dataclass
class Covariance:
    """A fit's uncertainty at its solution (one problem): ``cov`` (p, p) and ``std`` (p,)
    in natural units (std NaN where ``undetermined``), ``corr`` (p, p), ``cond`` the 2-norm
    condition number of ``H + s^2 Lambda`` in x, ``s2`` the s^2 it used."""

    cov: np.ndarray
    std: np.ndarray
    corr: np.ndarray
    cond: float
    s2: float
    undetermined: np.ndarray


@dataclass
class ProblemModel:
    """The parameters of a fit (module doc): ``names`` (p,), ``log`` (p,) bool, ``ref`` (..., p)
    the values at x = 0 (the starts; a leading axis: one row per problem of a batch),
    ``step`` (p,) dv/dx of the linear parameters, ``lower``/``upper`` (p,) the fit range in
    natural units, ``prior_mu``/``prior_sd`` (p,) Gaussian priors in x (None: none; an
    infinite sd: none for that parameter), ``noise_estimated``: s^2 is the reduced chi^2
    rather than 1."""

    names: list[str]
    log: np.ndarray
    ref: np.ndarray
    step: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    prior_mu: np.ndarray | None = None
    prior_sd: np.ndarray | None = None
    noise_estimated: bool = False

    @classmethod
    def from_params(cls, params, prior=None, noise_estimated: bool = False) -> "ProblemModel":
        """The model of :class:`tawarp.model.effects.Param` ``params`` (their ``start``,
        ``scale``, ``lower``, ``upper``, ``log``); ``prior`` None or (mu, sd) (p,) in x."""
        mu, sd = (None, None) if prior is None else (np.asarray(a, dtype=float) for a in prior)
        return cls(
            [par.label for par in params],
            np.array([par.log for par in params], dtype=bool),
            np.array([par.start for par in params], dtype=float),
            np.array([par.scale for par in params], dtype=float),
            np.array([par.lower for par in params], dtype=float),
            np.array([par.upper for par in params], dtype=float),
            mu,
            sd,
            noise_estimated,
        )

    @property
    def p(self) -> int:
        return len(self.names)

    def _ref(self, rows):
        return self.ref if rows is None else self.ref[rows]

    @property
    def scale(self) -> np.ndarray:
        """dv/dx at x = 0: ``ref`` for log parameters, ``step`` for linear ones."""
        return np.where(self.log, self.ref, self.step)

    @property
    def offset(self) -> np.ndarray:
        """v at x = 0 of the linear parameters (0 for log ones): v = offset + scale x."""
        return np.where(self.log, 0.0, self.ref)

    def values(self, x, rows=None) -> np.ndarray:
        """v of fit variables x (..., p); ``rows``: the rows of ``ref`` they belong to."""
        ref, x = self._ref(rows), np.asarray(x, dtype=float)
        return np.where(self.log, ref * np.exp(np.where(self.log, x, 0.0)), ref + self.step * x)

    def x_of(self, v, rows=None) -> np.ndarray:
        """Fit variables of values v (..., p)."""
        ref, v = self._ref(rows), np.asarray(v, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.log, np.log(v / ref), (v - ref) / self.step)

    def dv_dx(self, x, rows=None) -> np.ndarray:
        """dv/dx at x: v for log parameters, ``step`` for linear ones (the delta method's D)."""
        return np.where(self.log, self.values(x, rows), np.broadcast_to(self.step, np.shape(x)))

    def bounds_x(self, rows=None) -> tuple[np.ndarray, np.ndarray]:
        """The fit range in x (a log parameter's lower bound 0 is -inf)."""
        ref = self._ref(rows)
        with np.errstate(divide="ignore", invalid="ignore"):
            lo = np.where(self.log, np.log(np.maximum(self.lower, 0.0) / ref), (self.lower - ref) / self.step)
            hi = np.where(self.log, np.log(self.upper / ref), (self.upper - ref) / self.step)
        return lo, hi

    def precision(self) -> np.ndarray:
        """Lambda's diagonal (p,): 1/sd^2 of the priors, 0 without."""
        if self.prior_sd is None:
            return np.zeros(self.p)
        return 1.0 / np.asarray(self.prior_sd, dtype=float) ** 2

    def covariance(self, x, cost: float, dof: int, J: np.ndarray | None = None, H: np.ndarray | None = None):
        """:class:`Covariance` at the solution x (p,) of one problem (module doc), from the
        Jacobian ``J`` (n, p) of its weighted residuals in x (the more accurate: singular
        values of J are resolved to its rounding, eigenvalues of J^T J only to their square's)
        or from ``H`` = J^T J (p, p); ``cost`` the data's weighted sum of squares."""
        if H is None:
            return covariances([self], [x], [cost], [dof], [J])[0]
        s2 = float(noise_variance(cost, dof, self.noise_estimated))
        if self.p == 0:
            return _covariances(np.zeros((1, 0)), np.array([s2]), None, None, None)[0]
        A = np.asarray(H, dtype=float) + np.diag(s2 * self.precision())
        unit_x, undetermined = determined_inverse(A)
        return _covariances(self.dv_dx(x)[None], np.array([s2]), unit_x[None], A[None], undetermined[None])[0]


def covariances(models: list[ProblemModel], x: list, cost: list, dof: list, J: list) -> list[Covariance]:
    """:meth:`ProblemModel.covariance` of many problems from their Jacobians: ``models``, the
    solutions ``x`` (p_i,), ``cost``, ``dof`` and ``J`` (n_i, p_i) of each (None: no
    parameter). Problems whose stacked matrix (J over the priors' rows) has one shape are
    done together in array operations (the loop's batches: hundreds of fits), the same
    numbers as one at a time: a stack's LAPACK calls and matrix products are each matrix's
    own (``tests/test_evidence.py::test_covariances_of_a_batch_are_each_problems_own``)."""
    out: list = [None] * len(models)
    groups: dict = {}
    for i, (model, Ji) in enumerate(zip(models, J)):
        groups.setdefault((model.p, 0 if Ji is None else len(Ji)), []).append(i)
    for (p, m), idx in groups.items():
        estimated = np.array([models[i].noise_estimated for i in idx], dtype=bool)
        s2 = np.ones(len(idx))
        if estimated.any():
            s2[estimated] = noise_variance(
                np.array([cost[i] for i in idx])[estimated], np.array([dof[i] for i in idx])[estimated], True
            )
        lam = s2[:, None] * np.array([models[i].precision() for i in idx]).reshape(len(idx), p)
        # a prior's row only where lam > 0 (none at s^2 = 0, exact data)
        rows = m + np.count_nonzero(lam > 0, axis=-1)
        for n in np.unique(rows):
            sub = np.flatnonzero(rows == n)
            members = [idx[j] for j in sub]
            got = _stacked_covariances(
                [models[i] for i in members], [x[i] for i in members], [J[i] for i in members], s2[sub], lam[sub]
            )
            for i, c in zip(members, got):
                out[i] = c
    return out


def _stacked_covariances(models: list, x: list, J: list, s2: np.ndarray, lam: np.ndarray) -> list:
    """:func:`covariances` of problems with one shape of the stacked matrix R: Jacobians
    ``J`` of as many rows each (or all None), noise variances ``s2`` (k,) and ``lam`` (k, p),
    s^2 times the priors' precision, with as many positive entries in every row."""
    k, p = lam.shape
    D = np.array([model.dv_dx(xi) for model, xi in zip(models, x)]).reshape(k, p)
    if p == 0:
        return _covariances(D, s2, None, None, None)
    # R (J over diag(sqrt(lam)) without its zero rows) written into one stack: a vstack
    # per problem and their np.stack cost two copies and several calls a problem
    m = 0 if J[0] is None else len(J[0])
    member, column = np.nonzero(lam > 0)
    n = m + len(member) // k
    R = np.zeros((k, n, p))
    if m:
        for j, Jj in enumerate(J):
            R[j, :m] = Jj
    R[member, m + np.cumsum(lam > 0, axis=-1)[member, column] - 1, column] = np.sqrt(lam[member, column])
    A = np.swapaxes(R, -1, -2) @ R
    # np.linalg.norm's sum of squares over the strided row axis took three times as long
    norm = np.sqrt(np.einsum("kij,kij->kj", R, R))
    norm[norm == 0] = 1.0
    R /= norm[:, None, :]
    # V (p, p) is all we need, and the same singular values and V come from the
    # triangular factor of a tall R (n > p rows: the residuals and the priors'):
    # LAPACK's SVD of the whole stack took about twice as long at n = 888
    _, sv, Vt = np.linalg.svd(r_factor(R) if n > p else R, full_matrices=n < p)
    ev = np.concatenate([sv, np.zeros((k, p - sv.shape[-1]))], axis=-1) ** 2
    unit_x, undetermined = _pseudo_inverse(ev, np.swapaxes(Vt, -1, -2), norm)
    return _covariances(D, s2, unit_x, A, undetermined)


def _covariances(D: np.ndarray, s2: np.ndarray, unit_x, A, undetermined) -> list:
    """[:class:`Covariance`] of problems with dv/dx ``D`` (k, p), noise variance ``s2`` (k,),
    inverse ``unit_x`` (k, p, p) in x of their matrices ``A`` (k, p, p) and ``undetermined``
    (k, p) (None where p = 0)."""
    k, p = D.shape
    if p == 0:
        empty = np.zeros((0, 0))
        return [Covariance(empty, np.zeros(0), empty, 1.0, float(v), np.zeros(0, dtype=bool)) for v in s2]
    unit = unit_x * D[:, :, None] * D[:, None, :]
    cov = s2[:, None, None] * unit
    diagonal = np.arange(p)
    std = np.sqrt(np.maximum(cov[:, diagonal, diagonal], 0.0))
    std[undetermined] = np.nan  # undetermined: None in JSON, never +-tiny
    su = np.sqrt(np.maximum(unit[:, diagonal, diagonal], 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = unit / (su[:, :, None] * su[:, None, :])
    corr[:, diagonal, diagonal] = 1.0
    w = np.linalg.eigvalsh(A)
    return [
        Covariance(
            cov[j],
            std[j],
            corr[j],
            float(w[j, -1] / w[j, 0]) if w[j, 0] > 0 else math.inf,
            float(s2[j]),
            undetermined[j],
        )
        for j in range(k)
    ]
