"""Four-microphone scattering matrices as a measurement kind, and their empty-tube
calibration.

The kind: scattering matrices converted to core T-matrices on load
(:meth:`tawarp.measure.files.ScatteringData.to_tmatrix`), then fitted as
:class:`TMatrixKind`.

Empty-tube calibration (:func:`calibrate_empty_tube`): a second measurement in the same
tube, at the same reference planes and frequencies, with no sample, calibrates the
sample's. Model of both measurements, per frequency (stated assumptions):

1. The microphone errors are one complex gain ``g`` (gain and phase) of the downstream
   microphone pair relative to the upstream pair, the same in both measurements. It
   scales the downstream wave amplitudes, so the measured ``S12' = S12 / g`` and
   ``S21' = g S21`` (``S11``, ``S22`` are ratios on one side and keep no trace of it).
   Errors within one pair, which bias the wave decomposition itself, are not removed.
2. The tube is uniform: on both sides plane waves of one complex wavenumber ``k_t`` (wall
   losses, the actual sound speed of the gas in the tube, whatever ``T_ambient`` says).
   Its characteristic impedance is taken lossless, ``rho0 c0 / S`` from the metadata: the
   relative error is of the order of the tube's loss, ``delta_visc / radius`` (2e-3 at
   100 Hz in a 100 mm tube).
3. With no sample, the tube between the planes is a duct of length
   ``D = L + plane_downstream - plane_upstream`` (``L`` the sample's length, x1 to x6):
   ``S11 = S22 = 0`` and ``S12 = S21 = exp(i k_t D)``.

So the empty tube measures ``g^2 = S21'/S12'`` (``g`` the root with positive real part:
phase errors below 90 degrees) and ``exp(2 i k_t D) = S12' S21'`` (``k_t`` the branch
nearest the lossless ``w / c0``; when ``D`` is below :data:`MIN_PLANE_DISTANCE`, as for
coinciding planes, it carries no propagation and ``k_t = w / c0``). The sample's ``S`` is
corrected by ``g`` and converted with ``k_t``; the standard deviations of both files
propagate to the T-matrices (:func:`tawarp.measure.files.propagated_sigma`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..model.core import Core
from .files import MeasurementError, ScatteringData, TMatrixData, propagated_sigma, read_scattering
from .tmatrix import TMatrixKind, core_for

#: Plane distance [m] below which an empty tube carries no propagation (k_t = w / c0).
MIN_PLANE_DISTANCE = 1e-4
#: Largest |S11|, |S22| of a file accepted as an empty tube.
MAX_EMPTY_REFLECTION = 0.2


def empty_tube_terms(empty: ScatteringData, length: float, S=None) -> tuple[np.ndarray, np.ndarray]:
    """The microphone gain ``g`` (m,) and tube wavenumber ``k_t`` (m,) [1/m] measured by the
    empty tube ``empty`` (its ``S``, or ``S`` (m, 2, 2)) for a sample of ``length`` [m]
    (module doc)."""
    S = empty.S if S is None else S
    g = np.sqrt(S[:, 1, 0] / S[:, 0, 1])
    D = length + empty.plane_downstream - empty.plane_upstream
    k0 = 2 * np.pi * empty.freq / empty.sound_speed
    if D < MIN_PLANE_DISTANCE:
        return g, k0.astype(complex)
    P = S[:, 0, 1] * S[:, 1, 0]
    phase = np.angle(P)
    n = np.round((2 * k0 * D - phase) / (2 * np.pi))
    return g, (phase + 2 * np.pi * n - 1j * np.log(np.abs(P))) / (2 * D)


def _check_pair(sample: ScatteringData, empty: ScatteringData, length: float) -> None:
    src = empty.source
    if empty.freq.shape != sample.freq.shape or not np.allclose(empty.freq, sample.freq, rtol=1e-9, atol=0):
        raise MeasurementError(f"{src}: the empty tube's frequencies differ from {sample.source}'s; "
                               "measure both on the same frequencies")
    for key, a, b in (("ref_plane_upstream", empty.plane_upstream, sample.plane_upstream),
                      ("ref_plane_downstream", empty.plane_downstream, sample.plane_downstream),
                      ("tube_radius", empty.tube_radius, sample.tube_radius)):
        if abs(a - b) > 1e-9 * max(1.0, abs(b)):
            raise MeasurementError(f"{src}: metadata {key} = {a!r} differs from {sample.source}'s {b!r}; "
                                   "the empty tube must be measured in the same tube at the same planes")
    if empty.gas != sample.gas:
        raise MeasurementError(f"{src}: gas = {empty.gas!r} differs from {sample.source}'s {sample.gas!r}")
    D = length + empty.plane_downstream - empty.plane_upstream
    if D < 0:
        raise MeasurementError(f"{src}: the downstream reference plane lies {-D!r} m upstream of the upstream one "
                               f"(sample length {length!r} m); check ref_plane_upstream and ref_plane_downstream")
    zero = np.flatnonzero(empty.S[:, 1, 0] == 0)
    if zero.size:
        raise MeasurementError(f"{src}: S21 = 0 at {empty.freq[zero[0]]!r} Hz: an empty tube transmits")
    refl = float(np.max(np.abs(empty.S[:, [0, 1], [0, 1]])))
    if refl > MAX_EMPTY_REFLECTION:
        raise MeasurementError(f"{src}: |S11| or |S22| reaches {refl:.3g} (> {MAX_EMPTY_REFLECTION}); an empty tube "
                               "reflects almost nothing: is this the empty-tube measurement?")


def calibrate_empty_tube(sample: ScatteringData, empty: ScatteringData, length: float) -> TMatrixData:
    """Core T-matrices of ``sample`` calibrated by the empty-tube measurement ``empty``
    (module doc) for a sample of ``length`` [m] (plane x1 to plane x6). Sigma: both
    files' propagated to first order (none when ``sample`` has none)."""
    _check_pair(sample, empty, length)

    def transfer(S, SE):
        g, k = empty_tube_terms(empty, length, SE)
        Sc = S.copy()
        Sc[:, 0, 1] *= g
        Sc[:, 1, 0] /= g
        return dataclasses.replace(sample, S=Sc, sigma=None, wavenumber=k).transfer()

    T = transfer(sample.S, empty.S)
    sigma = None if sample.sigma is None else propagated_sigma(transfer, [sample.S, empty.S],
                                                               [sample.sigma, empty.sigma])
    g, k = empty_tube_terms(empty, length)
    meta = dict(sample.metadata)
    meta.update({"converted_from": "scattering matrix", "empty_tube": empty.source,
                 "empty_tube.gain_abs": f"{np.min(np.abs(g)):.6g}..{np.max(np.abs(g)):.6g}",
                 "empty_tube.gain_phase_deg": f"{np.degrees(np.min(np.angle(g))):.6g}.."
                                              f"{np.degrees(np.max(np.angle(g))):.6g}",
                 "empty_tube.sound_speed": f"{np.mean(2 * np.pi * sample.freq / k.real):.6g}"})
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
