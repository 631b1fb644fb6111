"""Four-microphone scattering matrices as a measurement kind: converted to core
T-matrices on load (:func:`read_scattering_csv`), then fitted as :class:`TMatrixKind`."""

from __future__ import annotations

from .files import read_scattering_csv
from .tmatrix import TMatrixKind, core_for


class ScatteringKind(TMatrixKind):
    """T-matrices converted from a scattering matrix; ``data.metadata['converted_from']``."""

    name = "scattering"

    @classmethod
    def from_file(cls, path, core=None, settings=None) -> "ScatteringKind":
        data = read_scattering_csv(path)
        return cls(data, core_for(data, core, path), settings)
