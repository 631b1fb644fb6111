"""Averaged cross-spectra of microphone signals and the random error of the transfer
functions built from them.

Convention: ``matrix[f, i, j] = E[conj(X_i) X_j]`` (one-sided), as :func:`scipy.signal.csd`
returns for ``csd(x_i, x_j)``. The discrete Fourier transform analyses a signal
``Re(A exp(+i omega t))`` into ``A``, so every transfer function here carries the
``exp(+i omega t)`` time dependence; the methods convert to the convention they write.

The random error follows Bendat & Piersol, *Random Data* (4th ed., 2010), eqs. 9.52-9.53:
the H1 estimate ``H_ij = G_ij / G_ii`` from ``n_d`` independent averages with coherence
``gamma^2`` has a normalized random error ``sqrt(1 - gamma^2) / (|gamma| sqrt(2 n_d))`` in
magnitude and the same number, in radians, in phase. Overlapping windows are not
independent: the number of independent averages is Welch's (1967, eq. 11) equivalent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.signal

BLOCK = 8192  # samples per Welch block: 6.25 Hz lines at 51.2 kHz, the E2611 peers' default
WINDOW = "hann"
OVERLAP = 0.5


@dataclass(frozen=True)
class CrossSpectra:
    """Averaged one-sided cross-spectral matrix of a set of channels.

    frequencies: (nf,) [Hz]. matrix: (nf, nch, nch) complex [unit^2/Hz],
    ``matrix[f, i, j] = E[conj(X_i) X_j]``. averages: the equivalent number of independent
    averages ``n_d`` (not the number of overlapping blocks)."""

    frequencies: np.ndarray
    matrix: np.ndarray
    averages: float

    def __post_init__(self):
        nf = len(self.frequencies)
        if self.matrix.ndim != 3 or self.matrix.shape[0] != nf or self.matrix.shape[1] != self.matrix.shape[2]:
            raise ValueError(f"cross-spectral matrix has shape {self.matrix.shape}; expected ({nf}, nch, nch)")
        if not self.averages >= 1:
            raise ValueError(f"averages = {self.averages}: needs at least one average")

    @property
    def channels(self) -> int:
        return self.matrix.shape[1]

    def band(self, lo: float, hi: float) -> CrossSpectra:
        """The lines with lo <= f <= hi [Hz]."""
        keep = (self.frequencies >= lo) & (self.frequencies <= hi)
        return CrossSpectra(self.frequencies[keep], self.matrix[keep], self.averages)

    def transfer(self, ref: int, ch: int) -> np.ndarray:
        """H1 transfer function from channel ``ref`` to ``ch``: ``G_ref,ch / G_ref,ref``."""
        return self.matrix[:, ref, ch] / self.matrix[:, ref, ref].real

    def coherence(self, ref: int, ch: int) -> np.ndarray:
        """Ordinary coherence gamma^2 between two channels, in [0, 1]."""
        g = self.matrix
        return np.abs(g[:, ref, ch]) ** 2 / (g[:, ref, ref].real * g[:, ch, ch].real)

    def transfers(self, ref: int, channels: list[int] | tuple[int, ...]) -> Transfers:
        """H1 transfer functions from ``ref`` to each of ``channels`` with the covariance of
        their random errors. For one input the errors of ``H_j`` and ``H_k`` are correlated
        through the residual cross-spectrum ``G_jk.r = G_jk - G_jr G_rk / G_rr``:
        ``E[dH_j conj(dH_k)] = conj(G_jk.r) / (n_d G_rr)`` (Bendat & Piersol, sec. 9.3;
        on the diagonal this is eq. 9.52 squared, summed over real and imaginary parts)."""
        g = self.matrix
        grr = g[:, ref, ref].real
        ch = list(channels)
        h = g[:, ref, ch] / grr[:, None]
        resid = g[:, ch][:, :, ch] - np.conj(g[:, ref, ch])[:, :, None] * g[:, ref, ch][:, None, :] / grr[:, None, None]
        cov = np.conj(resid) / (self.averages * grr[:, None, None])
        return Transfers(self.frequencies, h, cov)

    def transfer_error(self, ref: int, ch: int) -> np.ndarray:
        """Standard deviation of the real part (equal to that of the imaginary part) of
        :meth:`transfer`: ``|H| sqrt(1 - gamma^2) / (|gamma| sqrt(2 n_d))`` (Bendat &
        Piersol, eq. 9.52; the phase error in radians is the same ratio)."""
        gamma2 = np.clip(self.coherence(ref, ch), 1e-300, 1.0)
        eps = np.sqrt((1.0 - gamma2) / (2.0 * self.averages * gamma2))
        return np.abs(self.transfer(ref, ch)) * eps


@dataclass(frozen=True)
class Transfers:
    """Transfer functions from a reference channel to several channels, with their errors.

    frequencies: (nf,) [Hz]. values: (nf, n) complex, exp(+i omega t). covariance: (nf, n, n)
    complex, ``E[dH_j conj(dH_k)]``; the errors are circular (real and imaginary parts
    each carry half of the diagonal), so a holomorphic function ``y(H)`` has
    ``E|dy|^2 = J C J^H`` with ``J = dy/dH``."""

    frequencies: np.ndarray
    values: np.ndarray
    covariance: np.ndarray

    def sd(self) -> np.ndarray:
        """(nf, n): standard deviation of the real part (equal to the imaginary part's)."""
        return np.sqrt(np.real(np.einsum("fjj->fj", self.covariance)) / 2.0)


def independent_averages(blocks: int, window: np.ndarray, step: int) -> float:
    """Welch's (1967) equivalent number of independent averages of ``blocks`` windowed
    blocks advanced by ``step`` samples: ``K / (1 + 2 sum_j (1 - j/K) c(j step)^2)``, with
    ``c(s)`` the window's normalized overlap correlation."""
    w2 = float(np.sum(window**2))
    total = 0.0
    for j in range(1, blocks):
        s = j * step
        if s >= len(window):
            break
        c = float(np.sum(window[: len(window) - s] * window[s:])) / w2
        total += (1.0 - j / blocks) * c * c
    return blocks / (1.0 + 2.0 * total)


def welch(
    signals: np.ndarray, sample_rate: float, block: int = BLOCK, window: str = WINDOW, overlap: float = OVERLAP
) -> CrossSpectra:
    """Cross-spectra of time signals ``(samples, channels)`` sampled at ``sample_rate`` [Hz]
    by Welch's method (:func:`scipy.signal.csd`): ``block`` samples per segment, ``window``
    (a :func:`scipy.signal.get_window` name), ``overlap`` the fraction of a block shared
    with the next."""
    x = np.asarray(signals, dtype=float)
    if x.ndim != 2:
        raise ValueError(f"signals have shape {x.shape}; expected (samples, channels)")
    if not np.all(np.isfinite(x)):
        raise ValueError("signals contain NaN or infinite samples")
    if not 0.0 <= overlap < 1.0:
        raise ValueError(f"overlap = {overlap}: must be in [0, 1)")
    n, nch = x.shape
    if n < block:
        raise ValueError(f"{n} samples are fewer than one block of {block}")
    noverlap = int(round(overlap * block))
    step = block - noverlap
    blocks = 1 + (n - block) // step
    w = scipy.signal.get_window(window, block)
    # one call per reference row: csd broadcasts y against x
    rows = []
    for i in range(nch):
        f, g = scipy.signal.csd(x[:, i : i + 1], x, fs=sample_rate, window=w, nperseg=block, noverlap=noverlap, axis=0)
        rows.append(g)
    matrix = np.stack(rows, axis=1)  # (nf, i, j)
    return CrossSpectra(f, matrix, independent_averages(blocks, w, step))
