"""Surface impedance of rigid-backed porous layers as a measurement kind.

Layers of one material measured at one or more thicknesses, at one ambient state: rows
(layer, frequency), ``group`` = layer thickness [m], one observable ``Zs`` (specific
surface impedance over rho0 c0, exp(-iwt)). The model is the one-segment layer core of
:mod:`tawarp.model.layer` (no ``--core``): one forward launch over the union of the
layers' frequencies for every (parameter set, layer). ``layer.length_offset`` [m] (an
effect) adds to every thickness. Files: :func:`read_impedance_csv`.
"""

from __future__ import annotations

import numpy as np

from ..model.biot import FLUID_SLICE, FRAME_POISSON_RATIO, JCAFluid, equivalent_fluid, fluid_surface_impedance
from ..model.effects import FRAME_LOSS_FACTOR, FRAME_MOBILITY, FRAME_WAVE_SPEED, P_WAVE_FACTOR, impedance_library
from ..model.forward import ForwardSettings
from ..model.gas import GASES
from ..model.layer import LAYER_BASE, characteristic_impedance, layer_core, surface_impedance_from_T
from .files import ImpedanceData, MeasurementError, read_impedance_csv
from .kind import MeasurementKind, get_engine

#: Start of the layer model (a typical foam): porosity, pore radius [m], tortuosity.
LAYER_START = {"layer.porosity": 0.95, "layer.pore_radius": 1.5e-4, "layer.tortuosity": 1.1}


class ImpedanceKind(MeasurementKind):
    """Surface impedance ``data`` (list of :class:`ImpedanceData`, thickness known);
    ``start`` {name: value} of the layer core (default :data:`LAYER_START`)."""

    name = "impedance"
    group_name = "thickness_m"
    coef_names = ("Zs",)
    #: the frame's wave speed and loss factor and the thickness are host-side (:meth:`predict`)
    neighbours_share_columns = True

    def __init__(
        self,
        data: list[ImpedanceData],
        settings: ForwardSettings | None = None,
        start: dict | None = None,
        gas: str = "air",
    ):
        self.data = [data] if isinstance(data, ImpedanceData) else list(data)
        if not self.data:
            raise MeasurementError("impedance: no data sets")
        for d in self.data:
            if d.thickness is None:
                raise MeasurementError(f"{d.source}: layer thickness unknown (metadata 'thickness')")
        self.settings = settings or ForwardSettings()
        d0 = self.data[0]
        self.core = layer_core(
            d0.thickness, T_ambient=d0.T_ambient or 293.15, p_ambient=d0.p_ambient or 101325.0, gas=gas
        ).replace(**(LAYER_START if start is None else start))
        self.freqs = np.unique(np.concatenate([d.freq for d in self.data]))
        self._index = [np.searchsorted(self.freqs, d.freq) for d in self.data]
        self.thickness = np.array([d.thickness for d in self.data])
        self.y = np.concatenate([d.Zs for d in self.data])
        self.freq = np.concatenate([d.freq for d in self.data])
        self.group = np.concatenate([np.full(len(d), d.thickness) for d in self.data])
        self.coef = np.zeros(self.y.size, dtype=int)
        self.has_sigma = all(d.sigma is not None for d in self.data)
        self.w = 1.0 / np.concatenate([d.sigma for d in self.data]) if self.has_sigma else self.unit_weights()

    @classmethod
    def from_file(cls, path, core=None, settings=None) -> "ImpedanceKind":
        """One layer from a surface-impedance CSV (``core`` is not used: the layer model)."""
        return cls([read_impedance_csv(path)], settings)

    def default_names(self) -> list[str]:
        return list(LAYER_BASE)

    def effect_library(self) -> list:
        """A rigid-backed layer: :func:`tawarp.model.effects.impedance_library` of the core."""
        return impedance_library(self.core)

    def extra_groups(self) -> list[float]:
        """A second sample length: twice and half the thickest layer's."""
        t = float(np.max(self.thickness))
        return [2.0 * t, 0.5 * t]

    def at_rows(self, groups, freqs) -> "ImpedanceKind":
        d0 = self.data[0]
        data = [
            ImpedanceData(
                np.asarray(freqs, dtype=float),
                np.ones(len(freqs), dtype=complex),
                float(t),
                d0.T_ambient,
                d0.p_ambient,
                source=f"{d0.source} (planned)",
            )
            for t in groups
        ]
        out = ImpedanceKind(data, self.settings)
        out.core = self.core
        return out

    def predict(self, values: dict, n: int, effect=None) -> np.ndarray:
        """Zs (n, rows) of ``n`` parameter sets. The rigid-frame layer is the kernels' porous
        segment, and so is a limp frame (``layer.frame_mobility`` m > 0, frame wave speed
        ``layer.frame_wave_speed`` c 0 or not given: Biot's frame at E -> 0, the kernels' limp
        frame). A set with an elastic frame (m > 0, c > 0: Young's modulus
        E = c^2 / (m (1 - nu)/((1 + nu)(1 - 2 nu)))) takes the kernels' equivalent fluid of
        the same parameters (:func:`equivalent_fluid`, from a thin slice of the rigid frame in
        the same launch) under the Biot frame of :func:`tawarp.model.biot.fluid_surface_impedance` of density
        1/m. At m = 0 the set is the rigid model bit for bit (the frame's other fields are
        then not read): an infinitely heavy frame does not move.

        One launch for the distinct columns alone: a rigid set needs its layers, an elastic
        set only its slice, and the sets of one LM iteration (a trial point and its
        forward-difference neighbours) differing in the host-side fields share their
        columns (the kernels compute each column on its own, so sharing changes no bit)."""
        host = (FRAME_WAVE_SPEED, FRAME_LOSS_FACTOR, "layer.length_offset", "layer.length")
        names = sorted(k for k in values if k not in host)
        eng = get_engine(self.core, self.freqs, names + ["layer.length"], self.settings)
        per_set = lambda k, default: np.broadcast_to(np.asarray(values.get(k, default), dtype=float), (n,))  # noqa: E731
        m = per_set(FRAME_MOBILITY, 0.0)
        c = per_set(FRAME_WAVE_SPEED, 0.0)
        elastic = np.flatnonzero((m > 0) & (c > 0))
        rigid = np.setdiff1d(np.arange(n), elastic)
        L = len(self.data)
        d = self.thickness[None, :] + per_set("layer.length_offset", 0.0)[:, None]
        # columns: every rigid set's L layers, then every elastic set's slice of the rigid frame
        sets = np.concatenate([np.repeat(rigid, L), elastic])
        table = np.empty((2 + len(names), sets.size))
        table[0] = 0.0
        for j, name in enumerate(names):
            table[1 + j] = per_set(name, None)[sets]
            if name == FRAME_MOBILITY:
                table[1 + j, rigid.size * L :] = 0.0
        table[-1] = np.concatenate([d[rigid].reshape(-1), np.full(elastic.size, FLUID_SLICE)])
        distinct, column = np.unique(table, axis=1, return_inverse=True)
        out, _, _ = eng.evaluate(np.ascontiguousarray(distinct))
        T = out.numpy().view(np.complex128).reshape(distinct.shape[1], len(self.freqs), 2, 2)
        Z = np.empty((n, L, len(self.freqs)), dtype=complex)
        Z[rigid] = surface_impedance_from_T(T[column[: rigid.size * L].reshape(rigid.size, L)], self.core)
        if elastic.size:
            slices, slice_of = np.unique(column[rigid.size * L :], return_inverse=True)
            Z[elastic] = self._elastic(
                T[slices],
                slice_of,
                d[elastic],
                {k: per_set(k, None)[elastic] for k in names},
                c[elastic] ** 2 / m[elastic] / P_WAVE_FACTOR,
                per_set(FRAME_LOSS_FACTOR, 0.0)[elastic],
                1.0 / m[elastic],
            )
        return np.concatenate([Z[:, k, self._index[k]] for k in range(L)], axis=1)

    def _elastic(self, T_slice, slice_of, d, vals, E, eta, rho_1) -> np.ndarray:
        """Zs (k, L, freqs) of an elastic frame (Young's modulus E, loss factor eta, density rho_1,
        Poisson ratio :data:`FRAME_POISSON_RATIO`) in the fluid of the thin slices ``T_slice``
        (set i's is ``T_slice[slice_of[i]]``)."""
        g = GASES[self.core.gas.name]
        T0 = vals.get("gas.T_cold", np.full(E.size, self.core.gas.T_cold))[:, None]
        p0 = vals.get("gas.p_mean", np.full(E.size, self.core.gas.p_mean))[:, None]
        rho0, c0 = p0 / (g.R_gas * T0), np.sqrt(g.gamma * g.R_gas * T0)
        rho_eq, K_eq = (
            a[slice_of] for a in equivalent_fluid(T_slice, FLUID_SLICE, 2 * np.pi * self.freqs, self.core.area)
        )
        fl = JCAFluid(rho_eq, K_eq, rho0, c0)
        phi = vals.get("layer.porosity", np.full(E.size, self.core.segments[0].porosity))
        Zs = fluid_surface_impedance(
            self.freqs,
            JCAFluid(*(a[:, None] for a in fl)),
            thickness=d,
            phi=phi[:, None],
            E=E[:, None],
            eta=eta[:, None],
            nu=FRAME_POISSON_RATIO,
            rho_1=rho_1[:, None],
        )
        # biot normalizes by the set's rho0 c0; the rigid path (and the data) by the core's
        return Zs * (rho0 * c0)[:, None] / characteristic_impedance(self.core)
