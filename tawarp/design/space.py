"""Design space: the variables of a design search or sweep over a thermoacoustic core.

A :class:`DesignSpace` holds continuous variables (any ``SEGMENT.FIELD`` of the core,
``heat_input`` [W], ``stack.position`` = length of the segment before the stack) and
optionally the categorical ``material`` (a :mod:`tawarp.design.catalogue` entry put in the
stack; explicit ``stack.*`` variables then override the material's values, which makes
a material parametric). It maps design points to the parameter table of
:class:`tawarp.model.forward.Engine` and to/from the unit cube the samplers work in.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .catalogue import PARAMS as MATERIAL_PARAMS, CORE_FIELD, Catalogue, default_catalogue
from ..model.core import Core, CoreError, check_values


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
            _finite_bounds(text, name, [("lower bound", lo), ("upper bound", hi)])
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
        _finite_bounds(text, name, [("value", v) for v in vals])
        return Variable(name, min(vals), max(vals), values=tuple(vals))
    except ValueError as e:
        if str(e).startswith(repr(text)):
            raise
        raise ValueError(
            f"{text!r}: expected NAME=LOW:HIGH[:log], NAME=LOW:HIGH:COUNT[:log] or NAME=v1,v2,..."
        ) from None


def _finite_bounds(text: str, name: str, bounds: list[tuple[str, float]]) -> None:
    """Refuse a NaN or infinite bound: min and max would drop a NaN or pass it on (a range
    read as one fixed value, a grid with a NaN coordinate)."""
    for which, v in bounds:
        if not math.isfinite(v):
            raise ValueError(f"{text!r}: the {which} of {name} is {v}; expected a finite number")


class DesignSpace:
    """Design variables over ``core``.

    ``variables``: :class:`Variable` list or ``parse_variable`` strings. Continuous names:
    ``heat_input`` [W] (alias ``Q``), any ``SEGMENT.FIELD`` of the core, and
    ``stack.position`` (the length of the segment before the stack, i.e. x2 - x1 when
    the stack is second). ``material``: categorical over ``catalogue`` names, put in the
    ``segment`` (default ``stack``). ``heat_input``: its value when not a variable.
    """

    def __init__(
        self, core: Core, variables, catalogue: Catalogue | None = None, segment: str = "stack", heat_input: float = 0.0
    ):
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
                raise KeyError(
                    f"{v.name!r} is not a parameter of {self.core.source}; "
                    f"parameters are {', '.join(self.core.parameter_names())}"
                )
            fld = name.partition(".")[2]
            check_values(fld, np.array([v.low, v.high]), f"design variable {v.name}")
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
        """(1 + len(param_names), n) table for :class:`tawarp.model.forward.Engine`: row 0 the heat
        input. ``values``: variable name -> (n,) array; ``material`` as names or indices."""
        n = max(len(np.atleast_1d(a)) for a in values.values()) if values else 1
        names = self.param_names
        # rows are written in place: a sweep chunk of 4M points is a 300 MB table, and
        # stacking temporaries doubled the host time that kept the device waiting
        out = np.empty((1 + len(names), n))
        out[0] = self.heat_input
        row = {k: 1 + j for j, k in enumerate(names)}
        if self.material is not None:
            idx = self.material_index(values["material"])
            for p in MATERIAL_PARAMS:
                table = np.array([getattr(self.catalogue[c], p) for c in self.material.choices])
                np.take(table, idx, out=out[row[f"{self.segment}.{CORE_FIELD[p]}"]])
        for v in self.continuous:
            name = self.core_name(v.name)
            out[0 if name == "heat_input" else row[name]] = values[v.name]
        return out

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

    def binding(self) -> dict:
        """What a study is bound to: the core, the designed segment, the fixed heat input
        [W] and the variables (JSON types, so that a stored copy compares equal)."""
        return {
            "core": str(self.core.source),
            "segment": self.segment,
            "heat_input_W": self.heat_input,
            "variables": self.describe(),
        }

    def describe(self) -> list[dict]:
        return [
            (
                {"name": v.name, "choices": list(v.choices)}
                if v.categorical
                else {"name": v.name, "low": v.low, "high": v.high, "log": v.log}
            )
            for v in self.variables
        ]

    # -- sampler coordinates --------------------------------------------------------------
    @property
    def n_categories(self) -> int:
        """Number of materials (1 without a ``material`` variable)."""
        return len(self.material.choices) if self.material is not None else 1

    def values_from_unit(self, X: np.ndarray) -> dict[str, np.ndarray]:
        """``{variable: (n,) array}`` of sampler coordinates ``X`` (n, len(continuous)
        [+ 1]): unit-cube columns of the continuous variables, then, with a ``material``
        variable, the material index (kept as an integer array)."""
        nc = len(self.continuous)
        vals = self.from_unit(X[:, :nc])
        if self.material is not None:
            vals["material"] = X[:, nc].astype(np.int64)
        return vals

    def unit_from_values(self, values: dict) -> np.ndarray:
        """Inverse of :meth:`values_from_unit` (the coordinates a sampler is told);
        materials as indices or names."""
        u = self.to_unit({v.name: values[v.name] for v in self.continuous})
        if self.material is not None:
            u = np.concatenate([u, self.material_index(values["material"])[:, None].astype(float)], axis=1)
        return u

    def material_index(self, materials) -> np.ndarray:
        """Indices into ``material.choices`` of materials given as names or indices."""
        m = np.atleast_1d(materials)
        if m.dtype.kind in "iu":
            return m.astype(np.int64)
        lookup = {c: i for i, c in enumerate(self.material.choices)}
        return np.array([lookup[str(x)] for x in m], dtype=np.int64)

    def points_of(self, values: dict, rows=None) -> list[dict]:
        """Design points ``{name: value}`` (material by name) of ``values`` (as
        :meth:`values_from_unit` gives them), at ``rows`` (default all)."""
        rows = range(len(next(iter(values.values())))) if rows is None else rows
        mats = self.material_index(values["material"]) if self.material is not None else None
        points = []
        for j in rows:
            p = {v.name: float(values[v.name][j]) for v in self.continuous}
            if mats is not None:
                p["material"] = self.material.choices[int(mats[j])]
            points.append(p)
        return points

    def points_from_unit(self, X: np.ndarray) -> list[dict]:
        """Design points ``{name: value}`` of sampler coordinates ``X`` (see
        :meth:`values_from_unit`)."""
        return self.points_of(self.values_from_unit(X))

    def unit_from_points(self, points: list[dict]) -> np.ndarray:
        """Inverse of :meth:`points_from_unit` (the coordinates a sampler is told)."""
        return self.unit_from_values(self.values_of(points))

    def values_of(self, points: list[dict]) -> dict:
        """``{variable: (n,) array}`` of design points (input of :meth:`varying_table`)."""
        vals = {v.name: np.array([p[v.name] for p in points], dtype=float) for v in self.continuous}
        if self.material is not None:
            vals["material"] = np.array([p["material"] for p in points])
        return vals


class DeviceTable:
    """:meth:`DesignSpace.varying_table` built on a Warp ``device`` by one kernel launch
    (:func:`tawarp.kernels.design.design_table`), from point indices of the space's grid
    or from unit-cube points, so that a sweep uploads no table: only the variables' grids
    (once) or the (m, d) unit points. The tables are those of the host, value for value:
    grid values and material rows are copied, unit points scaled as :meth:`DesignSpace.from_unit`
    scales them (to rounding, the device may fuse the multiply-add).

    Variables are in the order of the unit cube's columns: ``space.continuous``, then the
    material (:attr:`names`)."""

    def __init__(self, space: DesignSpace, device):
        import warp as wp

        from ..kernels.design import LINEAR, LOG, MATERIAL, DesignVariables

        self.space, self.device = space, device
        self.variables = space.continuous + ([space.material] if space.material is not None else [])
        self.names = [v.name for v in self.variables]
        params = space.param_names
        row = {k: 1 + j for j, k in enumerate(params)}
        grids, starts, rows, kinds, lows, spans = [], [], [], [], [], []
        for v in self.variables:
            starts.append(sum(len(g) for g in grids))
            if v.categorical:
                kinds.append(MATERIAL)
                rows.append(-1)
                lows.append(0.0)
                spans.append(0.0)
                grids.append(np.zeros(0))
                continue
            name = space.core_name(v.name)
            rows.append(0 if name == "heat_input" else row[name])
            kinds.append(LOG if v.log else LINEAR)
            # the same float64 operands as from_unit: low + x (high - low), or in logs
            lo, hi = (np.log(v.low), np.log(v.high)) if v.log else (v.low, v.high)
            lows.append(lo)
            spans.append(hi - lo)
            grids.append(np.asarray(v.values, dtype=np.float64))
        # C-order strides of the grid over space.variables (the sweep file's dimensions)
        shape = [len(v.grid()) for v in space.variables]
        strides = {v.name: int(np.prod(shape[j + 1 :], dtype=np.int64)) for j, v in enumerate(space.variables)}
        sizes = [len(v.choices) if v.categorical else len(v.values) for v in self.variables]
        mats = space.material.choices if space.material is not None else ()
        materials = np.array(
            [[getattr(space.catalogue[c], p) for p in MATERIAL_PARAMS] for c in mats], dtype=np.float64
        ).reshape(len(mats), len(MATERIAL_PARAMS))
        material_rows = [row[f"{space.segment}.{CORE_FIELD[p]}"] for p in MATERIAL_PARAMS] if mats else []

        def up(a, dtype):
            return wp.array(np.asarray(a), dtype=dtype, device=device)

        dv = self._variables = DesignVariables()
        dv.grid = up(np.concatenate(grids) if grids else np.zeros(0), wp.float64)
        dv.kind = up(kinds, wp.int32)
        dv.stride = up([strides[v.name] for v in self.variables], wp.int64)
        dv.size = up(sizes, wp.int32)
        dv.start = up(starts, wp.int32)
        dv.low = up(lows, wp.float64)
        dv.span = up(spans, wp.float64)
        dv.row = up(rows, wp.int32)
        dv.materials = wp.array2d(materials, dtype=wp.float64, device=device)
        dv.material_rows = up(np.asarray(material_rows, dtype=np.int32), wp.int32)
        self.rows = 1 + len(params)
        self._sobol = None  # (seed, directions, shift, scale) on the device, made by the first sobol()

    def _launch(self, lo: int, m: int, unit, values, table=None):
        import warp as wp

        from ..kernels.design import design_table

        if table is None:
            table = wp.empty((self.rows, m), dtype=wp.float64, device=self.device)
        wp.launch(
            design_table,
            dim=m,
            device=self.device,
            inputs=[wp.int64(lo), unit, self._variables, float(self.space.heat_input), table, values],
        )
        return table

    def grid(self, lo: int, hi: int):
        """Varying table (Warp, on the device) of the grid points lo..hi-1, numbered in C
        order over ``space.variables`` (each variable's ``values``, the material's choices)."""
        return self._launch(lo, hi - lo, None, None)

    def sobol(self, lo: int, hi: int, seed: int):
        """:meth:`unit` of the points lo..hi-1 of :func:`tawarp.design.samplers.sobol_unit`'s
        sequence for (len(names), seed), made on the device (:func:`tawarp.kernels.design.sobol_points`)."""
        import warp as wp

        from ..kernels.design import sobol_points
        from .samplers import sobol_directions

        u = wp.empty((hi - lo, len(self.names)), dtype=wp.float64, device=self.device)
        if self.names:
            if self._sobol is None or self._sobol[0] != seed:
                directions, shift, scale = sobol_directions(len(self.names), seed)
                self._sobol = (
                    seed,
                    wp.array(directions, dtype=wp.int64, device=self.device),
                    wp.array(shift, dtype=wp.int64, device=self.device),
                    scale,
                )
            _, directions, shift, scale = self._sobol
            wp.launch(
                sobol_points,
                dim=u.shape,
                device=self.device,
                inputs=[wp.int64(lo), directions, shift, wp.float64(scale), u],
            )
        return self.unit(u)

    def coordinates(self, values, out=None):
        """Sampler coordinates (m, len(names)) on the device of design ``values``
        (len(names), m) (a Warp array on the device or NumPy, the material as its index):
        the unit cube's coordinates of the continuous variables, then the material index
        (:func:`tawarp.kernels.design.sampler_coordinates`; what
        :meth:`DesignSpace.unit_from_values` computes on the host, to rounding); into
        ``out`` where given."""
        import warp as wp

        from ..kernels.design import sampler_coordinates

        if not isinstance(values, wp.array):
            values = wp.array(np.ascontiguousarray(values, dtype=np.float64), dtype=wp.float64, device=self.device)
        m = values.shape[1]
        X = wp.empty((m, len(self.names)), dtype=wp.float64, device=self.device) if out is None else out
        wp.launch(sampler_coordinates, dim=X.shape, device=self.device, inputs=[values, self._variables, X])
        return X

    def unit(self, u, out=None):
        """(varying table, values) on the device of unit-cube points ``u`` (m, len(names)),
        a NumPy array or a float64 Warp array on the device: ``values`` (len(names), m) the
        variables' values (the material as its index); into ``out`` = (table, values)
        where given."""
        import warp as wp

        if not isinstance(u, wp.array):
            u = wp.array(np.ascontiguousarray(u, dtype=np.float64), dtype=wp.float64, device=self.device)
        if out is not None:
            table, values = out
            return self._launch(0, u.shape[0], u, values, table), values
        values = wp.empty((len(self.names), u.shape[0]), dtype=wp.float64, device=self.device)
        return self._launch(0, u.shape[0], u, values), values
