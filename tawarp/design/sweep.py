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
next, so memory stays flat whatever the size (two chunks on the host at most). The file is written to a temporary name
beside the target and renamed at the end (:func:`tawarp.io.atomic_path`: nothing
half-written on failure or interruption, normal permissions).
"""

from __future__ import annotations

import gc
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import warp as wp

from .evaluate import DEFAULT_FREQS, Evaluator
from .objectives import kernel_metrics, objective
from .samplers import SOBOL_MAX_POINTS
from .space import DesignSpace, DeviceTable
from ..io import atomic_path
from ..model.forward import ForwardSettings, resolve_device


@dataclass
class SweepInfo:
    """``path``, ``n_points``, ``seconds`` (wall), ``evaluations_per_hour``, ``chunks``,
    ``evaluation_seconds`` (launches, transfers and waiting for the device: the device
    time that the writing did not hide), ``write_seconds``."""

    path: Path
    n_points: int
    seconds: float
    evaluations_per_hour: float
    chunks: int
    evaluation_seconds: float
    write_seconds: float


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
    trailing = [int(np.prod(shape[j + 1:])) for j in range(k)]
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


def sweep(space: DesignSpace, path: str | Path, mode: str = "grid", n_samples: int | None = None,
          chunk: int = 1 << 20, seed: int = 0, settings: ForwardSettings | None = None,
          progress: bool = False, attrs: dict | None = None, outputs=None, freqs=DEFAULT_FREQS,
          client=None) -> SweepInfo:
    """Evaluate ``space`` on a grid (every variable needs ``values``: ``NAME=LOW:HIGH:COUNT``)
    or on ``n_samples`` Sobol points (``mode="sobol"``, variables need ranges) and stream the
    results to the netCDF file ``path``. ``outputs``: objective names written (default: the
    kernel's metrics); ``freqs`` [Hz] for ``acoustic_loss``; ``client``: a Dask
    ``distributed.Client`` whose workers evaluate each chunk in equal shares, one per
    device (:mod:`tawarp.distributed`; the file is the same). See the module docstring."""
    import h5netcdf
    import h5py

    from ..progress import progress_bar

    if mode not in ("grid", "sobol"):
        raise ValueError(f"mode must be 'grid' or 'sobol', got {mode!r}")
    if chunk < 1:
        raise ValueError("chunk must be >= 1")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    settings = settings or ForwardSettings()
    outputs = list(outputs) if outputs is not None else kernel_metrics()
    rows = [objective(k) for k in outputs]
    if client is None:
        ev = Evaluator(space, extra=outputs, freqs=freqs, settings=settings)
    else:
        from ..distributed import ClusterEvaluator

        ev = ClusterEvaluator(client, space, extra=outputs, freqs=freqs, settings=settings)
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
            raise ValueError(f"sobol sweep: at most {SOBOL_MAX_POINTS} points (2^30, the sequence's), "
                             f"got {n_samples}")
        n = int(n_samples)
        shape = (n,)
        dims = ["sample"]
    # each chunk's table is built where it is evaluated (for a cluster, here, then sent)
    tables = DeviceTable(space, ev.device if client is None else resolve_device(settings.device))
    # two host buffers of the float32 columns, alternated: chunk k lands in one while chunk
    # k - 1 is written from the other; page-locked on CUDA, so the copy is one DMA that
    # overlaps the writing and no fresh host array is paged in per chunk
    def host_buffers(rows: int, dtype):
        pinned = wp.get_device(ev.device).is_cuda
        return [wp.empty((rows, min(chunk, n)), dtype=dtype, device="cpu", pinned=pinned) for _ in range(2)]

    host = host_buffers(len(outputs), wp.float32) if isinstance(ev, Evaluator) and not ev.extra else None
    # the same for a Sobol sweep's design values (made on the device with its points)
    staged = isinstance(ev, Evaluator) and mode == "sobol" and bool(tables.names)
    values_host = host_buffers(len(tables.names), wp.float64) if staged else None
    t0 = time.perf_counter()
    t_eval = t_write = 0.0
    nchunks = 0
    bar = progress_bar(n, "sweep", progress, unit="pt")
    try:
        with atomic_path(path) as tmp, h5netcdf.File(tmp, "w") as f:
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
                for v in cont:
                    var = f.create_variable(v.name, ("sample",), dtype="f8")
                    var.attrs["units"] = _units(space, v.name)
                if space.material is not None:
                    var = f.create_variable("material", ("sample",), dtype="i1")
                    var.attrs["flag_values"] = np.arange(len(space.material.choices), dtype=np.int8)
                    var.attrs["flag_meanings"] = " ".join(space.material.choices)
            outs = {}
            for o in rows:
                var = f.create_variable(o.name, tuple(dims), dtype="f4")
                var.attrs["units"] = o.unit
                var.attrs["long_name"] = o.long_name
                outs[o.name] = var
            if mode == "grid":
                blocks = _blocks(shape, chunk)
            else:
                blocks = ((lo, min(n, lo + chunk), (slice(lo, min(n, lo + chunk)),)) for lo in range(0, n, chunk))

            def write(lo, hi, sl, res, values):
                nonlocal t_write
                t = time.perf_counter()
                block = tuple(s.stop - s.start if isinstance(s, slice) else 1 for s in sl)
                full = sl + tuple(slice(None) for _ in range(len(dims) - len(sl)))
                sub_shape = block + tuple(shape[len(sl):])
                for k in outputs:
                    outs[k][full] = np.asarray(res[k], dtype=np.float32).reshape(sub_shape)
                if values is not None:
                    for j, name in enumerate(tables.names):
                        v = values[j].astype(np.int8) if name == "material" else values[j]
                        f.variables[name][lo:hi] = v
                t_write += time.perf_counter() - t
                bar.update(hi - lo)

            # chunk k is launched; while the device works (Warp launches return at once on
            # CUDA) chunk k - 1 is written; then chunk k is fetched: two chunks at most on the
            # host, one on the device
            pending = None
            for lo, hi, sl in blocks:
                t = time.perf_counter()
                table, values = (tables.grid(lo, hi), None) if mode == "grid" else tables.sobol(lo, hi, seed)
                finish = _launch(ev, table, outputs, host[nchunks % 2] if host else None)
                if staged:   # queued behind the chunk's evaluation
                    for j in range(len(tables.names)):
                        wp.copy(values_host[nchunks % 2][j], values[j], count=hi - lo)
                t_eval += time.perf_counter() - t
                if pending is not None:
                    write(*pending)
                t = time.perf_counter()
                done = finish()
                if staged:   # (finish() of a chunk with objectives outside the kernel may not wait for the copy)
                    wp.synchronize_device(ev.device)
                    values = values_host[nchunks % 2].numpy()[:, :hi - lo]
                elif values is not None:
                    values = values.numpy()
                pending = (lo, hi, sl, done, values)
                t_eval += time.perf_counter() - t
                nchunks += 1
                del table, values, finish
                if nchunks % 16 == 0:
                    gc.collect()  # launches leave reference cycles (ctypes structs): keep memory flat
            if pending is not None:
                write(*pending)
    finally:
        bar.close()
    wall = time.perf_counter() - t0
    return SweepInfo(path, n, wall, 3600.0 * n / max(wall, 1e-12), nchunks, t_eval, t_write)


def _launch(ev, table, outputs: list, host: wp.array | None):
    """Start the evaluation of a chunk's device ``table``; returns the call that waits
    for its ``outputs``. An :class:`Evaluator` launches and returns at once (on CUDA), and
    when every output is a kernel column rounds them to float32 on the device (half the
    copy, no cast on the host) and copies them into the host buffer ``host`` (len(outputs),
    >= chunk) in the same stream; the call waits for that copy and returns views of it,
    valid until the buffer's next use. A cluster evaluator works in that call."""
    if not isinstance(ev, Evaluator):
        return lambda: ev.evaluate_table(table)
    out = ev.evaluate_device(table)
    if ev.extra:
        return lambda: ev.objectives_of(out, table)
    f32 = ev.columns_float32(out, outputs)
    m = f32.shape[1]
    for j in range(len(outputs)):
        wp.copy(host[j], f32[j], count=m)

    def finish():
        wp.synchronize_device(ev.device)
        arr = host.numpy()
        return {k: arr[j, :m] for j, k in enumerate(outputs)}

    return finish
