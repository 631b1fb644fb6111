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
import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from .coefficients import duct_impedance, normalize
from .core import GLOBAL_FIELDS, SEGMENT_FIELDS, Core, CoreError, check_values
from .gas import GASES
from .kernels import forward as kf
from .kernels import layout

assert SEGMENT_FIELDS == ("length", "porosity", "pore_radius", "tortuosity", "solid_conductivity", "h")

#: Default Magnus cells per thermal segment. bench/forward.py measures the accuracy of
#: each setting against a converged reference (README, "Accuracy of the cells setting").
DEFAULT_CELLS = 16
_GLOBAL_ROWS = {"gas.T_cold": layout.T_COLD, "gas.p_mean": layout.P_MEAN, "tube.radius": layout.RADIUS}


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
        raise RuntimeError(f"device {device!r} requested but Warp finds no CUDA GPU; use device='cpu'")
    wp.get_device(device)  # raises for an unknown name
    return device


def parameter_row(core: Core, name: str) -> int:
    """Row of parameter ``name`` in the kernels' parameter table."""
    if name in _GLOBAL_ROWS:
        return _GLOBAL_ROWS[name]
    if name not in core.parameter_names():
        raise KeyError(f"{name!r} is not a parameter of core {core.source}; "
                       f"parameters are {', '.join(core.parameter_names())}")
    seg, _, fld = name.partition(".")
    s = [x.name for x in core.segments].index(seg)
    return layout.N_GLOBAL + s * layout.N_FIELDS + SEGMENT_FIELDS.index(fld)


def base_table(core: Core) -> np.ndarray:
    """The core's own values as one column of the parameter table, shape (rows,)."""
    base = np.zeros(layout.N_GLOBAL + len(core.segments) * layout.N_FIELDS)
    for name in GLOBAL_FIELDS:
        base[_GLOBAL_ROWS[name]] = core.get(name)
    for s, seg in enumerate(core.segments):
        for f, fld in enumerate(SEGMENT_FIELDS):
            v = core.get(f"{seg.name}.{fld}")
            base[layout.N_GLOBAL + s * layout.N_FIELDS + f] = v if math.isfinite(v) else 0.0
    return base


def structure_flags(core: Core) -> np.ndarray:
    """Per-segment structure (porous, pore model, thermal, heater) as int32 (nseg, 4)."""
    from .kernels.pore import PORE_CIRCULAR, PORE_PLATES

    model = {"circular": PORE_CIRCULAR, "plates": PORE_PLATES}
    return np.array([[s.is_porous, model[s.pore_model] if s.is_porous else PORE_CIRCULAR, s.thermal, s.heater]
                     for s in core.segments], dtype=np.int32)


@dataclass
class ForwardResult:
    """Result of a batched forward run.

    ``T`` (n, m, 2, 2) complex: core T-matrices, exp(-iwt), ``(p, U)(x6) = T (p, U)(x1)``.
    ``freqs`` (m,) [Hz]; ``heat_input`` (n,) [W]; ``theta`` (n, nodes) nodal temperature
    excess [K] of the heat grid; ``params`` (rows, n) the table the kernels read.
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

    def temperature(self, x: np.ndarray, device: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """T(x) [K] and dT/dx [K/m], each (n, len(x)), at positions x [m] from plane x1."""
        device = resolve_device(device or self.settings.device)
        x = np.ascontiguousarray(x, dtype=np.float64)
        n = self.params.shape[1]
        T = wp.zeros((n, len(x)), dtype=wp.float64, device=device)
        dT = wp.zeros((n, len(x)), dtype=wp.float64, device=device)
        first, _ = _thermal_range(self.core)
        wp.launch(kf.profile_kernel, dim=(n, len(x)), device=device,
                  inputs=[wp.array(self.params, dtype=wp.float64, device=device),
                          wp.array(structure_flags(self.core), dtype=wp.int32, device=device),
                          wp.array(GASES[self.core.gas.name].as_tuple(), dtype=wp.float64, device=device),
                          wp.array(self.theta, dtype=wp.float64, device=device),
                          first, self.settings.heat_cells, wp.array(x, dtype=wp.float64, device=device), T, dT])
        return T.numpy(), dT.numpy()


@dataclass(frozen=True)
class ForwardSettings:
    """Numerical settings. ``cells``: Magnus cells per thermal segment (an int, or a
    dict segment name -> int); ``heat_cells``: heat-grid cells per thermal segment;
    ``fitted``: exact (exponentially fitted) heat scheme, else plain second order;
    ``chunk``: parameter sets per launch (bounds device memory); ``device``."""

    cells: int | dict = DEFAULT_CELLS
    heat_cells: int = 1
    fitted: bool = True
    chunk: int = 1 << 16
    device: str | None = None

    def cells_per_segment(self, core: Core) -> np.ndarray:
        if isinstance(self.cells, dict):
            unknown = set(self.cells) - {s.name for s in core.segments}
            if unknown:
                raise KeyError(f"cells given for unknown segment(s) {sorted(unknown)}")
            counts = [self.cells.get(s.name, DEFAULT_CELLS) for s in core.segments]
        else:
            counts = [self.cells] * len(core.segments)
        if any(int(c) < 1 for c in counts):
            raise ValueError(f"cells must be >= 1, got {self.cells}")
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
    if np.any(q > 0) and not core.thermal_indices:
        raise CoreError(f"{core.source}: heat_input > 0 but the core has no thermal segment with heater = true")
    for name, a in out.items():
        check_values(name.partition(".")[2], a, f"parameter {name}")
    return n, q, out


def transfer_matrices(core: Core, freqs, heat_input=0.0, params: dict | None = None,
                      settings: ForwardSettings | None = None, **kw) -> ForwardResult:
    """Core T-matrices for a batch of parameter sets and frequencies.

    Parameters
    ----------
    core : the core description (its values are the defaults of every parameter).
    freqs : (m,) frequencies [Hz].
    heat_input : scalar or (n,) heat input Q [W] dissipated in the heater segment.
    params : ``{"SEGMENT.FIELD": scalar or (n,) array}`` values replacing the core's.
    settings : :class:`ForwardSettings`; keyword arguments (``cells=``, ``device=``, ...)
        are a shortcut for it.

    Returns a :class:`ForwardResult` with ``T`` of shape (n, m, 2, 2), complex128.
    """
    settings = dataclasses.replace(settings or ForwardSettings(), **kw)
    device = resolve_device(settings.device)
    settings = dataclasses.replace(settings, device=device)
    freqs = np.atleast_1d(np.asarray(freqs, dtype=np.float64))
    if freqs.ndim != 1 or not np.all(np.isfinite(freqs)) or np.any(freqs <= 0):
        raise ValueError("freqs [Hz] must be a 1-D array of positive finite values")
    n, q, arrays = broadcast_batch(core, heat_input, params)
    names = list(arrays)
    varying = np.stack([q] + [arrays[k] for k in names]) if n else np.zeros((1, 0))
    rows = np.array([layout.HEAT_INPUT] + [parameter_row(core, k) for k in names], dtype=np.int32)
    first, count = _thermal_range(core)
    hc = int(settings.heat_cells)
    if hc < 1:
        raise ValueError(f"heat_cells must be >= 1, got {hc}")
    nodes = count * hc + 1
    base = wp.array(base_table(core), dtype=wp.float64, device=device)
    flags = wp.array(structure_flags(core), dtype=wp.int32, device=device)
    gas = wp.array(GASES[core.gas.name].as_tuple(), dtype=wp.float64, device=device)
    seg_cells = wp.array(settings.cells_per_segment(core), dtype=wp.int32, device=device)
    w_rows = wp.array(rows, dtype=wp.int32, device=device)
    w_freqs = wp.array(freqs, dtype=wp.float64, device=device)
    T = np.empty((n, len(freqs), 2, 2), dtype=np.complex128)
    theta = np.empty((n, nodes))
    table = np.empty((len(base_table(core)), n))
    for lo in range(0, n, settings.chunk):
        hi = min(n, lo + settings.chunk)
        k = hi - lo
        w_var = wp.array(np.ascontiguousarray(varying[:, lo:hi]), dtype=wp.float64, device=device)
        w_params = wp.empty((base.shape[0], k), dtype=wp.float64, device=device)
        w_theta = wp.zeros((k, nodes), dtype=wp.float64, device=device)
        w_scratch = wp.empty((k, nodes), dtype=wp.float64, device=device)
        w_out = wp.empty((k, len(freqs), 8), dtype=wp.float64, device=device)
        wp.launch(kf.expand_parameters, dim=k, inputs=[base, w_var, w_rows, w_params], device=device)
        if count:
            wp.launch(kf.heat_kernel, dim=k, inputs=[w_params, flags, gas, first, count, hc, int(settings.fitted),
                                                     w_theta, w_scratch], device=device)
        wp.launch(kf.transfer_kernel, dim=(k, len(freqs)),
                  inputs=[w_params, flags, gas, w_theta, w_freqs, seg_cells, first, hc, w_out], device=device)
        T[lo:hi] = w_out.numpy().view(np.complex128).reshape(k, len(freqs), 2, 2)
        theta[lo:hi] = w_theta.numpy()
        table[:, lo:hi] = w_params.numpy()
    return ForwardResult(core, freqs, q.copy(), T, theta, table, settings)
