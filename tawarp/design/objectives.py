"""The one table of design objectives and metrics.

Each row (:class:`Objective`) says what a design quantity is: its ``name``, whether a
search maximizes or minimizes it (``direction``), its ``unit``, a ``long_name``, and how
it is computed: either a ``column`` of the metrics kernel's output
(:func:`tawarp.kernels.design.design_metrics`, one heat solve per design) or a host
function ``compute(evaluator, table, metrics) -> (n,)`` for derived quantities (the
acoustic loss needs a T-matrix cascade; a user objective may combine kernel metrics).

Built-in rows (all from the steady heat model of docs/physics.md):

- ``gradient`` [K/m], maximized: ``(T(x3) - T(x2)) / l_s``, x2/x3 the stack's cold and
  hot planes (exact at the nodes of the exponentially fitted heat grid).
- ``T_max`` [K], minimized: maximum temperature of the core; more often a constraint
  ``T_max <= T_limit``.
- ``heat_leak`` [W], minimized: heat leaked to the wall in the stack,
  ``∫_stack (2 h_s / R) theta S dx``, exact cell by cell.
- ``T_hot`` [K], minimized: temperature at the hot end of the stack, ``T(x3)``.
- ``acoustic_loss`` [-], minimized: fraction of incident plane-wave power absorbed at
  ``Q = 0`` with anechoic cold ducts on both sides, ``1 - |r|^2 - |t|^2``, mean of
  incidence from x1 and x6 and over the evaluator's frequencies.

Onset rows (:mod:`tawarp.model.onset`): the designed core closed by the resonator of a
reference engine (the evaluator's :class:`OnsetSpec`, default the bundled
``standing_wave``), one batched onset search for all designs of a batch:

- ``Q_onset`` [W], minimized: the heat input where the fundamental starts to grow
  (Im omega crosses 0); inf where it does not start by ``Q_max`` (no onset is the worst).
- ``onset_T_ratio`` [-], minimized: T_hot / T_cold at onset (T_hot the largest steady
  temperature of the core); inf without onset.
- ``Q_onset_p90`` [W], minimized: the robust objective, the 90th percentile of Q_onset
  over ``OnsetSpec.n_draws`` stack parameter sets drawn from the covariance of
  ``OnsetSpec.uncertainty`` (a material, e.g. from a fit.json) added to each design's
  stack values; the same draws for every design (common random numbers).

Extension: ``register_objective(Objective(...))`` from anywhere; :func:`search` and
:func:`sweep` then accept the new name.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..kernels import design as _kernel
from ..model.coefficients import duct_impedance, normalize
from ..rng import checked_seed


@dataclass(frozen=True)
class Objective:
    """One design quantity; exactly one of ``column`` (metrics kernel output column) and
    ``compute`` (host function ``(evaluator, table, metrics) -> (n,) array``) is given.
    ``metrics`` holds every kernel column by name when ``compute`` is called."""

    name: str
    direction: str
    unit: str
    long_name: str
    column: int | None = None
    compute: Callable | None = None

    def __post_init__(self):
        if self.direction not in ("maximize", "minimize"):
            raise ValueError(
                f"objective {self.name!r}: direction must be 'maximize' or 'minimize', got {self.direction!r}"
            )
        if (self.column is None) == (self.compute is None):
            raise ValueError(f"objective {self.name!r}: give exactly one of column (kernel output) and compute (host)")
        if self.column is not None and not 0 <= self.column < _kernel.N_METRICS:
            raise ValueError(f"objective {self.name!r}: kernel column {self.column} outside [0, {_kernel.N_METRICS})")

    @property
    def sign(self) -> float:
        """+1 for a minimized objective, -1 for a maximized one (searches minimize sign * value)."""
        return 1.0 if self.direction == "minimize" else -1.0


def _acoustic_loss(evaluator, table: np.ndarray, metrics: dict) -> np.ndarray:
    v0 = np.array(table, dtype=np.float64, copy=True)
    v0[0] = 0.0  # a passive property of the geometry: Q = 0
    eng = evaluator.acoustic_engine()
    T, _, _ = eng.evaluate(v0)
    n, m = v0.shape[1], len(eng.freqs)
    T = T.numpy().view(np.complex128).reshape(n, m, 2, 2)
    return absorbed_fraction(T, duct_impedance(evaluator.core)).mean(axis=1)


def absorbed_fraction(T: np.ndarray, Zc: float) -> np.ndarray:
    """(n, m) fraction of incident plane-wave power absorbed by two-ports ``T`` (n, m, 2, 2),
    anechoic ducts of impedance ``Zc`` [Pa s/m^3] on both sides, mean of incidence from
    x1 and from x6."""
    Y = normalize(T, Zc)
    a, b, c, d = Y[..., 0], Y[..., 1], Y[..., 2], Y[..., 3]
    den = a - b - c + d
    r = (c + d - a - b) / den
    t = a + b + r * (a - b)
    s = 2.0 / den
    r2 = s * (a - b) - 1.0
    left = 1.0 - np.abs(r) ** 2 - np.abs(t) ** 2
    right = 1.0 - np.abs(r2) ** 2 - np.abs(s) ** 2
    return 0.5 * (left + right)


@dataclass(frozen=True)
class OnsetSpec:
    """How the onset objectives close a designed core: the resonator and ends of
    ``engine`` (an engine name or file; its core is replaced by the design's), heat inputs
    searched up to ``Q_max`` [W] on ``n_bracket`` points, and for ``Q_onset_p90`` the
    material ``uncertainty`` (a :class:`tawarp.design.catalogue.Material`: its covariance
    over the stack parameters) drawn ``n_draws`` times with ``seed``."""

    engine: str = "standing_wave"
    Q_max: float = 200.0
    n_bracket: int = 9
    uncertainty: object = None
    n_draws: int = 64
    seed: int = 0
    segment: str = "stack"

    def __post_init__(self):
        checked_seed(self.seed, "OnsetSpec")


def _Q_onset(evaluator, table, metrics):
    return evaluator.onset_metrics(table)[0]


def _onset_T_ratio(evaluator, table, metrics):
    T_cold = (
        table[1 + evaluator.names.index("gas.T_cold")] if "gas.T_cold" in evaluator.names else evaluator.core.gas.T_cold
    )
    return evaluator.onset_metrics(table)[1] / T_cold


def _Q_onset_p90(evaluator, table, metrics):
    with np.errstate(invalid="ignore"):  # inf - inf between draws without onset: the point is inf
        return np.percentile(evaluator.onset_metrics(table, draws=True)[0], 90, axis=1)


#: Default constraint T_max <= T_limit [K] (673 K: a typical limit for carbon in air).
DEFAULT_T_LIMIT = 673.0

OBJECTIVES: dict[str, Objective] = {}


def register_objective(obj: Objective, replace: bool = False) -> Objective:
    """Add ``obj`` to the table (``replace=True`` to redefine an existing name)."""
    if obj.name in OBJECTIVES and not replace:
        raise ValueError(f"objective {obj.name!r} is already registered")
    OBJECTIVES[obj.name] = obj
    return obj


for _row in (
    Objective(
        "gradient",
        "maximize",
        "K/m",
        "temperature gradient across the stack (T(x3) - T(x2)) / l_s",
        column=_kernel.GRADIENT,
    ),
    Objective("T_max", "minimize", "K", "maximum temperature of the core", column=_kernel.T_MAX),
    Objective(
        "heat_leak",
        "minimize",
        "W",
        "heat leaked to the wall in the stack, integral of (2 h_s/R) theta S dx",
        column=_kernel.HEAT_LEAK,
    ),
    Objective("T_hot", "minimize", "K", "temperature at the hot end of the stack, T(x3)", column=_kernel.T_HOT),
    Objective(
        "acoustic_loss",
        "minimize",
        "-",
        "absorbed fraction of incident plane-wave power at Q = 0, mean over freqs",
        compute=_acoustic_loss,
    ),
    Objective(
        "Q_onset", "minimize", "W", "onset heat input of the core in the reference engine's resonator", compute=_Q_onset
    ),
    Objective(
        "onset_T_ratio",
        "minimize",
        "-",
        "T_hot / T_cold at onset in the reference engine's resonator",
        compute=_onset_T_ratio,
    ),
    Objective(
        "Q_onset_p90",
        "minimize",
        "W",
        "90th percentile of the onset heat input over draws from the material's covariance",
        compute=_Q_onset_p90,
    ),
):
    register_objective(_row)


def objective(name: str) -> Objective:
    """The table row of ``name``; a KeyError listing the known names otherwise."""
    try:
        return OBJECTIVES[name]
    except KeyError:
        raise KeyError(f"unknown objective {name!r}; choose from {', '.join(OBJECTIVES)}") from None


def kernel_metrics() -> list[str]:
    """Names of the kernel's output columns, in column order."""
    rows = sorted((o for o in OBJECTIVES.values() if o.column is not None), key=lambda o: o.column)
    return [o.name for o in rows]


def directions(names) -> list[str]:
    return [objective(n).direction for n in names]


def signs(names) -> np.ndarray:
    """+1 / -1 per objective: ``signs * values`` is minimized."""
    return np.array([objective(n).sign for n in names])
