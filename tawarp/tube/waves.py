"""Plane waves between microphones: the pieces every tube method shares.

Everything here is in the ``exp(+i omega t)`` convention of the measured transfer
functions (:mod:`.spectra`). In a uniform tube of wavenumber ``k`` and characteristic
impedance ``z0`` the state ``(p, U)`` at a distance ``x`` downstream of a plane is

    p(x) = p cos(kx) - i z0 U sin(kx),        U(x) = U cos(kx) - i (p / z0) sin(kx),

(``p = A e^{-ikx} + B e^{ikx}``, ``U = (A e^{-ikx} - B e^{ikx}) / z0``), so two microphones at
``x_a`` and ``x_b`` fix the state at the plane unless ``sin(k (x_b - x_a)) = 0``.
"""

from __future__ import annotations

import numpy as np

from .spectra import Transfers

#: Microphone spacing band [wavelengths] where a pair resolves the two waves, ISO 10534-2's
#: working range: s > 0.05 wavelength (below, the two pressures differ too little) and
#: s < 0.45 wavelength (at 0.5 the pair cannot separate the waves).
SPACING_BAND = (0.05, 0.45)
#: Largest condition number of a method's linear solve with a written value: beyond it the
#: solved states (or loads) are alike to within 1 % of their size, and the first-order
#: error propagation no longer describes the error.
MAX_CONDITION = 100.0


def checked(t: Transfers, channels: int, what: str) -> tuple[np.ndarray, np.ndarray]:
    """The values (nf, channels) and covariance (nf, channels, channels) of ``t``, or a
    ValueError naming ``what`` and the problem."""
    if not isinstance(t, Transfers):
        raise ValueError(f"{what}: expected a Transfers (CrossSpectra.transfers), got {type(t).__name__}")
    h, c = np.asarray(t.values), np.asarray(t.covariance)
    nf = len(t.frequencies)
    if h.shape != (nf, channels):
        raise ValueError(
            f"{what}: transfer functions have shape {h.shape}; expected ({nf}, {channels}), one per microphone in order"
        )
    if c.shape != (nf, channels, channels):
        raise ValueError(f"{what}: covariance has shape {c.shape}; expected ({nf}, {channels}, {channels})")
    bad = ~(np.all(np.isfinite(h), axis=1) & np.all(np.isfinite(c), axis=(1, 2)))
    if bad.any():
        f = np.asarray(t.frequencies)[bad]
        raise ValueError(
            f"{what}: NaN or infinite transfer functions at {bad.sum()} frequencies (first {f[0]:g} Hz): select a band without them (CrossSpectra.band)"
        )
    if not np.all(np.asarray(t.frequencies) >= 0):
        raise ValueError(f"{what}: negative frequencies")
    return h.astype(complex), c.astype(complex)


def same_frequencies(first: Transfers, *others: Transfers) -> None:
    """ValueError unless every Transfers has the first one's frequencies."""
    for i, o in enumerate(others, start=2):
        if len(o.frequencies) != len(first.frequencies) or not np.allclose(
            o.frequencies, first.frequencies, rtol=1e-12, atol=0
        ):
            raise ValueError(
                f"measurement {i} has other frequencies than measurement 1: compute both with the same block and sample rate"
            )


def per_frequency(x, nf: int, name: str) -> np.ndarray:
    """``x`` (scalar or (nf,)) as (nf,) complex, finite, or a ValueError naming ``name``."""
    try:
        out = np.broadcast_to(np.asarray(x, dtype=complex), (nf,)).copy()
    except (ValueError, TypeError):
        raise ValueError(f"{name} has shape {np.shape(x)}; expected ({nf},), one per frequency, or a scalar") from None
    if not np.all(np.isfinite(out)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return out


def tube_constants(k, z0, nf: int) -> tuple[np.ndarray, np.ndarray]:
    """``k`` and ``z0`` as (nf,) complex, checked finite with ``Re k >= 0`` and ``z0 != 0``."""
    kk, zz = per_frequency(k, nf, "k"), per_frequency(z0, nf, "z0")
    if np.any(kk.real < 0):
        raise ValueError("k has a negative real part: give the wavenumber of exp(+i omega t), Re k = omega / c > 0")
    if np.any(zz == 0):
        raise ValueError("z0 is zero")
    return kk, zz


def state_from_pair(k, z0, xa: float, xb: float) -> np.ndarray:
    """(nf, 2, 2): the matrix taking the pressures ``(p(xa), p(xb))`` at two microphones to the
    state ``(p, U)`` at the plane ``x = 0`` (``xa``, ``xb`` [m], signed, positive downstream).
    NaN rows where ``sin(k (xb - xa)) = 0``."""
    m = np.empty(k.shape + (2, 2), dtype=complex)
    for row, x in enumerate((xa, xb)):
        m[:, row, 0] = np.cos(k * x)
        m[:, row, 1] = -1j * z0 * np.sin(k * x)
    # inverse of [[a, b], [c, d]] with det = -i z0 sin(k (xb - xa)); NaN where singular
    det = -1j * z0 * np.sin(k * (xb - xa))
    det = np.where(det == 0, np.nan, det)
    adj = np.stack([np.stack([m[:, 1, 1], -m[:, 0, 1]], -1), np.stack([-m[:, 1, 0], m[:, 0, 0]], -1)], -2)
    with np.errstate(invalid="ignore"):
        inv = adj / det[:, None, None]
    return inv


def spacing_reasons(k, spacings: dict[str, float], band: tuple[float, float] = SPACING_BAND) -> np.ndarray:
    """(nf,) str: '' where every named spacing [m] lies within ``band`` wavelengths (the
    wavelength ``2 pi / Re k``), else e.g. 'mic spacing s1 0.49 wavelength'."""
    reasons = np.full(k.shape, "", dtype=object)
    for name, s in spacings.items():
        ratio = s * k.real / (2 * np.pi)
        out = (ratio < band[0]) | (ratio > band[1])
        for i in np.flatnonzero(out & (reasons == "")):
            reasons[i] = f"mic spacing {name} {ratio[i]:.2f} wavelength (outside {band[0]:g}-{band[1]:g})"
    return reasons


def normalized_condition(m: np.ndarray) -> np.ndarray:
    """(nf,) 2-norm condition numbers of (nf, r, c) matrices after scaling each column to unit
    norm (a column's scale is arbitrary: a load's reference amplitude); inf where singular
    or not finite."""
    norms = np.linalg.norm(m, axis=1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        scaled = m / norms
    cond = np.full(m.shape[0], np.inf)
    ok = np.all(np.isfinite(scaled), axis=(1, 2))
    if ok.any():
        cond[ok] = np.linalg.cond(scaled[ok])
    return np.where(np.isfinite(cond), cond, np.inf)


def two_state_solve(up: np.ndarray, down: np.ndarray, h: np.ndarray, cov: np.ndarray, z0) -> tuple:
    """The 2x2 matrix ``T`` with ``s_down_j = T s_up_j`` for two independent states ``j``, and
    its error.

    ``up``, ``down``: (nf, 2, 2, n) linear maps from the measured transfer functions ``h``
    (nf, n) to the states ``s_up_j = up[:, j] h``, ``s_down_j = down[:, j] h`` (state
    ``(p, U)``); ``cov`` (nf, n, n) is ``E[dh conj(dh)^T]``. With ``S = [s_1, s_2]`` (columns),
    ``T = S_down S_up^-1`` and, to first order, ``dT = sum_j (down_j - T up_j) dh V[j, :]``,
    ``V = S_up^-1``. Returns ``T`` (nf, 2, 2), ``E|dT|^2`` (nf, 2, 2) and the condition number
    of ``S_up`` with rows ``(p, z0 U)`` and unit columns."""
    with np.errstate(invalid="ignore"):  # NaN maps where a microphone pair is singular
        s_up = np.einsum("fjqn,fn->fqj", up, h)
        s_down = np.einsum("fjqn,fn->fqj", down, h)
    scale = np.stack([np.ones_like(z0), z0], -1)[:, :, None]
    condition = normalized_condition(s_up * scale)
    ok = np.isfinite(condition) & (condition < 1e14)
    t = np.full(s_up.shape, np.nan + 0j)
    var = np.full(s_up.shape, np.nan)
    v = np.linalg.inv(s_up[ok])
    t[ok] = s_down[ok] @ v
    k = down[ok] - np.einsum("frq,fjqn->fjrn", t[ok], up[ok])  # (f, j, r, n)
    jac = np.einsum("fjc,fjrn->frcn", v, k)
    var[ok] = np.real(np.einsum("frcn,fnm,frcm->frc", jac, cov[ok], np.conj(jac)))
    return t, var, condition


def condition_reasons(condition: np.ndarray, what: str, limit: float = MAX_CONDITION) -> np.ndarray:
    """(nf,) str: '' where ``condition <= limit``, else e.g. 'loads too alike (cond 3e+04)'."""
    return np.array([f"{what} (cond {c:.1e})" if not c <= limit else "" for c in condition], dtype=object)


def merge_reasons(*reasons: np.ndarray) -> np.ndarray:
    """The first non-empty reason per frequency."""
    out = np.array(reasons[0], dtype=object)
    for r in reasons[1:]:
        out = np.where(out == "", r, out)
    return out
