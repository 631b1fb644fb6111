"""Readers of the lab's signal files, each to averaged cross-spectra
(:class:`tawarp.tube.spectra.CrossSpectra`).

Formats (chosen by the file's suffix; docs/formats.md, "Signal files"):

- HDF5 (``.h5``, ``.hdf5``): a dataset ``time_data`` (samples x channels) with the
  attribute ``sample_freq`` [Hz] (the layout of acoular's ``TimeSamples``);
- WAV (``.wav``, :func:`scipy.io.wavfile.read`): one channel per track; integer samples
  are scaled to [-1, 1) (a common gain cancels in every transfer function);
- CSV time series (``.csv`` with ``ch0, ch1, ...`` columns): one row per sample, the
  sample rate in a ``# sample_rate = ...`` line or the description's
  ``measurement.sample_rate``;
- averaged cross-spectra (``.csv`` with a ``freq_Hz`` column): ``G_i_j_re``, ``G_i_j_im``
  for every ``i <= j`` (``G_ij = E[conj(X_i) X_j]``, the lower triangle is its conjugate)
  and a ``# averages = ...`` line (the number of independent averages).

Every error names the file (and the line or dataset).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..measure.table import MeasurementError, _meta_float, _read_table
from .spectra import CrossSpectra, welch

_CHANNEL = re.compile(r"ch(\d+)$")
_SPECTRUM = re.compile(r"G_(\d+)_(\d+)_(re|im)$")


def read_time_signals(path: str | Path, sample_rate: float | None = None) -> tuple[np.ndarray, float]:
    """Samples (n, channels) float64 and the sample rate [Hz] of a time-series file."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        return _read_hdf5(path)
    if suffix == ".wav":
        return _read_wav(path)
    if suffix == ".csv":
        return _read_csv(path, sample_rate)
    raise MeasurementError(f"{path}: unknown signal format {suffix!r}; expected .h5, .hdf5, .wav or .csv")


def _read_hdf5(path: Path) -> tuple[np.ndarray, float]:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if "time_data" not in f:
                raise MeasurementError(f"{path}: no dataset 'time_data' (samples x channels); found {sorted(f)}")
            d = f["time_data"]
            if "sample_freq" not in d.attrs:
                raise MeasurementError(f"{path}: dataset time_data has no attribute 'sample_freq' [Hz]")
            rate = float(np.asarray(d.attrs["sample_freq"]).reshape(-1)[0])
            x = np.asarray(d[...], dtype=np.float64)
    except OSError as e:
        raise MeasurementError(f"{path}: not a readable HDF5 file ({e})") from None
    return _checked(path, "time_data", x, rate)


def _read_wav(path: Path) -> tuple[np.ndarray, float]:
    import scipy.io.wavfile

    try:
        rate, x = scipy.io.wavfile.read(path)
    except (OSError, ValueError) as e:
        raise MeasurementError(f"{path}: not a readable WAV file ({e})") from None
    if np.issubdtype(x.dtype, np.integer):
        info = np.iinfo(x.dtype)
        x = (x.astype(np.float64) - (info.max + 1 + info.min) / 2) / ((info.max - info.min + 1) / 2)
    return _checked(path, "samples", np.asarray(x, dtype=np.float64).reshape(len(x), -1), float(rate))


def _read_csv(path: Path, sample_rate: float | None) -> tuple[np.ndarray, float]:
    t = _read_table(path, (), allowed=lambda c: bool(_CHANNEL.match(c)))
    channels = sorted(int(_CHANNEL.match(c).group(1)) for c in t.columns if _CHANNEL.match(c))
    if channels != list(range(len(channels))) or not channels:
        raise MeasurementError(
            f"{path}, line {t.header_line}: channel columns {channels}; expected ch0, ch1, ... without gaps"
        )
    rate = _meta_float(t, "sample_rate", "Hz", required=sample_rate is None, default=sample_rate)
    x = np.stack([t.values[f"ch{c}"] for c in channels], axis=1)
    return _checked(path, "rows", x, rate)


def _checked(path, what, x, rate) -> tuple[np.ndarray, float]:
    if x.ndim != 2 or x.shape[0] < 2:
        raise MeasurementError(f"{path}: {what} has shape {x.shape}; expected (samples, channels)")
    if not np.all(np.isfinite(x)):
        row = int(np.flatnonzero(~np.isfinite(x).all(axis=1))[0])
        raise MeasurementError(f"{path}: {what} sample {row} is NaN or infinite")
    if not (np.isfinite(rate) and rate > 0):
        raise MeasurementError(f"{path}: sample rate {rate!r}: expected a number > 0 Hz")
    return x, rate


def is_cross_spectra(path: str | Path) -> bool:
    """True for an averaged cross-spectra CSV (a ``freq_Hz`` column in its header)."""
    from ..measure.table import text_lines

    if Path(path).suffix.lower() != ".csv":
        return False
    for _, line in text_lines(path):
        if not line.startswith("#"):
            return "freq_Hz" in [f.strip() for f in line.split(",")]
    return False


def read_cross_spectra(path: str | Path) -> CrossSpectra:
    """An averaged cross-spectra CSV (module doc)."""
    t = _read_table(path, ("freq_Hz",), allowed=lambda c: bool(_SPECTRUM.match(c)))
    pairs = {tuple(int(v) for v in _SPECTRUM.match(c).groups()[:2]) for c in t.columns if _SPECTRUM.match(c)}
    n = 1 + max((max(p) for p in pairs), default=-1)
    for i in range(n):
        for j in range(i, n):
            for part in ("re", "im"):
                if f"G_{i}_{j}_{part}" not in t.columns:
                    raise MeasurementError(
                        f"{path}, line {t.header_line}: column G_{i}_{j}_{part} missing; give G_i_j_re and "
                        f"G_i_j_im for every 0 <= i <= j < {n}"
                    )
    lower = sorted(p for p in pairs if p[0] > p[1])
    if lower:
        raise MeasurementError(f"{path}, line {t.header_line}: G_{lower[0][0]}_{lower[0][1]}: give i <= j only")
    averages = _meta_float(t, "averages", "independent averages")
    G = np.empty((len(t.lines), n, n), dtype=complex)
    for i in range(n):
        for j in range(i, n):
            G[:, j, i] = t.values[f"G_{i}_{j}_re"] - 1j * t.values[f"G_{i}_{j}_im"]
            G[:, i, j] = t.values[f"G_{i}_{j}_re"] + 1j * t.values[f"G_{i}_{j}_im"]
    auto = np.einsum("fii->fi", G).real
    bad = np.argwhere(auto <= 0)
    if bad.size:
        r, i = bad[0]
        raise MeasurementError(f"{path}, line {t.lines[r]}: G_{i}_{i}_re must be > 0 (an auto-spectrum)")
    return CrossSpectra(t.values["freq_Hz"], G, averages)


def write_cross_spectra(path: str | Path, spectra: CrossSpectra) -> None:
    """Write ``spectra`` in the format :func:`read_cross_spectra` reads (atomically)."""
    from ..measure.table import _atomic_write

    n = spectra.channels
    names = [(i, j) for i in range(n) for j in range(i, n)]
    head = ["freq_Hz"] + [f"G_{i}_{j}_{p}" for i, j in names for p in ("re", "im")]
    rows = [f"# averages = {spectra.averages!r}", "# generator = tawarp", ",".join(head)]
    for f, G in zip(spectra.frequencies, spectra.matrix):
        vals = [f] + [v for i, j in names for v in (G[i, j].real, G[i, j].imag)]
        rows.append(",".join(repr(float(v)) for v in vals))
    _atomic_write(path, "\n".join(rows) + "\n")


def cross_spectra(path: str | Path, welch_options: dict, sample_rate: float | None = None) -> CrossSpectra:
    """Averaged cross-spectra of the signal file ``path``: read as they are, or by
    :func:`tawarp.tube.spectra.welch` with ``welch_options`` (block, window, overlap)."""
    if is_cross_spectra(path):
        return read_cross_spectra(path)
    x, rate = read_time_signals(path, sample_rate)
    try:
        return welch(x, rate, **welch_options)
    except ValueError as e:
        raise MeasurementError(f"{path}: {e}") from None
