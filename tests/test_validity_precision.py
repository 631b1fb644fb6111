"""The cascade's self-check: det T = 1 at uniform temperature, relative to the products it
cancels (tawarp.model.validity.check_precision).

The unscaled |det T - 1| of a strongly attenuating core is no measure of its accuracy:
the RVC foam with a 1 um pore radius gives 8e45 at 500 Hz, with every entry of T equal to
the independent reference (tawarp/reference.py: closed forms at Q = 0) to 1e-13. The
scaled deviation is the relative error rounding left in the entries: ~1e-16 there."""

import warnings

import numpy as np
import pytest

from tawarp import reference
from tawarp.model.core import load_core
from tawarp.model.forward import transfer_matrices
from tawarp.model.validity import PRECISION_LOST, PrecisionLostError, ValidityWarning, check_precision, precision_error

RVC = load_core("rvc_foam")
FREQS = [30.0, 100.0, 500.0]


@pytest.mark.parametrize(
    "name, value",
    [
        ("stack.pore_radius", 1e-6),
        ("stack.tortuosity", 100.0),
        ("stack.porosity", 1e-12),
        ("gas.p_mean", 1.0),
        ("gas.p_mean", 100.0),
    ],
)
def test_strongly_attenuating_cores_are_exact_and_pass_the_check(name, value):
    with warnings.catch_warnings():
        warnings.simplefilter("error", ValidityWarning)
        T = transfer_matrices(RVC, FREQS, 0.0, params={name: value}, device="cpu").T[0]
    R = reference.transfer_matrix(RVC.replace(**{name: value}), FREQS, 0.0)
    assert np.max(np.abs(T - R) / np.abs(R)) < 1e-12  # entry by entry, the reference's closed forms
    assert np.max(np.abs(np.linalg.det(T) - 1)) > 1e-3  # what a raw det check would have flagged
    assert precision_error(T[None])[0] < 1e-14


def test_a_perturbed_entry_is_measured_at_its_share_of_the_products():
    """A relative change e of Tpu moves det T by e Tpu Tup: the check reads
    e |Tpu Tup| / (|Tpp Tuu| + |Tpu Tup|) (here to 1 %)."""
    T = transfer_matrices(RVC, FREQS, 0.0, device="cpu").T
    a, b, c, d = T[0, :, 0, 0], T[0, :, 0, 1], T[0, :, 1, 0], T[0, :, 1, 1]
    share = np.abs(b * c) / (np.abs(a * d) + np.abs(b * c))
    P = T.copy()
    P[0, :, 0, 1] *= 1 + 1e-4
    np.testing.assert_allclose(precision_error(P)[0], 1e-4 * share.max(), rtol=1e-2)


def test_beyond_the_tolerance_warns_and_beyond_any_digit_raises():
    T = transfer_matrices(RVC, FREQS, [0.0, 0.0, 5.0], device="cpu").T
    values = {"stack.h": np.array([1.0, 2.0, 3.0])}
    q = np.array([0.0, 0.0, 5.0])
    P = T.copy()
    P[1, 1, 0, 0] *= 1 + 1e-3
    with pytest.warns(
        ValidityWarning,
        match=r"set 1 \(heat_input = 0 W, stack.h = 2\): rounding .* above the "
        r"tolerance 1e-06 .*1 of 3 sets",
    ):
        check_precision(RVC, q, values, P, 1e-6)
    P[2] *= 1 + 1.0  # a heated set: its exact det is not 1; left to the cells' error estimate
    with warnings.catch_warnings():
        warnings.simplefilter("error", ValidityWarning)
        check_precision(RVC, q, values, P, 1e-2)
    P[0, 0, 1, 1] = -P[0, 0, 1, 1]
    assert precision_error(P[:1])[0] > PRECISION_LOST
    with pytest.raises(PrecisionLostError, match=r"set 0 .*no significant digit is left"):
        check_precision(RVC, q, values, P, 1e-6)


def test_overflowing_products_are_scaled_first():
    """A lossy uniform part, T = [[cosh x, Z sinh x], [sinh x / Z, cosh x]] (det 1) at
    x = 400: the entries are 2.6e173 and the products overflow; the check does not."""
    x, Z = 400.0, 1e3
    T = np.array([[[[np.cosh(x), Z * np.sinh(x)], [np.sinh(x) / Z, np.cosh(x)]]]], dtype=complex)
    with np.errstate(over="ignore", invalid="ignore"):
        assert not np.isfinite(T[0, 0, 0, 0] * T[0, 0, 1, 1] - T[0, 0, 0, 1] * T[0, 0, 1, 0])
    assert precision_error(T)[0] < 1e-15
