"""Batched evaluation of design objectives: one heat-solve launch and one metrics launch
per batch (plus a T-matrix launch when a host objective such as ``acoustic_loss`` asks
for it). What is computed, and in which kernel column, is read from the objectives
table (:mod:`tawarp.design.objectives`)."""

from __future__ import annotations

import dataclasses

import numpy as np
import warp as wp

from .objectives import OnsetSpec, kernel_metrics, objective
from .space import DesignSpace
from ..model.core import Core
from ..model.forward import Engine, ForwardSettings

DEFAULT_FREQS = (50.0, 100.0, 200.0, 400.0)


class Evaluator:
    """Objectives of a :class:`DesignSpace` (or of ``core`` with varying rows ``names`` and
    the stack at segment ``stack_index``) on the device of ``settings``.

    :meth:`evaluate` returns ``{name: (n,) array}``: every kernel column, plus the host
    objectives named in ``extra`` (e.g. ``acoustic_loss``, at ``freqs`` [Hz]; the onset
    objectives, closed as ``onset`` says: :class:`tawarp.design.objectives.OnsetSpec`).
    ``settings.heat_cells`` sets the heat grid (1 is exact for piecewise-constant
    coefficients)."""

    def __init__(
        self,
        space: DesignSpace | None,
        extra=(),
        freqs=DEFAULT_FREQS,
        settings: ForwardSettings | None = None,
        *,
        core: Core | None = None,
        names=None,
        stack_index: int | None = None,
        onset=None,
    ):
        from ..kernels.design import N_METRICS

        self.space = space
        self.settings = settings or ForwardSettings()
        self.core = space.core if space is not None else core
        self.names = space.param_names if space is not None else list(names)
        self.stack_index = space.stack_index if space is not None else int(stack_index)
        self.engine = Engine(self.core, [1.0], self.names, self.settings)
        self.device = self.engine.device
        self.n_metrics = N_METRICS
        self.columns = kernel_metrics()
        self.extra = [objective(n) for n in extra if objective(n).column is None]
        self.freqs = tuple(float(f) for f in freqs)
        self._acoustic = None
        self.onset_spec = onset or OnsetSpec()
        self._onset_cache = (None, None, None)
        self._column_index: dict = {}

    def acoustic_engine(self) -> Engine:
        """T-matrix engine at ``freqs`` over the same varying rows (built on first use)."""
        if self._acoustic is None:
            self._acoustic = Engine(self.core, self.freqs, self.names, self.settings)
        return self._acoustic

    def onset_metrics(self, table: np.ndarray, draws: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(Q_onset [W], T_hot [K] at onset) of every design column of ``table``, inf where
        there is no onset by ``onset_spec.Q_max``; with ``draws``, (n, n_draws) arrays over
        the stack parameter sets drawn from ``onset_spec.uncertainty``'s covariance and added
        to each design's stack values (clipped to the fit ranges). One batched
        :func:`tawarp.model.onset.onset` call, kept for the other onset objectives of the
        same table."""
        from ..model.fields import field as parameter_field
        from ..model.onset import onset
        from ..model.resonator import load_engine
        from .catalogue import CORE_FIELD, PARAMS

        if self._onset_cache[0] is table and self._onset_cache[1] == draws:
            return self._onset_cache[2]
        spec = self.onset_spec
        ref = load_engine(spec.engine) if isinstance(spec.engine, str) else spec.engine
        engine = dataclasses.replace(ref, core=self.core)
        params = {k: table[1 + j] for j, k in enumerate(self.names)}
        n = table.shape[1]
        if draws:
            if spec.uncertainty is None:
                raise ValueError(
                    "objective Q_onset_p90 needs the stack material's uncertainty: OnsetSpec.uncertainty "
                    "(tawarp design --uncertainty MATERIAL|fit.json)"
                )
            m = spec.uncertainty
            dev = m.sample(spec.n_draws, spec.seed)
            seg = self.core.segment(spec.segment)
            for p in PARAMS:
                name = f"{spec.segment}.{CORE_FIELD[p]}"
                base = params.get(name, np.full(n, getattr(seg, CORE_FIELD[p])))
                lo, hi = parameter_field(CORE_FIELD[p]).fit_range
                params[name] = np.clip(base[:, None] + (dev[p] - getattr(m, p))[None, :], lo, hi).ravel()
            for k in self.names:
                if params[k].size == n:  # not a stack parameter: the same for every draw
                    params[k] = np.repeat(params[k], spec.n_draws)
        res = onset(engine, Q_max=spec.Q_max, params=params, n_bracket=spec.n_bracket, settings=self.settings)
        shape = (n, spec.n_draws) if draws else (n,)
        out = (
            np.where(np.isfinite(res.Q_onset), res.Q_onset, np.inf).reshape(shape),
            np.where(np.isfinite(res.T_hot), res.T_hot, np.inf).reshape(shape),
        )
        self._onset_cache = (table, draws, out)
        return out

    def evaluate_table(self, varying) -> dict[str, np.ndarray]:
        """Objectives of a (1 + len(names), n) table (NumPy, or Warp on the device)."""
        return self.objectives_of(self.evaluate_device(varying), varying)

    def objectives_of(self, out: wp.array, varying) -> dict[str, np.ndarray]:
        """:meth:`evaluate_table`'s objectives from the kernel metrics ``out`` that
        :meth:`evaluate_device` launched on ``varying``: waits for the device, copies them
        to the host and computes the host objectives. Launch, other host work, then this:
        the device works meanwhile (a sweep writes the previous chunk)."""
        # contiguous columns (transposed on the device): a strided column view costs Dask a
        # copy under the GIL to pass (0.15 s per 16.8M points), serialising worker threads
        res = self.metric_columns(out, self.columns, wp.float64).numpy()
        return self.with_host_objectives(dict(zip(self.columns, res)), varying)

    def with_host_objectives(self, metrics: dict, varying) -> dict[str, np.ndarray]:
        """``metrics`` (the kernel columns, host arrays) with the objectives computed on the
        host from them and the table ``varying`` (NumPy, or Warp, copied where one is asked)."""
        if self.extra:
            table = varying.numpy() if isinstance(varying, wp.array) else np.asarray(varying, dtype=np.float64)
            for o in self.extra:
                metrics[o.name] = np.asarray(o.compute(self, table, dict(metrics)), dtype=np.float64)
        return metrics

    def evaluate_device(self, varying, out: wp.array | None = None, work: tuple | None = None) -> wp.array:
        """Kernel metrics (n, N_METRICS) on the device, no host copy; into ``out`` where
        given, the heat solve into ``work`` (:meth:`tawarp.model.forward.Engine.heat_buffers`)."""
        from ..kernels.design import design_metrics

        eng = self.engine
        params, theta = eng.heat(varying, out=work)
        n = params.shape[1]
        if out is None:
            out = wp.empty((n, self.n_metrics), dtype=wp.float64, device=self.device)
        wp.launch(
            design_metrics,
            dim=n,
            device=self.device,
            inputs=[params, eng.flags, eng.gas, theta, eng.first, eng.count, eng.heat_cells, self.stack_index, out],
        )
        return out

    def metric_columns(self, out: wp.array, names, dtype=wp.float32, res: wp.array | None = None) -> wp.array:
        """Kernel columns ``names`` of the metrics ``out`` (n, N_METRICS) of
        :meth:`evaluate_device` as a (len(names), n) array of ``dtype`` on the device (into
        ``res`` where given): float32 is rounded as NumPy rounds a float64 (what a sweep
        file stores)."""
        from ..kernels.design import metric_columns

        key = tuple(names)
        if key not in self._column_index:  # once: no small copy to the device in a sweep's loop
            self._column_index[key] = wp.array(
                [self.columns.index(k) for k in names], dtype=wp.int32, device=self.device
            )
        cols = self._column_index[key]
        if res is None:
            res = wp.empty((len(names), out.shape[0]), dtype=dtype, device=self.device)
        wp.launch(metric_columns, dim=(len(names), out.shape[0]), inputs=[out, cols, res], device=self.device)
        return res

    def evaluate(self, values: dict) -> dict[str, np.ndarray]:
        """Objectives of design points ``{variable: (n,) array}``, in chunks of ``settings.chunk``."""
        table = self.space.varying_table(values)
        n = table.shape[1]
        parts = [
            self.evaluate_table(table[:, lo : lo + self.settings.chunk])
            for lo in range(0, max(n, 1), self.settings.chunk)
        ]
        return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
