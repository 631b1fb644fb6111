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

from ..model.forward import ForwardSettings
from ..model.layer import LAYER_BASE, layer_core, surface_impedance_from_T
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

    def __init__(self, data: list[ImpedanceData], settings: ForwardSettings | None = None,
                 start: dict | None = None, gas: str = "air"):
        self.data = [data] if isinstance(data, ImpedanceData) else list(data)
        if not self.data:
            raise MeasurementError("impedance: no data sets")
        for d in self.data:
            if d.thickness is None:
                raise MeasurementError(f"{d.source}: layer thickness unknown (metadata 'thickness')")
        self.settings = settings or ForwardSettings()
        d0 = self.data[0]
        self.core = layer_core(d0.thickness, T_ambient=d0.T_ambient or 293.15, p_ambient=d0.p_ambient or 101325.0,
                               gas=gas).replace(**(LAYER_START if start is None else start))
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

    def predict(self, values: dict, n: int, effect=None) -> np.ndarray:
        names = sorted(k for k in values if k not in ("layer.length_offset", "layer.length"))
        eng = get_engine(self.core, self.freqs, names + ["layer.length"], self.settings)
        L = len(self.data)
        table = np.empty((2 + len(names), n * L))
        table[0] = 0.0
        for j, name in enumerate(names):
            table[1 + j] = np.repeat(np.broadcast_to(np.asarray(values[name], dtype=float), (n,)), L)
        dL = np.broadcast_to(np.asarray(values.get("layer.length_offset", 0.0), dtype=float), (n,))
        table[-1] = (self.thickness[None, :] + dL[:, None]).reshape(-1)
        out, _, _ = eng.evaluate(table)
        T = out.numpy().view(np.complex128).reshape(n, L, len(self.freqs), 2, 2)
        Z = surface_impedance_from_T(T, self.core)
        return np.concatenate([Z[:, k, self._index[k]] for k in range(L)], axis=1)
