"""Large sweeps over a design space, streamed to a labelled netCDF file.

Two layouts (read back with ``xarray.open_dataset(path, engine="h5netcdf")``):

- ``grid``: one dimension per design variable, its grid as coordinate (``material`` as
  string labels); the outputs have shape (n_1, ..., n_k).
- ``sobol``: a ``sample`` dimension; the design variables are variables along it
  (``material`` as an int8 index with CF ``flag_values``/``flag_meanings``), points of a
  scrambled Sobol sequence (seeded, reproducible) scaled to the variable ranges.

Outputs (float32, CF ``units`` and ``long_name`` from the objectives table,
:mod:`tawarp.design.objectives`): by default the metrics kernel's columns
(``gradient`` [K/m] = (T(x3) - T(x2)) / l_s, ``T_max`` [K], ``heat_leak`` [W] (stack, to
the wall), ``T_hot`` [K] = T(x3)); ``outputs`` adds or selects any registered objective.
The work is done in chunks of ``chunk`` points: per chunk the device builds its
parameter table (:class:`tawarp.design.space.DeviceTable`: from the grid index, or from
the chunk's Sobol points, which it makes too: scipy's sequence, bit for bit), then one
heat-solve and one metrics launch; each chunk is written in place (an HDF5 hyperslab) while the device evaluates the
next, so memory stays flat whatever the size (two chunks on the host at most). Through a
Dask cluster (``client=``) each worker does the same for whole chunks on its device: a
task is a chunk's point range, and only what the file stores comes back (a few chunks in
flight per worker), so no table crosses between processes; with ``parts=True`` nothing
comes back: the workers write their chunks to part files that the file maps as HDF5
virtual datasets (:func:`parts_path`), so the writing runs on every worker. A reduced
sweep without raw values (``reduce=..., raw=False``) sends each worker one contiguous share
of the chunks (their ranges) and gets back that share's reductions alone, merged exactly
(:meth:`tawarp.design.reductions.Reducer.merge`). The file is written to a temporary name
beside the target and renamed at the end (:func:`tawarp.io.atomic_path`: nothing
half-written on failure or interruption, normal permissions).
"""

from __future__ import annotations

import contextlib
import functools
import gc
import itertools
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from .evaluate import DEFAULT_FREQS, Evaluator
from .objectives import kernel_metrics, objective
from .samplers import SOBOL_MAX_POINTS
from .space import DesignSpace, DeviceTable
from ..io import atomic_dir, atomic_path, ensure_free_space, hdf5_writing
from ..model.forward import ForwardSettings, resolve_device
from ..rng import checked_seed


#: Chunks between two collections of reference cycles (launches leave some, holding
#: device arrays).
GC_CHUNKS = 16


@dataclass
class SweepInfo:
    """``path``, ``n_points``, ``seconds`` (wall), ``evaluations_per_hour``, ``chunks``,
    ``evaluation_seconds`` (launches, transfers and waiting for the device: the device
    time that the writing did not hide), ``write_seconds``, ``reductions`` (a short summary
    of those asked: :mod:`tawarp.design.reductions`) and ``reduction_write_seconds`` (their
    results computed from the device's state and written, after the last chunk)."""

    path: Path
    n_points: int
    seconds: float
    evaluations_per_hour: float
    chunks: int
    evaluation_seconds: float
    write_seconds: float
    reductions: dict | None = None
    reduction_write_seconds: float = 0.0


def _units(space: DesignSpace, name: str) -> str:
    from ..model.fields import field

    if name == "heat_input":
        return "W"
    try:
        return field(space.core_name(name)).unit
    except KeyError:
        return ""


def _blocks(shape: tuple, chunk: int):
    """Contiguous C-order blocks of at most ~chunk points that are hyperslabs:
    yields (lo, hi, index tuple of slices)."""
    k = len(shape)
    trailing = [int(np.prod(shape[j + 1 :])) for j in range(k)]
    a = next((j for j in range(k) if trailing[j] <= chunk), k - 1)
    step = max(1, chunk // trailing[a])
    lead_shape = shape[:a]
    for lead in np.ndindex(*lead_shape) if lead_shape else [()]:
        base = int(np.ravel_multi_index(lead, lead_shape)) * shape[a] * trailing[a] if lead_shape else 0
        for i0 in range(0, shape[a], step):
            i1 = min(shape[a], i0 + step)
            lo = base + i0 * trailing[a]
            hi = base + i1 * trailing[a]
            yield lo, hi, tuple(lead) + (slice(i0, i1),)


#: Points per chunk by default: a GPU launch of 2^20 points takes milliseconds; on the CPU it
#: took 1-3 s, and a Ctrl-C waits for the launch in flight, so the CPU's chunk is 2^16.
CHUNK_GPU, CHUNK_CPU = 1 << 20, 1 << 16


def sweep(
    space: DesignSpace,
    path: str | Path,
    mode: str = "grid",
    n_samples: int | None = None,
    chunk: int | None = None,
    seed: int = 0,
    settings: ForwardSettings | None = None,
    progress: bool = False,
    attrs: dict | None = None,
    outputs=None,
    freqs=DEFAULT_FREQS,
    client=None,
    parts: bool = False,
    reduce=None,
    raw: bool = True,
    objectives=("gradient", "heat_leak"),
) -> SweepInfo:
    """Evaluate ``space`` on a grid (every variable needs ``values``: ``NAME=LOW:HIGH:COUNT``)
    or on ``n_samples`` Sobol points (``mode="sobol"``, variables need ranges) and stream the
    results to the netCDF file ``path``. ``outputs``: objective names written (default: the
    kernel's metrics); ``freqs`` [Hz] for ``acoustic_loss``; ``client``: a Dask
    ``distributed.Client`` whose workers (one per device, :mod:`tawarp.distributed`) each
    evaluate whole chunks: a task is the chunk's point range, the worker makes the chunk's
    table on its device as one process does, and sends back only what the file stores (the
    float32 outputs, a Sobol chunk's design values); the file is the same. ``parts``
    (with ``client``): nothing comes back either; each worker writes its chunks to part
    files in the folder :func:`parts_path` (``<file name>.parts``) and the file maps them
    as HDF5 virtual datasets, read as one file (xarray, h5netcdf, netCDF-C) while the folder
    stays beside it: the writing, which bounds a one-file sweep on one GPU, runs on every
    worker at once. The workers must see the client's file system. ``reduce``: reductions
    computed on the device while the sweep runs and written as groups of the file
    (``"best,quantiles,histogram,pareto,top=100"``, :mod:`tawarp.design.reductions`), of
    ``objectives`` (best and top: the first; pareto: the first two); ``raw=False`` writes
    them alone, without the raw outputs (nor a Sobol sweep's design values): nothing but
    small candidate sets crosses to the host; with ``client`` (and ``raw=False``) every
    worker reduces its share of the chunks and the reductions are merged here, the same as
    one process's. See the module docstring."""
    import h5netcdf
    import h5py

    from ..progress import progress_bar

    if mode not in ("grid", "sobol"):
        raise ValueError(f"mode must be 'grid' or 'sobol', got {mode!r}")
    checked_seed(seed, "sweep")
    for o in objectives or ():
        objective(o)  # a KeyError naming the known ones, with reduce= or not
    settings = settings or ForwardSettings()
    if chunk is None:
        chunk = CHUNK_CPU if client is None and resolve_device(settings.device) == "cpu" else CHUNK_GPU
    if chunk < 1:
        raise ValueError("chunk must be >= 1")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    outputs = list(outputs) if outputs is not None else kernel_metrics()
    rows = [objective(k) for k in outputs]
    cont = space.continuous
    if mode == "grid":
        for v in cont:
            if not v.values:
                raise ValueError(f"grid sweep: variable {v.name!r} needs grid values (NAME=LOW:HIGH:COUNT or a list)")
        dims = [v.name for v in space.variables]
        grids = {v.name: (list(v.choices) if v.categorical else np.asarray(v.values, float)) for v in space.variables}
        shape = tuple(len(grids[d]) for d in dims)
        n = int(np.prod(shape))
    else:
        if not n_samples or n_samples < 1:
            raise ValueError("sobol sweep: give n_samples >= 1")
        if n_samples > SOBOL_MAX_POINTS:
            raise ValueError(f"sobol sweep: at most {SOBOL_MAX_POINTS} points (2^30, the sequence's), got {n_samples}")
        n = int(n_samples)
        shape = (n,)
        dims = ["sample"]
    if parts and client is None:
        raise ValueError("parts=True: the cluster's workers write the parts; give client=")
    from .reductions import parse_reduce

    spec = parse_reduce(reduce or "")
    if spec and client is not None and (raw or parts):
        raise ValueError(
            "reduce with client=: the workers reduce their own points and send back the reductions alone; "
            "give raw=False (--no-raw) and no parts"
        )
    if not raw and not spec:
        raise ValueError("raw=False (--no-raw) keeps only reductions: give reduce= (--reduce)")
    job = _Job(space, mode, seed, outputs, tuple(freqs), settings)
    t0 = time.perf_counter()
    t_eval = t_write = t_reduce = 0.0
    nchunks = 0
    bar = progress_bar(n, "sweep", progress, unit="pt")
    variables = _stored_variables(space, mode, rows) if raw else {}
    ensure_free_space(path, n * sum(np.dtype(dtype).itemsize for dtype, _ in variables.values()))
    reducer, summary = None, None
    if spec:
        from .reductions import Reducer

        reducer = Reducer(
            spec,
            space,
            mode,
            outputs,
            objectives,
            # with a client this one only merges the workers' reductions, on the host
            wp.get_device("cpu" if client is not None else resolve_device(settings.device)),
            1 if client is not None else min(chunk, n),
            [grids[d] for d in dims] if mode == "grid" else None,
        )
    mapped = []  # parts=True: (chunk, index in the file, block shape) of each part written
    try:
        with atomic_path(path) as tmp, atomic_dir(parts_path(path)) if parts else contextlib.nullcontext() as pdir:
            with hdf5_writing(h5netcdf.File(tmp, "w")) as f:
                f.attrs["title"] = "tawarp sweep"
                f.attrs["core"] = str(space.core.source)
                f.attrs["mode"] = mode
                f.attrs["heat_input_W_default"] = space.heat_input
                f.attrs["gradient_definition"] = "(T(x3) - T(x2)) / l_s, steady heat model"
                for k, v in (attrs or {}).items():
                    f.attrs[k] = v
                if mode == "grid":
                    f.dimensions = {d: len(grids[d]) for d in dims}
                    for d in dims:
                        if d == "material":
                            var = f.create_variable(d, (d,), dtype=h5py.string_dtype())
                            var[:] = np.array(grids[d], dtype=object)
                        else:
                            var = f.create_variable(d, (d,), dtype="f8")
                            var[:] = grids[d]
                            var.attrs["units"] = _units(space, d)
                else:
                    f.dimensions = {"sample": n}
                if not parts:  # (parts=True: virtual variables over the parts, made below)
                    for name, (dtype, var_attrs) in variables.items():
                        var = f.create_variable(name, tuple(dims), dtype=dtype)
                        var.attrs.update(var_attrs)
                if mode == "grid":
                    blocks = _blocks(shape, chunk)
                else:
                    blocks = ((lo, min(n, lo + chunk), (slice(lo, min(n, lo + chunk)),)) for lo in range(0, n, chunk))
                if client is None:
                    chunks = _evaluated_here(job, blocks, chunk, n, reducer, raw)
                elif reducer is not None:
                    chunks = _reduced_on(client, job, list(blocks), chunk, reducer)
                else:
                    chunks = _evaluated_on(client, job, blocks, shape, None if pdir is None else str(pdir))
                while True:
                    t = time.perf_counter()
                    done = next(chunks, None)
                    t_eval += time.perf_counter() - t
                    if done is None:
                        break
                    lo, hi, sl, res, values = done
                    t = time.perf_counter()
                    full = sl + tuple(slice(None) for _ in range(len(dims) - len(sl)))
                    sub_shape = _block_shape(sl, shape)
                    if parts:
                        mapped.append((nchunks, full, sub_shape))
                    elif raw:
                        for k in outputs:
                            f.variables[k][full] = res[k].reshape(sub_shape)
                        for name, v in (values or {}).items():
                            f.variables[name][lo:hi] = v
                    t_write += time.perf_counter() - t
                    nchunks += 1
                    bar.update(hi - lo)
            if reducer is not None:  # the groups, written by h5py (Reducer.write) on the closed file
                t = time.perf_counter()
                with hdf5_writing(h5py.File(tmp, "r+")) as h5:
                    summary = reducer.write(h5)["summary"]
                t_reduce = time.perf_counter() - t
            if parts:
                t = time.perf_counter()
                _map_parts(tmp, parts_path(path).name, mapped, variables, dims, shape)
                t_write += time.perf_counter() - t
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    return SweepInfo(path, n, wall, 3600.0 * n / max(wall, 1e-12), nchunks, t_eval, t_write, summary, t_reduce)


def parts_path(path: str | Path) -> Path:
    """The folder of a sweep's part files (``sweep(..., parts=True)``): ``<file name>.parts``
    beside the file, which names its parts relative to its own folder."""
    path = Path(path)
    return path.with_name(path.name + ".parts")


def _part_name(k: int) -> str:
    return f"chunk_{k:07d}.h5"


def _block_shape(sl: tuple, shape: tuple) -> tuple:
    """The shape of a block (:func:`_blocks`) in the file: its index ``sl`` over the leading
    dimensions, the whole of the trailing ones of ``shape``."""
    return tuple(s.stop - s.start if isinstance(s, slice) else 1 for s in sl) + tuple(shape[len(sl) :])


def _stored_variables(space: DesignSpace, mode: str, rows) -> dict:
    """{name: (dtype, attributes)} of the variables a sweep's chunks fill, each over all of
    the file's dimensions: a Sobol sweep's design values (the material as an int8 index
    with CF flags; a Sobol file has the one dimension ``sample``), then the outputs."""
    out = {}
    if mode == "sobol":
        for v in space.continuous:
            out[v.name] = ("f8", {"units": _units(space, v.name)})
        if space.material is not None:
            out["material"] = (
                "i1",
                {
                    "flag_values": np.arange(len(space.material.choices), dtype=np.int8),
                    "flag_meanings": " ".join(space.material.choices),
                },
            )
    for o in rows:
        out[o.name] = ("f4", {"units": o.unit, "long_name": o.long_name})
    return out


def _map_parts(file, folder: str, mapped, variables: dict, dims: list, shape: tuple):
    """Add to the netCDF ``file`` each stored variable as an HDF5 virtual dataset over the
    part files ``folder/chunk_*.h5`` (``mapped``: (chunk, index, block shape) of each),
    with its dimensions attached as netCDF does (read back by h5netcdf, xarray, netCDF-C);
    a missing part reads as the fill value (NaN, -1 for the material index)."""
    import h5py

    with hdf5_writing(h5py.File(file, "r+")) as h5:
        for name, (dtype, var_attrs) in variables.items():
            layout = h5py.VirtualLayout(shape=shape, dtype=dtype)
            for k, full, sub_shape in mapped:
                layout[full] = h5py.VirtualSource(f"{folder}/{_part_name(k)}", name, shape=sub_shape)
            ds = h5.create_virtual_dataset(name, layout, fillvalue=-1 if dtype == "i1" else np.nan)
            ds.attrs.update(var_attrs)
            for i, d in enumerate(dims):
                ds.dims[i].attach_scale(h5[d])


@dataclass(frozen=True)
class _Job:
    """What a sweep's chunks are evaluated with (sent once per task to cluster workers:
    a few kB, no array)."""

    space: DesignSpace
    mode: str
    seed: int
    outputs: list
    freqs: tuple
    settings: ForwardSettings

    def evaluator(self, settings: ForwardSettings) -> Evaluator:
        """The job's Evaluator on the device of ``settings``."""
        return Evaluator(self.space, extra=self.outputs, freqs=self.freqs, settings=settings)

    def table(self, tables: DeviceTable, lo: int, hi: int):
        """(device table, design values on the device or None) of points lo..hi-1."""
        return (tables.grid(lo, hi), None) if self.mode == "grid" else tables.sobol(lo, hi, self.seed)

    def stored_values(self, tables: DeviceTable, values: np.ndarray | None) -> dict | None:
        """A Sobol chunk's design values (len(names), m) as the file stores them:
        ``{name: array}``, the material index as int8; None for a grid (its coordinates say it)."""
        if values is None:
            return None
        return {name: v.astype(np.int8) if name == "material" else v for name, v in zip(tables.names, values)}


def _evaluated_here(job: _Job, blocks, chunk: int, n: int, reducer=None, raw: bool = True):
    """Yield (lo, hi, index, outputs, values) of each block, evaluated in this process on
    ``job.settings``'s device. Chunk k is launched; while the device works (Warp launches
    return at once on CUDA) the caller writes chunk k - 1; then chunk k is fetched: two
    chunks at most on the host, one on the device. ``reducer``
    (:class:`tawarp.design.reductions.Reducer`): chunk k's reductions are launched with it
    and chunk k - 1's candidates merged meanwhile (the device is not left waiting for the
    host between chunks); without ``raw`` nothing else is fetched (outputs and values None)."""
    ev = job.evaluator(job.settings)
    tables = DeviceTable(job.space, ev.device)

    # two host buffers of the float32 columns, alternated: chunk k lands in one while chunk
    # k - 1 is written from the other; page-locked on CUDA, so the copy is one DMA that
    # overlaps the writing and no fresh host array is paged in per chunk
    def host_buffers(rows: int, dtype):
        pinned = wp.get_device(ev.device).is_cuda
        return [wp.empty((rows, min(chunk, n)), dtype=dtype, device="cpu", pinned=pinned) for _ in range(2)]

    host = host_buffers(len(job.outputs), wp.float32) if not ev.extra and raw else None
    # the same for a Sobol sweep's design values (made on the device with its points)
    staged = job.mode == "sobol" and bool(tables.names) and raw
    values_host = host_buffers(len(tables.names), wp.float64) if staged else None
    pending = None
    for k, (lo, hi, sl) in enumerate(blocks):
        if k % GC_CHUNKS == 0 and k:  # before a chunk, not after the last: nothing left to keep flat then
            gc.collect()  # launches leave reference cycles (ctypes structs): keep memory flat
        table, values = job.table(tables, lo, hi)
        reduce = None if reducer is None else functools.partial(reducer.add, k, lo, values)
        finish = _launch(ev, table, job.outputs, host[k % 2] if host else None, reduce, raw)
        if staged:  # queued behind the chunk's evaluation
            for j in range(len(tables.names)):
                wp.copy(values_host[k % 2][j], values[j], count=hi - lo)
        if reducer is not None and k > 0:  # chunk k - 1's candidates, while the device works on chunk k
            reducer.collect(k - 1)
        if pending is not None:
            yield pending
        done = finish()
        if not raw:
            values = None
        if staged:  # (finish() of a chunk with objectives outside the kernel may not wait for the copy)
            wp.synchronize_device(ev.device)
            values = values_host[k % 2].numpy()[:, : hi - lo]
        elif values is not None:
            values = values.numpy()
        pending = (lo, hi, sl, done, job.stored_values(tables, values))
        del table, values, finish
    if reducer is not None and pending is not None:
        reducer.collect(k)
    if pending is not None:
        yield pending


def _evaluated_on(client, job: _Job, blocks, shape: tuple, parts: str | None = None):
    """:func:`_evaluated_here` on the workers of a Dask ``client``: one task per block,
    whose arguments are its point range and the job (:func:`_cluster_chunk`), in order,
    a few blocks in flight per worker (:func:`tawarp.distributed.ordered_map`). With
    ``parts`` (a folder) the workers write the blocks there (as hyperslabs of the file's
    ``shape``) and send back nothing: the outputs and values yielded are None."""
    from ..distributed import ordered_map

    blocks, mine = itertools.tee(blocks)
    tasks = ((k, lo, hi, _block_shape(sl, shape)) for k, (lo, hi, sl) in enumerate(blocks))
    results = ordered_map(client, _cluster_chunk, tasks, uuid.uuid4().hex, job, parts)
    for (lo, hi, sl), (res, values) in zip(mine, results):
        yield lo, hi, sl, res, values


def _reduced_on(client, job: _Job, blocks: list, chunk: int, reducer):
    """Reduce the ``blocks`` on the workers of a Dask ``client``: each worker gets one
    contiguous share of them (their point ranges and the job: no table, no point), runs
    the one-process pipeline over it on its device with its own reducer
    (:func:`_reduce_share`) and sends back that reducer's state alone, merged into
    ``reducer`` here (exactly: :meth:`tawarp.design.reductions.Reducer.merge`). Yields
    (lo, hi, index, None, None) of each block once its worker's share is merged."""
    import distributed

    from ..distributed import worker_addresses

    workers = worker_addresses(client, fresh=True)
    share = -(-len(blocks) // len(workers))
    args = (reducer.spec, reducer.objectives, reducer.grids, chunk, uuid.uuid4().hex)
    futures = {
        client.submit(_reduce_share, blocks[i * share : (i + 1) * share], job, *args, workers=[w], pure=False): i
        for i, w in enumerate(workers)
        if blocks[i * share : (i + 1) * share]
    }
    for fut in distributed.as_completed(futures):
        reducer.merge(fut.result())
        i = futures[fut]
        yield from ((lo, hi, sl, None, None) for lo, hi, sl in blocks[i * share : (i + 1) * share])


def _reduce_share(blocks: list, job: _Job, spec, objectives, grids, chunk: int, key: str) -> dict:
    """The reductions (:meth:`Reducer.state`) of ``blocks`` evaluated on this Dask worker's
    device, as :func:`_evaluated_here` evaluates and reduces them in one process."""
    import dataclasses

    from .reductions import Reducer
    from ..distributed import worker_settings, worker_state

    job = dataclasses.replace(job, settings=worker_settings(job.settings))
    device = wp.get_device(resolve_device(job.settings.device))

    def reducer(m):
        return Reducer(spec, job.space, job.mode, job.outputs, objectives, device, m, grids)

    def load():  # one point through every kernel, under worker_state's lock (module loads)
        for _ in _evaluated_here(job, [(0, 1, (slice(0, 1),))], 1, 1, reducer(1), raw=False):
            pass
        return True

    worker_state(key, load)
    n = sum(hi - lo for lo, hi, _ in blocks)
    mine = reducer(min(chunk, n))
    for _ in _evaluated_here(job, blocks, chunk, n, mine, raw=False):
        pass
    return mine.state()


def _cluster_chunk(task: tuple, key: str, job: _Job, parts: str | None):
    """(outputs, stored values) of the points ``task`` = (chunk k, lo, hi, its block's
    shape in the file) on this Dask worker: the chunk's table made on
    the worker's device (:class:`DeviceTable`, kept with the worker's Evaluator for the
    sweep ``key``) and evaluated there, as one process does. With ``parts`` (a folder) they
    are written to its part file instead, and (None, None) comes back."""
    from ..distributed import worker_settings, worker_state

    def build():
        ev = job.evaluator(worker_settings(job.settings))
        tables = DeviceTable(job.space, ev.device)
        _launch(ev, job.table(tables, 0, 1)[0], job.outputs)()  # loads the modules (worker_state)
        return ev, tables, itertools.count()

    ev, tables, done = worker_state(key, build)
    k, lo, hi, block = task
    table, values = job.table(tables, lo, hi)
    res = _launch(ev, table, job.outputs)()
    values = job.stored_values(tables, None if values is None else values.numpy())
    del table
    if next(done) % GC_CHUNKS == GC_CHUNKS - 1:
        gc.collect()  # as _evaluated_here does
    if parts is None:
        return res, values
    _write_part(Path(parts) / _part_name(k), res, values, block)
    return None, None


def _write_part(path: Path, res: dict, values: dict | None, block: tuple):
    """One chunk's part file: the outputs shaped as its ``block`` of the file's variables,
    a Sobol chunk's design values. Written under a temporary name and renamed (a task run
    again replaces it whole)."""
    import h5py

    with atomic_path(path) as tmp, hdf5_writing(h5py.File(tmp, "w")) as h5:
        for name, v in res.items():
            h5.create_dataset(name, data=v.reshape(block))
        for name, v in (values or {}).items():
            h5.create_dataset(name, data=v)


def _launch(ev: Evaluator, table, outputs: list, host: wp.array | None = None, reduce=None, raw: bool = True):
    """Start the evaluation of a chunk's device ``table``; returns the call that waits
    for its ``outputs`` and returns them as float32 arrays (what the file stores, rounded
    as NumPy rounds). When every output is a kernel column, the device rounds them (half
    the copy, no cast on the host) and copies them into the host buffer ``host``
    (len(outputs), >= chunk) in the same stream: the launches return at once (on CUDA) and
    the call waits for that copy and returns views of it, valid until the buffer's next
    use; without ``host``, new arrays (a cluster worker's, handed to Dask). ``reduce``
    (with the outputs as a (len(outputs), m) float32 device array) launches reductions
    of them; without ``raw`` the call returns None and nothing is copied."""
    out = ev.evaluate_device(table)
    if ev.extra:

        def finish_extra():
            res = {k: np.asarray(v, dtype=np.float32) for k, v in ev.objectives_of(out, table).items() if k in outputs}
            if reduce is not None:  # host objectives: their values go to the device
                reduce(wp.array(np.stack([res[k] for k in outputs]), dtype=wp.float32, device=ev.device))
            return res if raw else None

        return finish_extra
    f32 = ev.metric_columns(out, outputs)
    if reduce is not None:
        reduce(f32)
    if not raw:
        return lambda: None
    if host is None:
        return lambda: dict(zip(outputs, f32.numpy()))
    m = f32.shape[1]
    for j in range(len(outputs)):
        wp.copy(host[j], f32[j], count=m)

    def finish():
        wp.synchronize_device(ev.device)
        arr = host.numpy()
        return {k: arr[j, :m] for j, k in enumerate(outputs)}

    return finish
