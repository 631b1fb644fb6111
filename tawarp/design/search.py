"""Design search over a thermoacoustic core: design space, objectives, batched search.

Objectives (all from the steady heat model of PHYSICS.md, one heat solve per design;
the acoustic one adds a T-matrix cascade at ``freqs``):

- ``gradient`` [K/m], maximized: the mean temperature gradient across the stack,
  ``(T(x3) - T(x2)) / l_s`` with x2, x3 the stack's cold and hot planes. The heat grid
  has nodes on the planes and the exponentially fitted scheme is exact there, so this
  is the exact value of the model.
- ``heat_leak`` [W], minimized: heat leaked to the wall in the stack,
  ``∫_stack (2 h_s / R) theta S dx``, integrated exactly cell by cell.
- ``acoustic_loss`` [-], minimized: the fraction of incident plane-wave power absorbed
  by the core at ``Q = 0`` (a passive property of the geometry), with anechoic cold
  ducts on both sides: ``1 - |r|^2 - |t|^2``, averaged over incidence from x1 and from
  x6 and over the frequencies ``freqs``.
- ``T_max`` [K], minimized when used as an objective; more often a constraint:
  ``T_max <= T_limit`` (the paper stops the RVC foam at 18 W for fear of combustion;
  673 K is a typical limit for carbon in air). Stored in each trial as Optuna's
  ``constraints`` system attribute ``[T_max - T_limit]`` (feasible when <= 0).

A design space (:class:`DesignSpace`) holds continuous variables (any ``SEGMENT.FIELD``
of the core, ``heat_input`` [W], ``stack.position`` = length of the segment before the
stack) and optionally the categorical ``material`` (a :mod:`tawarp.catalogue` entry put
in the stack; explicit ``stack.*`` variables then override the material's values, which
makes a material parametric).

Search (:func:`search`): generations of ``batch`` trials are asked as a whole, evaluated
in one kernel launch and told back. Two engines:

- ``engine="batched"`` (default): the samplers work on whole populations. Single
  objective: CMA-ES (the ``cmaes`` library that Optuna's ``CmaEsSampler`` wraps) with
  population = batch (split evenly between materials when ``material`` is a variable:
  one CMA-ES per material), its first generation a scrambled Sobol batch from which the
  CMA-ES is warm-started (``cmaes.get_warm_start_mgd``). Multi-objective: NSGA-II
  (constrained domination, crowding distance, binary tournament, SBX crossover and
  polynomial mutation), population = batch, first generation Sobol. Trials are stored in
  an Optuna study, written in bulk (one journal append per generation).
- ``engine="optuna"``: Optuna's own ``CmaEsSampler(popsize=batch)`` (QMC startup batch) or
  ``NSGAIISampler(population_size=batch)`` through ``study.ask()``/``study.tell()``; the
  reference for small runs, and the measure of what per-trial sampling costs.

Studies persist: ``storage`` is a journal file path (default for the command line), an
RDB URL (``sqlite:///...``, ``postgresql://...``) for several workers, or None (memory).
Each worker owns a *lineage* (``worker`` name) of generations; its sampler state is not
stored but replayed from its completed generations, so a run killed at any point resumes
exactly: trials that were asked but not told (RUNNING, their owner process gone) are
evaluated and told on resume, none is lost or asked twice. Several workers with
different names share one study (an island model); ``n_trials`` counts the worker's own
trials.
"""

from __future__ import annotations

import math
import os
import socket
import time
import uuid
from dataclasses import dataclass
from datetime import datetime, timezone

import numpy as np
import warp as wp

from .catalogue import PARAMS as MATERIAL_PARAMS, CORE_FIELD, Catalogue, default_catalogue
from ..model.coefficients import normalize, duct_impedance
from ..model.core import Core, CoreError, check_values
from ..model.forward import Engine, ForwardSettings

#: name -> (direction, unit, description)
OBJECTIVES = {
    "gradient": ("maximize", "K/m", "temperature gradient across the stack (T(x3) - T(x2)) / l_s"),
    "heat_leak": ("minimize", "W", "heat leaked to the wall in the stack, integral of (2 h_s/R) theta S dx"),
    "acoustic_loss": ("minimize", "-", "absorbed fraction of incident plane-wave power at Q = 0, mean over freqs"),
    "T_max": ("minimize", "K", "maximum temperature of the core"),
}
METRICS = ("gradient", "T_max", "heat_leak", "T_hot")
DEFAULT_T_LIMIT = 673.0
DEFAULT_FREQS = (50.0, 100.0, 200.0, 400.0)
_ATTR = "tawarp:"


# ======================================================================================
# Design space
# ======================================================================================
@dataclass(frozen=True)
class Variable:
    """A design variable: continuous ``[low, high]`` (``log`` scale optional) or
    categorical (``choices``, only ``material``). ``values`` fixes a grid for sweeps."""

    name: str
    low: float = math.nan
    high: float = math.nan
    log: bool = False
    choices: tuple = ()
    values: tuple = ()

    @property
    def categorical(self) -> bool:
        return bool(self.choices)

    def grid(self) -> np.ndarray | tuple:
        if self.categorical:
            return self.choices
        return np.asarray(self.values, dtype=float)


def parse_variable(text: str, grid: bool = False) -> Variable:
    """``NAME=LOW:HIGH[:log]`` (range), ``NAME=LOW:HIGH:COUNT[:log]`` (grid),
    ``NAME=v1,v2,...`` (list; materials for ``material``), ``NAME=v`` (fixed)."""
    name, eq, spec = text.partition("=")
    name, spec = name.strip(), spec.strip()
    if not eq or not name or not spec:
        raise ValueError(f"{text!r}: expected NAME=LOW:HIGH[:log], NAME=LOW:HIGH:COUNT or NAME=v1,v2")
    if name in ("Q", "Q_W"):
        name = "heat_input"
    if name == "material":
        return Variable(name, choices=tuple(s.strip() for s in spec.split(",") if s.strip()))
    try:
        if ":" in spec:
            parts = spec.split(":")
            log = parts[-1] == "log"
            if log:
                parts = parts[:-1]
            lo, hi = float(parts[0]), float(parts[1])
            if len(parts) == 3:
                n = int(parts[2])
                vals = np.geomspace(lo, hi, n) if log else np.linspace(lo, hi, n)
                return Variable(name, min(lo, hi), max(lo, hi), log, values=tuple(vals.tolist()))
            if len(parts) != 2:
                raise ValueError
            if grid:
                raise ValueError(f"{text!r}: a sweep grid needs LOW:HIGH:COUNT")
            return Variable(name, min(lo, hi), max(lo, hi), log)
        vals = [float(v) for v in spec.split(",") if v.strip()]
        return Variable(name, min(vals), max(vals), values=tuple(vals))
    except ValueError as e:
        if str(e).startswith(repr(text)):
            raise
        raise ValueError(f"{text!r}: expected NAME=LOW:HIGH[:log], NAME=LOW:HIGH:COUNT[:log] or NAME=v1,v2,...") from None


class DesignSpace:
    """Design variables over ``core``.

    ``variables``: :class:`Variable` list or ``parse_variable`` strings. Continuous names:
    ``heat_input`` [W] (alias ``Q``), any ``SEGMENT.FIELD`` of the core, and
    ``stack.position`` (the length of the segment before the stack, i.e. x2 - x1 when
    the stack is second). ``material``: categorical over ``catalogue`` names, put in the
    ``segment`` (default ``stack``). ``heat_input``: its value when not a variable.
    """

    def __init__(self, core: Core, variables, catalogue: Catalogue | None = None, segment: str = "stack",
                 heat_input: float = 0.0):
        self.core = core
        self.segment = segment
        self.catalogue = catalogue if catalogue is not None else default_catalogue()
        seg_names = [s.name for s in core.segments]
        if segment not in seg_names:
            raise CoreError(f"{core.source}: no segment {segment!r} for the design (have {seg_names})")
        self.stack_index = seg_names.index(segment)
        seg = core.segments[self.stack_index]
        if not seg.thermal:
            raise CoreError(f"{core.source}: segment {segment!r} is not thermal; the objectives need the heat model")
        vs = [parse_variable(v) if isinstance(v, str) else v for v in variables]
        self.variables: list[Variable] = []
        seen = set()
        for v in vs:
            if v.name in seen:
                raise ValueError(f"design variable {v.name!r} given twice")
            seen.add(v.name)
            self.variables.append(self._check(v))
        self.heat_input = float(heat_input)
        if not (math.isfinite(self.heat_input) and self.heat_input >= 0):
            raise ValueError(f"heat_input [W]: must be finite and >= 0, got {heat_input}")
        cats = [v for v in self.variables if v.categorical]
        self.material: Variable | None = cats[0] if cats else None
        self.continuous: list[Variable] = [v for v in self.variables if not v.categorical]

    def _check(self, v: Variable) -> Variable:
        if v.name == "material":
            if not v.choices:
                raise ValueError("material: give at least one material name")
            missing = [c for c in v.choices if c not in self.catalogue]
            if missing:
                raise KeyError(f"material: {missing} not in the catalogue ({', '.join(self.catalogue)})")
            if not self.core.segments[self.stack_index].is_porous:
                raise CoreError(f"{self.core.source}: segment {self.segment!r} is not porous; no material can go there")
            return v
        if v.categorical:
            raise ValueError(f"{v.name!r}: only 'material' can be categorical")
        if not (math.isfinite(v.low) and math.isfinite(v.high)) or v.low > v.high:
            raise ValueError(f"{v.name!r}: need finite low <= high, got [{v.low}, {v.high}]")
        name = self.core_name(v.name)
        if name == "heat_input":
            if v.low < 0:
                raise ValueError(f"heat_input [W]: must be >= 0, got low = {v.low}")
        else:
            if name not in self.core.parameter_names():
                raise KeyError(f"{v.name!r} is not a parameter of {self.core.source}; "
                               f"parameters are {', '.join(self.core.parameter_names())}")
            fld = name.partition(".")[2]
            check_values(fld, [v.low, v.high], f"design variable {v.name}")
        if v.log and v.low <= 0:
            raise ValueError(f"{v.name!r}: a log scale needs low > 0")
        return v

    def core_name(self, name: str) -> str:
        """The core parameter behind variable ``name`` (``stack.position`` -> preceding length)."""
        if name == f"{self.segment}.position":
            if self.stack_index == 0:
                raise CoreError(f"{self.core.source}: {self.segment} is the first segment; it has no position variable")
            return f"{self.core.segments[self.stack_index - 1].name}.length"
        return name

    # -- tables ------------------------------------------------------------------------
    @property
    def names(self) -> list[str]:
        return [v.name for v in self.variables]

    @property
    def param_names(self) -> list[str]:
        """Core parameters that vary over the space (the Engine's varying rows after Q)."""
        out = []
        if self.material is not None:
            out += [f"{self.segment}.{CORE_FIELD[p]}" for p in MATERIAL_PARAMS]
        for v in self.continuous:
            n = self.core_name(v.name)
            if n != "heat_input" and n not in out:
                out.append(n)
        return out

    def varying_table(self, values: dict) -> np.ndarray:
        """(1 + len(param_names), n) table for :class:`tawarp.forward.Engine`: row 0 the heat
        input. ``values``: variable name -> (n,) array; ``material`` as names or indices."""
        n = max(len(np.atleast_1d(a)) for a in values.values()) if values else 1
        rows = {}
        if self.material is not None:
            mat = np.atleast_1d(values["material"])
            if mat.dtype.kind in "iu":
                idx = mat
            else:
                lookup = {c: i for i, c in enumerate(self.material.choices)}
                idx = np.array([lookup[str(m)] for m in mat])
            for p in MATERIAL_PARAMS:
                table = np.array([getattr(self.catalogue[c], p) for c in self.material.choices])
                rows[f"{self.segment}.{CORE_FIELD[p]}"] = np.broadcast_to(table[idx], (n,))
        q = np.full(n, self.heat_input)
        for v in self.continuous:
            a = np.broadcast_to(np.asarray(values[v.name], dtype=float), (n,))
            name = self.core_name(v.name)
            if name == "heat_input":
                q = a
            else:
                rows[name] = a
        return np.stack([q] + [rows[k] for k in self.param_names]).astype(np.float64, copy=False)

    def core_for(self, point: dict) -> tuple[Core, float]:
        """(core, heat input [W]) of one design point ``{name: value}``."""
        core, q = self.core, self.heat_input
        if self.material is not None and "material" in point:
            core = self.catalogue[point["material"]].apply(core, self.segment)
        changes = {}
        for v in self.continuous:
            name = self.core_name(v.name)
            if name == "heat_input":
                q = float(point[v.name])
            else:
                changes[name] = float(point[v.name])
        return (core.replace(**changes) if changes else core), q

    # -- unit cube -----------------------------------------------------------------------
    def from_unit(self, u: np.ndarray) -> dict[str, np.ndarray]:
        """Continuous variables from the unit cube (n, len(continuous)); log scale where asked."""
        out = {}
        for j, v in enumerate(self.continuous):
            x = np.clip(u[:, j], 0.0, 1.0)
            if v.log:
                out[v.name] = np.exp(np.log(v.low) + x * (np.log(v.high) - np.log(v.low)))
            else:
                out[v.name] = v.low + x * (v.high - v.low)
        return out

    def to_unit(self, values: dict) -> np.ndarray:
        cols = []
        for v in self.continuous:
            a = np.asarray(values[v.name], dtype=float)
            if v.high == v.low:
                cols.append(np.zeros_like(a))
            elif v.log:
                cols.append((np.log(a) - np.log(v.low)) / (np.log(v.high) - np.log(v.low)))
            else:
                cols.append((a - v.low) / (v.high - v.low))
        return np.stack(cols, axis=-1) if cols else np.zeros((len(next(iter(values.values()), [])), 0))

    def distributions(self) -> dict:
        """Optuna distributions of the variables."""
        import optuna

        out = {}
        for v in self.variables:
            if v.categorical:
                out[v.name] = optuna.distributions.CategoricalDistribution(list(v.choices))
            else:
                out[v.name] = optuna.distributions.FloatDistribution(v.low, v.high, log=v.log)
        return out

    def describe(self) -> list[dict]:
        return [({"name": v.name, "choices": list(v.choices)} if v.categorical else
                 {"name": v.name, "low": v.low, "high": v.high, "log": v.log}) for v in self.variables]


# ======================================================================================
# Evaluation
# ======================================================================================
class Evaluator:
    """Batched objective evaluation of a :class:`DesignSpace`: one heat-solve launch and one
    metrics launch per batch (plus a T-matrix launch when ``acoustic`` is true).

    :meth:`evaluate` returns ``{metric: (n,) array}`` with :data:`METRICS` (and
    ``acoustic_loss``). ``settings.heat_cells`` sets the heat grid (1 is exact for
    piecewise-constant coefficients)."""

    def __init__(self, space: DesignSpace | None, acoustic: bool = False, freqs=DEFAULT_FREQS,
                 settings: ForwardSettings | None = None, *, core: Core | None = None, names=None,
                 stack_index: int | None = None):
        from ..kernels.design import N_METRICS

        self.space = space
        self.settings = settings or ForwardSettings()
        core = space.core if space is not None else core
        names = space.param_names if space is not None else list(names)
        self.stack_index = space.stack_index if space is not None else int(stack_index)
        self.names = names
        self.engine = Engine(core, [1.0], names, self.settings)
        self.device = self.engine.device
        self.n_metrics = N_METRICS
        self.acoustic = Engine(core, freqs, names, self.settings) if acoustic else None
        self.Zc = duct_impedance(core)

    def evaluate_table(self, varying) -> dict[str, np.ndarray]:
        """Metrics of a (1 + len(param_names), n) table (NumPy or Warp on the device)."""
        out = self.evaluate_device(varying)
        res = out.numpy()
        metrics = {k: res[:, j] for j, k in enumerate(METRICS)}
        if self.acoustic is not None:
            v0 = np.array(varying.numpy() if isinstance(varying, wp.array) else varying, dtype=np.float64, copy=True)
            v0[0] = 0.0
            T, _, _ = self.acoustic.evaluate(v0)
            n, m = v0.shape[1], len(self.acoustic.freqs)
            metrics["acoustic_loss"] = absorbed_fraction(T.numpy().view(np.complex128).reshape(n, m, 2, 2), self.Zc).mean(axis=1)
        return metrics

    def evaluate_device(self, varying, out: wp.array | None = None) -> wp.array:
        """Metrics (n, N_METRICS) on the device, no host copy."""
        from ..kernels.design import design_metrics

        eng = self.engine
        params, theta = eng.heat(varying)
        n = params.shape[1]
        if out is None:
            out = wp.empty((n, self.n_metrics), dtype=wp.float64, device=self.device)
        wp.launch(design_metrics, dim=n, device=self.device,
                  inputs=[params, eng.flags, eng.gas, theta, eng.first, eng.count, eng.heat_cells,
                          self.stack_index, out])
        return out

    def evaluate(self, values: dict) -> dict[str, np.ndarray]:
        """Metrics of design points ``{variable: (n,) array}``, in chunks of ``settings.chunk``."""
        table = self.space.varying_table(values)
        n = table.shape[1]
        parts = []
        for lo in range(0, max(n, 1), self.settings.chunk):
            parts.append(self.evaluate_table(table[:, lo:lo + self.settings.chunk]))
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def absorbed_fraction(T: np.ndarray, Zc: float) -> np.ndarray:
    """(n, m) fraction of incident plane-wave power absorbed by two-ports ``T`` (n, m, 2, 2),
    anechoic ducts of impedance ``Zc`` on both sides, mean of incidence from x1 and x6."""
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


# ======================================================================================
# Storage
# ======================================================================================
def make_storage(storage):
    """None -> in-memory; a URL (``sqlite:///x.db``, ``postgresql://...``) -> RDB; any other
    string/path -> a journal file (created when missing); a storage object passes."""
    import optuna
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend, JournalFileOpenLock

    if storage is None:
        return optuna.storages.InMemoryStorage()
    if not isinstance(storage, (str, os.PathLike)):
        return storage
    s = str(storage)
    if "://" in s:
        kw = {"connect_args": {"timeout": 60}} if s.startswith("sqlite") else {}
        for attempt in range(8):
            try:
                return optuna.storages.RDBStorage(s, engine_kwargs=kw)
            except Exception:  # workers creating a fresh database's schema at once race; retry
                if attempt == 7:
                    raise
                time.sleep(0.2 * (attempt + 1))
    os.makedirs(os.path.dirname(os.path.abspath(s)), exist_ok=True)
    return JournalStorage(JournalFileBackend(s, lock_obj=JournalFileOpenLock(s)))


def _is_journal(storage) -> bool:
    from optuna.storages import JournalStorage

    return isinstance(storage, JournalStorage) and hasattr(storage, "_backend") and hasattr(storage, "_replay_result")


def _iso(dt: datetime) -> str:
    return dt.astimezone(timezone.utc).isoformat(timespec="microseconds")


def create_trials(study, params: list[dict], distributions: dict, system_attrs: list[dict]) -> list[int]:
    """Create RUNNING trials with given params in bulk; returns their trial ids.

    Journal storage: one append (one lock, one fsync) for the whole batch; the ids are
    consecutive because the batch is one atomic write. Other storages: one call each."""
    from optuna.distributions import distribution_to_json
    from optuna.storages.journal._storage import JournalOperation
    from optuna.trial import FrozenTrial, TrialState

    storage = study._storage
    sid = study._study_id
    if not params:
        return []
    if _is_journal(storage):
        now = _iso(datetime.now(timezone.utc))
        djson = {k: distribution_to_json(d) for k, d in distributions.items()}
        with storage._thread_lock:
            wid = storage._replay_result.worker_id
            logs = []
            for p, sa in zip(params, system_attrs):
                logs.append({"op_code": JournalOperation.CREATE_TRIAL, "worker_id": wid, "study_id": sid,
                             "datetime_start": now, "state": TrialState.RUNNING, "value": None, "values": None,
                             "distributions": {k: djson[k] for k in p},
                             "params": {k: distributions[k].to_internal_repr(v) for k, v in p.items()},
                             "user_attrs": {}, "system_attrs": sa, "intermediate_values": {}})
            storage._backend.append_logs(logs)
            storage._sync_with_backend()
            last = storage._replay_result._last_created_trial_id_by_this_process
        ids = list(range(last - len(params) + 1, last + 1))
        return ids
    ids = []
    now = datetime.now()
    for p, sa in zip(params, system_attrs):
        tmpl = FrozenTrial(number=-1, state=TrialState.RUNNING, value=None, datetime_start=now, datetime_complete=None,
                           params=p, distributions={k: distributions[k] for k in p}, user_attrs={}, system_attrs=sa,
                           intermediate_values={}, trial_id=-1)
        ids.append(storage.create_new_trial(sid, template_trial=tmpl))
    return ids


def finish_trials(study, trial_ids: list[int], values: list, user_attrs: list[dict], constraints: list | None,
                  failed: np.ndarray | None = None) -> None:
    """Tell a batch: user attributes, constraints, then state COMPLETE (FAIL where ``failed``)."""
    from optuna.storages.journal._storage import JournalOperation
    from optuna.trial import TrialState

    storage = study._storage
    failed = np.zeros(len(trial_ids), bool) if failed is None else failed
    if _is_journal(storage):
        now = _iso(datetime.now(timezone.utc))
        with storage._thread_lock:
            wid = storage._replay_result.worker_id
            logs = []
            for j, tid in enumerate(trial_ids):
                for k, v in user_attrs[j].items():
                    logs.append({"op_code": JournalOperation.SET_TRIAL_USER_ATTR, "worker_id": wid,
                                 "trial_id": tid, "user_attr": {k: v}})
                if constraints is not None:
                    logs.append({"op_code": JournalOperation.SET_TRIAL_SYSTEM_ATTR, "worker_id": wid,
                                 "trial_id": tid, "system_attr": {"constraints": constraints[j]}})
                state = TrialState.FAIL if failed[j] else TrialState.COMPLETE
                logs.append({"op_code": JournalOperation.SET_TRIAL_STATE_VALUES, "worker_id": wid, "trial_id": tid,
                             "state": state, "values": None if failed[j] else values[j], "datetime_complete": now})
            storage._backend.append_logs(logs)
            storage._sync_with_backend()
        return
    for j, tid in enumerate(trial_ids):
        for k, v in user_attrs[j].items():
            storage.set_trial_user_attr(tid, k, v)
        if constraints is not None:
            storage.set_trial_system_attr(tid, "constraints", constraints[j])
        if failed[j]:
            storage.set_trial_state_values(tid, TrialState.FAIL)
        else:
            storage.set_trial_state_values(tid, TrialState.COMPLETE, values[j])


# ======================================================================================
# Batched samplers (state replayed from the lineage's generations)
# ======================================================================================
def sobol_unit(n: int, d: int, seed: int, skip: int = 0) -> np.ndarray:
    """n scrambled Sobol points in [0, 1)^d (points skip.. of the seeded sequence)."""
    from scipy.stats import qmc

    if d == 0:
        return np.zeros((n, 0))
    import warnings

    eng = qmc.Sobol(d, scramble=True, seed=seed)
    if skip:
        eng.fast_forward(skip)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # balance needs powers of 2; any n is fine here
        return eng.random(n)


def _penalized(f: np.ndarray, violation: np.ndarray) -> np.ndarray:
    """Deb's rule for a minimized scalar: infeasible points rank after every feasible one,
    by their violation."""
    f = np.where(np.isfinite(f), f, np.inf)
    feas = (violation <= 0) & np.isfinite(f)
    worst = np.max(f[feas]) if np.any(feas) else 0.0
    big = np.where(np.isfinite(violation), violation, 1e300)
    return np.where(feas, f, worst + 1.0 + np.abs(worst) + big)


class BatchCmaEs:
    """CMA-ES over the continuous variables, one instance per material, population = batch
    (split between materials). Generation 0 is scrambled Sobol; CMA-ES is warm-started
    from it. ``tell`` takes minimized values (penalized for constraints)."""

    def __init__(self, space: DesignSpace, batch: int, seed: int):
        self.space, self.batch, self.seed = space, batch, seed
        self.n_mat = len(space.material.choices) if space.material is not None else 1
        if batch < 2 * self.n_mat:
            raise ValueError(f"batch {batch} too small: CMA-ES needs at least 2 trials per material ({self.n_mat} materials)")
        self.d = max(len(space.continuous), 2)  # cmaes needs >= 2 dimensions: pad a dummy one
        self.sizes = [batch // self.n_mat + (1 if m < batch % self.n_mat else 0) for m in range(self.n_mat)]
        self.opts = [None] * self.n_mat
        self.generation = 0

    def ask(self) -> tuple[np.ndarray, np.ndarray]:
        """(unit (batch, d), material index (batch,)) of the next generation."""
        g = self.generation
        if g == 0:
            u = sobol_unit(self.batch, self.d, self.seed)
            mat = np.arange(self.batch) % self.n_mat
            return u, mat
        us, mats = [], []
        for m, opt in enumerate(self.opts):
            opt._rng.seed((self.seed * 7919 + g * 104729 + m) % (2**31 - 1))
            us.append(np.array([opt.ask() for _ in range(opt.population_size)]))
            mats.append(np.full(opt.population_size, m))
        return np.concatenate(us), np.concatenate(mats)

    def tell(self, u: np.ndarray, mat: np.ndarray, f: np.ndarray) -> None:
        import cmaes

        if self.generation == 0:
            for m in range(self.n_mat):
                sel = mat == m
                sols = [(u[i], f[i]) for i in np.flatnonzero(sel)]
                gamma = min(1.0, max(0.1, 1.0001 / len(sols)))
                try:
                    mean, sigma, cov = cmaes.get_warm_start_mgd(sols, gamma=gamma, alpha=0.1)
                    ok = np.all(np.isfinite(cov)) and np.isfinite(sigma) and sigma > 0
                except (AssertionError, np.linalg.LinAlgError, ValueError):
                    ok = False
                if not ok:
                    mean, sigma, cov = np.full(self.d, 0.5), 1.0 / 6.0, None
                mean = np.clip(mean, 0.0, 1.0)
                self.opts[m] = cmaes.CMA(mean=mean, sigma=max(float(sigma), 1e-8), cov=cov,
                                         bounds=np.tile([0.0, 1.0], (self.d, 1)),
                                         seed=(self.seed + 1000 * m) % (2**31 - 1) + 1,
                                         n_max_resampling=10 * self.d, population_size=self.sizes[m])
        else:
            for m, opt in enumerate(self.opts):
                sel = np.flatnonzero(mat == m)
                opt.tell([(u[i], float(f[i])) for i in sel])
        self.generation += 1


def nondominated_ranks(F: np.ndarray) -> np.ndarray:
    """Front index (0 = non-dominated) of each row of F (N, M), all minimized.

    Two objectives: O(N log N) sweep (points in lexicographic order; each front keeps its
    smallest second objective, a sorted list searched by bisection). More: Deb's fast
    non-dominated sort on the domination matrix (O(N^2) memory)."""
    import bisect

    F = np.asarray(F, dtype=float)
    N = F.shape[0]
    if F.shape[1] == 2:
        order = np.lexsort((F[:, 1], F[:, 0]))
        rank = np.empty(N, dtype=int)
        last: list[float] = []
        prev = None
        for i in order:
            f0, f1 = F[i, 0], F[i, 1]
            if prev is not None and f0 == F[prev, 0] and f1 == F[prev, 1]:
                rank[i] = rank[prev]  # identical points do not dominate each other
            else:
                k = bisect.bisect_right(last, f1)
                if k == len(last):
                    last.append(f1)
                else:
                    last[k] = f1
                rank[i] = k
            prev = i
        return rank
    dom = np.zeros((N, N), dtype=bool)  # dom[p, q]: p dominates q
    for lo in range(0, N, 1024):
        a = F[lo:lo + 1024, None, :]
        dom[lo:lo + 1024] = np.all(a <= F[None, :, :], axis=2) & np.any(a < F[None, :, :], axis=2)
    count = dom.sum(axis=0)
    rank = np.full(N, -1)
    front = np.flatnonzero(count == 0)
    r = 0
    while front.size:
        rank[front] = r
        count = count - dom[front].sum(axis=0)
        count[rank >= 0] = -1
        front = np.flatnonzero(count == 0)
        r += 1
    return rank


def pareto_mask(F: np.ndarray) -> np.ndarray:
    """Rows of F (N, M), all minimized, that no other row dominates. O(N x front size)."""
    F = np.asarray(F, dtype=float)
    if F.shape[1] == 2:
        return nondominated_ranks(F) == 0
    order = np.lexsort(F.T[::-1])
    front: list[int] = []
    for i in order:
        if front:
            P = F[front]
            if np.any(np.all(P <= F[i], axis=1) & np.any(P < F[i], axis=1)):
                continue
        front.append(i)
    mask = np.zeros(F.shape[0], dtype=bool)
    mask[front] = True
    return mask


def crowding(F: np.ndarray, rank: np.ndarray) -> np.ndarray:
    dist = np.zeros(F.shape[0])
    for r in np.unique(rank):
        idx = np.flatnonzero(rank == r)
        if idx.size <= 2:
            dist[idx] = np.inf
            continue
        for j in range(F.shape[1]):
            order = idx[np.argsort(F[idx, j], kind="stable")]
            span = F[order[-1], j] - F[order[0], j]
            dist[order[0]] = dist[order[-1]] = np.inf
            if span > 0:
                dist[order[1:-1]] += (F[order[2:], j] - F[order[:-2], j]) / span
    return dist


def constrained_objectives(F: np.ndarray, violation: np.ndarray) -> np.ndarray:
    """Objectives (minimized) under which plain Pareto domination is Deb's constrained
    domination: infeasible rows get ``max feasible + 1 + violation`` in every column."""
    F = np.where(np.isfinite(F), F, np.inf)
    feas = (violation <= 0) & np.all(np.isfinite(F), axis=1)
    top = np.max(F[feas], axis=0) if np.any(feas) else np.zeros(F.shape[1])
    span = np.abs(top) + 1.0
    v = np.where(np.isfinite(violation), np.maximum(violation, 0), 1e300)
    return np.where(feas[:, None], F, top + span + v[:, None])


class BatchNsga2:
    """NSGA-II, population = batch; generation 0 scrambled Sobol. ``tell`` takes minimized
    objective vectors and constraint violations."""

    def __init__(self, space: DesignSpace, batch: int, seed: int, eta_c: float = 15.0, eta_m: float = 20.0,
                 n_objectives: int = 2):
        self.space, self.batch, self.seed = space, batch, seed
        if n_objectives > 2 and batch > 4096:
            raise ValueError("NSGA-II with more than two objectives: batch at most 4096 (O(batch^2) sorting memory)")
        self.n_mat = len(space.material.choices) if space.material is not None else 1
        self.d = len(space.continuous)
        self.eta_c, self.eta_m = eta_c, eta_m
        self.pop = None  # (u, mat, F, violation)
        self.generation = 0

    def _select(self, u, mat, F, viol):
        G = constrained_objectives(F, viol)
        rank = nondominated_ranks(G)
        cd = crowding(G, rank)
        order = np.lexsort((-cd, rank))[: self.batch]
        self._rank, self._cd = rank[order], cd[order]
        return u[order], mat[order], F[order], viol[order]

    def ask(self) -> tuple[np.ndarray, np.ndarray]:
        g = self.generation
        if g == 0:
            return sobol_unit(self.batch, self.d, self.seed), np.arange(self.batch) % self.n_mat
        rng = np.random.default_rng([self.seed, g])
        u, mat = self.pop[0], self.pop[1]
        n, B = len(u), self.batch

        def tournament(k):
            a, b = rng.integers(0, n, k), rng.integers(0, n, k)
            better = (self._rank[a] < self._rank[b]) | ((self._rank[a] == self._rank[b]) & (self._cd[a] > self._cd[b]))
            return np.where(better, a, b)

        p1, p2 = tournament(B), tournament(B)
        x1, x2 = u[p1].copy(), u[p2].copy()
        child = x1.copy()
        if self.d:
            # SBX crossover, probability 0.9 per pair, each gene with probability 0.5
            do = (rng.random(B) < 0.9)[:, None] & (rng.random((B, self.d)) < 0.5)
            r = rng.random((B, self.d))
            beta = np.where(r <= 0.5, (2 * r) ** (1 / (self.eta_c + 1)), (1 / (2 * (1 - r))) ** (1 / (self.eta_c + 1)))
            c1 = 0.5 * ((1 + beta) * x1 + (1 - beta) * x2)
            c2 = 0.5 * ((1 - beta) * x1 + (1 + beta) * x2)
            pick = rng.random((B, self.d)) < 0.5
            child = np.where(do, np.where(pick, c1, c2), x1)
            # polynomial mutation, probability 1/d per gene
            mut = rng.random((B, self.d)) < 1.0 / max(self.d, 1)
            r = rng.random((B, self.d))
            delta = np.where(r < 0.5, (2 * r) ** (1 / (self.eta_m + 1)) - 1, 1 - (2 * (1 - r)) ** (1 / (self.eta_m + 1)))
            child = np.clip(np.where(mut, child + delta, child), 0.0, 1.0)
        cm = np.where(rng.random(B) < 0.5, mat[p1], mat[p2])
        if self.n_mat > 1:
            flip = rng.random(B) < 1.0 / (self.d + 1)
            cm = np.where(flip, rng.integers(0, self.n_mat, B), cm)
        return child, cm

    def tell(self, u, mat, F, viol) -> None:
        if self.pop is None:
            self.pop = self._select(u, mat, F, viol)
        else:
            P = self.pop
            self.pop = self._select(np.concatenate([P[0], u]), np.concatenate([P[1], mat]),
                                    np.concatenate([P[2], F]), np.concatenate([P[3], viol]))
        self.generation += 1


# ======================================================================================
# Search
# ======================================================================================
@dataclass
class SearchResult:
    """``study`` (Optuna), ``best`` (list of dicts: the best feasible trial, or the
    feasible Pareto front for several objectives), ``timing`` (seconds: ``sampler``,
    ``evaluation``, ``storage``, ``wall``; ``evaluations``, ``evaluations_per_minute``,
    ``sampler_share``, ``evaluation_share``), ``resumed`` trials adopted at start."""

    study: object
    objectives: tuple
    best: list
    timing: dict
    resumed: int = 0
    worker: str = "w0"


class StudyConflict(ValueError):
    """The study cannot be continued as asked (a live worker of the same name, another batch)."""


class SearchCrash(RuntimeError):
    """Raised by the ``_stop_after`` test hook (a simulated interruption)."""


def _interruption_hooks(asked: int, stop_after: int | None, crash_after: int | None) -> None:
    """Test hooks simulating an interruption once ``asked`` batches are asked but not told:
    ``crash_after`` kills the process, ``stop_after`` raises :class:`SearchCrash`."""
    if crash_after is not None and asked >= crash_after:
        os._exit(3)
    if stop_after is not None and asked >= stop_after:
        raise SearchCrash(f"stopped after asking {asked} batches (test hook)")


def _owner_alive(owner: str, run_id: str, stale_after: float, started) -> bool:
    """Is the process that asked a RUNNING trial still working on it?"""
    host, _, rest = (owner or "").partition(":")
    pid, _, rid = rest.partition(":")
    if rid == run_id:
        return True
    if host == socket.gethostname() and pid.isdigit():
        if int(pid) == os.getpid():
            return False  # an earlier run of this process: runs are sequential
        try:
            os.kill(int(pid), 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return True
    if started is None:
        return False
    return (datetime.now() - started).total_seconds() < stale_after


def _directions(objectives) -> list[str]:
    for o in objectives:
        if o not in OBJECTIVES:
            raise KeyError(f"unknown objective {o!r}; choose from {', '.join(OBJECTIVES)}")
    return [OBJECTIVES[o][0] for o in objectives]


def open_study(storage, study_name: str, objectives, create: bool = True):
    """Load or create the Optuna study ``study_name`` in ``storage`` (see :func:`make_storage`)."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    st = make_storage(storage)
    dirs = _directions(objectives)
    study = optuna.create_study(storage=st, study_name=study_name, directions=dirs, load_if_exists=True)
    if [d.name.lower() for d in study.directions] != dirs:
        raise ValueError(f"study {study_name!r} has directions {[d.name.lower() for d in study.directions]}, "
                         f"objectives {list(objectives)} need {dirs}")
    prev = study.user_attrs.get("tawarp_objectives")
    if prev is None:
        study.set_user_attr("tawarp_objectives", list(objectives))
    elif list(prev) != list(objectives):
        raise ValueError(f"study {study_name!r} was run with objectives {prev}, not {list(objectives)}")
    return study


def search(space: DesignSpace, objectives=("gradient",), n_trials: int = 1024, batch: int = 256, storage=None,
           study_name: str = "tawarp-design", worker: str = "w0", seed: int = 0, T_limit: float | None = DEFAULT_T_LIMIT,
           engine: str = "batched", settings: ForwardSettings | None = None, freqs=DEFAULT_FREQS,
           progress: bool = False, stale_after: float = 3600.0, _stop_after: int | None = None,
           _crash_after: int | None = None) -> SearchResult:
    """Run (or resume) a batched design search; see the module docstring.

    ``n_trials``: trials of this worker's lineage in the study when done (rounded up to
    whole batches). ``T_limit`` [K]: constraint ``T_max <= T_limit`` (None: none).
    ``stale_after`` [s]: a RUNNING trial of another host is adopted once this old (a
    trial of this host is adopted as soon as its process is gone). ``_stop_after`` /
    ``_crash_after``: test hooks that interrupt after asking that many batches (raise
    :class:`SearchCrash` / ``os._exit``)."""
    from optuna.trial import TrialState

    from ..progress import progress_bar

    objectives = tuple(objectives)
    dirs = _directions(objectives)
    if engine not in ("batched", "optuna"):
        raise ValueError(f"engine must be 'batched' or 'optuna', got {engine!r}")
    if batch < 1 or n_trials < 1:
        raise ValueError("batch and n_trials must be >= 1")
    if not space.continuous:
        raise ValueError("the design space needs at least one continuous variable")
    t_wall = time.perf_counter()
    study = open_study(storage, study_name, objectives)
    run_id = uuid.uuid4().hex[:12]
    owner = f"{socket.gethostname()}:{os.getpid()}:{run_id}"
    multi = len(objectives) > 1
    evaluator = Evaluator(space, acoustic="acoustic_loss" in objectives, freqs=freqs, settings=settings)
    dists = space.distributions()
    timing = dict(sampler=0.0, evaluation=0.0, storage=0.0, evaluations=0)
    sign = np.array([1.0 if d == "minimize" else -1.0 for d in dirs])

    def evaluate(points: list[dict]):
        """Evaluate params dicts; returns (values list, user attrs list, constraints, minimized F, violation, failed)."""
        t = time.perf_counter()
        vals = {v.name: np.array([p[v.name] for p in points], dtype=float) for v in space.continuous}
        if space.material is not None:
            vals["material"] = np.array([p["material"] for p in points])
        m = evaluator.evaluate(vals)
        timing["evaluation"] += time.perf_counter() - t
        timing["evaluations"] += len(points)
        F = np.stack([m[o] for o in objectives], axis=1)
        failed = ~np.all(np.isfinite(F), axis=1)
        viol = (m["T_max"] - T_limit) if T_limit is not None else np.zeros(len(points))
        user = [{k: float(m[k][j]) for k in m} for j in range(len(points))]
        cons = [[float(viol[j])] for j in range(len(points))] if T_limit is not None else None
        values = [[float(x) for x in F[j]] if multi else float(F[j, 0]) for j in range(len(points))]
        return values, user, cons, F * sign, viol, failed

    def tell(ids, values, user, cons, failed):
        t = time.perf_counter()
        finish_trials(study, ids, [v if isinstance(v, list) else [v] for v in values], user, cons, failed)
        timing["storage"] += time.perf_counter() - t

    # -- adopt trials asked but never told by a process that is gone -------------------
    t = time.perf_counter()
    trials = study.get_trials(deepcopy=False)
    mine = [tr for tr in trials if tr.system_attrs.get(_ATTR + "worker") == worker]
    orphans = [tr for tr in mine if tr.state == TrialState.RUNNING]
    live = [tr for tr in orphans if _owner_alive(tr.system_attrs.get(_ATTR + "owner", ""), run_id, stale_after, tr.datetime_start)]
    if live:
        raise StudyConflict(f"worker {worker!r} of study {study_name!r} has {len(live)} trials running in a live process "
                           f"({live[0].system_attrs.get(_ATTR + 'owner')}); give this run another worker name")
    timing["storage"] += time.perf_counter() - t
    if orphans:
        values, user, cons, _, _, failed = evaluate([tr.params for tr in orphans])
        tell([tr._trial_id for tr in orphans], values, user, cons, failed)
    resumed = len(orphans)
    n_target = -(-n_trials // batch) * batch
    bar = progress_bar(n_target, f"design ({worker})", progress, unit="trial")

    if engine == "optuna":
        _search_optuna(study, space, objectives, dirs, n_target, batch, worker, seed, T_limit, evaluate, owner,
                       timing, bar, _stop_after, _crash_after)
    else:
        # -- replay the lineage ---------------------------------------------------------
        t = time.perf_counter()
        mine = [tr for tr in study.get_trials(deepcopy=False) if tr.system_attrs.get(_ATTR + "worker") == worker]
        gens: dict[int, list] = {}
        for tr in mine:
            gens.setdefault(int(tr.system_attrs[_ATTR + "generation"]), []).append(tr)
        sampler = BatchNsga2(space, batch, seed, n_objectives=len(objectives)) if multi else BatchCmaEs(space, batch, seed)
        nc = len(space.continuous)

        def population(u, mat, indices):
            vals = space.from_unit(u[:, :nc])
            points, attrs = [], []
            for j in indices:
                p = {k: float(vals[k][j]) for k in vals}
                if space.material is not None:
                    p["material"] = space.material.choices[int(mat[j])]
                points.append(p)
                a = {_ATTR + "worker": worker, _ATTR + "generation": sampler.generation, _ATTR + "index": int(j),
                     _ATTR + "owner": owner}
                if u.shape[1] > nc:  # CMA-ES padding dimension: kept so that a replay is exact
                    a[_ATTR + "pad"] = [float(x) for x in u[j, nc:]]
                attrs.append(a)
            return points, attrs

        done = 0
        last = max(gens) if gens else -1
        for g in sorted(gens):
            trs = gens[g]
            if g == last and g == sampler.generation and len(trs) < batch:
                # a generation cut short while its trials were being created (per-trial storages):
                # the sampler is deterministic, so the missing members are asked again, exactly
                u, mat = sampler.ask()
                have = {int(tr.system_attrs.get(_ATTR + "index", -1)) for tr in trs}
                missing = [j for j in range(batch) if j not in have]
                points, attrs = population(u, mat, missing)
                ids = create_trials(study, points, dists, attrs)
                values, user, cons, _, _, failed = evaluate(points)
                tell(ids, values, user, cons, failed)
                resumed += len(missing)
                trs = [tr for tr in study.get_trials(deepcopy=False)
                       if tr.system_attrs.get(_ATTR + "worker") == worker
                       and int(tr.system_attrs[_ATTR + "generation"]) == g]
            trs = sorted(trs, key=lambda tr: tr.system_attrs.get(_ATTR + "index", 0))
            if g != sampler.generation or len(trs) != batch:
                raise StudyConflict(f"study {study_name!r}, worker {worker!r}: generation {g} has {len(trs)} trials, "
                                    f"expected generation {sampler.generation} with batch {batch}; resume with the same batch")
            _tell_replay(sampler, space, trs, sign, T_limit, multi, sampler.d)
            done += len(trs)
        timing["sampler"] += time.perf_counter() - t
        bar.update(min(done, n_target))
        asked = 0
        while done < n_target:
            t = time.perf_counter()
            u, mat = sampler.ask()
            points, attrs = population(u, mat, range(batch))
            timing["sampler"] += time.perf_counter() - t
            t = time.perf_counter()
            ids = create_trials(study, points, dists, attrs)
            timing["storage"] += time.perf_counter() - t
            asked += 1
            _interruption_hooks(asked, _stop_after, _crash_after)
            values, user, cons, F, viol, failed = evaluate(points)
            tell(ids, values, user, cons, failed)
            t = time.perf_counter()
            u_told = space.to_unit({v.name: np.array([p[v.name] for p in points]) for v in space.continuous})
            if u.shape[1] > u_told.shape[1]:
                u_told = np.concatenate([u_told, u[:, u_told.shape[1]:]], axis=1)
            u = u_told
            if multi:
                sampler.tell(u, mat, np.where(failed[:, None], np.inf, F), np.where(failed, np.inf, viol))
            else:
                sampler.tell(u, mat, _penalized(np.where(failed, np.inf, F[:, 0]), np.where(failed, np.inf, viol)))
            timing["sampler"] += time.perf_counter() - t
            done += batch
            bar.update(batch)
    bar.close()
    timing["wall"] = time.perf_counter() - t_wall
    timing["evaluations_per_minute"] = 60.0 * timing["evaluations"] / max(timing["wall"], 1e-12)
    for k in ("sampler", "evaluation", "storage"):
        timing[f"{k}_share"] = timing[k] / max(timing["wall"], 1e-12)
    return SearchResult(study, objectives, best_designs(study, objectives, T_limit), timing, resumed, worker)


def _tell_replay(sampler, space, trs, sign, T_limit, multi, d):
    """Tell the sampler a stored generation (trials in asked order)."""
    from optuna.trial import TrialState

    vals = {v.name: np.array([tr.params[v.name] for tr in trs]) for v in space.continuous}
    u = space.to_unit(vals)
    if u.shape[1] < d:
        pad = np.array([tr.system_attrs.get(_ATTR + "pad", [0.5] * (d - u.shape[1])) for tr in trs], dtype=float)
        u = np.concatenate([u, pad.reshape(len(trs), d - u.shape[1])], axis=1)
    mat = np.zeros(len(trs), dtype=int)
    if space.material is not None:
        mat = np.array([space.material.choices.index(tr.params["material"]) for tr in trs])
    ok = np.array([tr.state == TrialState.COMPLETE for tr in trs])
    F = np.array([list(tr.values) if ok[j] else [np.inf] * len(sign) for j, tr in enumerate(trs)]) * sign
    viol = np.array([tr.system_attrs.get("constraints", [0.0])[0] if ok[j] and T_limit is not None else (0.0 if ok[j] else np.inf)
                     for j, tr in enumerate(trs)])
    if multi:
        sampler.tell(u, mat, F, viol)
    else:
        sampler.tell(u, mat, _penalized(F[:, 0], viol))


def _search_optuna(study, space, objectives, dirs, n_target, batch, worker, seed, T_limit, evaluate, owner,
                   timing, bar, stop_after, crash_after):
    """Optuna's own samplers, one ``study.ask()`` per trial, one evaluation launch per batch."""
    import optuna
    from optuna.trial import TrialState

    def constraints_func(trial):
        return trial.system_attrs.get("constraints", [0.0])

    import warnings

    warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning, module="tawarp.design")
    warnings.filterwarnings("ignore", message="Constraints have been set, but CmaEsSampler")
    if len(objectives) > 1:
        sampler = optuna.samplers.NSGAIISampler(population_size=batch, seed=seed,
                                                constraints_func=constraints_func if T_limit is not None else None)
    else:
        sampler = optuna.samplers.CmaEsSampler(popsize=batch, n_startup_trials=batch, seed=seed,
                                               independent_sampler=optuna.samplers.QMCSampler(seed=seed, scramble=True, warn_independent_sampling=False),
                                               warn_independent_sampling=False)
    study.sampler = sampler
    dists = space.distributions()
    done = sum(1 for tr in study.get_trials(deepcopy=False) if tr.system_attrs.get(_ATTR + "worker") == worker)
    bar.update(min(done, n_target))
    asked = 0
    while done < n_target:
        t = time.perf_counter()
        trials = []
        for j in range(batch):
            tr = study.ask(dists)
            tr.storage.set_trial_system_attr(tr._trial_id, _ATTR + "worker", worker)
            tr.storage.set_trial_system_attr(tr._trial_id, _ATTR + "owner", owner)
            trials.append(tr)
        timing["sampler"] += time.perf_counter() - t
        asked += 1
        _interruption_hooks(asked, stop_after, crash_after)
        values, user, cons, F, viol, failed = evaluate([tr.params for tr in trials])
        t = time.perf_counter()
        for j, tr in enumerate(trials):
            for k, v in user[j].items():
                tr.set_user_attr(k, v)
            if cons is not None:
                study._storage.set_trial_system_attr(tr._trial_id, "constraints", cons[j])
            if failed[j]:
                study.tell(tr, state=TrialState.FAIL)
            else:
                study.tell(tr, values[j])
        timing["sampler"] += time.perf_counter() - t  # tell runs the sampler's after_trial
        done += batch
        bar.update(batch)


def best_designs(study, objectives, T_limit=DEFAULT_T_LIMIT, k: int = 1) -> list[dict]:
    """Best feasible trials: the ``k`` best for one objective, the Pareto front for several.
    Each: ``number``, ``params``, ``values`` {objective: value}, ``metrics`` (user attrs)."""
    from optuna.trial import TrialState

    trials = [t for t in study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))]
    if T_limit is not None:
        trials = [t for t in trials if t.system_attrs.get("constraints", [0.0])[0] <= 0]
    if not trials:
        return []
    dirs = _directions(objectives)
    sign = np.array([1.0 if d == "minimize" else -1.0 for d in dirs])
    F = np.array([t.values for t in trials]) * sign
    if len(objectives) == 1:
        order = np.argsort(F[:, 0], kind="stable")[:k]
    else:
        order = np.flatnonzero(pareto_mask(F))
        order = order[np.argsort(F[order, 0], kind="stable")]
    out, seen = [], set()
    for i in order:
        t = trials[i]
        key = tuple(sorted((k2, str(v)) for k2, v in t.params.items()))
        if key in seen:
            continue
        seen.add(key)
        out.append({"number": t.number, "params": dict(t.params),
                    "values": {o: float(v) for o, v in zip(objectives, t.values)},
                    "metrics": {k2: v for k2, v in t.user_attrs.items()},
                    "worker": t.system_attrs.get(_ATTR + "worker")})
    return out


def study_summary(study, objectives) -> dict:
    """Counts of trials by state and by worker, numbers unique (for checks and reports)."""
    from collections import Counter

    trials = study.get_trials(deepcopy=False)
    return {"trials": len(trials), "states": dict(Counter(t.state.name for t in trials)),
            "workers": dict(Counter(t.system_attrs.get(_ATTR + "worker") for t in trials)),
            "unique_numbers": len({t.number for t in trials}) == len(trials)}
