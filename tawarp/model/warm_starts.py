"""Warm starts of the temperature-dependent heat solve: an engine keeps the converged nodal
excesses of the last sets it computed, and a later set near one of them starts its
iterations there (:func:`tawarp.kernels.heat.solve_heat`): a finite-difference neighbour
that starts from its point's excess takes two or three solves where the cold start takes
four to six, to the same fixed point and stopping rule (tests/test_heat_warm_start.py).

Two stores keep them by one rule: :class:`WarmStarts` on the host (a CPU engine, whose
sets come to the host anyway), :class:`DeviceWarmStarts` on a GPU (:mod:`tawarp.kernels.warm`:
the excesses stay on the device and the search runs there, so a launch's start costs the
host neither a copy nor a search). tests/test_heat_warm_start.py holds both to the rule
written out set by set.
"""

from __future__ import annotations

import threading

import numpy as np
import warp as wp
from scipy.spatial import cKDTree

from ..kernels import warm as kw

#: Heated parameter sets whose converged heat-model excess an engine with a
#: temperature-dependent effect keeps: a loop's batch of finite-difference neighbours
#: follows the batch of their points, and its trial points lie near the fits' current
#: points, computed in the batches before.
WARM_SETS = 1024
#: A set starts its heat solve from a kept set's excess when each value of the set is
#: within this relative distance of the kept set's (|ln(v/v_kept)| for positive values,
#: the change in units of the largest |v| of the batch and the kept sets otherwise), the
#: heat input equal; others start cold.
WARM_RADIUS = 0.1


class _KeptSets:
    """The ring of the last ``limit`` kept sets of a store: ``count`` of them, the next one
    written at slot ``next``, the capacity growing to ``limit`` as sets come (a put then
    costs its own sets, not a copy of every kept excess). A set iterates where it is heated
    and a temperature-dependent field is on: one of the varying table's rows ``switches``
    is not 0, or ``always`` (one is on in the core and does not vary). Safe to share
    between threads (an engine is: :func:`tawarp.measure.kind.get_engine`)."""

    def __init__(self, limit: int, rows: int, columns: int, switches: np.ndarray, always: bool):
        self.limit, self.rows, self.columns = limit, rows, columns
        self.switches, self.always = switches, always
        self.capacity = self.count = self.next = 0
        self.lock = threading.Lock()

    def iterating(self, table: np.ndarray) -> np.ndarray:
        """Indices of the sets of ``table`` (rows, n) whose heat solve iterates."""
        on = np.any(table[self.switches] != 0.0, axis=0) | self.always
        return np.flatnonzero((table[0] > 0.0) & on)

    def _oldest(self) -> int:
        """The slot of the oldest kept set (the ring has wrapped only once it is full)."""
        return self.next if self.count == self.capacity else 0

    def _slots(self, m: int) -> np.ndarray:
        """The slots of ``m`` sets put now (under the lock), the capacity grown first where
        they do not fit and it is below ``limit``."""
        if self.count + m > self.capacity and self.capacity < self.limit:
            # (the ring has not wrapped yet: its sets are in order in the first count slots)
            self.capacity = min(self.limit, max(2 * self.capacity, self.count + m))
            self._grow()
            self.next = self.count
        at = (self.next + np.arange(m)) % self.capacity
        self.next = int(at[-1] + 1) % self.capacity
        self.count = min(self.count + m, self.capacity)
        return at

    def _grow(self) -> None:
        """Storage for ``capacity`` sets, the first ``count`` kept."""
        raise NotImplementedError


class WarmStarts(_KeptSets):
    """The kept sets on the host: their varying values (rows, capacity) and converged
    excesses (capacity, ``columns``)."""

    def __init__(self, limit: int, rows: int, columns: int, switches: np.ndarray, always: bool):
        super().__init__(limit, rows, columns, switches, always)
        self.table = np.zeros((rows, 0))
        self.theta = np.zeros((0, columns))

    def _grow(self) -> None:
        table, theta = np.zeros((self.rows, self.capacity)), np.zeros((self.capacity, self.columns))
        table[:, : self.count] = self.table[:, : self.count]
        theta[: self.count] = self.theta[: self.count]
        self.table, self.theta = table, theta

    def starts(self, table: np.ndarray, varying=None) -> np.ndarray | None:
        """Start iterates (n, columns) of the sets ``table`` (rows, n): the excess of the
        nearest kept set within :data:`WARM_RADIUS` (in the largest of the values' distances,
        at the same heat input), zeros where there is none or the set does not iterate; None
        where no set has one. (``varying``: the table on the device, which
        :class:`DeviceWarmStarts` reads.)"""
        heated = self.iterating(table)
        with self.lock:  # a put in another thread writes the ring in place
            if not heated.size or not self.count:
                return None
            kept_table = self.table[:, : self.count]
            new = table[:, heated]
            # only the rows that differ between the sets are transformed (most of a fit's
            # varying rows hold one value in every set): a row alike everywhere adds
            # nothing to a distance
            differ = np.minimum(kept_table.min(axis=1), new.min(axis=1)) < np.maximum(
                kept_table.max(axis=1), new.max(axis=1)
            )
            order = (np.arange(self.count) + self._oldest()) % self.count
            both = np.concatenate([kept_table[np.ix_(differ, order)], new[differ]], axis=1)
            positive = np.all(both > 0.0, axis=1)
            scale = np.max(np.abs(both), axis=1)
            u = np.where(
                positive[:, None],
                np.log(np.where(positive[:, None], both, 1.0)),
                both / np.where(scale > 0, scale, 1.0)[:, None],
            )
            u = np.ascontiguousarray(u.T)  # (kept + heated, rows that differ)
            kept = self.count
            if u.shape[1] == 0:  # every set alike: any kept one is the set itself
                nearest = np.zeros(heated.size, dtype=int)
            else:
                distance, nearest = cKDTree(u[:kept]).query(u[kept:], p=np.inf, distance_upper_bound=WARM_RADIUS)
                nearest[~np.isfinite(distance)] = kept
            near = nearest < kept
            if not near.any():
                return None
            start = np.zeros((table.shape[1], self.columns))
            start[heated[near]] = self.theta[order[nearest[near]]]
            return start

    def put(self, table: np.ndarray, varying, theta) -> None:
        """Keep the sets of ``table`` (rows, n) that iterate with their converged excesses
        ``theta`` (n, columns; a host array, or a Warp array copied here), the oldest kept
        ones given up beyond ``limit``."""
        heated = self.iterating(table)[-self.limit :]
        if not heated.size:
            return
        theta = theta.numpy() if isinstance(theta, wp.array) else theta
        with self.lock:
            at = self._slots(heated.size)
            self.table[:, at] = table[:, heated]
            self.theta[at] = theta[heated]


class DeviceWarmStarts(_KeptSets):
    """The kept sets on ``device``: their varying values (capacity, rows) and converged
    excesses (capacity, ``columns``), searched there (:mod:`tawarp.kernels.warm`) by
    :class:`WarmStarts`'s rule; of equally near kept sets the oldest starts a set."""

    def __init__(self, limit: int, rows: int, columns: int, switches: np.ndarray, always: bool, device):
        super().__init__(limit, rows, columns, switches, always)
        self.device = device
        self.kept = wp.zeros((0, rows), dtype=wp.float64, device=device)
        self.kept_theta = wp.zeros((0, columns), dtype=wp.float64, device=device)

    def _grow(self) -> None:
        kept = wp.zeros((self.capacity, self.rows), dtype=wp.float64, device=self.device)
        kept_theta = wp.zeros((self.capacity, self.columns), dtype=wp.float64, device=self.device)
        if self.count:
            wp.copy(kept, self.kept, count=self.count * self.rows)
            wp.copy(kept_theta, self.kept_theta, count=self.count * self.columns)
        self.kept, self.kept_theta = kept, kept_theta

    def starts(self, table: np.ndarray, varying: wp.array) -> wp.array | None:
        """:meth:`WarmStarts.starts` as a Warp array on the device (n, columns), of the sets
        ``table`` (rows, n) whose copy on the device is ``varying``."""
        heated = self.iterating(table)
        with self.lock:
            if not heated.size or not self.count:
                return None
            dev, count, rows = self.device, self.count, self.rows
            on_device = wp.array(heated.astype(np.int32), dtype=wp.int32, device=dev)
            # the search's steps a thread per part of the sets (kernels/warm.py, PARTS)
            lo, hi, big = (wp.empty((rows, kw.PARTS), dtype=wp.float64, device=dev) for _ in range(3))
            flags = wp.empty((rows, kw.PARTS), dtype=wp.int32, device=dev)
            wp.launch(
                kw.row_spread_parts,
                dim=(rows, kw.PARTS),
                inputs=[self.kept, count, varying, on_device, lo, hi, big, flags],
                device=dev,
            )
            differ = wp.empty(rows, dtype=wp.int32, device=dev)
            positive = wp.empty(rows, dtype=wp.int32, device=dev)
            scale = wp.empty(rows, dtype=wp.float64, device=dev)
            wp.launch(kw.row_spread, dim=rows, inputs=[lo, hi, big, flags, differ, positive, scale], device=dev)
            which = wp.empty(rows, dtype=wp.int32, device=dev)
            n_rows = wp.empty(1, dtype=wp.int32, device=dev)
            wp.launch(kw.differing_rows, dim=1, inputs=[differ, which, n_rows], device=dev)
            u = wp.empty((count + heated.size, rows), dtype=wp.float64, device=dev)
            wp.launch(
                kw.scaled_values,
                dim=(count + heated.size, rows),
                inputs=[self.kept, count, varying, on_device, which, n_rows, positive, scale, u],
                device=dev,
            )
            oldest = self._oldest()
            best = wp.empty((heated.size, kw.PARTS), dtype=wp.float64, device=dev)
            at = wp.empty((heated.size, kw.PARTS), dtype=wp.int32, device=dev)
            wp.launch(
                kw.nearest_parts, dim=(heated.size, kw.PARTS), inputs=[u, n_rows, count, oldest, best, at], device=dev
            )
            start = wp.zeros((table.shape[1], self.columns), dtype=wp.float64, device=dev)
            wp.launch(
                kw.nearest_start,
                dim=heated.size,
                inputs=[best, at, count, oldest, WARM_RADIUS, on_device, self.kept_theta, start],
                device=dev,
            )
            return start

    def put(self, table: np.ndarray, varying: wp.array, theta: wp.array) -> None:
        """:meth:`WarmStarts.put` of the sets ``table`` (rows, n), ``varying`` its copy on
        the device, and their excesses ``theta`` (n, columns) on the device."""
        heated = self.iterating(table)[-self.limit :]
        if not heated.size:
            return
        with self.lock:
            at = self._slots(heated.size)
            wp.launch(
                kw.keep_sets,
                dim=heated.size,
                inputs=[
                    varying,
                    theta,
                    wp.array(heated.astype(np.int32), dtype=wp.int32, device=self.device),
                    wp.array(at.astype(np.int32), dtype=wp.int32, device=self.device),
                    self.kept,
                    self.kept_theta,
                ],
                device=self.device,
            )
