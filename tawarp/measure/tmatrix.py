"""Core T-matrices as a measurement kind.

Rows: (heat input, frequency) x the four dimensionless coefficients ``Tpp, Tpu/Zc,
Tup*Zc, Tuu`` (:mod:`tawarp.model.coefficients`), Zc of the core as given (a constant
even when ``gas.T_cold`` is fitted). Predictions: one forward launch of the core's
T-matrices for every (parameter set, heat input). Files: :func:`read_tmatrix_csv`.
"""

from __future__ import annotations

import numpy as np

from ..model.coefficients import COEFFICIENTS, duct_impedance, normalize
from ..model.core import Core, load_core
from ..model.forward import ForwardSettings
from .files import MeasurementError, TMatrixData, read_tmatrix_csv
from .kind import MeasurementKind, get_engine, smooth_settings


def core_for(data, core: Core | str | None, path) -> Core:
    """``core`` (a Core, a TOML path or bundled name) or the file's ``# core = ...`` metadata."""
    if isinstance(core, Core):
        return core
    name = core or data.metadata.get("core")
    if name is None:
        raise MeasurementError(f"{path}: T-matrix data need a core (--core CORE.toml or a '# core = ...' line)")
    return load_core(name)


class TMatrixKind(MeasurementKind):
    """Core T-matrix data ``data`` (:class:`TMatrixData`) of ``core``; ``settings`` of the
    forward model (adaptive cells are fixed per segment: :func:`smooth_settings`)."""

    name = "tmatrix"
    group_name = "Q_W"
    coef_names = COEFFICIENTS

    def __init__(self, data: TMatrixData, core: Core, settings: ForwardSettings | None = None):
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
        self._fi = np.searchsorted(self.freqs, data.freq)
        if data.sigma is not None:
            scale = np.array([[1.0, 1.0 / self.Zc], [self.Zc, 1.0]])   # sigma of the dimensionless values
            s = np.asarray(data.sigma) * scale[None, :, :, None]
            self.w = 1.0 / s.reshape(nr * 4, 2)
            self.has_sigma = True
        else:
            self.w = self.unit_weights()

    @classmethod
    def from_file(cls, path, core=None, settings=None) -> "TMatrixKind":
        data = read_tmatrix_csv(path)
        return cls(data, core_for(data, core, path), settings)

    def default_names(self) -> list[str]:
        """The stack's porosity and pore radius and the h of thermal segments with h > 1;
        for a passive core (no stack) every porous segment's porosity, pore radius and
        tortuosity."""
        from ..model.effects import stack_and_heater

        stack, _ = stack_and_heater(self.core)
        if stack is None:
            return [f"{s.name}.{f}" for s in self.core.segments if s.is_porous
                    for f in ("porosity", "pore_radius", "tortuosity")]
        names = [f"{stack}.porosity", f"{stack}.pore_radius"]
        return names + [f"{s.name}.h" for s in (self.core.segments[i] for i in self.core.thermal_indices) if s.h > 1.0]

    def predict(self, values: dict, n: int, effect=None) -> np.ndarray:
        names = tuple(sorted(values))
        core = effect.transform(self.core) if effect is not None and effect.transform else self.core
        eng = get_engine(core, self.freqs, list(names), self.settings)
        nq = len(self.Qs)
        table = np.empty((1 + len(names), n * nq))
        table[0] = np.tile(self.Qs, n)
        for j, k in enumerate(names):
            table[1 + j] = np.repeat(np.broadcast_to(np.asarray(values[k], dtype=float), (n,)), nq)
        out, _, _ = eng.evaluate(table)
        T = out.numpy().view(np.complex128).reshape(n, nq, len(self.freqs), 2, 2)
        return normalize(T[:, self._qi, self._fi], self.Zc).reshape(n, -1)
