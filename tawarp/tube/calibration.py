"""Calibration of the microphones and of the tube.

**Switched microphones** (ISO 10534-2 sec. 7.5.2; ASTM E2611 sec. 8.4.5). Each channel
``j`` reads ``g_j p(x_j)``; the transfer function from the reference channel ``r`` is
measured twice in the empty tube, once with every microphone in its place (``H_I``) and
once with microphones ``j`` and ``r`` swapped (``H_II``). Then ``H_I = (g_j/g_r)
p(x_j)/p(x_r)`` and ``H_II = (g_j/g_r) p(x_r)/p(x_j)``, so the calibration factor
``H_c = sqrt(H_I H_II) = g_j / g_r`` (the root with a positive real part: gain-phase
mismatches below 90 degrees) and every later ``H_j`` is divided by it. Its relative
error ``dH_c / H_c = (dH_I / H_I + dH_II / H_II) / 2`` (first order); the two files are
independent, while the ``H_I`` of different channels share the direct file and are
correlated as :meth:`tawarp.tube.spectra.CrossSpectra.transfers` states.

**Empty-tube self-calibration** (the microphones' acoustic centres and the gas state
from the data; on why they matter, Boden & Abom, J. Acoust. Soc. Am. 79, 541, 1986; a
fit of the locations to the measured field, Katz, J. Acoust. Soc. Am. 108, 2231, 2000). In the empty tube the calibrated transfer
functions of ``n >= 3`` microphones at ``x_j`` are one plane-wave field,
``H_j = a exp(-i k x_j) + b exp(+i k x_j)`` (exp(+i omega t), the spectra's convention)
with ``a``, ``b`` free at each frequency and ``k`` Kirchhoff's wavenumber
(:mod:`.acoustics`). The interior positions, the temperature (the sound speed) and the
wall-loss factor are fitted to all frequencies at once by
:func:`scipy.optimize.least_squares`, ``a`` and ``b`` eliminated by linear least squares
at each frequency (variable projection); residuals are weighted by the transfer
functions' random errors. The outermost two positions stay as given: lengths and the
sound speed enter only as ``x / c``, so one length must be fixed, and the span is the one
a ruler measures best.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import scipy.optimize

from ..measure.table import MeasurementError
from .acoustics import plane_waves
from .setup import Gas, Tube
from .spectra import CrossSpectra, Transfers


@dataclass(frozen=True)
class MicrophoneGains:
    """Switched-microphone calibration factors ``H_c`` of ``channels`` relative to the
    reference (1 for the reference itself), (nf, n) complex, and ``covariance`` (nf, n, n)
    of their relative errors ``E[dc_j conj(dc_k)]``, ``dc = dH_c / H_c``."""

    frequencies: np.ndarray
    channels: tuple[int, ...]
    factors: np.ndarray
    covariance: np.ndarray

    def select(self, channels) -> MicrophoneGains:
        """The factors of ``channels`` (any order; the reference's is 1, exactly)."""
        idx = [self.channels.index(c) for c in channels]
        return MicrophoneGains(
            self.frequencies, tuple(channels), self.factors[:, idx], self.covariance[:, idx][:, :, idx]
        )


def switched_gains(
    direct: CrossSpectra, switched: dict[int, CrossSpectra], reference: int, sources: dict[int, str] | None = None
) -> MicrophoneGains:
    """Calibration factors (module doc) of every channel in ``switched`` {channel: its
    switched spectra} and of the reference, from the ``direct`` empty-tube spectra."""
    sources = sources or {}
    channels = (reference, *sorted(switched))
    for ch, s in switched.items():
        if s.frequencies.shape != direct.frequencies.shape or not np.allclose(s.frequencies, direct.frequencies):
            raise MeasurementError(
                f"{sources.get(ch, f'switched channel {ch}')}: frequencies differ from the direct file's; "
                "record the calibration with the same sample rate and block"
            )
        if max(ch, reference) >= s.channels:
            raise MeasurementError(f"{sources.get(ch, ch)}: has {s.channels} channels; channel {ch} is not there")
    direct_t = direct.transfers(reference, channels)
    h1 = direct_t.values
    nf, n = h1.shape
    factors = np.ones((nf, n), dtype=complex)
    cov = np.zeros((nf, n, n), dtype=complex)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel1 = direct_t.covariance / (h1[:, :, None] * np.conj(h1[:, None, :]))
        for m, ch in enumerate(channels[1:], start=1):
            t2 = switched[ch].transfers(reference, [ch])
            h2 = t2.values[:, 0]
            factors[:, m] = np.sqrt(h1[:, m] * h2)
            cov[:, m, m] += np.real(t2.covariance[:, 0, 0]) / np.abs(h2) ** 2 / 4
        sub = rel1[:, 1:, 1:] / 4
    cov[:, 1:, 1:] += sub
    return MicrophoneGains(direct.frequencies, channels, factors, cov)


def corrected(transfers: Transfers, gains: MicrophoneGains) -> Transfers:
    """``transfers`` (of ``gains.channels``, in that order) divided by the calibration
    factors; their random-error covariance scaled alike. The factors' own errors are
    not added here: they are common to every configuration, and the methods take each
    configuration's errors as independent (:func:`tawarp.tube.measure` propagates them)."""
    c = gains.factors
    if c.shape != transfers.values.shape:
        raise ValueError(f"gains {c.shape} and transfers {transfers.values.shape} differ")
    cov = transfers.covariance / (c[:, :, None] * np.conj(c[:, None, :]))
    return Transfers(transfers.frequencies, transfers.values / c, cov)


@dataclass(frozen=True)
class SelfCalibration:
    """The fitted tube: ``positions`` [m], ``temperature`` [K], ``loss`` (the factor on
    Kirchhoff's wall losses), with the nominal values and the covariance of
    ``parameters()`` (interior positions, temperature, loss)."""

    positions: tuple[float, ...]
    temperature: float
    loss: float
    nominal_positions: tuple[float, ...]
    nominal_temperature: float
    covariance: np.ndarray
    rms_before: float
    rms_after: float

    def parameters(self) -> np.ndarray:
        return np.array([*self.positions[1:-1], self.temperature, self.loss])

    def summary(self) -> dict:
        """The changes, for the output's header and the API's result."""
        moved = np.array(self.positions) - np.array(self.nominal_positions)
        sd = np.sqrt(np.diag(self.covariance))
        return {
            "positions_m": [round(float(v), 6) for v in self.positions],
            "position_shift_mm": [round(1e3 * float(v), 3) for v in moved],
            "position_sd_mm": [0.0] + [round(1e3 * float(v), 3) for v in sd[:-2]] + [0.0],
            "temperature_K": round(self.temperature, 3),
            "temperature_sd_K": round(float(sd[-2]), 3),
            "temperature_shift_K": round(self.temperature - self.nominal_temperature, 3),
            "wall_loss_factor": round(self.loss, 4),
            "wall_loss_factor_sd": round(float(sd[-1]), 4),
            "rms_misfit_before": round(self.rms_before, 4),
            "rms_misfit_after": round(self.rms_after, 4),
        }


def field_misfit(transfers: Transfers, positions, k_plus: np.ndarray) -> np.ndarray:
    """Weighted residuals (2 nf n,) of ``transfers`` (nf, n) against the best plane-wave
    field ``a exp(-i k x) + b exp(+i k x)`` at each frequency (exp(+i omega t) wavenumber
    ``k_plus``, (nf,)); each residual in units of its transfer function's random error."""
    x = np.asarray(positions, dtype=float)
    H = transfers.values
    sd = np.sqrt(np.maximum(np.real(np.einsum("fjj->fj", transfers.covariance)), 0.0) / 2)  # reference: 0
    floor = 0.1 * np.min(np.where(sd > 0, sd, np.inf), axis=1, keepdims=True)
    w = 1.0 / np.maximum(sd, np.where(np.isfinite(floor), floor, 1.0))
    E = np.stack([np.exp(-1j * k_plus[:, None] * x), np.exp(1j * k_plus[:, None] * x)], axis=2)  # (nf, n, 2)
    Ew, Hw = E * w[:, :, None], H * w
    q, _ = np.linalg.qr(Ew)
    r = Hw - np.einsum("fij,fj->fi", q, np.einsum("fji,fj->fi", np.conj(q), Hw))
    return np.concatenate([r.real.ravel(), r.imag.ravel()])


def self_calibrate(empty: Transfers, positions, gas: Gas, tube: Tube) -> SelfCalibration:
    """Fit the interior microphone positions, the temperature and the wall-loss factor
    to the calibrated empty-tube transfer functions ``empty`` (nf, n) of microphones at
    nominal ``positions`` [m] (module doc)."""
    x0 = np.asarray(positions, dtype=float)
    if x0.size < 3:
        raise MeasurementError("self-calibration needs at least three microphones")
    f = empty.frequencies

    def residual(theta):
        x = np.concatenate([[x0[0]], theta[:-2], [x0[-1]]])
        k, _ = plane_waves(f, dataclasses.replace(gas, temperature=theta[-2]), tube, loss=theta[-1])
        return field_misfit(empty, x, np.conj(k))

    theta0 = np.array([*x0[1:-1], gas.temperature, 1.0])
    r0 = residual(theta0)
    scale = np.array([1e-3] * (x0.size - 2) + [1.0, 0.1])
    fit = scipy.optimize.least_squares(residual, theta0, x_scale=scale, method="lm")
    J = fit.jac
    dof = max(1, fit.fun.size - theta0.size)
    s2 = max(1.0, float(fit.fun @ fit.fun) / dof)
    cov = np.linalg.pinv(J.T @ J) * s2
    th = fit.x
    if not (th[-2] > 0 and th[-1] > 0 and np.all(np.diff(np.concatenate([[x0[0]], th[:-2], [x0[-1]]])) > 0)):
        raise MeasurementError(
            f"the empty-tube self-calibration ran away (temperature {th[-2]:.4g} K, loss factor {th[-1]:.3g}, "
            f"positions {th[:-2]}); is calibration.direct an empty-tube measurement? set "
            "calibration.self_calibration = false to skip it"
        )
    rms = lambda r: float(np.sqrt(np.mean(r**2)))  # in random-error units
    return SelfCalibration(
        (float(x0[0]), *map(float, th[:-2]), float(x0[-1])),
        float(th[-2]),
        float(th[-1]),
        tuple(map(float, x0)),
        gas.temperature,
        cov,
        rms(r0),
        rms(fit.fun),
    )
