"""Dimensionless T-matrix coefficients and the error measure of docs/formats.md.

Residuals and plots use ``Tpp``, ``Tpu / Zc``, ``Tup * Zc``, ``Tuu`` with
``Zc = rho0 c0 / S`` of the empty duct at the cold temperature.
"""

from __future__ import annotations

import math

import numpy as np

from .core import Core
from .gas import GASES

COEFFICIENTS = ("Tpp", "Tpu/Zc", "Tup*Zc", "Tuu")


def duct_impedance(core: Core) -> float:
    """Zc = rho0 c0 / S [Pa s/m^3] of the empty tube at ``gas.T_cold`` (ideal gas)."""
    g = GASES[core.gas.name]
    rho0 = core.gas.p_mean / (g.R_gas * core.gas.T_cold)
    c0 = math.sqrt(g.gamma * g.R_gas * core.gas.T_cold)
    return rho0 * c0 / core.area


def normalize(T: np.ndarray, Zc: float | np.ndarray) -> np.ndarray:
    """Raw T-matrices (..., 2, 2) -> dimensionless coefficients (..., 4) in the order
    of :data:`COEFFICIENTS`. ``Zc`` broadcasts against the leading axes."""
    T = np.asarray(T)
    Zc = np.asarray(Zc, dtype=float)[..., None] if np.ndim(Zc) else Zc
    return np.stack([T[..., 0, 0], T[..., 0, 1] / Zc, T[..., 1, 0] * Zc, T[..., 1, 1]], axis=-1)


def normalize_entries(Y: np.ndarray, Zc: float) -> np.ndarray:
    """:func:`normalize` in place on raw T-matrix entries laid out as its result, (..., 4 k)
    of k matrices' ``T[0, 0], T[0, 1], T[1, 0], T[1, 1]`` (the same numbers); returns ``Y``."""
    Y[..., 1::4] /= Zc
    Y[..., 2::4] *= Zc
    return Y


def denormalize(Y: np.ndarray, Zc: float | np.ndarray) -> np.ndarray:
    """Inverse of :func:`normalize`: (..., 4) -> (..., 2, 2)."""
    Y = np.asarray(Y)
    Zc = np.asarray(Zc, dtype=float)[..., None] if np.ndim(Zc) else Zc
    T = np.stack([Y[..., 0], Y[..., 1] * Zc, Y[..., 2] / Zc, Y[..., 3]], axis=-1)
    return T.reshape(Y.shape[:-1] + (2, 2))


def rms_error(Y_meas: np.ndarray, Y_model: np.ndarray, axis=None) -> np.ndarray:
    """docs/formats.md error: rms |Y_meas - Y_model| / rms |Y_meas| over rows and coefficients
    (or over ``axis``)."""
    num = np.mean(np.abs(np.asarray(Y_meas) - np.asarray(Y_model)) ** 2, axis=axis)
    den = np.mean(np.abs(np.asarray(Y_meas)) ** 2, axis=axis)
    return np.sqrt(num / den)
