"""ASTM E2611-19 transfer-matrix methods: four microphones, two upstream and two downstream
of the specimen, and the specimen's T-matrix between its faces.

Geometry (E2611's symbols, metres, all from the reference plane, the specimen's upstream
face, positive downstream): microphone 1 at ``-(l1 + s1)``, 2 at ``-l1``, 3 at ``l2``, 4 at
``l2 + s2``; the downstream face at ``thickness``. The two-microphone decomposition
(:mod:`.waves`) gives the state ``(p, U)`` at each face; the methods differ in where the
second independent state comes from:

- :func:`two_load`: a second termination (E2611 sec. 8.5.4.3);
- :func:`two_source`: the source moved to the other end, microphones in place (the same
  algebra; Munjal & Doige's source-location method);
- :func:`one_load`: one termination and the specimen's symmetry and reciprocity, which
  make the mirrored state a second one (E2611 sec. 8.5.4.2).

The equations, their conventions and the conditioning rules: docs/measure.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import waves
from .result import TubeResult, finish
from .spectra import Transfers


@dataclass(frozen=True)
class FourMics:
    """Microphone positions of a four-microphone tube (one position set), E2611's symbols
    [m]: ``l1`` from microphone 2 to the specimen's upstream face, ``s1`` between
    microphones 1 and 2, ``l2`` from the upstream face (the reference plane) to microphone 3,
    ``s2`` between microphones 3 and 4, ``thickness`` of the specimen (``l2 >= thickness``)."""

    l1: float
    s1: float
    l2: float
    s2: float
    thickness: float

    def __post_init__(self):
        for name in ("l1", "s1", "l2", "s2", "thickness"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.floating)) and np.isfinite(v)):
                raise ValueError(f"FourMics.{name} = {v!r}: expected a finite number of metres")
        if not (self.s1 > 0 and self.s2 > 0):
            raise ValueError(
                f"FourMics: spacings s1 = {self.s1}, s2 = {self.s2} must be > 0 (microphone 1 upstream of 2, 3 upstream of 4)"
            )
        if not (self.l1 >= 0 and self.thickness >= 0):
            raise ValueError(
                f"FourMics: l1 = {self.l1}, thickness = {self.thickness} must be >= 0 (microphones 1, 2 upstream of the specimen)"
            )
        if not self.l2 >= self.thickness:
            raise ValueError(
                f"FourMics: l2 = {self.l2} < thickness = {self.thickness}: l2 is measured from the upstream face, microphone 3 must lie downstream of the specimen"
            )

    @property
    def positions(self) -> tuple[float, float, float, float]:
        """Microphones 1-4 [m] from the upstream face, positive downstream."""
        return (-(self.l1 + self.s1), -self.l1, self.l2, self.l2 + self.s2)


def _face_maps(mics: FourMics, k, z0) -> tuple[np.ndarray, np.ndarray]:
    """(nf, 2, 4) maps from ``H_1..H_4`` to ``(p, U)`` at the upstream and at the downstream face."""
    x1, x2, x3, x4 = mics.positions
    nf = k.shape[0]
    g_up = np.zeros((nf, 2, 4), dtype=complex)
    g_down = np.zeros((nf, 2, 4), dtype=complex)
    g_up[:, :, 0:2] = waves.state_from_pair(k, z0, x1, x2)
    g_down[:, :, 2:4] = waves.state_from_pair(k, z0, x3 - mics.thickness, x4 - mics.thickness)
    return g_up, g_down


def _spacing(mics: FourMics, k, band) -> np.ndarray:
    return waves.spacing_reasons(k, {"s1": mics.s1, "s2": mics.s2}, band)


def _two_states(measurements, mics, k, z0, what, max_condition, band) -> TubeResult:
    """T from two independent measurements of the four microphones (two loads or two sources)."""
    (ha, ca), (hb, cb) = (waves.checked(m, 4, f"{what} measurement {i}") for i, m in enumerate(measurements, 1))
    waves.same_frequencies(*measurements)
    a = measurements[0]
    k, z0 = waves.tube_constants(k, z0, len(a.frequencies))
    g_up, g_down = _face_maps(mics, k, z0)
    nf = k.shape[0]
    up = np.zeros((nf, 2, 2, 8), dtype=complex)
    down = np.zeros((nf, 2, 2, 8), dtype=complex)
    for j in range(2):
        up[:, j, :, 4 * j : 4 * j + 4] = g_up
        down[:, j, :, 4 * j : 4 * j + 4] = g_down
    h = np.concatenate([ha, hb], axis=1)
    cov = np.zeros((nf, 8, 8), dtype=complex)
    cov[:, :4, :4], cov[:, 4:, 4:] = ca, cb  # the measurements are independent
    t, var, condition = waves.two_state_solve(up, down, h, cov, z0)
    alike = "loads too alike" if what == "two_load" else "sources too alike"
    reasons = waves.merge_reasons(_spacing(mics, k, band), waves.condition_reasons(condition, alike, max_condition))
    return finish(a.frequencies, t, var, condition, reasons)


def two_load(
    a: Transfers,
    b: Transfers,
    mics: FourMics,
    k,
    z0,
    max_condition: float = waves.MAX_CONDITION,
    spacing_band: tuple[float, float] = waves.SPACING_BAND,
) -> TubeResult:
    """The specimen's T-matrix from two terminations (ASTM E2611-19 two-load method).

    ``a``, ``b``: transfer functions from the reference channel to microphones 1-4 (in
    order, calibrated, ``exp(+i omega t)``) with each of the two terminations. ``k`` (nf,)
    complex wavenumber of the tube in ``exp(+i omega t)`` (``Im k <= 0`` for a lossy tube),
    ``z0`` [Pa s/m^3] its characteristic impedance for the volume velocity (``rho c / S``),
    scalar or (nf,). Returns ``T`` with ``(p, U)(downstream face) = T (p, U)(upstream face)``
    in ``exp(-i omega t)``; ``condition`` is that of the two upstream-face states (rows
    ``(p, z0 U)``, unit columns). Invalid where a spacing leaves ``spacing_band``
    wavelengths or the condition exceeds ``max_condition``."""
    return _two_states((a, b), mics, k, z0, "two_load", max_condition, spacing_band)


def two_source(
    a: Transfers,
    b: Transfers,
    mics: FourMics,
    k,
    z0,
    max_condition: float = waves.MAX_CONDITION,
    spacing_band: tuple[float, float] = waves.SPACING_BAND,
) -> TubeResult:
    """The specimen's T-matrix from the source at the upstream end (``a``) and at the
    downstream end (``b``), the microphones and terminations in place. Arguments and
    result as :func:`two_load`; each measurement may use its own reference channel (a
    measurement's scale cancels)."""
    return _two_states((a, b), mics, k, z0, "two_source", max_condition, spacing_band)


def one_load(
    a: Transfers,
    mics: FourMics,
    k,
    z0,
    max_condition: float = waves.MAX_CONDITION,
    spacing_band: tuple[float, float] = waves.SPACING_BAND,
) -> TubeResult:
    """The T-matrix of a reciprocal, symmetric specimen from one termination (ASTM E2611-19
    one-load method). Symmetry maps the measured pair ``(s_up, s_down)`` to a second one,
    ``(D s_down, D s_up)`` with ``D = diag(1, -1)``; the result has ``Tpp = Tuu`` and
    ``det T = 1`` exactly. Arguments and result as :func:`two_load`; ``condition`` is that
    of the measured and mirrored upstream states."""
    h, c = waves.checked(a, 4, "one_load measurement")
    k, z0 = waves.tube_constants(k, z0, len(a.frequencies))
    g_up, g_down = _face_maps(mics, k, z0)
    mirror = np.array([1.0, -1.0])[None, :, None]
    with np.errstate(invalid="ignore"):  # NaN maps where a microphone pair is singular
        up = np.stack([g_up, mirror * g_down], axis=1)
        down = np.stack([g_down, mirror * g_up], axis=1)
    t, var, condition = waves.two_state_solve(up, down, h, c, z0)
    reasons = waves.merge_reasons(
        _spacing(mics, k, spacing_band),
        waves.condition_reasons(condition, "measured and mirrored states alike", max_condition),
    )
    return finish(a.frequencies, t, var, condition, reasons)
