"""Dimensionless T-matrix coefficients and docs/formats.md's error measure."""

import math

import numpy as np
import pytest

from tawarp.model.coefficients import denormalize, duct_impedance, normalize, normalize_entries, rms_error
from tawarp.model.core import load_core


def test_duct_impedance_is_rho_c_over_area():
    core = load_core("ceramic")
    rho = 101325.0 / (287.05 * 293.15)
    c = math.sqrt(1.4 * 287.05 * 293.15)
    assert duct_impedance(core) == pytest.approx(rho * c / (math.pi * core.radius**2), rel=1e-15)


def test_normalize_round_trip_and_lossless_duct():
    """A lossless duct of length L has Tpp = Tuu = cos kL, Tpu/Zc = Tup Zc = i sin kL
    (exp(-iwt)); normalize then denormalize is the identity."""
    Zc, kL = 4.2e5, np.linspace(0.1, 3.0, 7)
    T = np.empty(kL.shape + (2, 2), dtype=complex)
    T[:, 0, 0] = T[:, 1, 1] = np.cos(kL)
    T[:, 0, 1], T[:, 1, 0] = 1j * Zc * np.sin(kL), 1j * np.sin(kL) / Zc
    Y = normalize(T, Zc)
    np.testing.assert_allclose(Y[:, 1], 1j * np.sin(kL), rtol=1e-15)
    np.testing.assert_allclose(Y[:, 2], 1j * np.sin(kL), rtol=1e-15)
    np.testing.assert_allclose(denormalize(Y, Zc), T, rtol=1e-15)


def test_rms_error_definition():
    """rms |Y_meas - Y_model| / rms |Y_meas|: a uniform relative perturbation e gives e."""
    rng = np.random.default_rng(0)
    Y = rng.standard_normal((5, 4)) + 1j * rng.standard_normal((5, 4))
    assert float(rms_error(Y, Y * (1 + 0.01j))) == pytest.approx(0.01, rel=1e-12)
    assert float(rms_error(Y, Y)) == 0.0


def test_normalize_entries_in_place_gives_normalizes_numbers():
    """Raw entries laid out as normalize's result (k matrices' T00, T01, T10, T11 in a row),
    scaled in place: the same numbers bit for bit."""
    rng = np.random.default_rng(3)
    T = rng.normal(size=(5, 7, 2, 2)) + 1j * rng.normal(size=(5, 7, 2, 2))
    Zc = 413.7
    entries = T.reshape(5, 28).copy()
    assert normalize_entries(entries, Zc) is entries
    assert np.array_equal(entries, normalize(T, Zc).reshape(5, 28))
