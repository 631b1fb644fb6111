"""Measurements: file readers and writers (:mod:`.files`), measurement kinds (one module
each: :mod:`.tmatrix`, :mod:`.impedance`, :mod:`.scattering`) and their registry
(:mod:`.kind`), synthetic data (:mod:`.synthetic`)."""

from .files import (
    ImpedanceData,
    MeasurementError,
    ScatteringData,
    TMatrixData,
    atalla_panneton_samples,
    load_atalla_panneton,
    read_atalla_panneton,
    read_impedance_csv,
    read_scattering,
    read_scattering_csv,
    read_tmatrix_csv,
    scattering_to_transfer,
    transfer_to_scattering,
    write_scattering_csv,
    write_tmatrix_csv,
)
from .impedance import ImpedanceKind
from .kind import KINDS, MeasurementKind, get_engine, kind_of, load_measurement, register_kind
from .scattering import ScatteringKind, calibrate_empty_tube
from .tmatrix import TMatrixKind

register_kind("tmatrix", TMatrixKind, lambda cols: "Tpp_re" in cols)
register_kind("impedance", ImpedanceKind, lambda cols: "Zs_re" in cols)
register_kind("scattering", ScatteringKind, lambda cols: "S11_re" in cols)

__all__ = [
    "ImpedanceData",
    "MeasurementError",
    "ScatteringData",
    "TMatrixData",
    "calibrate_empty_tube",
    "read_scattering",
    "write_scattering_csv",
    "atalla_panneton_samples",
    "load_atalla_panneton",
    "read_atalla_panneton",
    "read_impedance_csv",
    "read_scattering_csv",
    "read_tmatrix_csv",
    "scattering_to_transfer",
    "transfer_to_scattering",
    "write_tmatrix_csv",
    "ImpedanceKind",
    "KINDS",
    "MeasurementKind",
    "get_engine",
    "kind_of",
    "load_measurement",
    "register_kind",
    "ScatteringKind",
    "TMatrixKind",
]
