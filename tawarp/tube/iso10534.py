"""ISO 10534-2:1998 two-microphone surface impedance of a layer on a rigid backing.

Microphone 1 at ``x1`` and microphone 2 at ``x2 < x1`` [m] upstream of the layer's front
face. ISO's own form, in ``exp(+i omega t)``: ``H12 = p2 / p1``,
``R = (H12 - e^{-iks}) / (e^{iks} - H12) e^{2ik x1}`` (``s = x1 - x2``) and
``Zs = z0 (1 + R) / (1 - R)``. Here the same number comes from the two-microphone state at
the face (:mod:`.waves`), ``Zs = p / U``, so that the errors of both transfer functions
propagate (docs/measure.md).
"""

from __future__ import annotations

import numpy as np

from . import waves
from .result import TubeResult, finish
from .spectra import Transfers


def surface_impedance(
    t: Transfers,
    x1: float,
    x2: float,
    k,
    z0,
    max_condition: float = waves.MAX_CONDITION,
    spacing_band: tuple[float, float] = waves.SPACING_BAND,
) -> TubeResult:
    """Surface impedance of a rigid-backed layer from two microphones (ISO 10534-2).

    ``t``: transfer functions from the reference channel to microphones 1 and 2 (in order,
    calibrated, ``exp(+i omega t)``; with microphone 1 as the reference its column is 1 with
    no error and the other is ISO's ``H12``). ``x1 > x2 >= 0`` [m]: distances of the
    microphones from the front face. ``k`` (nf,) complex wavenumber in
    ``exp(+i omega t)``; ``z0`` the tube's characteristic impedance in the unit wanted for
    ``Zs`` (1, or the lossy tube's ``Zc / (rho0 c0)``, for the normalized impedance that the
    surface-impedance CSV holds), scalar or (nf,). Returns ``Zs`` (nf,) in
    ``exp(-i omega t)``; ``condition`` is that of the two-microphone decomposition (rows
    ``(cos kx, -i sin kx)``). Invalid where ``x1 - x2`` leaves ``spacing_band``
    wavelengths or the condition exceeds ``max_condition``."""
    for name, v in (("x1", x1), ("x2", x2)):
        if not (isinstance(v, (int, float, np.floating)) and np.isfinite(v) and v >= 0):
            raise ValueError(f"{name} = {v!r}: expected a distance >= 0 [m] from the sample face")
    if not x1 > x2:
        raise ValueError(f"x1 = {x1} <= x2 = {x2}: microphone 1 is the one farther from the sample (x1 > x2)")
    h, c = waves.checked(t, 2, "surface_impedance")
    k, z0 = waves.tube_constants(k, z0, len(t.frequencies))
    g = waves.state_from_pair(k, z0, -x1, -x2)  # (p, U) at the face from (p1, p2)
    state = np.einsum("fqn,fn->fq", g, h)
    with np.errstate(divide="ignore", invalid="ignore"):
        zs = state[:, 0] / state[:, 1]
        jac = (g[:, 0, :] - zs[:, None] * g[:, 1, :]) / state[:, 1, None]
    var = np.real(np.einsum("fn,fnm,fm->f", jac, c, np.conj(jac)))
    rows = np.stack([np.cos(k * x1), -1j * np.sin(k * x1), np.cos(k * x2), -1j * np.sin(k * x2)], -1).reshape(-1, 2, 2)
    condition = np.full(k.shape, np.inf)
    finite = np.all(np.isfinite(rows), axis=(1, 2))
    condition[finite] = np.linalg.cond(rows[finite])
    reasons = waves.merge_reasons(
        waves.spacing_reasons(k, {"x1 - x2": x1 - x2}, spacing_band),
        waves.condition_reasons(condition, "two-microphone decomposition singular", max_condition),
        np.where(np.isfinite(zs), "", "no velocity at the face (Zs infinite)"),
    )
    return finish(t.frequencies, zs, var, condition, reasons)
