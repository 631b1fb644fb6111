"""What a tube method returns: a specimen's T-matrix or a layer's surface impedance per
frequency, with its standard deviation and the frequencies where the method cannot say.

Values are in tawarp's convention (docs/formats.md): ``exp(-i omega t)``; T-matrices map
``(p, U)`` at the upstream face to ``(p, U)`` at the downstream face, ``U`` the volume
velocity [m^3/s] positive downstream; a surface impedance is the pressure over the
velocity into the layer at its front face.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TubeResult:
    """A measured quantity per frequency.

    frequencies: (nf,) [Hz]. values: (nf, 2, 2) complex T-matrix ``[[Tpp, Tpu], [Tup, Tuu]]``
    (SI: 1, Pa s/m^3, m^3/(Pa s), 1) or (nf,) complex surface impedance (the unit of the
    characteristic impedance the method was given), ``exp(-i omega t)``. sd: the shape of
    ``values``, real: the standard deviation of the real part, equal to that of the
    imaginary part (the errors are circular). valid: (nf,) bool, False where the method is
    ill-conditioned; ``values`` and ``sd`` are NaN there. reason: (nf,) str, '' where valid,
    else why not. condition: (nf,) the condition number of the method's linear solve (its
    definition is the method's: docs/measure.md)."""

    frequencies: np.ndarray
    values: np.ndarray
    sd: np.ndarray
    valid: np.ndarray
    reason: np.ndarray
    condition: np.ndarray

    def __post_init__(self):
        nf = len(self.frequencies)
        if self.values.shape not in ((nf,), (nf, 2, 2)):
            raise ValueError(f"values have shape {self.values.shape}; expected ({nf},) or ({nf}, 2, 2)")
        if self.sd.shape != self.values.shape:
            raise ValueError(f"sd has shape {self.sd.shape}; expected {self.values.shape} as the values")
        for name in ("valid", "reason", "condition"):
            if getattr(self, name).shape != (nf,):
                raise ValueError(f"{name} has shape {getattr(self, name).shape}; expected ({nf},)")


def finish(frequencies, values_plus, var, condition, reasons) -> TubeResult:
    """A :class:`TubeResult` from a method's ``exp(+i omega t)`` values and ``E|dy|^2``.

    The values are complex-conjugated into ``exp(-i omega t)`` (the standard deviations of
    real and imaginary parts do not change); where ``reasons`` (nf,) is not empty the
    values and standard deviations are NaN and the frequency is not valid."""
    reasons = np.asarray(reasons, dtype=object).astype(str)
    valid = reasons == ""
    shape = (slice(None),) + (None,) * (np.ndim(values_plus) - 1)
    values = np.where(valid[shape], np.conj(values_plus), np.nan + 1j * np.nan)
    sd = np.where(valid[shape], np.sqrt(np.real(var) / 2.0), np.nan)
    return TubeResult(
        np.asarray(frequencies, dtype=float), values, sd, valid, reasons, np.asarray(condition, dtype=float)
    )
