"""The one result type of every fit: :class:`FitResult` (the T-matrix estimator,
the two-step characterization, fits of any measurement kind and the loop's fits)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import stats

#: A fit is adequate when its chi^2 (weights 1/sigma) has a p-value of at least this for
#: its degrees of freedom, and no parameter sits at a bound of its fit range.
ADEQUATE_P = 1e-3


@dataclass
class FitResult:
    """Result of a batched fit; arrays have the problem axis first (N problems, p params).

    ``values``, ``std`` (N, p) natural units (std NaN or inf: undetermined); ``covariance``,
    ``correlation`` (N, p, p): the posterior covariance of
    :meth:`tawarp.fit.problem_model.ProblemModel.covariance` (s^2 (J^T W J + s^2 Lambda)^-1
    by the delta method, Lambda the priors' precision, 0 for a least-squares fit);
    ``condition`` (N,) of the matrix it inverts, in the scaled variables; ``iterations`` (N,);
    ``converged`` (N,) bool; ``reason`` (N,) str (:data:`REASONS`); ``cost`` (N,) weighted
    sum of squares; ``rms_error`` (N,) the error measure of docs/formats.md; ``s2`` (N,) the
    s^2 of the covariance (1 with weights 1/sigma, else the reduced chi^2); ``dof`` = 8 m - p; ``start`` (N, p);
    ``warnings`` (batch summary) and ``problem_warnings`` (one list per problem, formatted
    when read: :class:`ProblemWarnings`);
    ``distinct_minima`` (N,) bool; ``restart_values`` (N, k, p), ``restart_cost`` (N, k)
    and ``restart_converged`` (N, k) when restarts ran (else None); ``evaluations``:
    forward parameter sets evaluated; ``launches``: forward launches; ``seconds``.
    """

    names: list[str]
    values: np.ndarray
    std: np.ndarray
    covariance: np.ndarray
    correlation: np.ndarray
    condition: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    reason: np.ndarray
    cost: np.ndarray
    rms_error: np.ndarray
    s2: np.ndarray
    dof: int
    start: np.ndarray
    warnings: list[str] = field(default_factory=list)
    problem_warnings: Sequence[list[str]] = field(default_factory=list)
    distinct_minima: np.ndarray | None = None
    restart_values: np.ndarray | None = None
    restart_cost: np.ndarray | None = None
    restart_converged: np.ndarray | None = None
    local_minima: np.ndarray | None = None
    evaluations: int = 0
    launches: int = 0
    seconds: float = 0.0
    std_statistical: np.ndarray | None = None
    #: when asked for (fits of a measurement kind): the scaled variables x (N, p) of
    #: :class:`tawarp.model.effects.Param` ``params``, the weighted residuals (N, n) and
    #: their Jacobian in x (N, n, p) at the solution, the model values (N, rows) complex,
    #: the fitted ``effect`` (None: the base model) and the number of real residuals ``n``
    params: list | None = None
    x: np.ndarray | None = None
    residuals: np.ndarray | None = None
    jacobian: np.ndarray | None = None
    model: np.ndarray | None = None
    effect: object = None
    n: int = 0
    #: the weights were 1/sigma (so the cost is a chi^2); the fit range of each parameter (p,)
    weighted: bool = False
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    #: the :class:`tawarp.fit.problem_model.ProblemModel` of a kind fit (scaling, priors,
    #: covariance): the one its ``covariance`` came from, and its evidence's (the loop)
    problem_model: object = None

    def at_bounds(self, i: int = 0) -> list[str]:
        """Parameters of problem ``i`` that ended on a bound of their fit range (to 1e-9
        relative)."""
        if self.lower is None:
            return []
        return [
            k
            for k, v, lo, hi in zip(self.names, self.values[i], self.lower, self.upper)
            if min(v - lo, hi - v) <= 1e-9 * max(abs(v), 1e-300)
        ]

    def goodness_of_fit(self, i: int = 0) -> dict:
        """The verdict on problem ``i`` (fit.json's ``goodness_of_fit``): reduced chi^2 and
        its p-value when the weights were 1/sigma, the parameters at bounds, and
        ``adequate`` by the rule of :data:`ADEQUATE_P` (None when there is no sigma and no
        parameter at a bound: the noise level is then unknown)."""
        at = self.at_bounds(i)
        out = {
            "reduced_chi2": None,
            "chi2_p_value": None,
            "adequate": False if at else None,
            "parameters_at_bounds": at,
            "rule": f"adequate when the weights are 1/sigma and chi^2 has p-value >= {ADEQUATE_P:g} for "
            f"{self.dof} degrees of freedom, and no parameter sits at a bound of its fit range",
        }
        if self.weighted:
            chi2 = float(self.cost[i])
            out["reduced_chi2"] = _json_float(chi2 / self.dof)
            out["chi2_p_value"] = _json_float(stats.chi2.sf(chi2, self.dof))
            out["adequate"] = bool(out["chi2_p_value"] is not None and out["chi2_p_value"] >= ADEQUATE_P and not at)
        else:
            out["note"] = "no sigma in the data: chi^2 needs sigma columns, the noise level is unknown"
        return out

    def add_covariance(self, extra: np.ndarray) -> None:
        """Add ``extra`` (N, p, p) natural units (e.g. propagated uncertainty of fixed
        parameters) to the covariance; ``std``, ``correlation`` follow and the former std is
        kept as ``std_statistical``."""
        if self.std_statistical is None:
            self.std_statistical = self.std.copy()
        self.covariance = self.covariance + extra
        self.std = np.sqrt(np.abs(np.einsum("nii->ni", self.covariance)))
        with np.errstate(divide="ignore", invalid="ignore"):
            self.correlation = self.covariance / (self.std[:, :, None] * self.std[:, None, :])
        p = self.std.shape[1]
        self.correlation[:, np.arange(p), np.arange(p)] = 1.0

    def __len__(self) -> int:
        return self.values.shape[0]

    def value_dict(self, i: int = 0) -> dict[str, float]:
        """``{name: value}`` of problem ``i``."""
        return {k: float(v) for k, v in zip(self.names, self.values[i])}

    def std_dict(self, i: int = 0) -> dict[str, float]:
        """``{name: std}`` of problem ``i``."""
        return {k: float(v) for k, v in zip(self.names, self.std[i])}

    def bic(self, has_sigma: bool, i: int = 0) -> float:
        """Bayesian information criterion of problem ``i`` over its ``n`` real residuals:
        ``chi^2 + p ln n`` with known sigma, else ``n ln(cost/n) + p ln n``."""
        return bic_of(float(self.cost[i]), self.n, len(self.names), has_sigma)

    def problem(self, i: int = 0) -> dict:
        """Problem ``i`` as a JSON-ready dict (the fit.json entry of docs/formats.md)."""
        d = {
            "parameters": {
                k: {
                    "value": float(self.values[i, a]),
                    "std": _json_float(self.std[i, a]),
                    "start": float(self.start[i, a]),
                }
                for a, k in enumerate(self.names)
            },
            "correlation": {"names": list(self.names), "matrix": _finite(self.correlation[i]).tolist()},
            "converged": bool(self.converged[i]),
            "reason": str(self.reason[i]),
            "iterations": int(self.iterations[i]),
            "cost": _json_float(self.cost[i]),
            "rms_error": _json_float(self.rms_error[i]),
            "s2": _json_float(self.s2[i]),
            "dof": int(self.dof),
            "condition": _json_float(self.condition[i]),
            "warnings": list(self.problem_warnings[i]),
            "goodness_of_fit": self.goodness_of_fit(i),
        }
        if self.std_statistical is not None:
            for a, k in enumerate(self.names):
                d["parameters"][k]["std_statistical"] = _json_float(self.std_statistical[i, a])
        if self.distinct_minima is not None:
            d["distinct_minima"] = bool(self.distinct_minima[i])
        if self.local_minima is not None:
            d["local_minima"] = int(self.local_minima[i])
        if self.restart_values is not None:
            d["restarts"] = [
                {"values": dict(zip(self.names, map(float, v))), "cost": float(c), "converged": bool(ok)}
                for v, c, ok in zip(self.restart_values[i], self.restart_cost[i], self.restart_converged[i])
            ]
        return d


def bic_of(cost: float, n: int, p: int, has_sigma: bool) -> float:
    """BIC of a least-squares fit of ``p`` parameters to ``n`` real residuals with weighted
    cost ``cost``: ``chi^2 + p ln n`` with known sigma, else ``n ln(cost/n) + p ln n``."""
    return cost + p * math.log(n) if has_sigma else n * math.log(max(cost, 1e-300) / n) + p * math.log(n)


def _json_float(x):
    x = float(x)
    return x if math.isfinite(x) else None


def _finite(a):
    a = np.array(a, dtype=float)
    a[~np.isfinite(a)] = np.nan
    return np.where(np.isnan(a), None, a).astype(object) if np.isnan(a).any() else a


class ProblemWarnings(Sequence):
    """The warnings of each problem of a batch, a list of messages per problem, formatted
    when read: a batch of 1e5 problems that all warn formatted 1e5 messages per fit before
    (a sixth of a GPU fit's time). Built from groups ``(key, rows, message)``: the sorted
    problem indices ``rows`` that have the warning ``key``, and ``message(i)`` its text for
    problem i; a problem's messages come in the groups' order. Compares equal to the same
    lists of messages."""

    def __init__(self, n: int, groups=()):
        self.n = int(n)
        self.groups = [(key, np.asarray(rows, dtype=np.int64), message) for key, rows, message in groups]

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(self.n))]
        i = range(self.n)[i]
        out = []
        for _, rows, message in self.groups:
            k = np.searchsorted(rows, i)
            if k < rows.size and rows[k] == i:
                out.append(message(i))
        return out

    def __reduce__(self):
        # pickled (a Dask worker's result) with the messages of the problems that have them
        # formatted: the closures, which hold the batch's arrays, stay here
        return ProblemWarnings, (
            self.n,
            [(key, rows, _Formatted(rows, [message(int(i)) for i in rows])) for key, rows, message in self.groups],
        )

    @classmethod
    def from_lists(cls, lists) -> "ProblemWarnings":
        """The warnings ``lists`` (a list of messages per problem) as groups: group j holds
        the j-th message of the problems that have one."""
        lists = [list(m) for m in lists]
        groups = []
        for j in range(max(map(len, lists), default=0)):
            rows = np.array([i for i, m in enumerate(lists) if len(m) > j], dtype=np.int64)
            groups.append((("message", j), rows, _Formatted(rows, [lists[i][j] for i in rows])))
        return cls(len(lists), groups)

    @classmethod
    def concatenate(cls, parts) -> "ProblemWarnings":
        """The warnings of consecutive batches ``parts`` (ProblemWarnings or lists of
        messages) as one, without formatting any message (joining 1e5 problems' lists took
        a second): groups of the same key are joined, in the order the keys first appear."""
        parts = [p if isinstance(p, ProblemWarnings) else cls.from_lists(p) for p in parts]
        starts = np.cumsum([0] + [p.n for p in parts])
        joined: dict = {}
        for k, part in enumerate(parts):
            for key, rows, message in part.groups:
                joined.setdefault(key, []).append((k, rows, message))
        groups = []
        for key, pieces in joined.items():
            rows = np.concatenate([r + starts[k] for k, r, _ in pieces])
            first = np.array([starts[k] for k, _, _ in pieces], dtype=np.int64)
            groups.append((key, rows, _Joined(first, [m for _, _, m in pieces])))
        return cls(int(starts[-1]), groups)

    def __eq__(self, other) -> bool:
        return (
            isinstance(other, Sequence)
            and len(other) == self.n
            and all(list(a) == list(b) for a, b in zip(self, other))
        )

    def summary(self) -> list[str]:
        """One line per warning key: its message for the first problem that has it, and how
        many problems have it."""
        out = []
        for _, rows, message in self.groups:
            if rows.size:
                head = (
                    f"problem {rows[0]}"
                    if rows.size == 1
                    else f"{rows.size} of {self.n} problems (e.g. problem {rows[0]})"
                )
                out.append(f"{head}: {message(int(rows[0]))}")
        return out


class _Formatted:
    """``message(i)`` of a group whose messages are formatted: ``texts[k]`` of problem
    ``rows[k]`` (rows sorted). Picklable, unlike the groups' closures."""

    def __init__(self, rows, texts):
        self.rows, self.texts = np.asarray(rows, dtype=np.int64), list(texts)

    def __call__(self, i) -> str:
        return self.texts[int(np.searchsorted(self.rows, i))]


class _Joined:
    """``message(i)`` of a group joined from consecutive batches: batch k starts at problem
    ``starts[k]`` and formats its messages with ``messages[k]`` (its own problem index)."""

    def __init__(self, starts, messages):
        self.starts, self.messages = np.asarray(starts, dtype=np.int64), list(messages)

    def __call__(self, i) -> str:
        k = int(np.searchsorted(self.starts, i, side="right")) - 1
        return self.messages[k](i - int(self.starts[k]))


# ----------------------------------------------------------------------------------------
