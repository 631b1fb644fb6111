"""Fits of any measurement kind on the one LM (:func:`tawarp.fit.lm.levenberg_marquardt`).

A fit is ``(params, effect, x0)``: the :class:`tawarp.model.effects.Param` list it frees
(scaled variables ``x = ln(v/start)`` for log fields, ``(v - start)/scale`` otherwise:
a unit step is a relative change of order one, or one ``scale`` of
:mod:`tawarp.model.fields`), the effect whose structure it needs (None: the kind's core)
and the start x0. :func:`fit_batch` runs several fits of one kind in lockstep
(:class:`KindProblems`: every iteration is one :meth:`MeasurementKind.predict` call per
structure for every active fit's trial point, and one for the forward-difference
neighbours of the trials that lower their fit's cost).
Residuals: ``w (Y_model - y)`` (re, im) on the fitted rows, w the kind's weights.
:func:`fit_kind` is the estimator's entry point for a kind (``tawarp fit``): parameter
names, bounds and scaling from :mod:`tawarp.model.fields`.

The T-matrix estimator (:func:`tawarp.fit.estimate.fit`) reduces its residuals on the
device instead (many problems, long frequency grids); both describe their problem by a
:class:`tawarp.fit.problem_model.ProblemModel` (scaling, priors, the one covariance: the
posterior one, s^2 = 1 with the kind's sigma, else the reduced chi^2) and return
:class:`FitResult`.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

import warp as wp

from ..kernels import lm_step
from ..kernels import misfit as kmisfit
from . import lockstep
from ..measure.kind import MeasurementKind
from ..model.effects import Effect, Param, base_params
from ..model.fields import field as field_of
from ..model.value_table import ValueTable, row_of, rows_in
from .lm import DROPPED, MERGED, levenberg_marquardt
from .problem_model import Covariance, ProblemModel, covariances
from .result import FitResult

#: Forward-difference step in the scaled variables x.
FD_STEP = 1e-6
#: The largest array a batch's misfits and parameter values are formed in at once: loops run
#: together give a batch thousands of fits, and arrays of all of them stream from memory
#: where blocks of this size stay in the caches (a study runs a process a core, which share
#: the memory's bandwidth).
BLOCK_BYTES = 1 << 22
#: Stopping rule of the kind fits: an accepted step below XTOL in x, or the gradient
#: cosine max |g_a| / sqrt(H_aa F) below GTOL. Tight: the loop compares the fits' costs
#: (F-test, BIC), so they must sit at the minimum; GTOL is about what forward differences
#: with step 1e-6 resolve (below it the fits only stall, spending launches).
XTOL = 1e-10
GTOL = 1e-6


def param_values(params: list[Param], X: np.ndarray, fixed: dict) -> dict:
    """Model parameter values {name: (n,)} of parameter sets X (n, p) of ``params``."""
    n = X.shape[0]
    out = {k: np.full(n, v) for k, v in fixed.items()}
    for j, par in enumerate(params):
        par.assign(par.value(X[:, j]), out)
    return out


def residual(kind: MeasurementKind, Y: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Weighted real residuals (..., 2 len(rows)): re parts, then im parts."""
    return weighted(Y[..., rows] - kind.y[rows], kind.w[rows])


def weighted(d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Real residuals (..., 2 n) of complex misfits ``d`` (..., n) with weights ``w`` (n, 2)
    of their re and im parts: re parts, then im parts."""
    return weighted_parts(d, w[:, 0], w[:, 1])


def weighted_parts(d: np.ndarray, w_re: np.ndarray, w_im: np.ndarray) -> np.ndarray:
    """:func:`weighted` with the weights of the re and im parts apart, each broadcast
    against ``d`` (..., n)."""
    n = d.shape[-1]
    out = np.empty(d.shape[:-1] + (2 * n,))
    np.multiply(d.real, w_re, out=out[..., :n])
    np.multiply(d.imag, w_im, out=out[..., n:])
    return out


class KindProblems:
    """The fits ``specs`` = [(params, effect, x0), ...] of one kind as one batch of
    :class:`tawarp.fit.lm.LMProblems`; a spec may carry its own rows as a fourth item
    ((params, effect, x0, rows): held-out and resampled refits in the same batch; rows may
    repeat, a bootstrap's weights), the others fit ``rows``. A fit that sees some rows alone
    asks a kind with :attr:`MeasurementKind.predicts_rows` for those (its model values at
    the others may then be NaN: a core's Q = 0 rows alone cost no heated T-matrices).

    z is x padded with zeros to the largest p of the batch, the padding pinned by the bounds
    ``zlo = zhi = 0`` (zero Jacobian columns: it never moves and adds nothing to the step
    and gradient tests). :meth:`evaluate` forms the trial points and the forward-difference
    neighbours (step ``FD_STEP`` in x, towards the interior at an upper bound) of the fits
    asked for, each in one :meth:`MeasurementKind.predict` call per structure: fits whose
    effects change no structure share one launch (the union of their parameters, each
    fit's others at their start values), a structural effect has its own.

    :meth:`merged` batches the fits of several kinds (:class:`FitCall`), each on its own
    data: the kinds of one family (:class:`Families`) share their launches too, each
    structure's sets in one parameter table (:meth:`_group`).
    """

    def __init__(
        self,
        kind: MeasurementKind,
        specs: list,
        fixed: dict | None = None,
        rows: np.ndarray | None = None,
        priors: list | None = None,
    ):
        self._setup([(kind, specs, fixed, rows, priors)], None)

    @classmethod
    def merged(cls, calls: list["FitCall"], families: "Families | None" = None) -> "KindProblems":
        """The fits of every call of ``calls`` as one batch, the calls' fits in their order;
        ``families``: the kinds that predict together (default: each kind alone)."""
        out = cls.__new__(cls)
        out._setup([(c.kind, c.specs, c.fixed, c.rows, c.priors) for c in calls], families)
        return out

    def _setup(self, parts: list[tuple], families: "Families | None"):
        """``parts`` = [(kind, specs, fixed, rows, priors), ...]: the fits of each kind."""
        self.kind = parts[0][0]
        #: :func:`levenberg_marquardt` passes :meth:`evaluate` the costs the trials must beat,
        #: unless a trial's neighbours share its launch's columns
        #: (:attr:`MeasurementKind.neighbours_share_columns`: apart they would cost more) or
        #: the kind predicts on a GPU (:meth:`MeasurementKind.predicts_on_gpu`), where a
        #: launch costs its latency and host work whatever its sets, and a second launch per
        #: iteration more than the neighbours of the trials it would leave out
        self.jacobian_if_below = not (self.kind.neighbours_share_columns or self.kind.predicts_on_gpu())
        families = families or Families([kind for kind, *_ in parts])
        self.kinds, self.specs, self.rows, self.part = [], [], [], []
        all_priors: list = []
        for j, (kind, specs, _, rows, priors) in enumerate(parts):
            rows = np.arange(kind.y.size) if rows is None else np.asarray(rows)
            self.kinds += [kind] * len(specs)
            self.part += [j] * len(specs)
            #: the rows each fit sees
            self.rows += [rows if len(sp) < 4 or sp[3] is None else np.asarray(sp[3]) for sp in specs]
            self.specs += [tuple(sp[:3]) for sp in specs]
            priors = list(priors or [])
            all_priors += [priors[c] if c < len(priors) else None for c in range(len(specs))]
        #: per fit, the rows its predictions need where the kind leaves out the others'
        #: work (:attr:`MeasurementKind.predicts_rows`) and the fit sees some rows alone
        self.needed, self.every_row = [], []
        seen: dict = {}  # (kind, rows array) -> (needed, every row): most fits share both
        for k, r in zip(self.kinds, self.rows):
            key = (id(k), id(r))
            if key not in seen:
                every = r.size == k.y.size and np.array_equal(r, np.arange(k.y.size))
                seen[key] = (None if every or not k.predicts_rows or np.unique(r).size == k.y.size else r, every)
            self.needed.append(seen[key][0])
            #: per fit, whether it sees every row once, in order (its misfits need no gather)
            self.every_row.append(seen[key][1])
        #: the kinds' families: their sets share launches (:func:`predict_sets`)
        self.families = families
        #: per fit, the fits whose residuals are formed together: those that see every row of
        #: data of one size (several kinds' data stacked, :attr:`data_y`), else those that share
        #: their kind and rows
        self.data_y: dict = {}  # data size -> (the kinds' y (kinds, size), their w (kinds, 2, size))
        self.data_of = np.zeros(len(self.kinds), dtype=np.int64)  # per fit, its kind's row there
        stacked: dict = {}
        alike: dict = {}
        self.alike_key = []
        for c, (k, r) in enumerate(zip(self.kinds, self.rows)):
            if self.every_row[c]:
                kinds = stacked.setdefault(k.y.size, {})
                self.data_of[c] = kinds.setdefault(id(k), (len(kinds), k))[0]
                key = ("every row", k.y.size)
            else:
                key = (id(k), r.tobytes()) if len(parts) > 1 else id(r)
            self.alike_key.append(alike.setdefault(key, len(alike)))
        for size, kinds in stacked.items():
            ks = [k for _, k in kinds.values()]
            self.data_y[size] = (np.stack([k.y for k in ks]), np.stack([k.w.T for k in ks]))
        self._group(parts, families)
        #: each fit's problem model: scaling, fit range, priors, noise (s^2 = 1 with sigma)
        self.models = [
            ProblemModel.from_params(params, pri, not kind.has_sigma)
            for (params, _, _), pri, kind in zip(self.specs, all_priors, self.kinds)
        ]
        #: free parameters per fit; z is padded to the largest
        self.p = np.array([m.p for m in self.models], dtype=int)
        P = int(self.p.max(initial=0))
        self.zlo, self.zhi = np.zeros((len(self.specs), P)), np.zeros((len(self.specs), P))
        #: Gaussian priors in x per fit, padded like z: mean and 1/sd (0 where a fit has none)
        self.prior_mu, self.prior_isd = np.zeros_like(self.zlo), np.zeros_like(self.zlo)
        for c, m in enumerate(self.models):
            self.zlo[c, : m.p], self.zhi[c, : m.p] = m.bounds_x()
            if m.prior_mu is not None:
                self.prior_mu[c, : m.p], self.prior_isd[c, : m.p] = m.prior_mu, 1.0 / m.prior_sd
        #: per slot of the last :meth:`evaluate`: (J (2 len(rows), p_c) in x, model values (y.size,))
        self.last: list = []
        #: per fit, its evaluation of lowest cost so far on the host: (cost, padded z, J, model
        #: values); the LM accepts a trial only where it lowers the cost, so this is the one at
        #: its solution (fits reduced on the device keep none: :meth:`at_solutions` evaluates them)
        self.best: dict = {}
        #: the kinds predict on a GPU and reduce there (:attr:`MeasurementKind.reduces_on_device`):
        #: :meth:`evaluate` forms the fits' normal equations where the model values are
        self.on_device = all(k.reduces_on_device and k.predicts_on_gpu() for k in self.kinds)
        self._on_device: dict = {}  # per device, :meth:`_device_data`

    def _group(self, parts: list[tuple], families: "Families"):
        """The fits' launch groups: the fits of one family of kinds (:class:`Families`) and
        one structure predict as one :class:`Sets` (loops run together: one table for all
        their cores, where one a loop cost the host a table's overhead each). A set's values
        where its fit does not set them: its part's (its call's ``fixed`` and the start
        values of the parameters of the part's fits of that structure), else its kind's core
        value or the field's neutral value (:func:`_absent`). A part with a name that has
        neither keeps a group of its own, as :func:`run_sets` predicts it alone."""
        own: dict = {}  # (part, structure) -> {name: value}
        of_fit = []
        for c, (params, effect, _) in enumerate(self.specs):
            key = (self.part[c], effect.name if effect is not None and effect.transform else None)
            v = own.get(key)
            if v is None:
                v = own[key] = dict(parts[key[0]][2] or {})
            for par in params:
                par.assign(par.start, v)
            of_fit.append(key)
        place = {k: i for i, k in enumerate(own)}  # (part, structure) -> its place in _own
        #: per (part, structure), in order: its own names, and its kind's family
        self._own = [(frozenset(v), families.of(parts[k[0]][0])) for k, v in own.items()]
        #: per fit, its (part, structure)'s place in _own
        self._own_of = np.array([place[k] for k in of_fit], dtype=np.int64)
        by_family: dict = {}
        for k, i in place.items():
            fam = self._own[i][1]
            by_family.setdefault((id(fam), k[1]), (fam, []))[1].append(k)
        launch_of: dict = {}  # (part, structure) -> its launch group's key
        #: per launch group: its names and the values of each (part, structure) in it, by its place
        self._bases: dict = {}
        for (fam_id, structure), (fam, keys) in by_family.items():
            names = tuple(dict.fromkeys([n for k in keys for n in own[k]] + list(fam.differ)))
            rows = {}
            for k in keys:
                missing = frozenset(names).difference(own[k])
                core = getattr(parts[k[0]][0], "core", None)
                rest = {} if not missing else None if core is None else _absent_values(core, missing)
                if rest is None:  # a name this part's core cannot fill: a launch of its own
                    launch_of[k] = k
                    self._bases[k] = (tuple(own[k]), {place[k]: np.array(list(own[k].values()), dtype=float)})
                    continue
                rows[place[k]] = np.array([own[k][n] if n in own[k] else rest[n] for n in names], dtype=float)
                launch_of[k] = (fam_id, structure)
            if rows:
                self._bases[(fam_id, structure)] = (names, rows)
        self.groups: dict = {}
        #: per fit, its launch group's key
        self.group_of = []
        for c, key in enumerate(of_fit):
            self.groups.setdefault(launch_of[key], []).append(c)
            self.group_of.append(launch_of[key])
        self._layouts: dict = {}  # per group, its ValueLayout (_layout)

    def start(self) -> np.ndarray:
        """The specs' x0, padded (K, P)."""
        z = np.zeros_like(self.zlo)
        for c, (_, _, x0) in enumerate(self.specs):
            z[c, : self.p[c]] = np.asarray(x0, dtype=float)
        return z

    def change_rule(self):
        """|dz| against ``xtol``: the scaled variables already measure relative change
        (:class:`Param`)."""
        P = self.zlo.shape[1]
        return np.full(P, lm_step.CHANGE_ABSOLUTE, dtype=np.int32), np.ones_like(self.zlo), np.zeros_like(self.zlo)

    def _layout(self, key) -> "ValueLayout":
        """The :class:`ValueLayout` of group ``key`` (made once)."""
        lay = self._layouts.get(key)
        if lay is None:
            members = self.groups[key]
            names, rows = self._bases[key]
            base = np.stack([rows[i] for i in self._own_of[members].tolist()]) if members else np.zeros((0, len(names)))
            lay = self._layouts[key] = ValueLayout(names, base, members, [self.specs[c][0] for c in members])
        return lay

    def _launch_names(self, names: tuple[str, ...], fits: np.ndarray) -> tuple[str, ...]:
        """The names of a group's table (``names``) that a launch of the requests of
        ``fits`` carries: those of the parts (calls) asked for, and the fields their
        family's cores differ in where several parts share it or their kind is not the
        family's (as :func:`run_sets` merges jobs): the names a launch carries choose its
        engine (:func:`tawarp.measure.kind.get_engine`, whose heat solve iterates only
        where a temperature-dependent field is among them), so a launch carries the same
        names whichever other parts' fits share its table."""
        here = np.unique(self._own_of[fits]).tolist()
        want = set().union(*(self._own[k][0] for k in here))
        fam = self._own[here[0]][1]
        if len(here) > 1 or self.kinds[int(fits[0])] is not fam.kind:
            want.update(fam.differ)
        return tuple(n for n in names if n in want)

    def predict(self, requests: list) -> list:
        """[(c, X (n, p_c)), ...] -> [model values (n, rows)], one launch per structure
        and family of kinds (:func:`predict_sets`)."""
        return self._predict_arrays(*_stacked(requests))

    def _predict_arrays(self, fits: np.ndarray, sizes: np.ndarray, X: np.ndarray, neighbours=None) -> list:
        """:meth:`predict` of the requests of :meth:`_jobs`."""
        jobs, assemble = self._prediction(fits, sizes, X, neighbours=neighbours)
        return assemble(predict_sets(jobs, self.families))

    def prediction(self, requests: list, on_device: bool = False) -> tuple[list["Sets"], Callable[[list], list]]:
        """:meth:`predict` in two halves: the sets to predict (a caller may predict them
        with others', :func:`predict_sets`), and the function that takes their model values
        to ``requests``' results (``on_device``: :class:`tawarp.measure.kind.DeviceValues`)."""
        return self._prediction(*_stacked(requests), on_device)

    def _prediction(
        self, fits: np.ndarray, sizes: np.ndarray, X: np.ndarray, on_device: bool = False, neighbours=None
    ) -> tuple:
        """:meth:`prediction` of the requests of :meth:`_jobs`."""
        jobs, members, at = self._jobs(fits, sizes, X, on_device, neighbours)

        def assemble(got: list) -> list:
            out = [None] * fits.size
            for todo, Y in zip(members, got):
                for i in todo.tolist():
                    out[i] = Y[at[i] : at[i] + sizes[i]]
            return out

        return jobs, assemble

    def _jobs(self, fits: np.ndarray, sizes: np.ndarray, X: np.ndarray, on_device: bool, neighbours=None) -> tuple:
        """(jobs, members, at) of the requests of fits ``fits`` (r,), ``sizes`` (r,) sets
        each, their sets' x the rows of ``X`` (sizes.sum(), P) in order (zeros past a fit's
        p): one :class:`Sets` per group (:attr:`group_of`), in the order of the groups'
        first requests, each with its requests' sets in their order; ``members`` per job
        its requests (indices into ``fits``), ``at`` (r,) where each request's sets start
        in its job's. ``neighbours``: (z, step) where X is :meth:`_with_neighbours`' of them,
        each fit's point and its neighbours (a group's values then from its points',
        :meth:`ValueLayout.neighbour_table`)."""
        first = np.concatenate([[0], np.cumsum(sizes)])
        by_group: dict = {}
        for i, c in enumerate(fits.tolist()):
            by_group.setdefault(self.group_of[c], []).append(i)
        jobs, members = [], []
        at = np.empty(fits.size, dtype=np.int64)
        for key, todo in by_group.items():
            todo = np.array(todo, dtype=np.int64)
            n = sizes[todo]
            at[todo] = np.cumsum(n) - n
            # each set's row of X: its request's first set plus its place in the request
            rows_of = np.repeat(first[todo] - at[todo], n) + np.arange(int(n.sum()))
            set_fits = np.repeat(fits[todo], n)
            c0 = int(fits[todo[0]])
            needed = [self.needed[c] for c in fits[todo].tolist()]
            rows = None
            if any(r is not None for r in needed):
                rows = [r for k, r in zip(n.tolist(), needed) for _ in range(k)]
            effect = self.specs[c0][1] if key[1] is not None else None
            layout = self._layout(key)
            names = self._launch_names(layout.names, fits[todo])
            if neighbours is not None and not layout.expanding:
                z, step = neighbours
                table = layout.neighbour_table(fits[todo], z[todo], step[todo], self.p[fits[todo]], names)
            else:
                table = layout.table(set_fits, X[rows_of], names)
            jobs.append(Sets(self.kinds[c0], table, int(n.sum()), effect, rows, on_device))
            members.append(todo)
        return jobs, members, at

    def evaluate(self, pid, z, max_sets: int = 0, below=None, host: bool = False):
        """(cost, raw, g, H) of fits ``pid`` at padded z (n, P): cost = r^T r of the
        weighted residuals, raw the unweighted sum |Y - y|^2 over the rows, g = J^T r,
        H = J^T J with the forward-difference J (``max_sets`` is not used: the batches
        are small). A fit with a prior adds its rows ``(z - mu) / sd`` to r (and 1/sd to J):
        the LM then finds the maximum a posteriori. ``below`` (n,): the cost each fit's
        point must beat to be taken (the LM's trials); where it does not, its
        forward-difference neighbours are not evaluated and g, H are NaN (the LM rejects
        such a trial whatever its Jacobian, so the steps are the same): the points first,
        in one launch per structure, then the neighbours of those that beat it (the same
        numbers as in one launch where the kind predicts each parameter set alike in any
        batch, as the forward kernels do: one thread per set).

        Where the kinds predict and reduce on a GPU (:attr:`on_device`), without ``below``
        (a GPU's fits evaluate a trial with its neighbours), the misfits and normal
        equations are formed where the launches left the model values
        (:meth:`_reduced_on_device`): only cost, raw, g and H come to the host, and
        :meth:`at_solutions` evaluates each fit at its solution again for its J and model
        values. ``host``: the host's path whatever the device (the CPU's numbers)."""
        n, P = z.shape
        step = np.where(z + FD_STEP > self.zhi[pid], -FD_STEP, FD_STEP)
        d, isd = (z - self.prior_mu[pid]) * self.prior_isd[pid], self.prior_isd[pid]
        prior_cost = np.sum(d**2, axis=1)
        if self.on_device and below is None and not host:
            cost, raw, g, H = self._reduced_on_device(pid, z, step)
            self.last = []  # no J or model values on the host: nothing for best
        else:
            cost, raw, g, H = self._reduced_on_host(pid, z, step, below, prior_cost)
        cost += prior_cost
        g += d * isd
        H += isd[:, :, None] ** 2 * np.eye(P)[None]
        bad = ~(np.isfinite(cost) & np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(H), axis=(1, 2)))
        cost[bad] = np.inf
        for i, c in enumerate(pid if self.last else ()):
            if c not in self.best or cost[i] < self.best[c][0]:
                # copies: a view would keep its whole block (and launch) alive
                J, Y = self.last[i]
                self.best[c] = (cost[i], z[i].copy(), None if J is None else J.copy(), Y.copy())
        return cost, raw, g, H

    def _with_neighbours(self, pid, z, step, point: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(sizes, X): the sets of fits ``pid`` at z with their forward-difference
        neighbours ``z + step_a e_a``, as :meth:`_jobs` takes them: each fit's point first
        (``point`` False: the neighbours alone), ``sizes`` (len(pid),) 1 + p_c (p_c)."""
        sizes = self.p[pid] + (1 if point else 0)
        slot = np.repeat(np.arange(len(pid)), sizes)
        # each set's place in its fit's: 0 the point, a + 1 the neighbour along a
        place = np.arange(slot.size) - np.repeat(np.cumsum(sizes) - sizes, sizes) + (0 if point else 1)
        X = z[slot]
        nb = np.flatnonzero(place)
        X[nb, place[nb] - 1] += step[slot[nb], place[nb] - 1]
        return sizes, X

    def _reduced_on_device(self, pid, z, step) -> tuple:
        """(cost, raw, g, H) of :meth:`evaluate` without the priors' terms, of fits ``pid``
        at z with their neighbours, reduced where the launches left the model values
        (:mod:`tawarp.kernels.misfit`: the misfits a launch per launch of model values,
        their sums one for all) and copied to the host in one array."""
        n, P = z.shape
        if n == 0:
            return np.empty(0), np.empty(0), np.empty((0, P)), np.empty((0, P, P))
        sizes, X = self._with_neighbours(pid, z, step)
        jobs, members, at = self._jobs(pid, sizes, X, on_device=True, neighbours=(z, step))
        launched = predict_sets(jobs, self.families)
        device = launched[0].values.device
        data_y, data_w, rows, data_index, row_start, row_count = self._device_data(device)
        # the launches' fits share these arrays, each in its slot
        n_rows = int(row_count[pid].max())
        # zeros: the kernels leave g's and H's padding (past a fit's p) as the host path does
        out = wp.zeros((n, 2 + P + P * P), dtype=wp.float64, device=device)
        r = wp.empty((n, P + 1, 2 * n_rows), dtype=wp.float64, device=device)
        raw = wp.empty((n, n_rows), dtype=wp.float64, device=device)
        partial = wp.empty((n, P + 1, P + 1, kmisfit.CHUNKS), dtype=wp.float64, device=device)
        partial_raw = wp.empty((n, kmisfit.CHUNKS), dtype=wp.float64, device=device)
        # each fit's (first set, p, data, row start, row count, slot) for the kernels
        first = np.empty(n, dtype=np.int64)
        by_launch: dict = {}
        for todo, values in zip(members, launched):
            first[todo] = values.start + at[todo]
            by_launch.setdefault(id(values.values), (values, []))[1].append(todo)
        table = np.stack([first, self.p[pid], data_index[pid], row_start[pid], row_count[pid], np.arange(n)], axis=1)
        table = table.astype(np.int32)
        for v, parts in by_launch.values():
            slots = np.sort(np.concatenate(parts))
            wp.launch(
                kmisfit.weighted_misfits,
                dim=(len(slots), P + 1, int(row_count[pid[slots]].max())),
                inputs=[v.table(), wp.array(table[slots], device=device), data_y, data_w, rows],
                outputs=[r, raw],
                device=device,
            )
        # the sums of every launch's fits at once
        fits = wp.array(table, device=device)
        wp.launch(
            kmisfit.partial_products,
            dim=(n, P + 1, P + 1, kmisfit.CHUNKS),
            inputs=[fits, wp.array(step, device=device), r, raw],
            outputs=[partial, partial_raw],
            device=device,
        )
        wp.launch(
            kmisfit.normal_equations,
            dim=(n, P + 1, P + 1),
            inputs=[fits, partial, partial_raw],
            outputs=[out],
            device=device,
        )
        res = out.numpy()
        g = res[:, 2 : 2 + P]
        H = res[:, 2 + P :].reshape(n, P, P)
        # a fit without parameters has none (NaN) in a batch with some, as there
        none = self.p[pid] == 0
        g[none], H[none] = np.nan, np.nan
        return res[:, 0], res[:, 1], g, H

    def _device_data(self, device) -> tuple:
        """(data y, data w, rows, data index, row start, row count), made once: on
        ``device`` every kind's y and w (kinds, size, re / im) and the rows each fit sees,
        one array per distinct rows array; on the host, per fit, its kind's index there and
        where its rows start and how many."""
        got = self._on_device.get(str(device))
        if got is not None:
            return got
        kinds: dict = {}
        for k in self.kinds:
            kinds.setdefault(id(k), (len(kinds), k))
        size = max(k.y.size for _, k in kinds.values())
        y, w = np.zeros((len(kinds), size, 2)), np.zeros((len(kinds), size, 2))
        for j, k in kinds.values():
            y[j, : k.y.size, 0], y[j, : k.y.size, 1] = k.y.real, k.y.imag
            w[j, : k.y.size] = k.w
        data_index = np.array([kinds[id(k)][0] for k in self.kinds], dtype=np.int32)
        at: dict = {}
        chunks, start, count = [], np.zeros(len(self.rows), dtype=np.int32), np.zeros(len(self.rows), dtype=np.int32)
        total = 0
        for c, r in enumerate(self.rows):
            if id(r) not in at:
                at[id(r)] = total
                chunks.append(r)
                total += r.size
            start[c], count[c] = at[id(r)], r.size
        rows = np.concatenate(chunks).astype(np.int32)
        got = self._on_device[str(device)] = (
            wp.array(y, device=device),
            wp.array(w, device=device),
            wp.array(rows, device=device),
            data_index,
            start,
            count,
        )
        return got

    def _reduced_on_host(self, pid, z, step, below, prior_cost) -> tuple:
        """(cost, raw, g, H) of :meth:`evaluate` without the priors' terms, from the model
        values on the host; :attr:`last` each slot's (J, model values)."""
        n, P = z.shape
        # each fit's model values (1 + p or 1, rows) in parts: the point's, then its neighbours'
        if below is None:
            sets = self._with_neighbours(pid, z, step)
            parts = [(Y,) for Y in self._predict_arrays(pid, *sets, (z, step))]
        else:
            points = self._predict_arrays(pid, np.ones(n, dtype=np.int64), z)
            with np.errstate(over="ignore", invalid="ignore"):  # the same sums as the cost below
                point_cost = [
                    r @ r for r in (residual(self.kinds[c], points[i], self.rows[c])[0] for i, c in enumerate(pid))
                ]
            point_cost = np.array(point_cost) + prior_cost
            taken = [i for i in range(n) if point_cost[i] < below[i]]
            parts = [(Y,) for Y in points]
            neighbours = self._with_neighbours(pid[taken], z[taken], step[taken], point=False)
            for i, Yn in zip(taken, self._predict_arrays(pid[taken], *neighbours)):
                parts[i] = (points[i], Yn)
        sizes = [sum(part.shape[0] for part in fit) for fit in parts]
        cost, raw = np.empty(n), np.empty(n)
        g, H = np.full((n, P), np.nan), np.full((n, P, P), np.nan)
        self.last = [None] * n
        # the fits that see the same rows with as many evaluations share their array work,
        # in blocks of at most BLOCK_BYTES of misfits (loops run together: thousands of fits)
        alike: dict = {}
        for i, c in enumerate(pid):
            alike.setdefault((self.alike_key[c], sizes[i]), []).append(i)
        blocks = []
        for (_, m), members in alike.items():
            size = max(1, BLOCK_BYTES // (16 * m * parts[members[0]][0].shape[-1]))
            blocks += [(m, members[a : a + size]) for a in range(0, len(members), size)]
        for m, members in blocks:
            c0, k = pid[members[0]], m - 1
            rows = self.rows[c0]
            kind = self.kinds[c0]
            D = np.empty((len(members), m, parts[members[0]][0].shape[-1]), dtype=np.complex128)
            for j, i in enumerate(members):  # (fits, 1 + p or 1, y.size)
                a = 0
                for part in parts[i]:
                    D[j, a : a + part.shape[0]] = part
                    a += part.shape[0]
            with np.errstate(over="ignore", invalid="ignore"):  # a diverging trial: cost inf below
                # the misfits, the same numbers as residual()'s
                if self.every_row[c0]:
                    y, w = self.data_y[kind.y.size]
                    own = self.data_of[pid[members]]
                    if np.all(own == own[0]):  # one kind's data: broadcast, not gathered
                        own = own[0]
                    D -= y[own][..., None, :]
                    R = weighted_parts(D, w[own][..., None, 0, :], w[own][..., None, 1, :])
                    raw[members] = np.sum(np.abs(D[:, 0]) ** 2, axis=1)
                else:
                    D -= kind.y
                    R = weighted(D[..., rows], kind.w[rows])
                    raw[members] = np.sum(np.abs(D[:, 0, rows]) ** 2, axis=1)
                r = R[:, 0]
                cost[members] = np.einsum("ij,ij->i", r, r)
                J = None
                if k:  # (fits, p, rows)
                    J = R[:, 1:] - r[:, None]
                    J /= step[members, :k, None]
                    g[members], H[members] = 0.0, 0.0
                    g[members, :k] = np.einsum("ipj,ij->ip", J, r)
                    H[np.ix_(members, range(k), range(k))] = J @ np.swapaxes(J, 1, 2)
            for j, i in enumerate(members):
                self.last[i] = (J[j].T if k else None, parts[i][0][0])
        return cost, raw, g, H

    def at_solutions(self, z: np.ndarray, fits: np.ndarray | None = None) -> list:
        """(J, model values) of fits ``fits`` (default every one) at their solutions, z (K, P)
        every fit's: the evaluation there where the LM's iterations made it on the host
        (:attr:`best`, the same numbers), one more :meth:`evaluate` on the host for the
        others."""
        fits = np.arange(len(z)) if fits is None else np.asarray(fits, dtype=int)
        out = [
            self.best[c][2:] if c in self.best and np.array_equal(self.best[c][1], z[c]) else None
            for c in fits.tolist()
        ]
        stale = np.array([i for i, v in enumerate(out) if v is None], dtype=int)
        if stale.size:
            self.evaluate(fits[stale], z[fits[stale]], host=True)
            for j, i in enumerate(stale.tolist()):
                out[i] = self.last[j]
        return out


def _stacked(requests: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(fits, sizes, X) of requests [(c, X (n_c, p_c)), ...] as :meth:`KindProblems._jobs`
    takes them: each request's x rows in one array, zeros past its p_c."""
    sizes = np.array([X.shape[0] for _, X in requests], dtype=np.int64)
    X = np.zeros((int(sizes.sum()), max([1] + [X.shape[1] for _, X in requests])))
    k0 = 0
    for (_, x), n in zip(requests, sizes.tolist()):
        X[k0 : k0 + n, : x.shape[1]] = x
        k0 += n
    return np.array([c for c, _ in requests], dtype=np.int64), sizes, X


class ValueLayout:
    """How the parameter sets of a group of fits (one structure of one family of kinds) take
    their model parameter values: each fit's row of ``base`` (fits, names) where it does
    not set a name, else the value of the fit's parameter that sets it (the last, where
    several do), its ``start * exp(x)`` or ``start + scale x`` (:meth:`Param.value`), for
    every set of every fit in a few array operations: with hundreds of fits of a dozen
    parameters a launch, parameter by parameter in Python (:meth:`Param.assign`) cost the
    host more than the rest of the launch's bookkeeping. A parameter with its own
    ``expand`` (a frame's ties) is assigned as :meth:`Param.assign` does, after the others
    of its fit."""

    def __init__(self, names: tuple[str, ...], base: np.ndarray, fits: list[int], params: list[list[Param]]):
        self.names = tuple(names)
        column = {k: t for t, k in enumerate(self.names)}
        #: per fit (in the order of ``fits``), the values of the names it does not set
        self.base = np.asarray(base, dtype=float)
        #: each fit's row in this layout's tables, indexed by the fit (-1: not of the group)
        self.local = np.full(max(fits, default=-1) + 1, -1, dtype=np.int64)
        self.local[fits] = np.arange(len(fits))
        N, K = len(self.names), len(fits)
        #: per fit and name: the index of the parameter that sets it (-1: none), its start,
        #: scale and whether it is a log parameter
        self.slot = np.full((K, N), -1, dtype=np.int64)
        self.start, self.scale = np.zeros((K, N)), np.ones((K, N))
        self.log = np.zeros((K, N), dtype=bool)
        #: per fit, its parameters with their own expand, in order (index, Param)
        self.expanding: dict[int, list] = {}
        # (fit, name) -> (slot, start, scale, log), the last parameter that sets it kept,
        # then written in one assignment each (a fancy assignment per parameter cost a
        # batch of hundreds of fits more than the rest of its layout)
        sets: dict[tuple[int, int], tuple] = {}
        for i, ps in enumerate(params):
            for j, par in enumerate(ps):
                if par.expand is not None:
                    self.expanding.setdefault(fits[i], []).append((j, par))
                    continue
                for t in par.targets:
                    sets[i, column[t]] = (j, par.start, par.scale, par.log)
        if sets:
            at = tuple(np.array(list(sets)).T)
            slot, start, scale, log = zip(*sets.values())
            self.slot[at], self.start[at], self.scale[at], self.log[at] = slot, start, scale, log

    def table(self, fits: np.ndarray, X: np.ndarray, names: tuple[str, ...] | None = None) -> "ValueTable":
        """{name: (sets,)} of sets of the fits ``fits`` (sets,) at the x of the rows of
        ``X`` (sets, P) (a fit's x in its first p columns); ``names``: those of this
        layout's names alone (default all), each a name the fits' parameters may set."""
        names = self.names if names is None else names
        # each fit's rows, then the names' columns of them (a 2-D gather cost more)
        cols = slice(None) if names == self.names else rows_in(self.names, names)
        total = fits.size
        local = self.local[fits]
        v = np.empty((len(names), total))
        step = max(1, BLOCK_BYTES // (8 * max(len(names), 1)))  # sets a block
        for a in range(0, total, step):
            fit = local[a : a + step]
            slot = self.slot[fit][:, cols].T  # (names, sets)
            x = X[a + np.arange(fit.size)[None, :], np.maximum(slot, 0)]
            start, scale = self.start[fit][:, cols].T, self.scale[fit][:, cols].T
            with np.errstate(over="ignore", invalid="ignore"):
                block = np.where(self.log[fit][:, cols].T, start * np.exp(x), start + scale * x)
            v[:, a : a + step] = np.where(slot >= 0, block, self.base[fit][:, cols].T)
        out = ValueTable(names, v)
        for c in np.unique(fits).tolist() if self.expanding else ():
            sets = np.flatnonzero(fits == c)
            for j, par in self.expanding.get(c, ()):
                own: dict = {}
                par.assign(par.value(X[sets, j]), own)
                for k, w in own.items():
                    out[k][sets] = w
        return out

    def neighbour_table(self, fits: np.ndarray, z: np.ndarray, step: np.ndarray, p: np.ndarray, names=None):
        """:meth:`table` of the sets of :meth:`KindProblems._with_neighbours`: per fit of
        ``fits`` (n,) at ``z`` (n, P) with steps ``step`` (n, P) and ``p`` (n,) parameters,
        its point, then its neighbours ``z + step_a e_a``. A neighbour takes its point's
        values but for the names its parameter a sets, so only the points' table and those
        names are computed: a batch of 500 fits' 4100 sets 0.37 ms against 1.45 in full
        (the loop's refits on a GPU are batches of thousands of fits)."""
        names = self.names if names is None else names
        cols = slice(None) if names == self.names else rows_in(self.names, names)
        first = np.cumsum(p + 1) - (p + 1)  # each fit's point's set
        out = self.table(fits, z, names).array[:, np.repeat(np.arange(fits.size), p + 1)]
        local = self.local[fits]
        slot = self.slot[local][:, cols]  # (fits, names)
        i, t = np.nonzero(slot >= 0)
        a = slot[i, t]
        x = z[i, a] + step[i, a]  # the neighbour's x along a, as _with_neighbours forms it
        start, scale = self.start[local][:, cols][i, t], self.scale[local][:, cols][i, t]
        with np.errstate(over="ignore", invalid="ignore"):
            value = np.where(self.log[local][:, cols][i, t], start * np.exp(x), start + scale * x)
        out[t, first[i] + 1 + a] = value
        return ValueTable(names, out)


def kind_result(
    kind: MeasurementKind,
    params: list[Param],
    model: ProblemModel,
    x,
    J,
    Y,
    rows,
    effect,
    converged: bool,
    reason: str,
    iterations: int,
    r: np.ndarray,
    c: Covariance,
    evaluations: int = 0,
    seconds: float = 0.0,
) -> FitResult:
    """:class:`FitResult` (one problem) of a kind fit at x with Jacobian J (n, p) in x,
    model values Y, weighted residuals ``r`` there and covariance ``c`` (``model``'s,
    :func:`tawarp.fit.problem_model.covariances`: the posterior covariance, s^2 = 1 with the
    kind's sigma, else the reduced chi^2)."""
    cost = float(r @ r)
    n, p = r.size, len(params)
    dof = max(n - p, 1)
    values = np.array([float(par.value(x[j])) for j, par in enumerate(params)])
    one = lambda a, dt=float: np.array([a], dtype=dt)  # noqa: E731
    return FitResult(
        names=[par.label for par in params],
        values=values[None],
        std=c.std[None],
        covariance=c.cov[None],
        correlation=c.corr[None],
        condition=one(c.cond),
        iterations=one(iterations, int),
        converged=one(converged, bool),
        reason=one(reason, object).astype(str),
        cost=one(cost),
        rms_error=one(kind.error(Y, rows)),
        s2=one(c.s2),
        dof=dof,
        start=np.array([[par.start for par in params]]),
        problem_warnings=[[]],
        evaluations=evaluations,
        seconds=seconds,
        params=list(params),
        x=np.asarray(x, dtype=float)[None],
        residuals=r[None],
        jacobian=J[None],
        model=Y[None],
        effect=effect,
        n=n,
        weighted=kind.has_sigma,
        lower=np.array([par.lower for par in params]),
        upper=np.array([par.upper for par in params]),
        problem_model=model,
    )


@dataclass
class FitCall:
    """The arguments of one :func:`fit_batch` call (its specs with x0 filled in)."""

    kind: MeasurementKind
    specs: list
    fixed: dict | None = None
    rows: np.ndarray | None = None
    max_iter: int = 100
    xtol: float = XTOL
    gtol: float = GTOL
    priors: list | None = None
    drop: Callable | None = None
    decrement: float = 0.0
    starts: np.ndarray | None = None
    merge: float = 0.0

    def iteration(self) -> tuple:
        """What the LM's iteration takes from the call: calls alike in it share one LM (the
        decrement is each fit's own)."""
        return self.max_iter, self.xtol, self.gtol


def fit_batch(
    kind: MeasurementKind,
    specs: list,
    fixed: dict | None = None,
    rows: np.ndarray | None = None,
    max_iter: int = 100,
    xtol: float = XTOL,
    gtol: float = GTOL,
    priors: list | None = None,
    drop=None,
    decrement: float = 0.0,
    starts: np.ndarray | None = None,
    merge: float = 0.0,
) -> list[FitResult | None]:
    """Several fits of ``kind`` in lockstep, ``specs`` = [(params, effect, x0), ...] (x0
    None: every parameter at its start; an optional fourth item: that fit's own rows), the
    others at ``fixed`` {name: value} or the core's values, on ``rows`` (default all): :func:`levenberg_marquardt` (Nielsen's
    damping ``mu I``, steps projected onto the bounds) on :class:`KindProblems`; the
    Jacobians and model values at the solutions are those the iterations evaluated there
    (:meth:`KindProblems.at_solutions`). ``priors``: per
    spec None or (mu, sd) (p,) each, a Gaussian prior in the scaled variables x: the fit is
    then the maximum a posteriori (the result's cost and residuals stay the data's).
    ``drop``, ``decrement`` and ``merge``: :func:`levenberg_marquardt`'s, the fits by their
    index in ``specs``; ``starts`` (one label a spec): specs of one label are starts of one
    fit, and ``merge`` stops a start that meets a better one; a start that stopped as
    dropped or merged while another start of its fit did neither is superseded by it, and
    its result is None (no Jacobian, model values or covariance made for it). Inside
    :func:`tawarp.fit.lockstep.run_together` the call waits for the other threads' and runs
    in one batch with theirs (:func:`fit_calls`)."""
    specs = [(list(sp[0]), sp[1], np.zeros(len(sp[0])) if sp[2] is None else sp[2], *sp[3:]) for sp in specs]
    call = FitCall(kind, specs, fixed, rows, max_iter, xtol, gtol, priors, drop, decrement, starts, merge)
    together = lockstep.current()
    if together is not None:
        return together.call(call, fit_calls)
    return fit_calls([call])[0]


def fit_calls(calls: list[FitCall], families: "Families | None" = None) -> list[list[FitResult | None]]:
    """The fits of every call of ``calls`` (:func:`fit_batch`'s results per call), those
    alike in their iteration (:meth:`FitCall.iteration`) in one LM on one batch
    (:meth:`KindProblems.merged`; ``families``: the kinds that share launches)."""
    out: list = [None] * len(calls)
    alike: dict = {}
    for i, call in enumerate(calls):
        alike.setdefault(call.iteration(), []).append(i)
    for idx in alike.values():
        for i, fits in zip(idx, _fit_together([calls[i] for i in idx], families)):
            out[i] = fits
    return out


def _fit_together(calls: list[FitCall], families: "Families | None") -> list[list[FitResult | None]]:
    t0 = time.perf_counter()
    lm = KindProblems.merged(calls, families)
    K = len(lm.specs)
    if K == 0:
        return [[] for _ in calls]
    first = np.cumsum([0] + [len(c.specs) for c in calls])
    pid = np.arange(K)
    starts = _starts(calls)
    if lm.zlo.shape[1]:
        call = calls[0]
        st = levenberg_marquardt(
            lm,
            pid,
            lm.start(),
            xtol=call.xtol,
            gtol=call.gtol,
            max_iter=call.max_iter,
            drop=_drops(calls, first),
            decrement=np.repeat([c.decrement for c in calls], np.diff(first)),
            **starts,
        )
        z, converged, its, reason = st.z, st.converged, st.iterations, st.reason
    else:  # nothing free: the model at the fixed values
        z, converged, its, reason = lm.start(), np.ones(K, dtype=bool), np.zeros(K, dtype=int), ["gtol"] * K
    keep = np.flatnonzero(~_superseded(starts.get("starts_of"), reason))
    at = lm.at_solutions(z, keep)
    dt = time.perf_counter() - t0
    r = [residual(lm.kinds[c], Y, lm.rows[c]) for c, (_, Y) in zip(keep.tolist(), at)]
    x = [z[c, : lm.p[c]] for c in keep.tolist()]
    dof = [max(rc.size - lm.p[c], 1) for c, rc in zip(keep.tolist(), r)]
    cov = covariances([lm.models[c] for c in keep.tolist()], x, [float(rc @ rc) for rc in r], dof, [J for J, _ in at])
    fits: list = [None] * K
    for i, c in enumerate(keep.tolist()):
        params, effect, _ = lm.specs[c]
        fits[c] = kind_result(
            lm.kinds[c],
            params,
            lm.models[c],
            x[i],
            at[i][0],
            at[i][1],
            lm.rows[c],
            effect,
            bool(converged[c]),
            str(reason[c]),
            int(its[c]),
            r[i],
            cov[i],
            seconds=dt,
        )
    return [fits[a:b] for a, b in zip(first[:-1], first[1:])]


def _superseded(labels: np.ndarray | None, reason) -> np.ndarray:
    """Per fit of a batch whose start labels are ``labels`` (:func:`_starts`; None: no
    labels) and stop reasons ``reason``: a start of a fit that stopped as dropped or merged
    while another start of that fit did neither, whose result that one supersedes
    (:func:`fit_batch`)."""
    if labels is None:
        return np.zeros(len(reason), dtype=bool)
    stopped = np.array([str(r) in (DROPPED, MERGED) for r in reason], dtype=bool) & (labels >= 0)
    survives = np.zeros(int(labels.max(initial=-1)) + 1, dtype=bool)
    survives[labels[(labels >= 0) & ~stopped]] = True
    out = np.zeros(len(reason), dtype=bool)
    out[stopped] = survives[labels[stopped]]
    return out


def _starts(calls: list[FitCall]) -> dict:
    """:func:`levenberg_marquardt`'s ``starts_of`` and ``merge`` for the batch of the calls'
    fits: each call's labels after those of the calls before it (-1 where a call has none)."""
    if all(c.starts is None for c in calls):
        return {}
    labels, merge, base = [], [], 0
    for c in calls:
        own = np.full(len(c.specs), -1) if c.starts is None else base + np.asarray(c.starts, dtype=int)
        base = max(base, int(own.max(initial=-1)) + 1)
        labels.append(own)
        merge.append(np.full(len(c.specs), c.merge))
    return {"starts_of": np.concatenate(labels), "merge": np.concatenate(merge)}


def _drops(calls: list[FitCall], first: np.ndarray):
    """The calls' ``drop`` tests as one of the batch of all their fits (``first``: each
    call's first fit in it), each asked about its own fits by their index in its call."""
    own = [(call.drop, a, b) for call, a, b in zip(calls, first[:-1], first[1:]) if call.drop is not None]
    if not own:
        return None
    if len(calls) == 1:
        return own[0][0]

    def drop(slots: np.ndarray, cost: np.ndarray) -> np.ndarray:
        # the LM's slots come in increasing order: each call's are one run of them
        out = np.zeros(slots.size, dtype=bool)
        lo = np.searchsorted(slots, [a for _, a, _ in own])
        hi = np.searchsorted(slots, [b for _, _, b in own])
        for (test, a, b), i, j in zip(own, lo.tolist(), hi.tolist()):
            if j > i:
                out[i:j] = test(slots[i:j] - a, cost[a:b])
        return out

    return drop


@dataclass
class Sets:
    """``n`` parameter sets of ``kind`` to predict: ``values`` {name: (n,)} (the others at
    the kind's core values), in the structure of ``effect`` (None: the core's); ``rows``:
    None, or per set the rows it needs (:meth:`MeasurementKind.predict`); ``on_device``: the
    model values as :class:`tawarp.measure.kind.DeviceValues`."""

    kind: MeasurementKind
    values: dict
    n: int
    effect: Effect | None = None
    rows: list | None = None
    #: the model values left on the device (:meth:`MeasurementKind.predict_on_device`)
    on_device: bool = False


def predict_sets(jobs: list[Sets], families: "Families | None" = None) -> list[np.ndarray]:
    """Each job's model values (n, rows): inside :func:`tawarp.fit.lockstep.run_together`
    with the other threads' jobs, else at once (:func:`run_sets`)."""
    together = lockstep.current()
    if together is not None and not together.running:
        return together.call(jobs, _run_set_lists)
    return run_sets(jobs, families or (together.state if together else None))


def _run_set_lists(lists: list[list[Sets]], families: "Families | None") -> list[list[np.ndarray]]:
    """:func:`run_sets` of several callers' lists of jobs, all in one."""
    flat = run_sets([j for jobs in lists for j in jobs], families)
    out, k = [], 0
    for jobs in lists:
        out.append(flat[k : k + len(jobs)])
        k += len(jobs)
    return out


def run_sets(jobs: list[Sets], families: "Families | None" = None) -> list[np.ndarray]:
    """Each job's model values (n, rows), the jobs of one family (:class:`Families`) and
    structure in one :meth:`MeasurementKind.predict` call: each job's sets with its own
    core's values of the fields in which the family's cores differ, and of any name another
    job sets (or that field's neutral value, an effect off); a job lacking a name with
    neither predicts alone."""
    families = families or Families([j.kind for j in jobs])
    groups: dict = {}
    for i, j in enumerate(jobs):
        structure = j.effect.name if j.effect is not None and j.effect.transform else None
        groups.setdefault((families.of(j.kind), structure, j.on_device), []).append(i)
    out: list = [None] * len(jobs)
    for (fam, _, on_device), idx in groups.items():
        if len(idx) == 1 and set(fam.differ).issubset(jobs[idx[0]].values):
            # a job that holds each set's value of every field its family's cores differ in
            # (a batch's family-wide table, KindProblems): the family's kind predicts it as it is
            j = jobs[idx[0]]
            out[idx[0]] = _predict(fam.kind, j.values, j.n, j.effect, j.rows, on_device)
            continue
        merged = [i for i in idx if len(idx) > 1 or jobs[i].kind is not fam.kind]
        names = set(fam.differ).union(*(jobs[i].values for i in merged))
        fill = {i: _absent(jobs[i], names) for i in merged}
        alone = [i for i in idx if i not in fill or fill[i] is None]
        merged = [i for i in merged if fill[i] is not None]
        for i in alone:
            j = jobs[i]
            out[i] = _predict(j.kind, j.values, j.n, j.effect, j.rows, on_device)
        if not merged:
            continue
        total = sum(jobs[i].n for i in merged)
        names = tuple(sorted(names))
        values = np.empty((len(names), total))
        row = row_of(names)
        k0 = 0
        for i in merged:
            j = jobs[i]
            own = j.values
            if isinstance(own, ValueTable):
                values[rows_in(names, own.names), k0 : k0 + j.n] = own.array
            else:
                for k, v in own.items():
                    values[row[k], k0 : k0 + j.n] = v
            if fill[i]:
                values[rows_in(names, tuple(fill[i])), k0 : k0 + j.n] = np.fromiter(
                    fill[i].values(), dtype=float, count=len(fill[i])
                )[:, None]
            k0 += j.n
        values = ValueTable(names, values)
        rows = None
        if any(jobs[i].rows is not None for i in merged):
            rows = [r for i in merged for r in (jobs[i].rows or [None] * jobs[i].n)]
        Y = _predict(fam.kind, values, total, jobs[merged[0]].effect, rows, on_device)
        k0 = 0
        for i in merged:
            out[i] = Y[k0 : k0 + jobs[i].n]
            k0 += jobs[i].n
    return out


def _predict(kind: MeasurementKind, values: dict, n: int, effect, rows, on_device: bool = False):
    if on_device:
        return kind.predict_on_device(values, n, effect, rows)
    return kind.predict(values, n, effect) if rows is None else kind.predict(values, n, effect, rows=rows)


def _absent(job: Sets, names: set) -> dict | None:
    """{name: the value ``job``'s sets take} of ``names`` it does not set: its core's, or
    the field's neutral value; None where a name has neither (a dict to read, not to
    change: shared by the jobs of one core that lack the same names)."""
    return _absent_values(job.kind.core, frozenset(names.difference(job.values)))


@functools.lru_cache(maxsize=1024)
def _absent_values(core, names: frozenset) -> dict | None:
    """:func:`_absent` of a core's ``names``: made once for every launch whose jobs of
    that core lack them (a fit's batch asks for a hundred names, a loop hundreds of times)."""
    out = {}
    core_names = _parameter_names(core)
    for k in names:
        if k in core_names:
            out[k] = core.get(k)
            continue
        try:
            neutral = field_of(k).neutral
        except KeyError:
            neutral = None
        if neutral is None:
            return None
        out[k] = neutral
    return out


@functools.lru_cache(maxsize=256)
def _parameter_names(core) -> frozenset:
    return frozenset(core.parameter_names())


class Families:
    """Kinds that predict in one launch (:meth:`MeasurementKind.family`: one structure, the
    same rows), each set with the core values in which its kind's core differs from the
    family's first kind's. A kind joins its family when first asked for (a loop's
    noise-weighted copy of its kind too); a kind without a family predicts alone."""

    def __init__(self, kinds: list = ()):
        self._of: dict = {}  # id(kind) -> its family (whose members keep the kind, and its id, alive)
        self._by_key: dict = {}
        for k in kinds:
            self.of(k)

    def of(self, kind) -> "_Family":
        """``kind``'s family."""
        fam = self._of.get(id(kind))
        if fam is None:
            key = kind.family()
            fam = _Family(kind) if key is None else self._by_key.setdefault(key, _Family(kind))
            fam.join(kind)
            self._of[id(kind)] = fam
        return fam


@dataclass(eq=False)
class _Family:
    """A family's predicting kind (:meth:`MeasurementKind.for_family` of its first), its
    members and the core fields in which they differ."""

    lead: MeasurementKind
    members: list = field(default_factory=list)
    differ: list = field(default_factory=list)

    def __post_init__(self):
        self.kind = self.lead
        self._lead_values: dict | None = None  # the lead's core values, once a second member joins

    def join(self, kind) -> None:
        self.members.append(kind)
        if kind is self.lead:
            return
        if self._lead_values is None:
            self._lead_values = {n: self.lead.core.get(n) for n in self.lead.core.parameter_names()}
        self.differ += [
            n
            for n, a in self._lead_values.items()
            if a == a
            and a != kind.core.get(n)
            and n not in self.differ  # (a field unset, NaN, is unset in every member)
        ]
        self.kind = self.lead.for_family(self.members)


def fit_one(
    kind: MeasurementKind,
    params: list[Param],
    fixed: dict | None = None,
    effect: Effect | None = None,
    rows: np.ndarray | None = None,
    x0=None,
    **kw,
) -> FitResult:
    """One fit of ``kind`` (:func:`fit_batch` of one spec)."""
    return fit_batch(kind, [(params, effect, x0)], fixed, rows, **kw)[0]


def fit_kind(kind: MeasurementKind, names=None, start: dict | None = None, **kw) -> FitResult:
    """Fit the parameters ``names`` (default ``kind.default_names()``) of any measurement
    kind from ``start`` {name: value} (default the kind's core), scaling and bounds from
    :mod:`tawarp.model.fields` (:func:`tawarp.model.effects.base_params`)."""
    names = list(names or kind.default_names())
    core = kind.core.replace(**start) if start else kind.core
    return fit_one(kind, base_params(core, names), **kw)
