"""Core T-matrices as a measurement kind.

Rows: (heat input, frequency) x the four dimensionless coefficients ``Tpp, Tpu/Zc,
Tup*Zc, Tuu`` (:mod:`tawarp.model.coefficients`), Zc of the core as given (a constant
even when ``gas.T_cold`` is fitted). Predictions: one forward launch of the core's
T-matrices for every (parameter set, heat input). Files: :func:`read_tmatrix_csv`.
"""

from __future__ import annotations

import copy
import dataclasses
import functools

import numpy as np
import warp as wp

from ..model.biot import FLUID_SLICE, FRAME_POISSON_RATIO, JCAFluid, equivalent_fluid, fluid_transfer_matrix
from ..model.coefficients import COEFFICIENTS, duct_impedance, normalize, normalize_entries
from ..model.core import Core, load_core
from ..model.effects import (
    CALIBRATION_GAIN,
    CALIBRATION_PHASE,
    graded_cells,
    graded_parts,
    same_material_ties,
    stack_and_heater,
    tmatrix_library,
)
from ..model.forward import ForwardSettings, base_table, resolve_device, structure_flags
from ..model.gas import GASES
from ..model.value_table import ValueTable
from .files import MeasurementError, TMatrixData, read_tmatrix_csv
from .kind import DeviceValues, MeasurementKind, get_engine, smooth_settings


def core_for(data, core: Core | str | None, path) -> Core:
    """``core`` (a Core, a TOML path or bundled name) or the file's ``# core = ...`` metadata."""
    if isinstance(core, Core):
        return core
    name = core or data.metadata.get("core")
    if name is None:
        raise MeasurementError(f"{path}: T-matrix data need a core (--core CORE.toml or a '# core = ...' line)")
    return load_core(name)


@functools.lru_cache(maxsize=64)
def structure_of(transform, core: Core) -> Core:
    """``transform(core)``, a structural effect's core (:attr:`Effect.transform`), kept per
    (transform, core): a fit's every launch asks for the same one, and building a core (its
    checks) costs more than a launch's host work."""
    return transform(core)


#: The suffixes of an elastic frame's fields: its sets' T-matrices are formed on the host.
FRAME_FIELDS = (".frame_modulus", ".frame_loss_factor")


@functools.lru_cache(maxsize=256)
def _table_plan(names: tuple[str, ...]) -> tuple | None:
    """(the engine's names, their rows, the calibration gain's row, its phase's row) of a
    :class:`ValueTable` of ``names`` (None: not there), the rows of the values a launch's
    engine takes, sorted by name as :meth:`TMatrixKind._launch` asks for them; None where
    an elastic frame or a porosity gradient reshapes the sets (their own path)."""
    if any(k.endswith(FRAME_FIELDS + (".porosity_gradient",)) for k in names):
        return None
    row = {k: r for r, k in enumerate(names)}
    engine = tuple(sorted(k for k in names if k not in (CALIBRATION_GAIN, CALIBRATION_PHASE)))
    return (
        engine,
        np.array([row[k] for k in engine], dtype=np.intp),
        row.get(CALIBRATION_GAIN),
        row.get(CALIBRATION_PHASE),
    )


class TMatrixKind(MeasurementKind):
    """Core T-matrix data ``data`` (:class:`TMatrixData`) of ``core``; ``settings`` of the
    forward model (adaptive cells are fixed per segment: :func:`smooth_settings`)."""

    name = "tmatrix"
    group_name = "Q_W"
    coef_names = COEFFICIENTS
    groups_are_heat_inputs = True
    predicts_rows = True
    reduces_on_device = True

    def __init__(self, data: TMatrixData, core: Core, settings: ForwardSettings | None = None):
        heated = sorted({float(q) for q in data.heat_input if q != 0.0})
        if heated and not any(s.heater for s in core.segments):
            # a passive core's model reads no heat input: rows at several would be fitted as one
            raise MeasurementError(
                f"{data.source}: rows at Q = {', '.join(f'{q:g}' for q in heated)} W, but the core "
                f"{core.source} has no heater (a passive core: its data are at Q = 0 only)"
            )
        self.data, self.core = data, core
        # fixed cells: finite-difference Jacobians need a model smooth in the parameters
        self.settings = smooth_settings(core, data.frequencies, settings, heat_input=data.heat_inputs)
        self.Zc = duct_impedance(core)
        self.freqs = data.frequencies
        self.Qs = data.heat_inputs
        nr = len(data)
        self.y = normalize(data.T, self.Zc).reshape(-1)
        self.freq = np.repeat(data.freq, 4)
        self.group = np.repeat(data.heat_input, 4)
        self.coef = np.tile(np.arange(4), nr)
        self._qi = np.searchsorted(self.Qs, data.heat_input)
        self._row_qi = np.repeat(self._qi, 4)  # each row's heat input, an index into Qs
        self._fi = np.searchsorted(self.freqs, data.freq)
        # per heat input: its rows, and their places in a set's T-matrices (m, 2, 2) flattened
        # (None: all of them, in order); slices where the rows are one run
        row_fc = 4 * np.repeat(self._fi, 4) + self.coef
        self._gather = []
        self._row_tables: dict = {}  # per device, the rows' tables of predict_on_device
        for q in range(len(self.Qs)):
            sel = np.flatnonzero(self._row_qi == q)
            if sel.size and np.array_equal(sel, np.arange(sel[0], sel[0] + sel.size)):
                sel = slice(int(sel[0]), int(sel[0]) + sel.size)
            fc = row_fc[sel]
            self._gather.append((q, sel, None if np.array_equal(fc, np.arange(4 * len(self.freqs))) else fc))
        if data.sigma is not None:
            scale = np.array([[1.0, 1.0 / self.Zc], [self.Zc, 1.0]])  # sigma of the dimensionless values
            s = np.asarray(data.sigma) * scale[None, :, :, None]
            self.w = 1.0 / s.reshape(nr * 4, 2)
            self.has_sigma = True
        else:
            self.w = self.unit_weights()

    def family(self) -> tuple:
        """The core's structure (segments, pore models, gas, which fields are set), the
        duct's impedance, the rows' heat inputs and frequencies and the settings: the kinds
        that share these differ only in values that a launch takes per set."""
        return (
            type(self),
            tuple(s.name for s in self.core.segments),
            structure_flags(self.core).tobytes(),
            np.isfinite(base_table(self.core)).tobytes(),
            self.core.gas.name,
            self.Zc,
            self.Qs.tobytes(),
            self.freqs.tobytes(),
            self._qi.tobytes(),
            self._fi.tobytes(),
            repr(dataclasses.replace(self.settings, cells=None)),
        )

    def for_family(self, members: list) -> "TMatrixKind":
        """This kind with each thermal segment's fixed cells the most of ``members``' (each
        sized them for its own core, :func:`smooth_settings`): every member's predictions at
        least as fine as its own settings make them."""
        cells = [m.settings.cells for m in members]
        if all(c == cells[0] for c in cells):
            return self
        out = copy.copy(self)
        out.settings = dataclasses.replace(self.settings, cells={k: max(c[k] for c in cells) for k in cells[0]})
        return out

    @classmethod
    def from_file(cls, path, core=None, settings=None) -> "TMatrixKind":
        data = read_tmatrix_csv(path)
        return cls(data, core_for(data, core, path), settings)

    def default_names(self) -> list[str]:
        """The stack's porosity and pore radius and the h of thermal segments with h > 1;
        for a passive core (no stack) every porous segment's porosity, pore radius and
        tortuosity."""
        stack, _ = stack_and_heater(self.core)
        if stack is None:
            return [
                f"{s.name}.{f}"
                for s in self.core.segments
                if s.is_porous
                for f in ("porosity", "pore_radius", "tortuosity")
            ]
        names = [f"{stack}.porosity", f"{stack}.pore_radius"]
        return names + [f"{s.name}.h" for s in (self.core.segments[i] for i in self.core.thermal_indices) if s.h > 1.0]

    def base_names(self) -> list[str]:
        """The paper's full base fit (docs/physics.md, "Inverse problem"): the porosity, pore
        radius and tortuosity of every porous segment that is not the heater (the stack, a
        passive sample: the material under test) and, with heat input in the data, every
        thermal segment's h, whatever its size. The hot exchanger's geometry is part of the
        rig, as in the paper: freeing it lets it bend towards the bounds to take up an
        effect's misfit (add it with ``--fit``); where it is the stack's material it moves
        with the stack's (:meth:`ties`)."""
        names = [
            f"{s.name}.{f}"
            for s in self.core.segments
            if s.is_porous and not s.heater
            for f in ("porosity", "pore_radius", "tortuosity")
        ]
        if np.any(self.group > 0):
            names += [f"{s.name}.h" for s in self.core.segments if s.thermal]
        return names

    def ties(self) -> dict[str, list[str]]:
        """The hot exchanger's geometry with the stack's where the core file gives both one
        material (:func:`tawarp.model.effects.same_material_ties`): fitted as one, as the
        paper's first step and ``tawarp fit`` do. Left at the file's values while the
        stack's moved, a file's nominal geometry became a misfit that the loop's effects
        took up."""
        return same_material_ties(self.core)

    def effect_library(self) -> list:
        """2-port data: :func:`tawarp.model.effects.tmatrix_library` of the core."""
        return tmatrix_library(self.core)

    def first_step_rows(self) -> np.ndarray:
        """The Q = 0 rows, where the h's do not act (the paper's step 1)."""
        return np.flatnonzero(self.group == 0)

    def heat_groups(self) -> list[float]:
        return [float(q) for q in np.unique(self.group) if q > 0]

    def extra_groups(self) -> list[float]:
        """Heat inputs 1.5 and 2 times the highest measured (a core's safe limit is not in its
        file: the report gives the values, the user judges them)."""
        q = float(np.max(self.Qs))
        return [1.5 * q, 2.0 * q] if q > 0 else []

    def at_rows(self, groups, freqs) -> "TMatrixKind":
        g, f = np.meshgrid(np.asarray(groups, dtype=float), np.asarray(freqs, dtype=float), indexing="ij")
        T = np.broadcast_to(np.eye(2, dtype=complex), (g.size, 2, 2))
        data = TMatrixData(g.reshape(-1), f.reshape(-1), T, source=f"{self.data.source} (planned)")
        return TMatrixKind(
            data,
            self.core,
            dataclasses.replace(self.settings, cells=None) if self.settings.cells is None else self.settings,
        )

    def predict(self, values: dict, n: int, effect=None, rows: list | None = None) -> np.ndarray:
        """Dimensionless coefficients (n, rows) of ``n`` parameter sets; the calibration
        effect's gain g (``calibration.gain`` exp(i ``calibration.phase``), see
        :func:`tawarp.model.effects.calibration_effect`) multiplies all four (g = 1 + 0i:
        exactly the uncalibrated values); a stack's ``porosity_gradient`` splits it into
        parts (:func:`tawarp.model.effects.graded_parts`). ``rows``
        (:meth:`MeasurementKind.predict`): a set's T-matrices at the heat inputs none of its
        rows reads are not computed (NaN there): the loop's fits of the Q = 0 rows alone and
        of one heat input each (each column is computed on its own: the others' values are
        the same bit for bit)."""
        launch = self._launch(values, n, effect, rows, on_device=False)
        if launch is None:
            return np.full((n, self.y.size), np.nan, dtype=np.complex128)
        T, columns, needed, factor, frame, values = launch
        # a diverging trial's T-matrices hold infinities: its cost is inf, which the LM rejects
        with np.errstate(over="ignore", invalid="ignore"):
            if frame:
                T = self._with_elastic_frame(T[columns], values, frame, n)
                T[~needed] = np.nan
                Y = normalize(T[:, self._qi, self._fi], self.Zc).reshape(n, -1)
            else:
                # the distinct columns made dimensionless (each once: T is this call's own),
                # then each set's rows gathered per heat input
                flat = normalize_entries(T.reshape(T.shape[0], -1), self.Zc)
                Y = np.empty((n, self.y.size), dtype=np.complex128)
                for q, sel, fc in self._gather:
                    Y[:, sel] = flat[columns[:, q]] if fc is None else flat[columns[:, q]][:, fc]
                    if not needed[:, q].all():
                        Y[np.ix_(~needed[:, q], np.arange(self.y.size)[sel])] = np.nan
            if factor is not None:
                Y *= factor[:, None]
        return Y

    def predict_on_device(self, values: dict, n: int, effect=None, rows: list | None = None) -> DeviceValues:
        """:meth:`predict`'s model values as the launch left them on the device
        (:class:`tawarp.measure.kind.DeviceValues`: the distinct columns' raw T-matrices, each
        set's column per heat input, the calibration's gain, the rows' entries and the
        factors that make them dimensionless): the same numbers, never gathered on the
        host. An elastic frame's sets (Biot's 2-port, formed on the host) are copied there."""
        plain = isinstance(values, ValueTable) and _table_plan(values.names) is not None
        if not plain and any(k.endswith(FRAME_FIELDS) for k in values):
            return super().predict_on_device(values, n, effect, rows)
        device = resolve_device(self.settings.device)
        launch = self._launch(values, n, effect, rows, on_device=True)
        factor = None
        if launch is None:
            T, columns = wp.zeros((1, 2), dtype=wp.float64, device=device), np.full((n, len(self.Qs)), -1)
        else:
            T, columns, needed, factor, _, _ = launch
            T = T.reshape((T.shape[0], T.shape[1] * T.shape[2]))
            columns = np.where(needed, columns, -1)
        tables = self._row_tables.get(device)
        if tables is None:
            coef_scale = np.array([1.0, 1.0 / self.Zc, self.Zc, 1.0])  # normalize_entries' operations
            tables = self._row_tables[device] = (
                wp.zeros((0, 2), dtype=wp.float64, device=device),  # no gain: 1
                wp.array(self._row_qi.astype(np.int32), device=device),
                wp.array((4 * np.repeat(self._fi, 4) + self.coef).astype(np.int32), device=device),
                wp.array(coef_scale[self.coef], device=device),
            )
        gain = tables[0] if factor is None else wp.array(np.stack([factor.real, factor.imag], axis=1), device=device)
        return DeviceValues(T, wp.array(columns.astype(np.int32), device=device), gain, *tables[1:], 0, n)

    def _launch(self, values: dict, n: int, effect, rows: list | None, on_device: bool):
        """The launch of :meth:`predict`: (T, columns, needed, factor, frame, values): the
        distinct columns' T-matrices (``on_device``: :meth:`Engine.distinct`'s Warp array),
        each set's column per heat input (n, heat inputs) and whether it is needed there,
        the calibration's complex factor (n,) (None: uncalibrated), the elastic frame's
        fields and the other values; None where no set needs any heat input."""
        core = structure_of(effect.transform, self.core) if effect is not None and effect.transform else self.core
        settings = self.settings
        plan = _table_plan(values.names) if isinstance(values, ValueTable) else None
        if plan is not None:  # a batch's table: the engine's rows gathered in one step
            names, order, gain_row, phase_row = plan
            per_set = values.array[order]
            gain = None if gain_row is None else values.array[gain_row]
            phase = None if phase_row is None else values.array[phase_row]
            frame: dict = {}
        else:
            values = dict(values)
            gain = values.pop(CALIBRATION_GAIN, None)
            phase = values.pop(CALIBRATION_PHASE, None)
            frame = {k: values.pop(k) for k in list(values) if k.endswith(FRAME_FIELDS)}
            whole = core
            core, values = graded_parts(whole, values, n)
            if isinstance(settings.cells, dict) and len(core.segments) != len(whole.segments):
                settings = dataclasses.replace(settings, cells=graded_cells(settings.cells, core))
            names = tuple(sorted(values))
            per_set = np.empty((len(names), n))
            for j, k in enumerate(names):
                per_set[j] = values[k]
        eng = get_engine(core, self.freqs, list(names), settings)
        nq = len(self.Qs)
        table = np.empty((1 + len(names), n * nq))
        table[0] = np.tile(self.Qs, n)
        table[1:] = np.repeat(per_set, nq, axis=1)
        # sets that differ in host-side fields alone (the gain, the frame) or in what a heat
        # input of 0 does not read share one column
        needed = self._needed_heat_inputs(rows, n).reshape(-1)
        if not needed.any():
            return None
        T, column = eng.distinct(table if needed.all() else table[:, needed], on_device=on_device)
        # the column of each (set, heat input); where not needed the first (its rows set to NaN)
        columns = np.zeros(n * nq, dtype=column.dtype)
        columns[needed] = column
        factor = None
        if gain is not None or phase is not None:
            g = np.broadcast_to(np.asarray(1.0 if gain is None else gain, dtype=float), (n,))
            ph = np.broadcast_to(np.asarray(0.0 if phase is None else phase, dtype=float), (n,))
            with np.errstate(over="ignore", invalid="ignore"):
                factor = g * np.exp(1j * ph)
        return T, columns.reshape(n, nq), needed.reshape(n, nq), factor, frame, values

    def _needed_heat_inputs(self, rows: list | None, n: int) -> np.ndarray:
        """(n, heat inputs) bool: the heat inputs whose rows each set's ``rows`` (None: all,
        the default of every set) holds."""
        out = np.ones((n, len(self.Qs)), dtype=bool)
        if rows is None:
            return out
        seen: dict = {}  # a fit's sets share its rows' array
        for i, r in enumerate(rows):
            if r is not None:
                if id(r) not in seen:
                    seen[id(r)] = np.bincount(self._row_qi[r], minlength=len(self.Qs)) > 0
                out[i] = seen[id(r)]
        return out

    def _with_elastic_frame(self, T: np.ndarray, values: dict, frame: dict, n: int) -> np.ndarray:
        """``T`` (n, nq, m, 2, 2) with the sample's 2-port replaced by the Biot 2-port
        (:func:`tawarp.model.biot.fluid_transfer_matrix`, frame sliding at the wall) in the
        sets whose ``SAMPLE.frame_mobility`` and ``SAMPLE.frame_modulus`` are > 0 (modulus 0:
        the kernels' limp frame as it stands): ``T_after T_biot T_before``, the parts
        before and after the sample and the sample's equivalent fluid (a thin slice,
        :func:`tawarp.model.biot.equivalent_fluid`) from the kernels, in one launch each."""
        sample = next(k for k in frame if k.endswith(".frame_modulus")).rpartition(".")[0]
        every = {**values, **frame}
        per_set = lambda k, default: np.broadcast_to(np.asarray(every.get(k, default), dtype=float), (n,))  # noqa: E731
        mob = per_set(f"{sample}.frame_mobility", self.core.get(f"{sample}.frame_mobility"))
        sets = np.flatnonzero((mob > 0) & (per_set(f"{sample}.frame_modulus", 0.0) > 0))
        if not sets.size:
            return T
        segs = self.core.segments
        k = next(i for i, s in enumerate(segs) if s.name == sample)
        seg = segs[k]
        glob = {g: per_set(g, None)[sets] for g in values if g.startswith(("gas.", "tube."))}
        freqs = self.freqs

        def part(sub: tuple, extra: dict | None = None) -> np.ndarray:
            """T (len(sets), m, 2, 2) of the segments ``sub`` at the sets' values."""
            if not sub:
                return np.broadcast_to(np.eye(2, dtype=complex), (sets.size, len(freqs), 2, 2))
            core = Core(sub, self.core.gas, self.core.radius, self.core.source)
            own = {nm: per_set(nm, None)[sets] for nm in values if nm.partition(".")[0] in {s.name for s in sub}}
            vals = {**glob, **own, **(extra or {})}
            names = sorted(vals)
            eng = get_engine(core, freqs, names, self.settings)
            table = np.vstack([np.zeros(sets.size)] + [np.broadcast_to(vals[nm], (sets.size,)) for nm in names])
            out, _, _ = eng.evaluate(table)
            return out.numpy().view(np.complex128).reshape(sets.size, len(freqs), 2, 2)

        rigid = dataclasses.replace(seg, frame_mobility=0.0)
        slab = part(
            (rigid,),
            {f"{sample}.length": np.full(sets.size, FLUID_SLICE), f"{sample}.frame_mobility": np.zeros(sets.size)},
        )
        g = GASES[self.core.gas.name]
        T0 = glob.get("gas.T_cold", np.full(sets.size, self.core.gas.T_cold))[:, None]
        p0 = glob.get("gas.p_mean", np.full(sets.size, self.core.gas.p_mean))[:, None]
        radius = glob.get("tube.radius", np.full(sets.size, self.core.radius))[:, None]
        area = np.pi * radius**2
        rho_eq, K_eq = equivalent_fluid(slab, FLUID_SLICE, 2 * np.pi * freqs, area)
        fluid = JCAFluid(rho_eq, K_eq, p0 / (g.R_gas * T0), np.sqrt(g.gamma * g.R_gas * T0))
        # Biot's parameters per set (its batch shape; it adds the frequency axis itself)
        Tb = fluid_transfer_matrix(
            freqs,
            fluid,
            thickness=per_set(f"{sample}.length", seg.length)[sets],
            phi=per_set(f"{sample}.porosity", seg.porosity)[sets],
            E=per_set(f"{sample}.frame_modulus", None)[sets],
            eta=per_set(f"{sample}.frame_loss_factor", None)[sets],
            nu=FRAME_POISSON_RATIO,
            rho_1=1.0 / mob[sets],
            area=area[:, 0],
        )
        T = T.copy()
        T[sets] = (part(segs[k + 1 :]) @ Tb @ part(segs[:k]))[:, None]
        return T
