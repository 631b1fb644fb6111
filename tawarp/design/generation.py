"""A generation of the batched design search on one device: the sampler's coordinates to
the designs' values, their metrics and the coordinates told back to the sampler, in arrays
kept for the whole run, copied to the host in one synchronization.

A generation of 8192 designs is about half a millisecond of an H100's time, while each
Warp array made and each launch cost the host some tens of microseconds: allocated per
generation, the arrays and launches of the evaluation and of the sampler's update were
several times the device's work. Kept here, the same launches on the same arrays serve
every generation, so that :meth:`tawarp.design.samplers.BatchCmaEs.launch_generation` can
run the sampler's update, its next sample and this evaluation as one CUDA graph
(bench/README.md, "A generation as one graph").
"""

from __future__ import annotations

import numpy as np
import warp as wp

from ..model.validity import ModelValidityError


class DeviceGeneration:
    """The evaluation of ``batch`` sampler coordinates by ``evaluator``
    (:class:`tawarp.design.evaluate.Evaluator`) through ``tables``
    (:class:`tawarp.design.space.DeviceTable`), on their device. :meth:`launches` issues
    it without waiting; :meth:`read` waits for the device and returns the host's copies."""

    def __init__(self, evaluator, tables, batch: int):
        self.evaluator, self.tables, self.batch = evaluator, tables, batch
        dev = tables.device
        d, space = len(tables.names), tables.space
        self.dims = (len(space.continuous), space.n_categories)
        self.unit = wp.empty((batch, d), dtype=wp.float64, device=dev)
        self.not_finite = wp.zeros(1, dtype=wp.int32, device=dev)
        self.table = wp.empty((tables.rows, batch), dtype=wp.float64, device=dev)
        self.values = wp.empty((d, batch), dtype=wp.float64, device=dev)
        self.told = wp.empty((batch, d), dtype=wp.float64, device=dev)
        self.work = evaluator.engine.heat_buffers(batch)
        self.metrics = wp.empty((batch, evaluator.n_metrics), dtype=wp.float64, device=dev)
        self.columns = wp.empty((len(evaluator.columns), batch), dtype=wp.float64, device=dev)
        # page-locked on a GPU: the copies to them run on with the launches (a graph's too)
        pinned = wp.get_device(dev).is_cuda
        self._host = [
            (wp.empty(a.shape, dtype=a.dtype, device="cpu", pinned=pinned), a)
            for a in (self.columns, self.values, self.not_finite)
        ]

    def launches(self, X: wp.array, told: wp.array | None = None) -> None:
        """Evaluate sampler coordinates ``X`` (batch, d) on the device and copy the metrics
        and values toward the host; the coordinates to tell go to ``told`` (default
        :attr:`told`). The same launches on the same arrays every call."""
        from ..kernels.sampler import to_table_unit

        self.not_finite.zero_()
        wp.launch(to_table_unit, dim=X.shape, device=X.device, inputs=[X, *self.dims, self.unit, self.not_finite])
        self.tables.unit(self.unit, out=(self.table, self.values))
        self.tables.coordinates(self.values, out=self.told if told is None else told)
        ev = self.evaluator
        ev.evaluate_device(self.table, out=self.metrics, work=self.work)
        ev.metric_columns(self.metrics, ev.columns, wp.float64, res=self.columns)
        for host, a in self._host:
            wp.copy(host, a)

    def read(self) -> tuple[dict, dict]:
        """(design values {variable: (batch,)}, the material as its index; metrics {name:
        (batch,)}, the evaluator's host objectives included) of the last :meth:`launches`,
        after the device's work: the host's own arrays (the buffers serve the next
        generation)."""
        wp.synchronize_device(self.tables.device)
        columns, values, not_finite = (h.numpy().copy() for h, _ in self._host)
        if not_finite[0]:  # as the host's table refuses them
            raise ModelValidityError(
                f"the sampler asked {not_finite[0]} coordinates that are not finite (nan or inf): none is stored"
            )
        metrics = self.evaluator.with_host_objectives(dict(zip(self.evaluator.columns, columns)), self.table)
        out = dict(zip(self.tables.names, values))
        if self.tables.space.material is not None:
            out["material"] = out["material"].astype(np.int64)
        return out, metrics
