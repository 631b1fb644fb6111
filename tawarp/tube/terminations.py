"""The T-matrix of a thermoacoustic core from an impedance sensor and known terminations
(the multi-termination method of Bannwart, Penelet, Lotton & Dalmont, JASA 133, 2013).

An impedance sensor on the core's upstream face x1 measures the input impedance
``Zin = p(x1) / U(x1)`` while the downstream face x6 is closed by a known termination
``ZL = p(x6) / U(x6)`` (``U`` positive from x1 to x6). With ``(p, U)(x6) = T (p, U)(x1)``
each termination gives one equation,

    Tpp Zin + Tpu = ZL (Tup Zin + Tuu),

homogeneous in ``T``: input impedances alone, under any number of terminations, leave
``T`` up to a complex factor (``c T`` satisfies every equation; for a reciprocal core,
``det T = 1`` fixes ``c`` up to its sign, a heated core is not reciprocal). The factor is
fixed by one more measured number per termination: the pressure at x6, a microphone at the
core's downstream face, read as the transfer impedance ``Z61 = p(x6) / U(x1)``. Then each
termination gives two equations linear in ``T``,

    Tpp Zin + Tpu = Z61,        ZL (Tup Zin + Tuu) = Z61,

and two or more terminations give ``T`` by weighted least squares (three or more leave
redundancy). The weights are the inverse covariances of the equations' errors (from the
measured ``Zin``, ``Z61`` covariances, at a first unweighted solution); the covariance of
``T`` is the sandwich form, exact to first order for any weights. docs/measure.md.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from . import waves
from .result import TubeResult, finish
from .spectra import Transfers


def closed_tube(k, z0, length: float) -> np.ndarray:
    """Impedance ``p / U`` [the unit of ``z0``] at the open mouth of a rigidly closed tube of
    ``length`` [m], ``exp(+i omega t)``: ``-i z0 cot(k length)`` (a compliance at low
    frequency). ``k``, ``z0`` as the methods take them."""
    k = np.asarray(k, dtype=complex)
    return -1j * np.asarray(z0) / np.tan(k * length)


def _design(zin, zl):
    """(nf, 2m, 4) rows of the linear equations in (tpp, tpu, tup, tuu), dimensionless."""
    nf, m = zin.shape
    a = np.zeros((nf, 2 * m, 4), dtype=complex)
    a[:, 0::2, 0], a[:, 0::2, 1] = zin, 1.0
    a[:, 1::2, 2], a[:, 1::2, 3] = zl * zin, zl
    return a


def _solve(a, b, w):
    """Weighted least squares per frequency: ``t = P A^H W b``, ``P = (A^H W A)^-1``."""
    ah_w = np.conj(np.swapaxes(a, 1, 2)) @ w
    p = np.linalg.inv(ah_w @ a)
    return np.einsum("fij,fj->fi", p @ ah_w, b), p, ah_w


def core_tmatrix(
    readings: Sequence[Transfers],
    loads: Sequence,
    z0,
    max_condition: float = waves.MAX_CONDITION,
) -> TubeResult:
    """A core's T-matrix from its input impedance and outlet pressure under known terminations.

    ``readings[j]``: the sensor's measurement with termination ``j``, a Transfers of two
    columns ``(Zin, Z61) = (p(x1), p(x6)) / U(x1)`` [Pa s/m^3], ``exp(+i omega t)``, with
    their covariance; ``loads[j]``: (nf,) or scalar complex ``ZL_j = p(x6) / U(x6)``
    [Pa s/m^3], ``exp(+i omega t)`` (e.g. :func:`closed_tube`), known exactly. ``z0``
    [Pa s/m^3], scalar or (nf,): the tube's characteristic impedance, the scale of the
    dimensionless solve. At least two terminations. Returns ``T`` (raw SI coefficients of
    ``(p, U)(x6) = T (p, U)(x1)``) in ``exp(-i omega t)``; ``condition`` is that of the
    equations' matrix in ``(Tpp, Tpu / z0, Tup z0, Tuu)`` with unit rows and columns;
    invalid where it exceeds ``max_condition`` (terminations too alike)."""
    readings, loads = list(readings), list(loads)
    if len(readings) < 2:
        raise ValueError(
            f"{len(readings)} termination(s): the core's T-matrix needs at least two (three or more for redundancy)"
        )
    if len(loads) != len(readings):
        raise ValueError(
            f"{len(readings)} readings but {len(loads)} loads: give one known termination impedance per reading"
        )
    checked = [waves.checked(r, 2, f"core_tmatrix reading {j + 1}") for j, r in enumerate(readings)]
    waves.same_frequencies(*readings)
    nf, m = len(readings[0].frequencies), len(readings)
    z0 = waves.per_frequency(z0, nf, "z0")
    if np.any(z0 == 0):
        raise ValueError("z0 is zero")
    zl = np.stack([waves.per_frequency(load, nf, f"load {j + 1}") for j, load in enumerate(loads)], axis=1)
    y = np.stack([h for h, _ in checked], axis=1) / z0[:, None, None]  # (nf, m, 2): (zin, z61)
    cov = np.stack([c for _, c in checked], axis=1) / np.abs(z0[:, None, None, None]) ** 2  # (nf, m, 2, 2)
    zin, z61 = y[..., 0], y[..., 1]
    zl = zl / z0[:, None]
    a = _design(zin, zl)
    b = np.repeat(z61, 2, axis=1)

    rows = a / np.linalg.norm(a, axis=2, keepdims=True)
    condition = waves.normalized_condition(rows)
    ok = np.isfinite(condition) & (condition < 1e14)
    t = np.full((nf, 4), np.nan + 0j)
    var = np.full((nf, 4), np.nan)
    if ok.any():
        a, b, cov, zl_ok = a[ok], b[ok], cov[ok], zl[ok]
        # first pass: every equation at unit weight (rows scaled to unit norm)
        t0, _, _ = _solve(a, b, np.einsum("fi,ij->fij", 1 / np.linalg.norm(a, axis=2) ** 2, np.eye(2 * m)))
        # error of equation (1), (2) of termination j from d(zin, z61): E_j = [[tpp, -1], [zl tup, -1]]
        e = np.zeros(cov.shape, dtype=complex)
        e[..., 0, 0], e[..., 1, 0] = t0[:, 0, None], zl_ok * t0[:, 2, None]
        e[..., :, 1] = -1.0
        sigma_e = e @ cov @ np.conj(np.swapaxes(e, -1, -2))  # (f, m, 2, 2)
        big = np.zeros((a.shape[0], 2 * m, 2 * m), dtype=complex)
        for j in range(m):
            big[:, 2 * j : 2 * j + 2, 2 * j : 2 * j + 2] = sigma_e[:, j]
        # a tiny ridge keeps exact (noise-free) data solvable; the sandwich below is exact for any weights
        level = np.real(np.trace(big, axis1=1, axis2=2)) / (2 * m)
        ridge = np.where(level > 0, 1e-12 * level, 1.0)
        w = np.linalg.inv(big + ridge[:, None, None] * np.eye(2 * m))
        t[ok], p, ah_w = _solve(a, b, w)
        g = p @ ah_w
        var[ok] = np.real(np.einsum("fin,fnm,fim->fi", g, big, np.conj(g)))
    scale = np.stack([np.ones(nf), z0, 1 / z0, np.ones(nf)], -1)
    t = (t * scale).reshape(nf, 2, 2)
    var = (var * np.abs(scale) ** 2).reshape(nf, 2, 2)
    reasons = waves.condition_reasons(condition, "terminations too alike", max_condition)
    return finish(readings[0].frequencies, t, var, condition, reasons)
