"""Batched forward model: T-matrices and temperature profiles of a core on Warp.

>>> from tawarp import load_core, transfer_matrices
>>> core = load_core("ceramic")
>>> res = transfer_matrices(core, freqs=[50, 100, 200], heat_input=[0, 40],
...                         params={"stack.h": [150, 120]}, device="cpu")
>>> res.T.shape            # (parameter sets, frequencies, 2, 2), complex
(2, 3, 2, 2)

A batch is n parameter sets (the broadcast length of ``heat_input`` and of every array
in ``params``, keyed ``SEGMENT.FIELD``) times m frequencies; each (set, frequency) is one
thread of the cascade kernel. The same code runs on ``device="cpu"`` and ``"cuda"``.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import math
import os
import threading
import warnings
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import warp as wp

from .coefficients import duct_impedance, normalize
from .core import Core, CoreError, check_values, segment_parameter_fields
from .fields import GLOBAL_FIELD_TABLE, NONLINEAR_FIELDS, SEGMENT_FIELD_TABLE, SEGMENT_FIELDS
from .gas import GASES
from .warm_starts import WARM_SETS, DeviceWarmStarts, WarmStarts
from .validity import (
    MAX_CELLS,
    ModelValidityError,
    ValidityWarning,
    check_frequencies,
    check_heat_inputs,
    check_precision,
    check_results,
    check_sets,
    describe_set,
)
from ..progress import progress_bar
from ..kernels import batch as kbatch
from ..kernels import forward as kf
from ..kernels import heat as kheat
from ..kernels import layout
from ..kernels.acoustics import PointCoefficients
from ..kernels.pore_table import circular_table

#: Default adaptive cell density (ForwardSettings). bench/forward.py measures the
#: accuracy of each setting against the converged NumPy reference.
DEFAULT_CELL_DENSITY = 1.5
#: Default relative error target of the adaptive cells (ForwardSettings.tolerance).
DEFAULT_TOLERANCE = 1e-6
#: Order of the Magnus scheme: a cell's error falls as (its length)^6 (tests/test_forward.py).
MAGNUS_ORDER = 6
#: Most rounds of the error estimate (each raises a set's density by 1.25x to 4x).
MAX_ESTIMATE_ROUNDS = 8
#: Largest raise of a set's density over ``cell_density`` (64^6 ~ 7e10 times less error).
MAX_DENSITY_FACTOR = 64.0
#: Memory [bytes] for the Gauss points of a cascade launch on the CPU, and the most on a
#: GPU (there at most a quarter of its free memory): a larger batch runs in blocks of sets
#: (:meth:`Engine._cascade`). On the GPU each block's last wave of threads leaves the
#: device part idle, so blocks are made large.
POINT_BUFFER_BYTES = 1 << 28
POINT_BUFFER_BYTES_GPU = 1 << 32
#: Points of a GPU launch below which its block is not sized from the free memory.
POINT_BUFFER_ASK_BYTES = 1 << 26
#: Step of the central differences of the Gauss points' coefficients that seed the tangent
#: cascade (:meth:`Engine.evaluate_tangents`), in scaled parameters: truncation ~ step^2,
#: rounding ~ 1e-16/step, both ~1e-10 relative at 1e-5 (tests/test_tangents.py). When the
#: heat solve iterates (a temperature-dependent effect) it stops at a change of
#: ``picard_tol`` = 1e-12, which a difference divides by the step: 1e-4 there (~1e-8).
TANGENT_STEP = 1e-5
TANGENT_STEP_NONLINEAR = 1e-4
#: Register cap of the tangent cascade's CUDA threads (None: none; it carries P more
#: matrices than the plain cascade: measurements in bench/README.md, "fits").
TANGENT_MAX_REGISTERS = None
#: Bytes of T-matrices that :meth:`Engine.distinct` keeps of a CPU engine's columns,
#: the least recently asked for given up first: a loop's later batches ask again for parameter
#: sets an earlier one computed (a fit continued from where it stopped, a start at a relative's
#: solution; 4 % of the columns of the loop bench's T-matrix cases), and on the CPU a column
#: costs about a millisecond, its look-up microseconds.
MEMO_BYTES = 32 << 20


class ColumnMemo:
    """A least-recently-used store {key: T-matrices (m, 2, 2)} of at most ``limit`` bytes,
    safe to share between threads."""

    def __init__(self, limit: int):
        self.limit, self.size = limit, 0
        self.items: OrderedDict = OrderedDict()
        self.lock = threading.Lock()

    def get(self, keys: list) -> list:
        """The stored value of each of ``keys``, None where there is none."""
        with self.lock:
            out = [self.items.get(k) for k in keys]
            for k, v in zip(keys, out):
                if v is not None:
                    self.items.move_to_end(k)
            return out

    def put(self, keys: list, values) -> None:
        """Store ``values`` (copies) under ``keys``."""
        with self.lock:
            for k, v in zip(keys, values):
                if k not in self.items:
                    self.items[k] = v = np.array(v)
                    self.size += v.nbytes
            while self.size > self.limit:
                self.size -= self.items.popitem(last=False)[1].nbytes


_MEMO = ColumnMemo(MEMO_BYTES)

#: Each engine's key in the memo: a number never given twice, so that the memo holds no
#: engine alive (an engine's entries age out after it goes) and a later engine never reads
#: an earlier one's columns.
_ENGINE_NUMBERS = itertools.count()


#: Iterations of the temperature-dependent heat solve launched between reads of how many
#: sets still iterate (:meth:`Engine._iterate_cells`): a warm-started set takes two or three,
#: a cold start four to a dozen; a read costs a round trip to the device.
PICARD_BURST = 4


def distinct_columns(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first, column) of the distinct columns of ``key`` (rows, n): ``first`` each one's
    first column, ``column`` (n,) which one each column is, the distinct ones ordered by
    the first row (the heat input) and, within one value of it, by a projection of the
    others. Equal columns project to equal numbers, so sorted on (first row, projection)
    they lie side by side and a comparison of neighbours in full tells them apart: one sort
    of two keys, where a lexicographic sort of every row (``np.unique(key, axis=1)``, or
    ``np.lexsort``) takes one pass a row. Two columns that differ can project alike only
    by rounding (each row is taken from its least value, scaled to its range); they are
    then kept apart, at worst a copy computed twice, never two columns merged. A column
    with NaN is distinct."""
    n = key.shape[1]
    lead = key[0] if key.shape[0] else np.zeros(n)
    if n:
        # a row alike in every column neither orders nor tells columns apart (most of a
        # fit's varying rows are alike in a batch)
        low, high = key.min(axis=1), key.max(axis=1)
        varies = ~(low == high)
        key, low, high = key[varies], low[varies], high[varies]
    if key.shape[0]:
        # row by row, the same operations in the same order for every column (a BLAS
        # product may round a column at the end of a block differently from its copies)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            scale = _projection_weights(key.shape[0]) / (high - low)
            projection = ((key - low[:, None]) * scale[:, None]).sum(axis=0)
        order = np.lexsort((projection, lead))
    else:
        order = np.arange(n)
    ranked = key[:, order]
    new = np.ones(n, dtype=bool)
    new[1:] = np.any(ranked[:, 1:] != ranked[:, :-1], axis=0)
    column = np.empty(n, dtype=np.int64)
    column[order] = np.cumsum(new) - 1
    return order[new], column


@functools.lru_cache(maxsize=None)
def _projection_weights(rows: int) -> np.ndarray:
    """Weights in [1, 2) of :func:`distinct_columns`' projection, no two alike: the
    fractional parts of multiples of the golden ratio (an evenly spread sequence)."""
    return 1.0 + np.modf(np.arange(1, rows + 1) * 0.6180339887498949)[0]


#: Segment fields that only the heat solve reads (kernels/heat.py): without heat input the
#: temperature rise is zero whatever their values, and with fixed cells a set's T-matrices do
#: not depend on them (:meth:`Engine.distinct`; tests/test_forward.py guards it).
HEAT_ONLY_FIELDS = (
    "h",
    "solid_conductivity",
    "conductivity_exponent",
    "radiative_conductivity",
    "h_convection",
    "wall_conductance",
    "wall_resistance",
    "end_conductance",
    "contact_resistance",
)
#: Bytes of one point (:class:`tawarp.kernels.acoustics.PointCoefficients`: six float64) and
#: its cell's length (the point kernel's ``spans``: one float64).
POINT_BYTES = wp.types.type_size_in_bytes(PointCoefficients) + 8


#: The first rerun of the error estimate (:meth:`Engine._adapted`) is queued before the
#: host knows how many sets it takes: room for RERUN_ROOM times the share of sets the
#: engine's last evaluation raised (INITIAL_RAISED_SHARE before any) plus RERUN_SLOTS. An
#: empty slot costs a set without cells; a set beyond the room waits for the next rerun
#: (bench/README.md, "The estimate's reruns on the device").
RERUN_ROOM = 1.25
RERUN_SLOTS = 32
INITIAL_RAISED_SHARE = 1.0 / 16.0


def point_room(factor: float, counts: np.ndarray, columns: int) -> tuple[int, int]:
    """(points, point-kernel slots) room for a set of ``columns`` cell columns whose density
    is at most ``factor`` times what it was in a launch whose largest counts (``most`` of
    :func:`tawarp.kernels.forward.cell_counts`) were ``counts``: a column's n = ceil(d s X)
    cells become at most factor n + 1, its refined grid's n + ceil(n/2) at most factor
    times its own + 2, so each column adds at most 6 points and 2 slots to factor times the
    old counts (8 and 3 allowed: a product's rounding)."""
    return int(factor * counts[0]) + 8 * columns, int(factor * counts[1]) + 3 * columns


def default_device() -> str:
    """``"cuda"`` when Warp sees a GPU, else ``"cpu"``."""
    wp.init()
    return "cuda" if wp.is_cuda_available() else "cpu"


def resolve_device(device: str | None) -> str:
    """Validate a device name (``cpu``, ``cuda``, ``cuda:N``); ``None`` picks the default."""
    if device is None:
        return default_device()
    wp.init()
    if device.startswith("cuda") and not wp.is_cuda_available():
        raise ValueError(f"device {device!r} requested but Warp finds no CUDA GPU; use device 'cpu'")
    try:
        wp.get_device(device)
    except (RuntimeError, ValueError):
        raise ValueError(f"device {device!r}: unknown; expected cpu, cuda or cuda:N") from None
    return device


#: Freed device memory a CUDA memory pool keeps for reuse across synchronizations, as a
#: fraction of the device's memory (:func:`keep_pool_memory`; 0: CUDA's default).
POOL_KEEP = 0.25


def keep_pool_memory(device: str) -> None:
    """Let ``device``'s memory pool keep up to :data:`POOL_KEEP` of its memory in freed
    blocks. An evaluation allocates its tables and T-matrices anew (GBs for 1e5 sets), and
    with CUDA's default threshold of 0 every host read (a synchronization) hands the freed
    blocks back to the driver, so the next evaluation maps its memory again. A threshold
    set higher elsewhere is kept; nothing on the CPU or without a pool."""
    dev = wp.get_device(device)
    if dev.is_cuda and wp.is_mempool_enabled(dev):
        keep = int(POOL_KEEP * dev.total_memory)
        if wp.get_mempool_release_threshold(dev) < keep:
            wp.set_mempool_release_threshold(dev, keep)


def parameter_row(core: Core, name: str) -> int:
    """Row of parameter ``name`` in the kernels' parameter table."""
    if name in GLOBAL_FIELD_TABLE:
        return GLOBAL_FIELD_TABLE[name].row
    seg, _, fld = name.partition(".")
    s = next((i for i, x in enumerate(core.segments) if x.name == seg), None)
    # the segment's own fields (the core's whole list of names, built per call, was most
    # of an engine's construction)
    if s is None or fld not in segment_parameter_fields(core.segments[s]):
        raise KeyError(
            f"{name!r} is not a parameter of core {core.source}; parameters are {', '.join(core.parameter_names())}"
        )
    return layout.N_GLOBAL + s * layout.N_FIELDS + SEGMENT_FIELDS[fld].row


def base_table(core: Core) -> np.ndarray:
    """The core's own values as one column of the parameter table, shape (rows,)."""
    base = np.zeros(layout.N_GLOBAL + len(core.segments) * layout.N_FIELDS)
    for name, f in GLOBAL_FIELD_TABLE.items():
        base[f.row] = core.get(name)
    for s, seg in enumerate(core.segments):
        for f in SEGMENT_FIELD_TABLE:
            v = core.get(f"{seg.name}.{f.name}")
            base[layout.N_GLOBAL + s * layout.N_FIELDS + f.row] = v if math.isfinite(v) else 0.0
    return base


def structure_flags(core: Core) -> np.ndarray:
    """Per-segment structure (porous, pore model, thermal, heater, imposed temperatures) as
    int32 (nseg, layout.N_FLAGS)."""
    from ..kernels.pore import PORE_CIRCULAR, pore_model_code

    return np.array(
        [
            [
                s.is_porous,
                pore_model_code(s.pore_model, s.pore_shape) if s.is_porous else PORE_CIRCULAR,
                s.thermal,
                s.heater,
                s.imposed,
            ]
            for s in core.segments
        ],
        dtype=np.int32,
    )


@dataclass
class ForwardResult:
    """Result of a batched forward run.

    ``T`` (n, m, 2, 2) complex: core T-matrices, exp(-iwt), ``(p, U)(x6) = T (p, U)(x1)``.
    ``freqs`` (m,) [Hz]; ``heat_input`` (n,) [W]; ``theta`` (n, nodes) nodal temperature
    excess [K] of the heat grid (n, 2 nodes where the wall may be a field of its own,
    :func:`wall_field`: the wall's excess in the second half); ``params`` (rows, n) the table the kernels read.
    """

    core: Core
    freqs: np.ndarray
    heat_input: np.ndarray
    T: np.ndarray
    theta: np.ndarray
    params: np.ndarray
    settings: "ForwardSettings"

    def dimensionless(self) -> np.ndarray:
        """(n, m, 4): ``Tpp, Tpu/Zc, Tup*Zc, Tuu`` with the core's cold duct impedance."""
        return normalize(self.T, duct_impedance(self.core))

    def temperature(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """T(x) [K] and dT/dx [K/m], each (n, len(x)), at positions x [m] from plane x1."""
        engine = Engine(self.core, self.freqs, (), self.settings)
        dev = engine.device
        return engine.temperature(
            wp.array(self.params, dtype=wp.float64, device=dev), wp.array(self.theta, dtype=wp.float64, device=dev), x
        )


@dataclass(frozen=True)
class ForwardSettings:
    """Numerical settings.

    ``cells = None`` (default): the Magnus cells of a thermal segment are
    ``ceil(d s (1 + k L + w L / c))`` (k the heat model's decay rate, w/c the cold
    wavenumber at the batch's highest frequency; s <= 1 the share of them a grid graded to
    the heat model's excess needs for the same error,
    :func:`tawarp.kernels.forward.graded_share`, 1 on a uniform grid), adapted per
    parameter set: one grid
    serves all of a set's frequencies, whose Gauss-point factors are computed once
    (:func:`tawarp.kernels.forward.make_point_kernel`). The density d of each set
    starts at ``cell_density`` and is raised until an error estimate is below
    ``tolerance``/2: Richardson's estimate (the cascade on the set's cells against the
    refined grid's, n + ceil(n/2) cells where it has n, whose difference times
    1/(1 - 1.5^-6) is the error on the n cells, the scheme being sixth order:
    :func:`tawarp.kernels.forward.refined_cells`) at the lowest, geometric middle and
    highest frequency of the batch, on the row-relative dimensionless error
    (:meth:`Engine._adapted`: the refined cascades run in the main launch, whose
    values at the sampled frequencies they are compared with on the device, and only the
    sets above target run again); ``tolerance = None`` keeps d = ``cell_density`` (the
    rule alone meets 1e-6 on the paper-like cores, README, "How the forward model works",
    but not on every core in the documented ranges). ``cells`` = an int,
    or a dict segment name -> int, fixes the count per thermal segment instead, as
    convergence studies need (a set without heat input takes none: its parts are at the
    cold temperature, and exp(A L) is exact). The adaptive count jumps by whole cells as k (h, the
    conductivities) or w change, so the model is piecewise smooth in those parameters at
    the 1e-7 level: finite-difference Jacobians must use fixed cells
    (:func:`tawarp.measure.kind.smooth_settings` picks them). ``heat_cells``: heat-grid cells per thermal segment;
    ``fitted``: exact (exponentially fitted) heat scheme, else plain second order;
    ``chunk``: parameter sets per launch (bounds device memory); ``block_dim``: GPU
    threads per block of the cascade kernel (bench/forward.py compares values);
    ``max_registers``: register cap of a CUDA thread of the plain cascade (None: none;
    measurements in bench/README.md; the tangent cascade's is :data:`TANGENT_MAX_REGISTERS`);
    ``cpu_threads``: on the CPU, Warp runs a kernel serially, so a batch is split into
    this many parts run in parallel threads (Warp's CPU launches release the GIL; None:
    every core this process may use; results are bit-for-bit those of one thread);
    ``cell_threads``: the iterations of a temperature-dependent heat solve run as launches
    with a thread per heat cell (:func:`tawarp.kernels.forward.heat_rows_kernel`; None: on a
    GPU, where one thread per set iterating over its cells was most of a loop's device time;
    the same numbers to rounding; the cells' rows take 48 bytes a cell, 4.6 kB a set of 97
    heat nodes, 0.3 GB at the default ``chunk``, and 168 bytes a cell where the wall may be a
    field of its own, 1.1 GB at the default ``chunk``); ``device``.
    When a temperature-dependent effect (``fields.NONLINEAR_FIELDS``) is on in the core or
    varies in the batch, the heat grid has at least ``nonlinear_heat_cells`` cells per
    segment and the heat solve iterates (Kirchhoff cells, kernels/heat.py: at most ``picard_iterations`` solves,
    until the largest nodal change is below ``picard_tol`` of the largest theta)."""

    cells: int | dict | None = None
    cell_density: float = DEFAULT_CELL_DENSITY
    tolerance: float | None = DEFAULT_TOLERANCE
    heat_cells: int = 1
    nonlinear_heat_cells: int = 32
    picard_iterations: int = 100
    picard_tol: float = 1e-12
    fitted: bool = True
    chunk: int = 1 << 16
    block_dim: int = 256
    max_registers: int | None = 128
    cpu_threads: int | None = None
    cell_threads: bool | None = None
    device: str | None = None

    def cells_per_segment(self, core: Core) -> np.ndarray:
        """Fixed Magnus cells per segment, 0 where the count adapts (``cells = None``)."""
        if self.cells is None:
            if not self.cell_density > 0:
                raise ValueError(f"cell_density must be > 0, got {self.cell_density}")
            return np.zeros(len(core.segments), dtype=np.int32)
        if isinstance(self.cells, dict):
            unknown = set(self.cells) - {s.name for s in core.segments}
            if unknown:
                raise KeyError(f"cells given for unknown segment(s) {sorted(unknown)}")
            missing = [s.name for s in core.segments if s.thermal and s.name not in self.cells]
            if missing:
                raise KeyError(f"cells missing for thermal segment(s) {missing}")
            counts = [self.cells.get(s.name, 1) for s in core.segments]
        else:
            counts = [self.cells] * len(core.segments)
        if any(not 1 <= int(c) <= MAX_CELLS for c in counts):
            raise ValueError(
                f"Magnus cells must lie in [1, {MAX_CELLS}] per segment, got {self.cells} (a count "
                f"sized this large means an extreme h, length or frequency: docs/trusted_ranges.md)"
            )
        return np.array(counts, dtype=np.int32)


def _thermal_range(core: Core) -> tuple[int, int]:
    idx = core.thermal_indices
    return (idx[0], len(idx)) if idx else (0, 0)


def broadcast_batch(core: Core, heat_input, params: dict | None) -> tuple[int, np.ndarray, dict[str, np.ndarray]]:
    """Check names and values, broadcast to a common batch length n."""
    params = dict(params or {})
    arrays = {"heat_input": np.atleast_1d(np.asarray(heat_input, dtype=np.float64))}
    for name, v in params.items():
        parameter_row(core, name)  # raises for unknown names
        arrays[name] = np.atleast_1d(np.asarray(v, dtype=np.float64))
    try:
        shape = np.broadcast_shapes(*(a.shape for a in arrays.values()))
    except ValueError:
        raise ValueError(f"batch arrays do not broadcast: { {k: a.shape for k, a in arrays.items()} }") from None
    if len(shape) != 1:
        raise ValueError(f"batch arrays must be 1-D, got shape {shape}")
    n = shape[0]
    out = {k: np.broadcast_to(a, (n,)) for k, a in arrays.items()}
    q = out.pop("heat_input")
    if not np.all(np.isfinite(q)) or np.any(q < 0):
        raise CoreError(f"heat_input [W]: must be finite and >= 0, got {q[~(np.isfinite(q) & (q >= 0))][:3]}")
    check_heat_inputs(q)
    if np.any(q > 0) and not core.thermal_indices:
        raise CoreError(f"{core.source}: heat_input > 0 but the core has no thermal segment with heater = true")
    for name, a in out.items():
        check_values(name.partition(".")[2], a, f"parameter {name}")
    return n, q, out


def nonlinear_heat(core: Core, names=()) -> bool:
    """True when a temperature-dependent effect is on in a thermal segment of ``core``
    or among the varying parameter ``names``."""
    if any(n.partition(".")[2] in NONLINEAR_FIELDS for n in names):
        return True
    return any(getattr(core.segments[i], f) != 0.0 for i in core.thermal_indices for f in NONLINEAR_FIELDS)


def wall_field(core: Core, names=()) -> bool:
    """True when the wall may be a temperature field of its own in a set of a batch of
    ``core`` varying ``names`` (a ``wall_resistance`` varies or is not 0 in a thermal
    segment): the heat solve then stores the wall's nodal excess beside the gas's
    (kernels/heat.py, :func:`tawarp.kernels.heat.solve_heat_wall`)."""
    if any(n.partition(".")[2] == "wall_resistance" for n in names):
        return True
    return any(core.segments[i].wall_resistance != 0.0 for i in core.thermal_indices)


def plain_parts(core: Core, names=()) -> bool:
    """True when every part of a batch of ``core`` varying ``names`` is plain
    (:func:`tawarp.kernels.acoustics.plain_part`: circular pores or a duct, a rigid frame, no
    viscous shape factor, no bypass gap): its value cascade compiles without the other parts' code
    (:func:`tawarp.kernels.forward.make_transfer_kernel`'s ``plain``)."""
    from ..kernels.pore import PORE_CIRCULAR

    base = base_table(core)
    models = structure_flags(core)[:, layout.F_PORE_MODEL]
    varied = {parameter_row(core, name) for name in names}
    for s, seg in enumerate(core.segments):
        if not seg.is_porous:
            continue
        row = layout.N_GLOBAL + s * layout.N_FIELDS
        mobility, shape = row + layout.FRAME_MOBILITY, row + layout.VISCOUS_SHAPE_FACTOR
        gap = row + layout.BYPASS_GAP
        if models[s] != PORE_CIRCULAR or mobility in varied or shape in varied or gap in varied:
            return False
        if not (base[mobility] <= 0.0 and (base[shape] == 1.0 or base[shape] <= 0.0) and base[gap] <= 0.0):
            return False
    return True


class Engine:
    """A compiled batch layout: one core structure, one frequency grid, a fixed list of
    varying parameters; evaluates device-resident batches with no host round trip.

    ``names`` are the parameters that vary across the batch (``heat_input`` is always
    the first varying row). :meth:`evaluate` takes a (1 + len(names), n) float64 array
    (NumPy or a Warp array on the engine's device) and returns Warp arrays on the device:
    ``out`` (n, m, 8) float64 = (Tpp, Tpu, Tup, Tuu) as (re, im), and ``theta`` (n, ``theta_columns``): the nodal
    excesses, the wall's after the gas's where it may be a field of its own (:func:`wall_field`).
    ``out.numpy().view(complex).reshape(n, m, 2, 2)`` gives the T-matrices; Warp arrays
    share memory with PyTorch/CuPy through ``__cuda_array_interface__``.
    """

    def __init__(self, core: Core, freqs, names=(), settings: ForwardSettings | None = None):
        self.settings = settings or ForwardSettings()
        self.device = resolve_device(self.settings.device)
        self.number = next(_ENGINE_NUMBERS)  # (its key in the memo of computed columns)
        keep_pool_memory(self.device)
        self.core = core
        self.freqs = np.atleast_1d(np.asarray(freqs, dtype=np.float64))
        if self.freqs.ndim != 1 or not np.all(np.isfinite(self.freqs)) or np.any(self.freqs <= 0):
            raise ValueError("freqs [Hz] must be a 1-D array of positive finite values")
        check_frequencies(self.freqs)
        self.names = list(names)
        self.rows = np.array([layout.HEAT_INPUT] + [parameter_row(core, k) for k in self.names], dtype=np.int32)
        self.first, self.count = _thermal_range(core)
        self.heat_cells = int(self.settings.heat_cells)
        if self.heat_cells < 1:
            raise ValueError(f"heat_cells must be >= 1, got {self.heat_cells}")
        self.nonlinear = nonlinear_heat(core, self.names)
        if self.nonlinear:
            self.heat_cells = max(self.heat_cells, int(self.settings.nonlinear_heat_cells))
        self.nodes = self.count * self.heat_cells + 1
        threads = self.settings.cell_threads
        self.cell_threads = (
            self.nonlinear
            and self.count > 0
            and (wp.get_device(self.device).is_cuda if threads is None else bool(threads))
        )
        # nodal excesses per set: the gas's, then the wall's where it is a field of its own
        self.theta_columns = self.nodes * (2 if wall_field(core, self.names) else 1)
        # the stored rows of a heat cell where the heat solve iterates a thread per cell: the
        # two fields' blocks where the wall may be a field of its own
        self.row_values = int(kheat.WALL_ROW_VALUES if self.theta_columns > self.nodes else kf.ROW_VALUES)
        dev = self.device
        self.base = wp.array(base_table(core), dtype=wp.float64, device=dev)
        self.flags = wp.array(structure_flags(core), dtype=wp.int32, device=dev)
        self.gas = wp.array(GASES[core.gas.name].as_tuple(), dtype=wp.float64, device=dev)
        self.seg_cells = wp.array(self.settings.cells_per_segment(core), dtype=wp.int32, device=dev)
        self.w_rows = wp.array(self.rows, dtype=wp.int32, device=dev)
        s = self.settings
        # Magnus cells (and their error estimate) where a temperature varies along a segment
        self.graded = self.count > 0 or any(seg.imposed for seg in core.segments)
        self.estimating = s.cells is None and s.tolerance is not None and self.graded
        # the error estimate's frequencies: the grid's lowest, geometric middle and highest
        f = self.freqs
        self.sample = (
            np.unique(np.abs(f[:, None] - np.geomspace(f.min(), f.max(), 3)[None]).argmin(0))
            if self.estimating
            else np.zeros(0, dtype=np.int64)
        )
        self.columns = self._columns(f, self.sample)  # evaluate
        self.sample_columns = self._columns(f[self.sample], np.arange(self.sample.size))  # cell_densities
        self.pore_table = circular_table(dev, structure_flags(core)[:, 1])
        self.omega_max = 2.0 * math.pi * float(self.freqs.max())
        self.plain = plain_parts(core, self.names)
        self.transfer_kernel = _transfer_kernel(self.settings.max_registers, 0, self.plain)
        self.point_kernel = _point_kernel(self.nonlinear)
        # the plain cascade's stand-ins for the tangent kernel's step and tangent arrays
        self._no_step = wp.zeros((1, 1), dtype=wp.float64, device=dev)
        self._no_tangent = wp.zeros((1, 1, 1, 1), dtype=wp.float64, device=dev)
        self._no_order = wp.zeros(0, dtype=wp.int32, device=dev)
        # the heat kernel's stand-ins for the tables of the iterations a cell per thread
        self._no_rows = wp.zeros((1, 1), dtype=wp.float64, device=dev)
        self._no_pending = wp.zeros(0, dtype=wp.int32, device=dev)
        self._modules_loaded = set()  # strides whose modules a thread of _threaded has loaded
        self._raised_share = INITIAL_RAISED_SHARE  # of the last evaluation's first rerun (RERUN_ROOM)
        self._point_counts: dict = {}  # _fixed_point_counts per number of grid columns
        # queue each rerun of the error estimate before its count is read back (_adapted): a
        # GPU's launches run behind the host, which would wait on each read; a CPU's launch has
        # ended when it returns, so there the count costs nothing and a rerun takes its sets alone
        self.queue_ahead = wp.get_device(dev).is_cuda
        # rows of the varying table that a set without heat input does not read (fixed cells:
        # no count adapts to them; no imposed temperatures)
        inert = s.cells is not None and not any(seg.imposed for seg in core.segments)
        self.heat_only = np.array(
            [1 + j for j, k in enumerate(self.names) if inert and k.partition(".")[2] in HEAT_ONLY_FIELDS], dtype=int
        )
        # a temperature-dependent set's heat solve costs about as much as its cascade on the
        # CPU, and on a GPU, where one thread iterates it, most of a loop's device time
        # (distinct keeps the converged excesses as warm starts)
        self.warm = None
        if self.nonlinear and self.count:
            thermal = {core.segments[k].name for k in core.thermal_indices}
            switch = [n.partition(".") for n in self.names]
            switches = [1 + j for j, (seg, _, f) in enumerate(switch) if seg in thermal and f in NONLINEAR_FIELDS]
            always = any(
                getattr(core.segments[k], f) != 0.0 and f"{core.segments[k].name}.{f}" not in self.names
                for k in core.thermal_indices
                for f in NONLINEAR_FIELDS
            )
            rows = 1 + len(self.names)
            store = WarmStarts if wp.get_device(dev).is_cpu else functools.partial(DeviceWarmStarts, device=dev)
            self.warm = store(WARM_SETS, rows, self.theta_columns, np.array(switches, dtype=int), always)

    def _sets(self, params: wp.array) -> kf.SetTable:
        """The kernels' :class:`tawarp.kernels.forward.SetTable` of ``params`` (rows, n)."""
        sets = kf.SetTable()
        sets.params = params
        sets.flags = self.flags
        sets.gas = self.gas
        return sets

    def heat_buffers(self, n: int) -> tuple[wp.array, wp.array, wp.array | None]:
        """(params, theta, scratch) for :meth:`heat` of ``n`` sets, on the device: a caller that
        solves batches of one size again and again keeps them (no allocation per batch)."""
        params = wp.empty((self.base.shape[0], n), dtype=wp.float64, device=self.device)
        theta = wp.empty((n, self.theta_columns), dtype=wp.float64, device=self.device)
        # the Thomas sweep's super-diagonal and the previous iterate: 2 per node, 6 with the wall
        width = (6 if self.theta_columns > self.nodes else 2) * self.nodes
        scratch = wp.empty((n, width), dtype=wp.float64, device=self.device) if self.count else None
        return params, theta, scratch

    def device_table(self, varying) -> wp.array:
        """A host table ``varying`` (1 + len(names), n) on the engine's device, its heat
        inputs checked (:func:`tawarp.model.validity.check_heat_inputs`)."""
        check_heat_inputs(np.asarray(varying)[0])
        return wp.array(np.ascontiguousarray(varying, dtype=np.float64), dtype=wp.float64, device=self.device)

    def heat(self, varying, start: np.ndarray | None = None, out: tuple | None = None) -> tuple[wp.array, wp.array]:
        """Expand the parameter table and solve the heat model: (params, theta) on the device.
        ``start`` (n, ``theta_columns``, a host array or a Warp array on the device): the
        iterations' start per set where the heat solve iterates
        (:func:`tawarp.kernels.heat.solve_heat`; rows of zeros: the cold start, the default;
        a row of a set without heat input must be zeros). ``out``: the arrays of
        :meth:`heat_buffers` to solve into, else new ones."""
        if not isinstance(varying, wp.array):  # (a device table's values were checked where they were made)
            varying = self.device_table(varying)
        n = varying.shape[1]
        params, theta, scratch = self.heat_buffers(n) if out is None else out
        if start is None:
            theta.zero_()
        else:
            theta.assign(start if isinstance(start, wp.array) else np.ascontiguousarray(start, dtype=np.float64))
        wp.launch(kf.expand_parameters, dim=n, inputs=[self.base, varying, self.w_rows, params], device=self.device)
        if self.count:
            rows, pending = self._no_rows, self._no_pending
            # a graph being captured (a design search's generation) cannot wait on a count:
            # there every set iterates in the heat kernel's thread
            if self.cell_threads and n and not wp.get_device(self.device).is_capturing:
                rows = wp.empty((n, self.row_values * (self.nodes - 1)), dtype=wp.float64, device=self.device)
                pending = wp.empty(n, dtype=wp.int32, device=self.device)
            s = self.settings
            wp.launch(
                kf.heat_kernel,
                dim=n,
                inputs=[
                    self._sets(params),
                    self.first,
                    self.count,
                    self.heat_cells,
                    int(s.fitted),
                    int(s.picard_iterations),
                    float(s.picard_tol),
                    theta,
                    scratch,
                    rows,
                    pending,
                ],
                device=self.device,
            )
            if pending.shape[0]:
                self._iterate_cells(params, theta, scratch, rows, pending)
        return params, theta

    def _iterate_cells(self, params: wp.array, theta: wp.array, scratch: wp.array, rows: wp.array, pending: wp.array):
        """The iterations of the sets the heat kernel left ``pending``, a thread per heat cell
        (:attr:`cell_threads`): each iteration a launch of the cells' rows and one of the sets'
        sweeps (recorded once, replayed: a launch's arguments cost the host more than the
        replay), at most ``picard_iterations``, :data:`PICARD_BURST` at a time between reads of
        how many sets still iterate (a set that has stopped returns at once in the launches
        after)."""
        n, dev, s = pending.shape[0], self.device, self.settings
        sets = self._sets(params)
        left = wp.zeros(1, dtype=wp.int32, device=dev)
        cell_rows = wp.launch(
            kf.heat_rows_kernel,
            dim=(n, self.nodes - 1),
            inputs=[sets, self.first, self.heat_cells, int(s.fitted), pending, theta, rows],
            device=dev,
            record_cmd=True,
        )
        sweep = wp.launch(
            kf.picard_kernel,
            dim=n,
            inputs=[
                sets,
                self.first,
                self.count,
                self.heat_cells,
                int(s.fitted),
                float(s.picard_tol),
                theta,
                scratch,
                rows,
                pending,
                left,
            ],
            device=dev,
            record_cmd=True,
        )
        done, most = 0, int(s.picard_iterations)
        while done < most:
            burst = min(PICARD_BURST, most - done)
            for b in range(burst):
                if b == burst - 1:
                    left.zero_()
                cell_rows.launch()
                sweep.launch()
            done += burst
            if not int(left.numpy()[0]):
                return

    def evaluate(
        self, varying, out: wp.array | None = None, start: np.ndarray | None = None
    ) -> tuple[wp.array, wp.array, wp.array]:
        """T-matrices of one device batch: returns (out, params, theta), see the class doc.
        A large batch on the CPU runs split over ``settings.cpu_threads`` threads.
        ``start``: the heat solve's start per set (:meth:`heat`)."""
        parts = self._cpu_parts(varying.shape[1])
        if parts > 1:
            T, params, theta = self._host_threaded(varying, parts, start)
            if out is None:
                out = wp.array(T, dtype=wp.float64, device=self.device)
            else:
                out.assign(T)
            return (
                out,
                wp.array(params, dtype=wp.float64, device=self.device),
                wp.array(theta, dtype=wp.float64, device=self.device),
            )
        return self.evaluate_serial(varying, out, start)

    def distinct(self, varying: np.ndarray, on_device: bool = False) -> tuple:
        """(T, column): the T-matrices (d, m, 2, 2) complex of the d distinct sets of a host
        table ``varying`` (1 + len(names), n), a new array (the caller's own), and which one
        each set is (n,), so that a caller that reads part of each set's T-matrices gathers
        it from ``T`` in one pass. ``on_device``: T as the launch left it, a Warp array (d, m,
        8) float64 on the engine's device (re, im of the four entries), for a caller that
        reduces them there (:mod:`tawarp.kernels.misfit`).
        Each distinct set is computed once and shared by its copies: sets that differ only in
        fields the model does not read for them count as copies (at zero heat input the
        :data:`HEAT_ONLY_FIELDS`, with fixed cells), as do sets that a caller's host-side
        fields told apart, and on the CPU each set this engine computed before (:data:`MEMO_BYTES`).
        The kernels compute each set on its own, so sharing changes no bit. A set whose heat
        solve iterates starts it from the converged excess of a set computed
        before near it (:attr:`warm`, :class:`WarmStarts`): the same fixed point, to the
        solve's tolerance."""
        key = np.array(varying, dtype=np.float64)
        cold = key[0] == 0.0
        if self.heat_only.size and cold.any():
            key[np.ix_(self.heat_only, np.flatnonzero(cold))] = 0.0
        first, column = distinct_columns(key)
        table = np.asarray(varying, dtype=np.float64)[:, first]
        column = column.reshape(-1)
        if not wp.get_device(self.device).is_cpu:
            return self._computed(table, on_device), column
        # on the CPU, the columns this engine computed before from the memo (MEMO_BYTES)
        ids = [(self.number, set_key.tobytes()) for set_key in np.ascontiguousarray(key[:, first].T)]
        T = np.empty((first.size, len(self.freqs), 2, 2), dtype=np.complex128)
        todo = []
        for j, known in enumerate(_MEMO.get(ids)):
            if known is None:
                todo.append(j)
            else:
                T[j] = known
        if todo:
            T[todo] = self._computed(table[:, todo])
            _MEMO.put([ids[j] for j in todo], T[todo])
        if on_device:
            return wp.array(T.view(np.float64).reshape(first.size, len(self.freqs), 8), device=self.device), column
        return T, column

    def _computed(self, table: np.ndarray, on_device: bool = False):
        """T-matrices (n, m, 2, 2) complex of the host table ``table`` (1 + len(names), n)
        (``on_device``: the launch's Warp array (n, m, 8), :meth:`distinct`); with warm
        starts (:attr:`warm`) the sets' heat solves start from the kept excesses near them,
        and their converged excesses are kept."""
        table = np.ascontiguousarray(table)
        parts = self._cpu_parts(table.shape[1])
        if parts > 1:  # the threads' host arrays as they are (no device arrays made of them)
            start = None if self.warm is None else self.warm.starts(table)
            T, _, theta = self._host_threaded(table, parts, start, params=False)
            varying = None
        else:
            varying = self.device_table(table)
            start = None if self.warm is None else self.warm.starts(table, varying)
            out, _, theta = self.evaluate_serial(varying, start=start)
            T = out if on_device else out.numpy()
        if self.warm is not None:
            self.warm.put(table, varying, theta)
        if on_device:  # a GPU's launch: one part
            return T
        return T.view(np.complex128).reshape(table.shape[1], len(self.freqs), 2, 2)

    def _cpu_parts(self, n: int) -> int:
        """How many threads a CPU batch of n sets is split over (1 on a GPU or for small
        batches, where a thread's start costs more than it saves)."""
        if not wp.get_device(self.device).is_cpu:
            return 1
        threads = self.settings.cpu_threads or _usable_cores()
        least = MIN_HEATED_MODELS_PER_THREAD if self.graded else MIN_MODELS_PER_THREAD
        return max(1, min(threads, n, n * len(self.freqs) // least))

    def _threaded(self, one, table: np.ndarray, parts: int, stride: int = 1) -> list:
        """[one(columns) for each of ``parts`` column blocks of ``table``] (whole groups of
        ``stride`` sets each), run in threads: the first block in this thread. ``one`` is
        run once on the first group alone before, so that its modules are compiled and
        loaded in one thread."""
        groups = table.shape[1] // stride
        bounds = np.linspace(0, groups, parts + 1).astype(int) * stride
        blocks = [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]
        if stride not in self._modules_loaded:
            one(slice(0, stride))
            self._modules_loaded.add(stride)
        rest = [_thread_pool().submit(one, b) for b in blocks[1:]]
        return [one(blocks[0])] + [f.result() for f in rest]

    def _host_threaded(self, varying, parts: int, start: np.ndarray | None = None, params: bool = True) -> tuple:
        """(T (n, m, 8), params, theta) of :meth:`evaluate` as host arrays, the batch split
        over ``parts`` threads; ``params`` False: None for them (a set's expanded parameters,
        about 40 rows a segment, are the largest of the three and a caller of T alone does
        not read them)."""
        table = varying.numpy() if isinstance(varying, wp.array) else np.asarray(varying, dtype=np.float64)
        # the sets dealt to the threads' blocks like cards (block b takes sets b, b + parts, ...):
        # a caller's batch groups sets of unequal work (without heat input a fraction of a
        # heated set's, a temperature-dependent heat solve several times it), and equal runs of
        # it left one thread idle for up to half of a launch; each set is computed on its own,
        # so the T-matrices are the same bit for bit
        deal = np.concatenate([np.arange(b, table.shape[1], parts) for b in range(parts)])

        def one(b):
            out, w_params, theta = self.evaluate_serial(
                np.ascontiguousarray(table[:, deal[b]]), start=None if start is None else start[deal[b]]
            )
            return out.numpy(), w_params.numpy() if params else None, theta.numpy()

        done = self._threaded(one, table, parts)
        back = np.argsort(deal)
        T = np.concatenate([r[0] for r in done])[back]
        theta = np.concatenate([r[2] for r in done])[back]
        if not params:
            return T, None, theta
        return T, np.concatenate([r[1] for r in done], axis=1)[:, back], theta

    def evaluate_serial(
        self, varying, out: wp.array | None = None, start: np.ndarray | None = None
    ) -> tuple[wp.array, wp.array, wp.array]:
        """:meth:`evaluate` in the calling thread alone."""
        params, theta = self.heat(varying, start)
        n = params.shape[1]
        if out is None:
            out = wp.empty((n, len(self.freqs), 8), dtype=wp.float64, device=self.device)
        self._adapted(params, theta, self.columns, out)
        return out, params, theta

    def cell_densities(self, params: wp.array, theta: wp.array) -> wp.array:
        """Adaptive cell density (n,) of each set (:meth:`_adapted`), from the
        cascade at the sampled frequencies alone (for callers that need the density, not
        the T-matrices); ``cell_density`` for every set where the estimate is off."""
        out = wp.empty((params.shape[1], self.sample.size, 8), dtype=wp.float64, device=self.device)
        return self._adapted(params, theta, self.sample_columns, out)

    def _columns(self, freqs: np.ndarray, sample: np.ndarray) -> tuple[wp.array, wp.array]:
        """The cascade's frequency columns [Hz] on the device: ``freqs``, then ``freqs[sample]``
        again (run on the refined grid: the error estimate), and ``sample`` as int32."""
        return (
            wp.array(np.concatenate([freqs, freqs[sample]]), dtype=wp.float64, device=self.device),
            wp.array(sample.astype(np.int32), dtype=wp.int32, device=self.device),
        )

    @property
    def tangent_step(self) -> float:
        """The step in a scaled parameter (a relative change, or a field's ``scale``) of
        the central differences that seed :meth:`evaluate_tangents` (:data:`TANGENT_STEP`,
        :data:`TANGENT_STEP_NONLINEAR` when the heat solve iterates)."""
        return TANGENT_STEP_NONLINEAR if self.nonlinear else TANGENT_STEP

    def evaluate_tangents(self, varying, step, tangents: int) -> tuple[wp.array, wp.array]:
        """T-matrices and their derivatives along ``tangents`` = P parameters, in one pass.

        ``varying`` (rows, g (1 + 2P)): g groups of 1 + 2P sets, a point and its neighbours
        z +- step[k, a] e_a in P parameters (set k (1 + 2P) + 1 + 2a is the + neighbour of
        parameter a, the next one the - neighbour); ``step`` (g, P). Returns
        ``out`` (g, m, 8) the T-matrices at the points and ``tangent`` (g, P, m, 8) their
        derivatives dT/dz_a: the cascade carries them with the value
        (:func:`tawarp.kernels.forward.make_transfer_kernel`), the neighbours only get
        their heat solve and points. Needs fixed cells (``ForwardSettings.cells``, or
        :func:`tawarp.measure.kind.smooth_settings`): a neighbour's points must lie where
        its point's do. A large CPU batch runs split over threads, as :meth:`evaluate`."""
        if self.estimating:
            raise ValueError(
                "evaluate_tangents: the cell count must be fixed (ForwardSettings(cells=...) or "
                "smooth_settings), not adapted per set"
            )
        stride = 1 + 2 * tangents
        if varying.shape[1] % stride:
            raise ValueError(f"evaluate_tangents: {varying.shape[1]} sets is not a multiple of 1 + 2 P = {stride}")
        parts = min(self._cpu_parts(varying.shape[1]), varying.shape[1] // stride)
        if parts <= 1:
            return self._tangents_serial(varying, step, tangents)
        table = varying.numpy() if isinstance(varying, wp.array) else np.asarray(varying, dtype=np.float64)
        steps = step.numpy() if isinstance(step, wp.array) else np.asarray(step, dtype=np.float64)
        one = (
            lambda b: tuple(
                a.numpy()
                for a in self._tangents_serial(  # noqa: E731
                    np.ascontiguousarray(table[:, b]),
                    np.ascontiguousarray(steps[b.start // stride : b.stop // stride]),
                    tangents,
                )
            )
        )
        done = self._threaded(one, table, parts, stride)
        return tuple(
            wp.array(np.concatenate([r[k] for r in done]), dtype=wp.float64, device=self.device) for k in range(2)
        )

    def _tangents_serial(self, varying, step, tangents: int) -> tuple[wp.array, wp.array]:
        """:meth:`evaluate_tangents` in the calling thread alone."""
        params, theta = self.heat(varying)
        stride = 1 + 2 * tangents
        n = params.shape[1]
        groups = n // stride
        if not isinstance(step, wp.array):
            step = wp.array(np.ascontiguousarray(step, dtype=np.float64), dtype=wp.float64, device=self.device)
        out = wp.empty((groups, len(self.freqs), 8), dtype=wp.float64, device=self.device)
        tangent = wp.empty((groups, tangents, len(self.freqs), 8), dtype=wp.float64, device=self.device)
        density = wp.full(n, float(self.settings.cell_density), dtype=wp.float64, device=self.device)
        refined = wp.empty((groups, 0, 8), dtype=wp.float64, device=self.device)
        self._cascade(params, theta, self.columns[0], density, out, refined, step, tangent)
        return out, tangent

    def _cascade(
        self,
        params: wp.array,
        theta: wp.array,
        freqs: wp.array,
        density: wp.array,
        out: wp.array,
        refined: wp.array,
        step: wp.array | None = None,
        tangent: wp.array | None = None,
        room: tuple[float, np.ndarray] | None = None,
        most: wp.array | None = None,
    ) -> tuple[wp.array | None, wp.array | None, np.ndarray | None]:
        """The cascade: ``out`` (n, m, 8) at ``freqs[:m]`` and density ``density`` (n,),
        ``refined`` (n, s, 8) at ``freqs[m:]`` on the refined grid
        (:func:`tawarp.kernels.forward.refined_cells`). The sets' cells are
        counted first and the largest point count read back (the one host round trip; none
        with fixed cells: :meth:`_fixed_point_counts`, nor with ``room`` = (r, counts): no
        set's density is more than r times what it was in a launch whose largest counts were
        ``counts``, :func:`point_room`, and the caller checks ``most`` at its next read,
        :meth:`_checked_counts`); then
        blocks of sets whose points fit in :data:`POINT_BUFFER_BYTES` get their points
        (:func:`tawarp.kernels.forward.make_point_kernel`) and their cascade launch.
        With ``tangent`` (g, P, m, 8) the sets are g groups of 1 + 2P (:meth:`evaluate_tangents`),
        ``out`` and ``refined`` have a row per group, and a block holds whole groups.
        Returns (cells, most) of :meth:`_cell_counts` (``most`` there if given) and the counts
        read back (None where none were)."""
        n = params.shape[1]
        if n == 0:
            return None, None, None
        tangents = 0 if tangent is None else tangent.shape[1]
        stride = 1 + 2 * tangents
        kernel = (
            self.transfer_kernel if tangents == 0 else _transfer_kernel(TANGENT_MAX_REGISTERS, tangents, self.plain)
        )
        step = self._no_step if step is None else step
        tangent = self._no_tangent if tangent is None else tangent
        columns = len(self.core.segments) * (2 if refined.shape[1] else 1)
        cells, grids, most = self._cell_counts(params, theta, density, columns, most)
        # the host's share of the launches before a read-back, while the device counts cells
        sets = self._sets(params)
        counts = None
        if self.settings.cells is not None:
            n_points, n_slots = self._fixed_point_counts(columns)
        elif room is not None:
            n_points, n_slots = point_room(*room, columns)
        else:
            counts = self._checked_counts(params, cells, most.numpy())
            n_points, n_slots = int(counts[0]), int(counts[1])
        budget = self._point_buffer_bytes(n * n_points * POINT_BYTES)
        block = stride * max(1, min(n, budget // (n_points * POINT_BYTES)) // stride)
        points = wp.empty((block, n_points), dtype=PointCoefficients, device=self.device)
        spans = wp.empty((block, n_points), dtype=wp.float64, device=self.device)
        for lo in range(0, n, block):
            part = points if lo + block <= n else points[: n - lo]
            part_spans = spans if lo + block <= n else spans[: n - lo]
            wp.launch(
                self.point_kernel,
                dim=(part.shape[0], n_slots),
                device=self.device,
                inputs=[sets, theta, cells, grids, self.first, self.heat_cells, lo, part, part_spans],
            )
            g0, g1 = lo // stride, (lo + part.shape[0]) // stride
            threads = (g1 - g0) * (out.shape[1] + refined.shape[1])
            if threads >= 2**31:  # a 1-D launch's thread index is an int32
                raise ValueError(
                    f"{part.shape[0]} sets x {out.shape[1] + refined.shape[1]} frequencies is over 2^31 "
                    f"threads in one launch: split the batch (ForwardSettings.chunk)"
                )
            rows = lambda a: a[g0:g1] if a.size else a  # noqa: E731 (Warp will not slice an empty array)
            # warps of alike cells: nothing to gain with fixed cells (every heated set takes the
            # same) or on the CPU (a thread runs its sets one by one)
            alike = self.settings.cells is not None or not wp.get_device(self.device).is_cuda
            order = self._no_order if alike else self._order(cells, lo, g1 - g0, stride)
            wp.launch(
                kernel,
                dim=threads,
                inputs=[
                    sets,
                    freqs,
                    cells,
                    part,
                    part_spans,
                    lo,
                    order,
                    self.pore_table,
                    rows(out),
                    rows(refined),
                    rows(step) if tangents else step,
                    rows(tangent) if tangents else tangent,
                ],
                device=self.device,
                block_dim=self.settings.block_dim,
            )
        return cells, most, counts

    def _cell_counts(
        self, params: wp.array, theta: wp.array, density: wp.array, columns: int, most: wp.array | None = None
    ) -> tuple[wp.array, wp.array, wp.array]:
        """(cells, grids, most) of :func:`tawarp.kernels.forward.cell_counts` for the sets of
        ``params`` (their heat solve ``theta``) at densities ``density`` (n,), over ``columns``
        (the segments, or the segments of both grids); ``most`` (3,) zeros to count into (a
        new array where None)."""
        n = params.shape[1]
        cells = wp.empty((n, columns), dtype=wp.int32, device=self.device)
        grids = wp.empty((n, columns), dtype=wp.vec4d, device=self.device)
        most = wp.zeros(3, dtype=wp.int32, device=self.device) if most is None else most
        wp.launch(
            kf.cell_counts,
            dim=n,
            inputs=[
                self._sets(params),
                theta,
                self.first,
                self.heat_cells,
                self.seg_cells,
                density,
                self.omega_max,
                cells,
                grids,
                most,
            ],
            device=self.device,
        )
        return cells, grids, most

    def _order(self, cells: wp.array, set0: int, groups: int, stride: int) -> wp.array:
        """The cascade launch's order of its ``groups`` groups of ``stride`` sets from set
        ``set0``: by decreasing cell steps (:func:`tawarp.kernels.forward.cascade_keys`),
        sorted on the device."""
        keys = wp.empty(2 * groups, dtype=wp.int32, device=self.device)
        order = wp.empty(2 * groups, dtype=wp.int32, device=self.device)
        wp.launch(kf.cascade_keys, dim=groups, inputs=[cells, set0, stride, keys, order], device=self.device)
        wp.utils.radix_sort_pairs(keys, order, groups)
        return order[:groups]

    def _fixed_point_counts(self, columns: int) -> tuple[int, int]:
        """(points, point-kernel slots) of a set over ``columns`` // n_seg grids with fixed
        cells (:func:`tawarp.kernels.forward.cell_counts`), known on the host: a set takes
        the most when every segment whose temperature may vary (thermal, or imposed) does, so
        these bound ``most`` of :meth:`_cascade` and equal it when a set of the batch has heat
        input and its imposed ends differ (a fit's heated sets: no host round trip per
        evaluation). Slots beyond a set's own return at once, so the T-matrices are the same
        bit for bit (tests/test_forward.py). The fixed counts lie in [1, MAX_CELLS]
        (:meth:`ForwardSettings.cells_per_segment`): nothing to refuse. Kept per ``columns``
        (every launch of the engine asks for the same)."""
        if columns not in self._point_counts:
            flags = structure_flags(self.core)
            varies = (flags[:, layout.F_THERMAL] != 0) | (flags[:, layout.F_IMPOSED] != 0)
            cells = self.settings.cells_per_segment(self.core).astype(np.int64)
            grids = columns // len(self.core.segments)
            points, slots = np.where(varies, 3 * cells, 1).sum(), np.where(varies, cells, 1).sum()
            self._point_counts[columns] = grids * int(points), grids * int(slots)
        return self._point_counts[columns]

    def _refuse_cells(self, params: wp.array, cells: np.ndarray):
        """Raise :class:`~tawarp.model.validity.ModelValidityError` for the first set whose
        cascade would need more than :data:`MAX_CELLS` cells in a segment (the kernel caps
        the count there): a heat-decay or acoustic length of tens of thousands of cells (an
        extreme ``h``, length or frequency) would not end, and overflows the point indices."""
        table = params.numpy()
        bad = np.flatnonzero((cells > MAX_CELLS).any(axis=1))
        i = int(bad[0])
        seg = self.core.segments[int(np.flatnonzero(cells[i] > MAX_CELLS)[0]) % len(self.core.segments)]
        values = {name: table[row] for name, row in zip(self.names, self.rows[1:])}
        raise ModelValidityError(
            f"{self.core.source}: {describe_set(i, table[layout.HEAT_INPUT], values)}: {seg.name} would need more "
            f"than {MAX_CELLS} Magnus cells up to {self.freqs.max():g} Hz (its heat-decay length or wavelength is "
            f"that many times shorter than the segment: an extreme h, conductivity, length or frequency; "
            f"docs/trusted_ranges.md); {bad.size} of {len(cells)} sets"
        )

    def _checked_counts(self, params: wp.array, cells: wp.array, counts: np.ndarray) -> np.ndarray:
        """``counts``, the read-back ``most`` of a launch of ``params`` whose cells are ``cells``
        (:func:`tawarp.kernels.forward.cell_counts`), as int64, after :meth:`_refuse_cells`
        where a segment would need more than :data:`MAX_CELLS` cells."""
        if counts[2] > MAX_CELLS:
            self._refuse_cells(params, cells.numpy())
        return counts.astype(np.int64)

    def _point_buffer_bytes(self, need: int) -> int:
        """Bytes a cascade launch's points may take (:data:`POINT_BUFFER_BYTES`), for a
        launch whose points would take ``need`` bytes in one block. A GPU's free memory is
        asked only for a launch above :data:`POINT_BUFFER_ASK_BYTES`: the driver's answer
        cost a study's processes about 1 % of their host time, and below that size a quarter
        of the free memory of any GPU that runs the kernels holds the block."""
        device = wp.get_device(self.device)
        if device.is_cpu:
            return POINT_BUFFER_BYTES
        if need <= POINT_BUFFER_ASK_BYTES:
            return POINT_BUFFER_ASK_BYTES
        return int(min(POINT_BUFFER_BYTES_GPU, device.free_memory // 4))

    def _estimated_cascade(
        self,
        params: wp.array,
        theta: wp.array,
        columns,
        density: wp.array,
        out: wp.array,
        room: tuple[float, np.ndarray] | None = None,
        most: wp.array | None = None,
    ) -> tuple[wp.array | None, wp.array | None, np.ndarray | None]:
        """The cascade into ``out`` at ``density`` and, in the same launch, on the refined
        grid at the sampled columns (:meth:`_cascade`, ``room`` and ``most`` passed on); the
        error estimate (n,) of each set compared on the device
        (:func:`tawarp.kernels.forward.refined_error`), left there (None where the estimate is
        off), the launch's cells and the counts :meth:`_cascade` read back."""
        freqs, sample = columns
        n = params.shape[1]
        refined = wp.empty((n, sample.shape[0], 8), dtype=wp.float64, device=self.device)
        cells, _, counts = self._cascade(params, theta, freqs, density, out, refined, room=room, most=most)
        if not self.estimating or n == 0:
            return None, cells, counts
        err = wp.empty(n, dtype=wp.float64, device=self.device)
        wp.launch(kf.refined_error, dim=n, inputs=[self._sets(params), out, refined, sample, err], device=self.device)
        return err, cells, counts

    def _adapted(self, params: wp.array, theta: wp.array, columns, out: wp.array) -> wp.array:
        """T-matrices of every set into ``out`` (n, m, 8) at the set's adaptive cell density,
        returned (n,) on the device (:class:`ForwardSettings`): ``cell_density``, raised where
        the error estimate exceeds ``tolerance``/2 (the factor 2 covers the frequencies
        between the three sampled). The first launch runs every set at d on all m columns and
        on the refined grid at the sampled ones (whose d values are the main cascade's own);
        each rerun raises the d of the sets still above target by (estimate / target)^(1/6)
        (the scheme's order) times 1.1, clipped to [1.25, 4] (and to
        :data:`MAX_DENSITY_FACTOR` times ``cell_density`` in all), gathers them, runs them
        the same way and scatters their rows into ``out``, all on the device
        (:meth:`_rerun`); on a GPU (``queue_ahead``) the first rerun is queued behind the first
        launch before any read-back, sized by the share of sets the engine's last evaluation
        raised (:data:`RERUN_ROOM`), and the host reads a few counts per rerun, the one round
        trip of each. A set is accepted only on a measured estimate (after
        :data:`MAX_ESTIMATE_ROUNDS` rounds a :class:`ValidityWarning` names the sets still
        above; a rerun too small for the sets above is run again and not counted)."""
        n = params.shape[1]
        cd = float(self.settings.cell_density)
        # filled on the device: no host copy before the main launch
        density = wp.full(n, cd if n else 0.0, dtype=wp.float64, device=self.device)
        err, _, seen = self._estimated_cascade(params, theta, columns, density, out)
        if err is None:
            return density
        target = 0.5 * self.settings.tolerance
        capacity = min(n, math.ceil(RERUN_ROOM * self._raised_share * n) + RERUN_SLOTS) if self.queue_ahead else n
        reruns, first = 0, True
        while reruns < MAX_ESTIMATE_ROUNDS - 1:
            tally, part, cells = self._rerun(params, theta, columns, out, err, density, target, capacity, seen)
            counts = tally.numpy()  # the rerun's one host round trip
            seen = np.maximum(seen, self._checked_counts(part, cells, counts[:3]))
            above, still = int(counts[3]), int(counts[4])
            if first:  # (a first rerun too small is run again at reruns 0: its count, not the next's)
                self._raised_share, first = above / n, False
            if above <= capacity:
                reruns += 1
            if still == 0:
                return density
            capacity = still
        errors, d = err.numpy(), density.numpy()
        above = errors > target
        if above.any():
            warnings.warn(
                f"{self.core.source}: the Magnus cells' error estimate of {above.sum()} of {n} sets is "
                f"still {errors[above].max():.2g} > {target:.2g} at cell density {d[above].max():.3g} "
                f"(cell_density {cd:g}); pass ForwardSettings(cells=...) for a fixed count",
                ValidityWarning,
                stacklevel=4,
            )
        return density

    def _rerun(
        self,
        params: wp.array,
        theta: wp.array,
        columns,
        out: wp.array,
        err: wp.array,
        density: wp.array,
        target: float,
        capacity: int,
        seen: np.ndarray,
    ) -> tuple[wp.array, wp.array, wp.array]:
        """Queue one rerun of :meth:`_adapted` on the device, with no host round trip: the sets
        whose estimate ``err`` (n,) exceeds ``target``, up to ``capacity`` of them, get their
        ``density`` raised (:func:`tawarp.kernels.forward.raise_density`), are gathered and
        run again, their points sized from the largest counts ``seen`` of any earlier launch
        (:func:`point_room`), and their rows of ``out`` and ``err`` scattered back. The slots
        beyond the sets above are empty: set 0 at density 0, which takes no cells and is not
        scattered. Without ``queue_ahead`` the count is read first and the rerun takes its sets
        alone, its points sized from their own counts. Returns (tally, params, cells): tally (5,)
        int32 on the device, the rerun's ``most`` (:func:`tawarp.kernels.forward.cell_counts`),
        the sets above target before it and after it; the rerun's parameter table and cells
        (:meth:`_checked_counts`; None where no set was above target)."""
        n, dev = params.shape[1], self.device
        tally = wp.zeros(5, dtype=wp.int32, device=dev)
        index = wp.zeros(capacity, dtype=wp.int32, device=dev)
        d = wp.zeros(capacity, dtype=wp.float64, device=dev)
        most_density = MAX_DENSITY_FACTOR * float(self.settings.cell_density)
        wp.launch(
            kf.raise_density, dim=n, inputs=[err, density, target, most_density, tally[3:4], index, d], device=dev
        )
        room = (float(kf.RAISE_MOST), seen)
        if not self.queue_ahead:
            capacity = min(capacity, int(tally.numpy()[3]))
            if capacity == 0:  # no set above target: none after either
                return tally, None, None
            index, d, room = index[:capacity], d[:capacity], None
        p = wp.empty((params.shape[0], capacity), dtype=wp.float64, device=dev)
        t = wp.empty((capacity, theta.shape[1]), dtype=wp.float64, device=dev)
        wp.launch(kbatch.gather_sets, dim=capacity, inputs=[params, theta, index, p, t], device=dev)
        part = wp.empty((capacity, out.shape[1], 8), dtype=wp.float64, device=dev)
        part_err, cells, _ = self._estimated_cascade(p, t, columns, d, part, room=room, most=tally[0:3])
        above = tally[3:4]
        wp.launch(kbatch.scatter_sets, dim=(capacity, out.shape[1]), inputs=[part, index, above, out], device=dev)
        wp.launch(
            kbatch.scatter_sets,
            dim=(capacity, 1),
            inputs=[part_err.reshape((capacity, 1, 1)), index, above, err.reshape((n, 1, 1))],
            device=dev,
        )
        wp.launch(kf.count_above, dim=n, inputs=[err, target, tally[4:5]], device=dev)
        return tally, p, cells

    def temperature(self, params: wp.array, theta: wp.array, x) -> tuple[np.ndarray, np.ndarray]:
        """T(x) [K] and dT/dx [K/m], each (n, len(x)), at positions x [m] from plane x1."""
        x = wp.array(np.ascontiguousarray(x, dtype=np.float64), dtype=wp.float64, device=self.device)
        n = params.shape[1]
        T = wp.zeros((n, x.shape[0]), dtype=wp.float64, device=self.device)
        dT = wp.zeros((n, x.shape[0]), dtype=wp.float64, device=self.device)
        wp.launch(
            kf.profile_kernel,
            dim=(n, x.shape[0]),
            device=self.device,
            inputs=[self._sets(params), theta, self.first, self.heat_cells, x, T, dT],
        )
        return T.numpy(), dT.numpy()


def _usable_cores() -> int:
    """Cores this process may run on (the affinity mask where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def cpu_share(processes: int) -> int:
    """The threads (:attr:`ForwardSettings.cpu_threads`) each of ``processes`` processes or
    CPU workers started from this one splits its CPU launches over: an equal share of the
    cores this process may use, at least one (each over all of them would run several
    times as many threads as cores)."""
    return max(1, _usable_cores() // max(1, processes))


#: Fewest forward models (set x frequency) worth a CPU thread of their own: a thread's
#: hand-off and copies cost about as much as 2000 unheated models (~3 us each, closed
#: form) or a few dozen heated ones (a Magnus cascade, 50-150 us each).
MIN_MODELS_PER_THREAD = 2000
MIN_HEATED_MODELS_PER_THREAD = 64


@functools.cache
def _thread_pool() -> ThreadPoolExecutor:
    """One pool for the CPU batches of the process, as wide as its cores: its threads start
    as batches need them and live as long as the process. (A pool per batch width left up to
    a core count's triangular number of idle threads in every process, and a study running
    one loop per core of a 64-core host ran out of threads.)"""
    return ThreadPoolExecutor(max_workers=_usable_cores(), thread_name_prefix="tawarp-cpu")


@functools.cache
def _point_kernel(nonlinear: bool, max_registers: int | None = kf.POINT_MAX_REGISTERS):
    """The point kernel for this heat model under a register cap (None: uncapped), compiled
    once per process."""
    return kf.make_point_kernel(nonlinear, max_registers)


@functools.cache
def _transfer_kernel(max_registers: int | None, tangents: int = 0, plain: bool = False):
    """The cascade kernel for this register cap (number of tangents, plain parts alone),
    compiled once per process."""
    return kf.make_transfer_kernel(max_registers, tangents, plain)


def batch_table(core: Core, heat_input, params: dict | None) -> tuple[list[str], np.ndarray]:
    """Validated varying-parameter names and their (1 + len(names), n) table."""
    n, q, arrays = broadcast_batch(core, heat_input, params)
    names = list(arrays)
    return names, np.stack([q] + [arrays[k] for k in names]) if n else np.zeros((1 + len(names), 0))


def transfer_matrices(
    core: Core,
    freqs,
    heat_input=0.0,
    params: dict | None = None,
    settings: ForwardSettings | None = None,
    progress: bool = False,
    **kw,
) -> ForwardResult:
    """Core T-matrices for a batch of parameter sets and frequencies.

    Parameters
    ----------
    core : the core description (its values are the defaults of every parameter).
    freqs : (m,) frequencies [Hz].
    heat_input : scalar or (n,) heat input Q [W] dissipated in the heater segment.
    params : ``{"SEGMENT.FIELD": scalar or (n,) array}`` values replacing the core's.
    settings : :class:`ForwardSettings`; keyword arguments (``cells=``, ``device=``, ...)
        are a shortcut for it.
    progress : show a progress bar over the launch chunks (on a terminal only).

    Returns a :class:`ForwardResult` with ``T`` of shape (n, m, 2, 2), complex128.
    Sets outside the model raise :class:`~tawarp.model.validity.ModelValidityError` or
    warn (:class:`~tawarp.model.validity.ValidityWarning`) naming the set: never a silent NaN.
    """
    if not isinstance(core, Core):
        raise TypeError(
            f"transfer_matrices: core must be a Core, e.g. load_core('ceramic') or load_core('my_core.toml'); "
            f"got {type(core).__name__}"
        )
    settings = dataclasses.replace(settings or ForwardSettings(), **kw)
    names, varying = batch_table(core, heat_input, params)
    engine = Engine(core, freqs, names, settings)
    values = dict(zip(names, varying[1:]))
    check_sets(core, varying[0], values, engine.freqs, settings.cell_density if settings.cells is None else None)
    n, m = varying.shape[1], len(engine.freqs)
    T = np.empty((n, m, 2, 2), dtype=np.complex128)
    theta = np.empty((n, engine.theta_columns))
    table = np.empty((engine.base.shape[0], n))
    bar = progress_bar(n, "forward models", progress, unit="set")
    for lo in range(0, n, settings.chunk):
        hi = min(n, lo + settings.chunk)
        out, w_params, w_theta = engine.evaluate(varying[:, lo:hi])
        T[lo:hi] = out.numpy().view(np.complex128).reshape(hi - lo, m, 2, 2)
        theta[lo:hi] = w_theta.numpy()
        check_results(core, varying[0], values, T[lo:hi], theta[lo:hi], lo, engine.freqs)
        check_precision(core, varying[0], values, T[lo:hi], settings.tolerance or DEFAULT_TOLERANCE, lo)
        table[:, lo:hi] = w_params.numpy()
        bar.update(hi - lo)
    bar.close()
    return ForwardResult(
        core, engine.freqs, varying[0].copy(), T, theta, table, dataclasses.replace(settings, device=engine.device)
    )


def steady_temperature(
    core: Core, x, heat_input=0.0, params: dict | None = None, settings: ForwardSettings | None = None, **kw
) -> tuple[np.ndarray, np.ndarray]:
    """Steady temperature T(x) [K] and dT/dx [K/m], each (n, len(x)), at positions x [m]
    from plane x1, for a batch (heat solve only, no acoustics). Arguments as
    :func:`transfer_matrices`."""
    settings = dataclasses.replace(settings or ForwardSettings(), **kw)
    names, varying = batch_table(core, heat_input, params)
    engine = Engine(core, [1.0], names, settings)
    values = dict(zip(names, varying[1:]))
    check_sets(core, varying[0], values)
    T = np.empty((varying.shape[1], len(np.atleast_1d(x))))
    dT = np.empty_like(T)
    for lo in range(0, varying.shape[1], settings.chunk):
        hi = min(varying.shape[1], lo + settings.chunk)
        params, theta = engine.heat(varying[:, lo:hi])
        check_results(core, varying[0], values, None, theta.numpy(), lo)
        T[lo:hi], dT[lo:hi] = engine.temperature(params, theta, np.atleast_1d(x))
    return T, dT
