"""Four-microphone scattering matrices as a measurement kind, and their empty-tube
calibration.

The kind: scattering matrices converted to core T-matrices on load
(:meth:`tawarp.measure.files.ScatteringData.to_tmatrix`), then fitted as
:class:`TMatrixKind`.

Empty-tube calibration (:func:`calibrate_empty_tube`): a second measurement in the same
tube, at the same reference planes and frequencies, with no sample, calibrates the
sample's. Model of both measurements (stated assumptions):

1. The microphone errors are one complex gain ``g`` (gain and phase, any function of
   frequency) of the downstream microphone pair relative to the upstream pair, the same
   in both measurements. It scales the downstream wave amplitudes: the measured
   ``S12' = S12 / g`` and ``S21' = g S21`` (``S11``, ``S22`` are ratios on one side).
   Errors within one pair, which bias the wave decomposition itself, are not removed.
2. The tube is uniform and wide (boundary layers thin against the radius): plane waves of
   Kirchhoff's wavenumber ``k_t = (w / c) (1 + (1 + i) eps)``, ``eps = beta / sqrt(f)``,
   with the gas's actual sound speed ``c`` (whatever ``T_ambient`` says) and a wall-loss
   coefficient ``beta``; the characteristic impedance of the same law,
   ``Zc_t = (rho c)/S (1 + r (1 + i) eps)``, ``rho c = gamma p_ambient / c``,
   ``r = (1 - (gamma - 1)/sqrt(Pr)) / (1 + (gamma - 1)/sqrt(Pr))`` (the terms of order
   ``eps^2``, ~1e-5 in a 100 mm tube, are left out).
3. With no sample the planes enclose a duct of length
   ``D = L + plane_downstream - plane_upstream`` (``L`` the sample's length, x1 to x6):
   ``S11 = S22 = 0`` and ``S12 = S21 = exp(i k_t D)``.

So the empty tube measures, per frequency, ``g^2 = S21'/S12'`` (``g`` the root with a
positive real part: phase errors below 90 degrees) and ``exp(2 i k_t D) = S12' S21'``
(``k_t`` on the branch nearest the metadata's ``w / c0``); ``c`` and ``beta`` are the
least-squares fit of the law to those ``k_t`` over all frequencies (linear in ``1/c``
and ``beta / c``). When ``D`` is below :data:`MIN_PLANE_DISTANCE` (coinciding planes) the
empty tube carries no propagation: the metadata's lossless tube is kept. The sample's
``S`` is corrected by ``g`` and converted with ``k_t`` and ``Zc_t``. Standard deviations of
both files propagate to the T-matrices (:func:`tawarp.measure.files.propagated_sigma`),
the two tube constants held fixed (fitted over all frequencies, their share is small).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ..model.core import Core
from ..model.gas import GASES
from ..model.layer import gas_transport
from .files import MeasurementError, ScatteringData, TMatrixData, propagated_sigma, read_scattering
from .table import number
from .tmatrix import TMatrixKind, core_for

#: Plane distance [m] below which an empty tube carries no propagation (k_t = w / c0).
MIN_PLANE_DISTANCE = 1e-4
#: Largest |S11|, |S22| of a file accepted as an empty tube.
MAX_EMPTY_REFLECTION = 0.2


def microphone_gain(S: np.ndarray) -> np.ndarray:
    """The downstream microphones' gain ``g`` (m,) measured by empty-tube matrices ``S``
    (m, 2, 2): ``sqrt(S21 / S12)``, the root with a positive real part."""
    return np.sqrt(S[:, 1, 0] / S[:, 0, 1])


def tube_waves(empty: ScatteringData, length: float) -> tuple[np.ndarray, np.ndarray, dict]:
    """Wavenumber ``k_t`` (m,) [1/m] and characteristic impedance ``Zc_t`` (m,) [Pa s/m^3]
    of the tube measured by ``empty`` for a sample of ``length`` [m] (module doc), and a
    summary {sound_speed [m/s], loss_beta [Hz^0.5], wavenumber_misfit (rms relative
    deviation of the per-frequency k_t from the fitted law)}; the metadata's lossless
    tube when the planes are closer than :data:`MIN_PLANE_DISTANCE`."""
    D = length + empty.plane_downstream - empty.plane_upstream
    k0 = 2 * np.pi * empty.freq / empty.sound_speed
    if D < MIN_PLANE_DISTANCE:
        return k0.astype(complex), np.full(len(empty), complex(empty.Zc)), {"sound_speed": empty.sound_speed}
    P = empty.S[:, 0, 1] * empty.S[:, 1, 0]
    phase = np.angle(P)
    n = np.round((2 * k0 * D - phase) / (2 * np.pi))
    k = (phase + 2 * np.pi * n - 1j * np.log(np.abs(P))) / (2 * D)
    # k_t = w a + (1 + i) w b / sqrt(f): linear least squares on the real and imaginary parts
    w, rf = 2 * np.pi * empty.freq, 1.0 / np.sqrt(empty.freq)
    A = np.block([[w[:, None], (w * rf)[:, None]], [np.zeros((w.size, 1)), (w * rf)[:, None]]])
    (a, b), *_ = np.linalg.lstsq(A, np.concatenate([k.real, k.imag]), rcond=None)
    c, eps = 1.0 / a, b / a * rf
    if not (0.5 < c / empty.sound_speed < 2.0 and abs(b / a) < 1.0):
        raise MeasurementError(
            f"{empty.source}: the empty tube's waves fit to a sound speed of {c:.6g} m/s and a loss "
            f"coefficient of {b / a:.3g} Hz^0.5 (T_ambient gives {empty.sound_speed:.6g} m/s); "
            "is this an empty-tube measurement at the sample's reference planes?"
        )
    k_t = w / c * (1 + (1 + 1j) * eps)
    gas = GASES[empty.gas]
    mu, lam = gas_transport(empty.gas, c * c / (gas.gamma * gas.R_gas))
    q = (gas.gamma - 1) / math.sqrt(float(mu[0]) * gas.cp / float(lam[0]))
    Zc_t = gas.gamma * empty.p_ambient / c / (math.pi * empty.tube_radius**2) * (1 + (1 - q) / (1 + q) * (1 + 1j) * eps)
    misfit = float(np.sqrt(np.mean(np.abs(k - k_t) ** 2 / np.abs(k_t) ** 2)))
    return k_t, Zc_t, {"sound_speed": float(c), "loss_beta": float(b / a), "wavenumber_misfit": misfit}


def _check_pair(sample: ScatteringData, empty: ScatteringData, length: float) -> None:
    src = empty.source
    if empty.freq.shape != sample.freq.shape or not np.allclose(empty.freq, sample.freq, rtol=1e-9, atol=0):
        raise MeasurementError(
            f"{src}: the empty tube's frequencies differ from {sample.source}'s; measure both on the same frequencies"
        )
    for key, a, b in (
        ("ref_plane_upstream", empty.plane_upstream, sample.plane_upstream),
        ("ref_plane_downstream", empty.plane_downstream, sample.plane_downstream),
        ("tube_radius", empty.tube_radius, sample.tube_radius),
    ):
        if abs(a - b) > 1e-9 * max(1.0, abs(b)):
            raise MeasurementError(
                f"{src}: metadata {key} = {a!r} differs from {sample.source}'s {b!r}; "
                "the empty tube must be measured in the same tube at the same planes"
            )
    if empty.gas != sample.gas:
        raise MeasurementError(f"{src}: gas = {empty.gas!r} differs from {sample.source}'s {sample.gas!r}")
    D = length + empty.plane_downstream - empty.plane_upstream
    if D < 0:
        raise MeasurementError(
            f"{src}: the downstream reference plane lies {-D!r} m upstream of the upstream one "
            f"(sample length {length!r} m); check ref_plane_upstream and ref_plane_downstream"
        )
    zero = np.flatnonzero(empty.S[:, 1, 0] == 0)
    if zero.size:
        raise MeasurementError(f"{src}: S21 = 0 at {number(empty.freq[zero[0]])} Hz: an empty tube transmits")
    refl = float(np.max(np.abs(empty.S[:, [0, 1], [0, 1]])))
    if refl > MAX_EMPTY_REFLECTION:
        raise MeasurementError(
            f"{src}: |S11| or |S22| reaches {refl:.3g} (> {MAX_EMPTY_REFLECTION}); an empty tube "
            "reflects almost nothing: is this the empty-tube measurement?"
        )


def calibrate_empty_tube(sample: ScatteringData, empty: ScatteringData, length: float) -> TMatrixData:
    """Core T-matrices of ``sample`` calibrated by the empty-tube measurement ``empty``
    (module doc) for a sample of ``length`` [m] (plane x1 to plane x6). Sigma: both
    files' propagated to first order (none when ``sample`` has none)."""
    _check_pair(sample, empty, length)
    k, Zc, tube = tube_waves(empty, length)

    def transfer(S, SE):
        g = microphone_gain(SE)
        Sc = S.copy()
        Sc[:, 0, 1] *= g
        Sc[:, 1, 0] /= g
        return dataclasses.replace(sample, S=Sc, sigma=None, wavenumber=k, impedance=Zc).transfer()

    T = transfer(sample.S, empty.S)
    sigma = (
        None if sample.sigma is None else propagated_sigma(transfer, [sample.S, empty.S], [sample.sigma, empty.sigma])
    )
    g = microphone_gain(empty.S)
    meta = dict(sample.metadata)
    meta.update(
        {
            "converted_from": "scattering matrix",
            "empty_tube": empty.source,
            "empty_tube.gain_abs": f"{np.min(np.abs(g)):.6g}..{np.max(np.abs(g)):.6g}",
            "empty_tube.gain_phase_deg": f"{np.degrees(np.min(np.angle(g))):.6g}.."
            f"{np.degrees(np.max(np.angle(g))):.6g}",
        }
    )
    meta.update({f"empty_tube.{k_}": f"{v:.6g}" for k_, v in tube.items()})
    data = TMatrixData(np.full(len(sample), sample.heat_input), sample.freq, T, sigma, meta, sample.source)
    data.check()
    return data


def sample_length(core: Core) -> float:
    """Length [m] of a core from plane x1 to plane x6 (the sample of a scattering measurement)."""
    return core.positions()[-1]


class ScatteringKind(TMatrixKind):
    """T-matrices converted from a scattering matrix; ``data.metadata['converted_from']``."""

    name = "scattering"

    @classmethod
    def from_file(cls, path, core=None, settings=None, empty_tube=None) -> "ScatteringKind":
        """The kind of the scattering CSV ``path``, calibrated by the empty-tube CSV
        ``empty_tube`` (same planes and frequencies) when given; ``core`` the model (its
        length x1 to x6 is the sample's)."""
        raw = read_scattering(path)
        if empty_tube is None:
            data = raw.to_tmatrix()
            return cls(data, core_for(data, core, path), settings)
        core = core_for(raw, core, path)
        return cls(calibrate_empty_tube(raw, read_scattering(empty_tube), sample_length(core)), core, settings)
