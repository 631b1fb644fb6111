"""Reductions of a sweep's outputs, computed on the device while the sweep runs
(:func:`tawarp.design.sweep.sweep` with ``reduce=``; kernels in
:mod:`tawarp.kernels.reduce`), written beside or instead of the raw values.

``reduce`` names them, comma-separated (``--reduce best,quantiles,histogram,pareto,top=100``):

- ``best``: per design variable and level (a grid's values; a Sobol sweep's continuous
  variable in :data:`LEVELS` equal bins of its range, of its logarithm for a log variable;
  each material), the best value of the first objective and the point index where it
  is (the smallest index among equals): the variable's *marginal best*;
- ``top=K``: the K best points of the first objective (values, every output, index);
- ``pareto``: the Pareto front of the first two objectives (each in its direction), its
  points with their values and outputs;
- ``histogram``: per output, the counts in bins of equal relative width 2^-11 (the
  float32 value's sign, exponent and 11 leading mantissa bits), the empty ones left out;
- ``quantiles``: per output, bounds that hold the quantiles (NumPy's linear definition)
  of :data:`QUANTILES`, from those histograms: the bins of the order statistics around
  each, so the bounds are 2^-11 apart in relative terms.

Counts, best values, the top K and the front are exact (integer atomics on an ordering
key, candidates merged on the host): the same as NumPy's reductions of the raw float32
values (``tests/test_sweep_reduce.py``). They merge exactly too: reductions of disjoint
point ranges (a sweep's workers, :meth:`Reducer.state`, :meth:`Reducer.merge`) fold into
those of the whole (counts summed, best keys minimized, top and front re-merged: each key
or tie-break holds the point index, so the order of the folds does not matter). Points whose objective is NaN (a failed
evaluation) are left out of best, top and front; NaN outputs are counted apart in the
histograms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .objectives import objective

#: Levels of a Sobol sweep's continuous variable for ``best``.
LEVELS = 64
#: Candidate slots of a chunk (top and pareto each) copied to the host with the chunk's
#: reductions; more wait for the device (a Sobol chunk's Pareto filter leaves a few hundred).
STAGED = 1 << 14
#: Probabilities of ``quantiles``.
QUANTILES = (0.001, 0.01, 0.05, 0.1, 0.25, 0.5, 0.75, 0.9, 0.95, 0.99, 0.999)


@dataclass(frozen=True)
class ReduceSpec:
    """What a sweep reduces its outputs to (see the module docstring)."""

    best: bool = False
    top: int = 0
    pareto: bool = False
    histogram: bool = False
    quantiles: bool = False

    def __bool__(self) -> bool:
        return self.best or self.top > 0 or self.pareto or self.histogram or self.quantiles


def parse_reduce(text) -> ReduceSpec:
    """``"best,quantiles,histogram,pareto,top=100"`` (any of them) as a :class:`ReduceSpec`."""
    if isinstance(text, ReduceSpec):
        return text
    kw = {}
    for item in (t.strip() for t in str(text).split(",") if t.strip()):
        name, _, value = item.partition("=")
        if name == "top":
            if not value.isdigit() or int(value) < 1:
                raise ValueError(f"reduce {item!r}: give top=K with K >= 1 points")
            kw["top"] = int(value)
        elif name in ("best", "pareto", "histogram", "quantiles") and not value:
            kw[name] = True
        else:
            raise ValueError(f"reduce {item!r}: not one of best, quantiles, histogram, pareto, top=K")
    return ReduceSpec(**kw)


def key_values(keys: np.ndarray) -> np.ndarray:
    """The float32 values (as float64) of ordering keys (:func:`tawarp.kernels.reduce.ordered_key`);
    keys beyond inf give inf."""
    keys = np.asarray(keys, dtype=np.int64)
    mag = np.minimum(np.abs(keys), 0x7F800000).astype(np.uint32)
    return np.where(keys < 0, -1.0, 1.0) * mag.view(np.float32).astype(np.float64)


def ordered_keys(v: np.ndarray) -> np.ndarray:
    """NumPy's :func:`tawarp.kernels.reduce.ordered_key` of float32 values (bit patterns as
    signed magnitudes)."""
    bits = np.asarray(v, dtype=np.float32).view(np.int32).astype(np.int64)
    mag = bits & 0x7FFFFFFF
    return np.where(bits < 0, -mag, mag)


def front_2d(G: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Places of the rows of G (N, 2), both minimized, that no other row dominates, in
    lexicographic order (then by ``index``), vectorized: in that order a row is dominated
    exactly when an earlier, different row has a second objective <= its own; identical
    rows share their first one's fate."""
    order = np.lexsort((index, G[:, 1], G[:, 0]))
    a, b = G[order, 0], G[order, 1]
    new = np.ones(len(order), dtype=bool)
    new[1:] = (a[1:] != a[:-1]) | (b[1:] != b[:-1])  # first of a run of identical rows
    run = np.cumsum(new) - 1
    firsts = np.flatnonzero(new)
    before = np.concatenate([[np.inf], np.minimum.accumulate(b[firsts])[:-1]])  # over earlier runs
    return order[(b[firsts] < before)[run]]


class Reducer:
    """Accumulates a sweep's reductions chunk by chunk on ``device``.

    ``outputs``: the sweep's output names (rows of each chunk's (len(outputs), m) float32
    array); ``objectives``: the outputs that ``best``, ``top`` and ``pareto`` rank (in
    their directions); ``names``: the design variables of a Sobol chunk's values rows
    (None for a grid, whose coordinates come from the point index and ``grids``)."""

    def __init__(self, spec: ReduceSpec, space, mode: str, outputs, objectives, device, chunk: int, grids=None):
        self.spec, self.space, self.mode, self.device = spec, space, mode, device
        self.outputs = list(outputs)
        self.objectives = list(objectives or [])
        need = 2 if spec.pareto else 1 if (spec.best or spec.top) else 0
        if len(self.objectives) < need:
            raise ValueError(f"reduce: {'pareto needs two' if need == 2 else 'best and top need an'} objective(s)")
        for o in self.objectives[:need]:
            if o not in self.outputs:
                raise ValueError(f"reduce: objective {o!r} is not among the sweep's outputs {self.outputs}")
        self.rows = [self.outputs.index(o) for o in self.objectives[:need]]
        self.signs = [-1.0 if objective(o).direction == "maximize" else 1.0 for o in self.objectives[:need]]
        self.grids = grids
        self.variables = (
            space.variables
            if mode == "grid"
            else space.continuous + ([space.material] if space.material is not None else [])
        )
        self.names = [v.name for v in self.variables]
        n_val = 0 if mode == "grid" else len(self.names)
        self.n = 0
        dev = device
        if spec.histogram or spec.quantiles:
            from ..kernels.reduce import HIST_BINS

            self.counts = wp.zeros((len(self.outputs), HIST_BINS), dtype=wp.int64, device=dev)
            self.nan = wp.zeros(len(self.outputs), dtype=wp.int64, device=dev)
        if spec.best:
            self._best_setup()
        # candidates of top and pareto, two sets: chunk k + 1 is launched before chunk k is
        # read (:meth:`collect`), each with its first STAGED slots' host copy, queued with the
        # chunk's kernels, and the event that says it landed
        self._cand, self._staged, self._landed = {}, {}, [None, None]
        self._cuda = wp.get_device(dev).is_cuda
        for kind in ("top", "pareto"):
            if (kind == "top" and spec.top) or (kind == "pareto" and spec.pareto):
                self._cand[kind] = [self._candidates(chunk, n_val) for _ in range(2)]
                self._staged[kind] = [self._candidates(min(chunk, STAGED), n_val, "cpu") for _ in range(2)]
        if spec.pareto:
            from ..kernels.reduce import PARETO_BINS

            self._bins = [wp.empty(PARETO_BINS, dtype=wp.int64, device=dev) for _ in range(2)]
        empty = (np.zeros(0, np.int64), np.zeros((len(self.outputs), 0), np.float32), np.zeros((n_val, 0)))
        self.top, self.front = empty, empty  # (keys or indices, outputs, values) on the host
        self._folded = None  # merge(): other ranges' histograms, nan counts and best keys (host)
        self._no_values = wp.empty((0, 0), dtype=wp.float64, device=dev)

    def _candidates(self, chunk: int, n_val: int, device=None):
        """Candidate slots on the device (or their page-locked host copy: ``device`` cpu)."""
        from ..kernels.reduce import Candidates

        dev, c = device or self.device, Candidates()
        pinned = device == "cpu" and self._cuda
        c.count = wp.zeros(1, dtype=wp.int32, device=dev, pinned=pinned)
        c.key = wp.empty(chunk, dtype=wp.int64, device=dev, pinned=pinned)
        c.out = wp.empty((chunk, len(self.outputs)), dtype=wp.float32, device=dev, pinned=pinned)
        c.val = wp.empty((chunk, n_val), dtype=wp.float64, device=dev, pinned=pinned)
        return c

    def _best_setup(self):
        from ..kernels.reduce import NONE_KEY

        dev = self.device
        if self.mode == "grid":
            shape = [len(g) for g in self.grids]
            stride = [int(np.prod(shape[j + 1 :], dtype=np.int64)) for j in range(len(shape))]
            levels = shape
            low, span, log = np.zeros(len(shape)), np.zeros(len(shape)), np.zeros(len(shape), np.int32)
            self.level_coords = [np.asarray(g) for g in self.grids]
        else:
            stride, shape, levels, low, span, log, self.level_coords = [], [], [], [], [], [], []
            for v in self.variables:
                if v.categorical:
                    levels.append(len(v.choices))
                    low.append(0.0)
                    span.append(0.0)
                    log.append(0)
                    self.level_coords.append(np.array(v.choices, dtype=object))
                else:
                    lo, hi = (np.log(v.low), np.log(v.high)) if v.log else (v.low, v.high)
                    levels.append(LEVELS)
                    low.append(lo)
                    span.append(hi - lo)
                    log.append(int(v.log))
                    mid = lo + (np.arange(LEVELS) + 0.5) / LEVELS * (hi - lo)
                    self.level_coords.append(np.exp(mid) if v.log else mid)
            stride, shape = [1] * len(levels), [1] * len(levels)
        self.levels = list(levels)
        first = np.concatenate([[0], np.cumsum(levels)[:-1]]).astype(np.int32)
        self._best_inputs = [
            wp.array(np.asarray(stride, np.int64), dtype=wp.int64, device=dev),
            wp.array(np.asarray(shape, np.int32), dtype=wp.int32, device=dev),
            None,  # the chunk's values
            wp.array(np.asarray(low, np.float64), dtype=wp.float64, device=dev),
            wp.array(np.asarray(span, np.float64), dtype=wp.float64, device=dev),
            wp.array(np.asarray(log, np.int32), dtype=wp.int32, device=dev),
            wp.array(np.asarray(levels, np.int32), dtype=wp.int32, device=dev),
            wp.array(first, dtype=wp.int32, device=dev),
        ]
        self.first_level = first
        self.best = wp.full(int(np.sum(levels)), NONE_KEY, dtype=wp.int64, device=dev)

    # -- per chunk ---------------------------------------------------------------------------
    def add(self, k: int, lo: int, values, out: wp.array) -> None:
        """Launch chunk k's reductions: points lo.. of ``out`` (len(outputs), m) float32 on
        the device, their design ``values`` (len(names), m) (a Sobol chunk) or None."""
        from ..kernels import reduce as R

        dev, m = self.device, out.shape[1]
        vals = values if values is not None and self.mode != "grid" else self._no_values
        self.n += m
        if self.spec.histogram or self.spec.quantiles:
            wp.launch(R.histogram, dim=out.shape, device=dev, inputs=[out, self.counts, self.nan])
        lo = wp.int64(lo)
        if self.spec.best:
            args = list(self._best_inputs)
            args[2] = vals
            wp.launch(
                R.marginal_best,
                dim=m,
                device=dev,
                inputs=[lo, out[self.rows[0]], float(self.signs[0]), *args, self.best],
            )
        if self.spec.top:
            cand = self._cand["top"][k % 2]
            cand.count.zero_()
            row, sign = self.rows[0], float(self.signs[0])
            if len(self.top[0]) == self.spec.top:  # the K-th best so far bounds the candidates
                wp.launch(
                    R.top_candidates,
                    dim=m,
                    device=dev,
                    inputs=[lo, out, row, sign, wp.int64(int(self.top[0][-1])), vals, cand],
                )
            else:  # no bound yet: the chunk's own K best, by a radix sort on the device
                keys = wp.empty(2 * m, dtype=wp.int64, device=dev)
                point = wp.empty(2 * m, dtype=wp.int32, device=dev)
                wp.launch(R.chunk_rank_keys, dim=m, device=dev, inputs=[lo, out, row, sign, keys, point])
                wp.utils.radix_sort_pairs(keys, point, m)
                wp.launch(
                    R.first_candidates,
                    dim=min(self.spec.top, m),
                    device=dev,
                    inputs=[keys, point, out, vals, cand],
                )
        if self.spec.pareto:
            rows, signs = wp.vec2i(*self.rows[:2]), wp.vec2f(*self.signs[:2])
            a, b = self._bins
            a.fill_(R.NONE_KEY)
            wp.launch(R.pareto_bins, dim=m, device=dev, inputs=[out, rows, signs, a])
            step = 1
            while step < a.shape[0]:  # inclusive prefix minimum, ping-pong
                wp.launch(R.prefix_min_step, dim=a.shape[0], device=dev, inputs=[a, step, b])
                a, b = b, a
                step *= 2
            cand = self._cand["pareto"][k % 2]
            cand.count.zero_()
            wp.launch(R.pareto_candidates, dim=m, device=dev, inputs=[lo, out, rows, signs, a, vals, cand])
        for kind, sets in self._cand.items():  # queued: the host reads them without waiting for chunk k + 1
            c, h = sets[k % 2], self._staged[kind][k % 2]
            for name in ("count", "key", "out", "val"):
                if getattr(h, name).size:
                    wp.copy(getattr(h, name), getattr(c, name), count=getattr(h, name).size)
        if self._cand and self._cuda:
            self._landed[k % 2] = wp.get_stream(dev).record_event()

    def collect(self, k: int) -> None:
        """Merge chunk k's candidates into the top K and the front: waits for chunk k's
        reductions alone (not for a chunk launched after it) unless it has more than
        :data:`STAGED` candidates."""
        if self._landed[k % 2] is not None:
            wp.synchronize_event(self._landed[k % 2])
        for kind, sets in self._cand.items():
            h = self._staged[kind][k % 2]
            n = int(h.count.numpy()[0])
            if not n:
                continue
            # the n filled slots alone: the buffers hold a whole chunk (on a GPU, copying them
            # whole was most of a reduced sweep's time)
            c = h if n <= h.key.shape[0] else sets[k % 2]
            val = c.val[:n].numpy().T if c.val.shape[1] else np.zeros((0, n))  # (a grid's: none)
            cand = (c.key[:n].numpy(), c.out[:n].numpy().T, val)  # merged into new arrays
            if kind == "top":
                self.top = self._merge_top(cand)
            else:
                self.front = self._merge_front(cand)

    def _merge_top(self, cand):
        keys = np.concatenate([self.top[0], cand[0]])
        order = np.argsort(keys, kind="stable")[: self.spec.top]
        return (
            keys[order],
            np.concatenate([self.top[1], cand[1]], 1)[:, order],
            np.concatenate([self.top[2], cand[2]], 1)[:, order],
        )

    def _merge_front(self, cand):
        idx = np.concatenate([self.front[0], cand[0]])
        out = np.concatenate([self.front[1], cand[1]], 1)
        G = np.stack([self.signs[j] * out[self.rows[j]].astype(np.float64) for j in range(2)], axis=1)
        on = front_2d(G, idx)
        return idx[on], out[:, on], np.concatenate([self.front[2], cand[2]], 1)[:, on]

    # -- merging -------------------------------------------------------------------------
    def _histograms(self) -> list:
        """Per output, its histogram's occupied bins (increasing) and their counts,
        compacted on the device (:func:`tawarp.kernels.reduce.compact_bins`): the host
        reads these and the blocks' occupied counts, not every bin (tens of MB)."""
        from ..kernels import reduce as R

        dev = self.device
        occupied = wp.zeros((len(self.outputs), R.HIST_BINS // R.HIST_BLOCK_BINS), dtype=wp.int32, device=dev)
        wp.launch(R.occupied_bins, dim=self.counts.shape, device=dev, inputs=[self.counts, occupied])
        occ = occupied.numpy().astype(np.int64)
        start = (np.cumsum(occ) - occ.ravel()).reshape(occ.shape)  # each block's first place
        bins = wp.empty(int(occ.sum()), dtype=wp.int32, device=dev)
        count = wp.empty(bins.shape[0], dtype=wp.int64, device=dev)
        if bins.shape[0]:
            start_dev = wp.array(start.astype(np.int32), dtype=wp.int32, device=dev)
            wp.launch(
                R.compact_bins,
                dim=occ.shape,
                device=dev,
                inputs=[self.counts, occupied, start_dev, bins, count],
            )
        b, c = bins.numpy().astype(np.int64), np.array(count.numpy())  # (copies: the device arrays go)
        ends = np.cumsum(occ.sum(1))
        return [(b[lo:hi], c[lo:hi]) for lo, hi in zip(ends - occ.sum(1), ends)]

    def state(self) -> dict:
        """What this reducer holds, on the host (a few arrays: the candidates, the
        histograms' occupied bins, the best keys; no point's raw values): what a sweep's
        worker sends back, folded into another reducer by :meth:`merge`."""
        st = {"n": self.n, "top": self.top, "front": self.front}

        def host(a):  # a CUDA array's numpy() is a new host array; a CPU one's is a view
            return a.numpy() if self._cuda else a.numpy().copy()

        if self.spec.histogram or self.spec.quantiles:
            st["histograms"], st["nan"] = self._histograms(), host(self.nan)
        if self.spec.best:
            st["best"] = host(self.best)
        if self._folded is not None:
            for k, v in self._folded.items():
                st[k] = _fold(k, st[k], v)
        return st

    def merge(self, other: dict) -> None:
        """Fold the :meth:`state` of a reducer of the same sweep over other points into
        this one: exact (see the module docstring)."""
        self.n += other["n"]
        if other["top"][0].size:
            self.top = self._merge_top(other["top"])
        if other["front"][0].size:
            self.front = self._merge_front(other["front"])
        folded = {k: other[k] for k in ("histograms", "nan", "best") if k in other}
        if self._folded is None:
            self._folded = folded
        else:
            for k, v in folded.items():
                self._folded[k] = _fold(k, self._folded[k], v)

    # -- results ---------------------------------------------------------------------------
    def _coordinates(self, index: np.ndarray, values: np.ndarray) -> dict:
        """Design values of points ``index``: a grid's from the index, a Sobol sweep's as
        computed on the device (``values``); the material as its name."""
        if self.mode == "grid":
            at = np.unravel_index(index, [len(g) for g in self.grids]) if len(index) else [index] * len(self.grids)
            return {
                v.name: np.asarray(self.grids[j], dtype=object if v.categorical else float)[at[j]]
                for j, v in enumerate(self.variables)
            }
        out = {}
        for j, v in enumerate(self.variables):
            out[v.name] = np.array(v.choices, dtype=object)[values[j].astype(int)] if v.categorical else values[j]
        return out

    def results(self) -> dict:
        """``{group: {variable: (dims, array)}}`` of every reduction asked, plus a short
        ``summary`` (JSON types)."""
        from ..kernels.reduce import HIST_OFFSET_BINS, HIST_SHIFT_BITS, NONE_KEY

        res, summary = {}, {}
        st = self.state()
        if self.spec.top:
            keys, out, vals = self.top
            idx = keys & 0xFFFFFFFF
            g = {"point": (("rank",), idx.astype(np.int64))}
            g.update({o: (("rank",), out[j]) for j, o in enumerate(self.outputs)})
            g.update({k: (("rank",), v) for k, v in self._coordinates(idx, vals).items()})
            res["top"] = g
            if len(idx):
                summary["best"] = {k: _json(v[1][0]) for k, v in g.items()}
        if self.spec.best:
            best = st["best"]
            g = {}
            for j, v in enumerate(self.variables):
                sel = best[self.first_level[j] : self.first_level[j] + self.levels[j]]
                has = sel != NONE_KEY
                value = np.where(has, self.signs[0] * key_values(sel >> 32), np.nan)
                dim = f"{v.name}_level"
                g[dim] = ((dim,), self.level_coords[j])
                g[f"{v.name}_best"] = ((dim,), value.astype(np.float32))
                g[f"{v.name}_point"] = ((dim,), np.where(has, sel & 0xFFFFFFFF, -1).astype(np.int64))
            res["best"] = g
        if self.spec.pareto:
            idx, out, vals = self.front
            g = {"point": (("front",), idx.astype(np.int64))}
            g.update({o: (("front",), out[j]) for j, o in enumerate(self.outputs)})
            g.update({k: (("front",), v) for k, v in self._coordinates(idx, vals).items()})
            res["pareto"] = g
            summary["pareto_points"] = int(len(idx))
        if self.spec.histogram or self.spec.quantiles:
            nan = st["nan"]
            hist, quant = {}, {"probability": (("probability",), np.array(QUANTILES))}
            for j, o in enumerate(self.outputs):
                nz, counts = st["histograms"][j]
                first = (nz - HIST_OFFSET_BINS) << HIST_SHIFT_BITS
                lower, upper = key_values(first), key_values(first + (1 << HIST_SHIFT_BITS) - 1)
                dim = f"{o}_bin"
                hist[f"{o}_lower"] = ((dim,), lower)
                hist[f"{o}_upper"] = ((dim,), upper)
                hist[f"{o}_count"] = ((dim,), counts)
                hist[f"{o}_nan"] = ((), np.int64(nan[j]))
                c = np.cumsum(counts)
                total = int(c[-1]) if len(c) else 0
                if total:
                    h = (total - 1) * np.asarray(QUANTILES)
                    lo_bin = np.searchsorted(c, np.floor(h), side="right")
                    hi_bin = np.searchsorted(c, np.ceil(h), side="right")
                    ql, qu = lower[lo_bin], upper[hi_bin]
                else:
                    ql = qu = np.full(len(QUANTILES), np.nan)
                quant[f"{o}_lower"] = (("probability",), ql)
                quant[f"{o}_upper"] = (("probability",), qu)
                summary.setdefault("median", {})[o] = [_json(ql[5]), _json(qu[5])]
            if self.spec.histogram:
                res["histogram"] = hist
            if self.spec.quantiles:
                res["quantiles"] = quant
        res["summary"] = summary
        return res

    def write(self, h5) -> dict:
        """The reductions as netCDF-4 groups of the open ``h5py.File`` ``h5`` (``best``,
        ``top``, ``pareto``, ``histogram``, ``quantiles``; ``xarray.open_dataset(path,
        group=...)``), written by :func:`netcdf_group`; returns :meth:`results` (computed
        once: it reads the device's state)."""
        results = self.results()
        dimid = 1 + max((int(d.attrs.get("_Netcdf4Dimid", -1)) for d in h5.values()), default=-1)
        for name, g in results.items():
            if name != "summary":
                units = {var: objective(var).unit for var in g if var in self.outputs}
                dimid = netcdf_group(h5, name, g, units, dimid)
        return results


#: the name HDF5 gives a netCDF dimension without a coordinate variable (netCDF-C's)
NOT_A_VARIABLE = "This is a netCDF dimension but not a netCDF variable.%10d"


def netcdf_group(h5, name: str, variables: dict, units: dict, dimid: int) -> int:
    """Write the group ``name`` of ``variables`` {var: (dims, array)} into the h5py file
    ``h5`` as netCDF-4 lays it out (what h5netcdf and netCDF-C read): each dimension a
    dimension scale numbered from ``dimid`` (a variable of its name is its coordinate,
    else a placeholder), the variables with their scales attached, their dimension ids
    and ``units`` {var: unit}. Returns the next free dimension id. h5netcdf's own writer
    looked every object up again per variable: 0.6 s for a reduced sweep's 60 variables
    on a loaded 2-core machine, most of the sweep's time outside its chunks."""
    import h5py

    grp = h5.create_group(name, track_order=True)

    def dataset(var, a):
        a = np.asarray(a)
        if a.dtype.kind in "OUS":
            return grp.create_dataset(
                var, data=a.astype(str).astype(object), dtype=h5py.string_dtype(), track_order=True
            )
        return grp.create_dataset(var, data=a, track_order=True)

    scales, ids = {}, {}
    for dims, a in variables.values():
        for d, size in zip(dims, np.shape(a)):
            if d in scales:
                continue
            if d in variables:  # a coordinate variable
                scales[d] = ds = dataset(d, variables[d][1])
                ds.make_scale(d)
            else:
                kw = {"maxshape": (None,)} if size == 0 else {}
                scales[d] = ds = grp.create_dataset(d, shape=(size,), dtype=">f4", track_order=True, **kw)
                ds.make_scale(NOT_A_VARIABLE % size)
            ids[d] = dimid
            _new_attribute(ds, "_Netcdf4Dimid", np.int32(dimid))
            dimid += 1
    for var, (dims, a) in variables.items():
        ds = scales[var] if var in scales else dataset(var, a)
        for j, d in enumerate(dims):
            if var not in scales:  # (HDF5's call: h5py's ds.dims[j] reads the dataspace again each time)
                h5py.h5ds.attach_scale(ds.id, scales[d].id, j)
        if dims:
            _new_attribute(ds, "_Netcdf4Coordinates", np.array([ids[d] for d in dims], dtype=np.int32))
            if var not in scales:  # netCDF-C marks a written variable with its first dimension's id
                _new_attribute(ds, "_Netcdf4Dimid", np.int32(ids[dims[0]]))
        if var in units:
            _new_attribute(ds, "units", units[var])
    return dimid


def _new_attribute(obj, name: str, value) -> None:
    """The attribute ``name`` of the new h5py object ``obj``: ``value`` an int32 (scalar
    or 1-D) or a str (a variable-length UTF-8 scalar), as h5py's ``obj.attrs[name] = value``
    writes it, by HDF5's calls (h5py's checks for an existing attribute to replace took a
    quarter of a reduced sweep's group writing)."""
    import h5py

    a = np.array(value, dtype=h5py.string_dtype() if isinstance(value, str) else np.int32)
    attr = h5py.h5a.create(
        obj.id, name.encode(), h5py.h5t.py_create(a.dtype, logical=True), h5py.h5s.create_simple(a.shape)
    )
    attr.write(a)


def merge_histograms(a: list, b: list) -> list:
    """Per output, the sum of two compacted histograms [(bins increasing, counts)]: the
    union of their bins, the counts of a bin in both added (exact integers)."""
    out = []
    for (bins_a, counts_a), (bins_b, counts_b) in zip(a, b):
        bins, at = np.unique(np.concatenate([bins_a, bins_b]), return_inverse=True)
        counts = np.zeros(len(bins), dtype=np.int64)
        np.add.at(counts, at, np.concatenate([counts_a, counts_b]))
        out.append((bins, counts))
    return out


def _fold(key: str, a, b):
    """Two reducers' ``key`` of :meth:`Reducer.state` as one: best keys minimized,
    histograms merged, NaN counts summed."""
    if key == "best":
        return np.minimum(a, b)
    return merge_histograms(a, b) if key == "histograms" else a + b


def _json(v):
    """A NumPy scalar as a JSON type."""
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        return float(v)
    return str(v)
