"""Measured data: loaders and writers for the file formats of docs/formats.md (pure NumPy).

Three kinds of measurement, all returned in the ``exp(-i w t)`` convention of docs/physics.md
(data in the other convention are complex-conjugated on load):

- core T-matrices ``(p, U)(x6) = T (p, U)(x1)``: :func:`read_tmatrix_csv`,
  :func:`write_tmatrix_csv`, held in :class:`TMatrixData`;
- surface impedance of a rigid-backed layer: :func:`read_impedance_csv`, and the real
  Atalla & Panneton (2005) data set (:func:`load_atalla_panneton`,
  :func:`atalla_panneton_samples`), held in :class:`ImpedanceData`;
- two-port scattering matrices of a four-microphone tube at signed reference planes:
  :func:`read_scattering` and :func:`write_scattering_csv` (held in
  :class:`ScatteringData`), converted to core T-matrices by :func:`read_scattering_csv`,
  with the pure conversions :func:`scattering_to_transfer` and
  :func:`transfer_to_scattering`.

Every reader raises :class:`MeasurementError` whose message names the file, the line
(or the metadata key) and what was expected (the shared CSV machinery: :mod:`.table`).
Writers validate everything before they touch the disk and replace the target atomically.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from ..model.gas import GASES
from .table import (
    CONVENTION,
    MeasurementError,
    _atomic_write,
    _check_convention,  # noqa: F401
    _check_positive_unique,
    _complex,
    _converted_metadata,
    _fail,
    _meta_float,
    _metadata_line,
    _needs_conjugate,
    _read_table,
    _Table,
    number,
)

#: The four raw coefficients and their (row, column) in the 2x2 T-matrix.
COEFFICIENTS = {"Tpp": (0, 0), "Tpu": (0, 1), "Tup": (1, 0), "Tuu": (1, 1)}
TMATRIX_COLUMNS = ("Q_W", "freq_Hz") + tuple(f"{c}_{p}" for c in COEFFICIENTS for p in ("re", "im"))
IMPEDANCE_COLUMNS = ("freq_Hz", "Zs_re", "Zs_im")
SCATTERING_COLUMNS = ("freq_Hz",) + tuple(f"S{ij}_{p}" for ij in ("11", "12", "21", "22") for p in ("re", "im"))


# -- data containers -------------------------------------------------------------------
@dataclass
class TMatrixData:
    """Measured (or simulated) core T-matrices, one row per (heat input, frequency).

    ``heat_input`` (rows,) [W]; ``freq`` (rows,) [Hz]; ``T`` (rows, 2, 2) complex raw
    coefficients of ``(p, U)(x6) = T (p, U)(x1)`` with p [Pa], U [m^3/s] (so ``Tpu`` in
    Pa s/m^3, ``Tup`` in m^3/(Pa s)), always in the ``exp(-iwt)`` convention.
    ``sigma`` is None or (rows, 2, 2, 2) float: ``sigma[..., 0]`` is the standard deviation
    of ``T.real`` and ``sigma[..., 1]`` that of ``T.imag``, same units as ``T``; a
    (rows, 2, 2) array is accepted and used for both parts. ``metadata`` holds the file's
    ``# key = value`` lines, ``source`` where the data came from.

    Construction checks shapes only; :meth:`check` checks values (the writer calls it).
    """

    heat_input: np.ndarray
    freq: np.ndarray
    T: np.ndarray
    sigma: np.ndarray | None = None
    metadata: dict[str, str] = field(default_factory=dict)
    source: str = "<data>"

    def __post_init__(self):
        self.heat_input = np.asarray(self.heat_input, dtype=float).reshape(-1)
        self.freq = np.asarray(self.freq, dtype=float).reshape(-1)
        self.T = np.asarray(self.T, dtype=np.complex128)
        n = self.freq.size
        if self.heat_input.shape != (n,) or self.T.shape != (n, 2, 2):
            raise MeasurementError(
                f"{self.source}: shapes heat_input {self.heat_input.shape}, freq {self.freq.shape}, "
                f"T {self.T.shape}; expected (n,), (n,), (n, 2, 2)"
            )
        if self.sigma is not None:
            s = np.asarray(self.sigma, dtype=float)
            if s.shape == (n, 2, 2):
                s = np.stack([s, s], axis=-1)
            if s.shape != (n, 2, 2, 2):
                raise MeasurementError(f"{self.source}: sigma shape {s.shape}; expected ({n}, 2, 2, 2) or ({n}, 2, 2)")
            self.sigma = s
        self.metadata = {str(k): str(v) for k, v in self.metadata.items()}

    def __len__(self) -> int:
        return self.freq.size

    @property
    def heat_inputs(self) -> np.ndarray:
        """Distinct heat inputs [W], sorted."""
        return np.unique(self.heat_input)

    @property
    def frequencies(self) -> np.ndarray:
        """Distinct frequencies [Hz], sorted."""
        return np.unique(self.freq)

    def select(self, heat_input: float) -> "TMatrixData":
        """The rows at heat input ``heat_input`` [W] (matched to 1e-9 relative), in file order."""
        mask = np.isclose(self.heat_input, heat_input, rtol=1e-9, atol=1e-12)
        if not mask.any():
            raise KeyError(f"{self.source}: no rows at Q = {heat_input} W; have {self.heat_inputs.tolist()}")
        return TMatrixData(
            self.heat_input[mask],
            self.freq[mask],
            self.T[mask],
            None if self.sigma is None else self.sigma[mask],
            dict(self.metadata),
            self.source,
        )

    def check(self) -> None:
        """Raise :class:`MeasurementError` naming the row if any value is not usable."""

        def fail(i, what):
            raise MeasurementError(
                f"{self.source}: row {i} (Q = {number(self.heat_input[i])} W, freq = {number(self.freq[i])} Hz): {what}"
            )

        for i in range(len(self)):
            if not (np.isfinite(self.heat_input[i]) and self.heat_input[i] >= 0):
                fail(i, "heat input must be a finite number >= 0 W")
            if not (np.isfinite(self.freq[i]) and self.freq[i] > 0):
                fail(i, "frequency must be a finite number > 0 Hz")
            if not np.all(np.isfinite(self.T[i])):
                fail(i, "T has a NaN or infinite entry")
            if self.sigma is not None and not np.all(np.isfinite(self.sigma[i]) & (self.sigma[i] > 0)):
                fail(i, "sigma must be finite and > 0")
        seen = {}
        for i, key in enumerate(zip(self.heat_input.tolist(), self.freq.tolist())):
            if key in seen:
                fail(i, f"duplicate of row {seen[key]} (same heat input and frequency)")
            seen[key] = i


@dataclass
class ImpedanceData:
    """Surface impedance of a rigid-backed layer.

    ``freq`` (m,) [Hz]; ``Zs`` (m,) complex specific surface impedance normalized by
    ``rho0 c0`` (dimensionless), ``exp(-iwt)`` convention; ``thickness`` [m] of the layer
    (None when unknown); ``T_ambient`` [K] and ``p_ambient`` [Pa] of the measurement, or
    None; ``metadata`` and ``source`` as in :class:`TMatrixData`; ``sigma`` None or (m, 2)
    standard deviations of ``Zs.real`` and ``Zs.imag``.
    """

    freq: np.ndarray
    Zs: np.ndarray
    thickness: float | None
    T_ambient: float | None = None
    p_ambient: float | None = None
    metadata: dict[str, str] = field(default_factory=dict)
    source: str = "<data>"
    sigma: np.ndarray | None = None

    def __post_init__(self):
        self.freq = np.asarray(self.freq, dtype=float).reshape(-1)
        self.Zs = np.asarray(self.Zs, dtype=np.complex128).reshape(-1)
        if self.Zs.shape != self.freq.shape:
            raise MeasurementError(f"{self.source}: freq {self.freq.shape} and Zs {self.Zs.shape} differ in length")
        if self.sigma is not None:
            self.sigma = np.asarray(self.sigma, dtype=float)
            if self.sigma.shape != (self.freq.size, 2):
                raise MeasurementError(f"{self.source}: sigma shape {self.sigma.shape}; expected ({self.freq.size}, 2)")

    def __len__(self) -> int:
        return self.freq.size


# -- core T-matrices -------------------------------------------------------------------
def _sigma_columns(entries) -> set[str]:
    """Names of the optional standard-deviation columns of complex columns ``entries``:
    ``sigma_E`` (both parts) or ``sigma_E_re`` and ``sigma_E_im``."""
    return {f"sigma_{c}{p}" for c in entries for p in ("", "_re", "_im")}


def _sigma_allowed(name: str) -> bool:
    return name in _sigma_columns(COEFFICIENTS)


def read_tmatrix_csv(path: str | os.PathLike) -> TMatrixData:
    """Read a measured core T-matrix CSV (docs/formats.md "Measured core T-matrices").

    Columns ``Q_W`` [W], ``freq_Hz`` [Hz], ``Tpp_re, Tpp_im, Tpu_re, ..., Tuu_im`` (raw SI
    coefficients) in any order; optional standard deviations ``sigma_Tpp`` (both parts)
    or ``sigma_Tpp_re`` and ``sigma_Tpp_im``, for all four coefficients or none.
    ``# convention = exp(+iwt)`` data are conjugated (sigma unchanged).
    """
    t = _read_table(path, TMATRIX_COLUMNS, allowed=_sigma_allowed)
    conj = _needs_conjugate(t)
    for v, n in zip(t.values["Q_W"], t.lines):
        if v < 0:
            raise _fail(t.source, n, f"Q_W = {number(v)}: expected a heat input >= 0 W")
    _check_positive_unique(t, "freq_Hz", others=("Q_W",))
    rows = len(t.lines)
    T = np.empty((rows, 2, 2), dtype=np.complex128)
    for c, (i, j) in COEFFICIENTS.items():
        T[:, i, j] = _complex(t, c)
    sigma = _read_sigma(t, COEFFICIENTS).reshape(rows, 2, 2, 2) if _has_sigma(t) else None
    T = T.conj() if conj else T
    _check_convention(t, conj, tmatrix_convention_evidence(t.values["Q_W"], t.values["freq_Hz"], T))
    return TMatrixData(t.values["Q_W"], t.values["freq_Hz"], T, sigma, _converted_metadata(t, conj), t.source)


def tmatrix_convention_evidence(heat_input, freq, T) -> str | None:
    """Why core T-matrices ``T`` (rows, 2, 2), taken as exp(-iwt), look like exp(+iwt)
    data, or None. Below a core's first resonance its gas is an inertance and a
    compliance: for a duct, ``Tpu = i Zc sin kL`` and ``Tup = i sin(kL) / Zc`` in
    exp(-iwt), so ``Im Tpu > 0`` and ``Im Tup > 0`` while ``Re Tpp = cos kL > 0``,
    heated or not (viscous and thermal losses change the real parts). The evidence: at
    the lowest frequency of every heat input, ``Re Tpp > 0`` and both imaginary parts < 0."""
    low = [np.flatnonzero(heat_input == q)[np.argmin(freq[heat_input == q])] for q in np.unique(heat_input)]
    t = T[low]
    if np.all((t[:, 0, 0].real > 0) & (t[:, 0, 1].imag < 0) & (t[:, 1, 0].imag < 0)):
        return (
            f"Im Tpu < 0 and Im Tup < 0 at {freq[low[0]]:g} Hz, the lowest frequency, where a passive core "
            "has both > 0 in exp(-iwt)"
        )
    return None


def _has_sigma(t: _Table) -> bool:
    return any(c.startswith("sigma_") for c in t.columns)


def _read_sigma(t: _Table, entries) -> np.ndarray:
    """Standard deviations (rows, len(entries), 2) of the (re, im) parts of the complex
    columns ``entries``, from ``sigma_E`` (both parts) or ``sigma_E_re``/``sigma_E_im``
    columns that cover every entry; errors name the header line or the data line."""
    sigma = np.empty((len(t.lines), len(entries), 2))
    for e, c in enumerate(entries):
        one, re, im = (f"sigma_{c}{p}" in t.columns for p in ("", "_re", "_im"))
        if one and (re or im):
            raise _fail(t.source, t.header_line, f"give either sigma_{c} or sigma_{c}_re/_im, not both")
        if not one and not (re and im):
            raise _fail(
                t.source,
                t.header_line,
                f"sigma for {c} incomplete; expected sigma_{c} or both sigma_{c}_re and sigma_{c}_im "
                f"(sigma columns cover all of {', '.join(entries)} or none)",
            )
        for k, p in enumerate(("_re", "_im")):
            name = f"sigma_{c}" if one else f"sigma_{c}{p}"
            sigma[:, e, k] = t.values[name]
            bad = np.flatnonzero(t.values[name] <= 0)
            if bad.size:
                raise _fail(
                    t.source,
                    t.lines[bad[0]],
                    f"{name} = {number(t.values[name][bad[0]])}: expected a standard deviation > 0",
                )
    return sigma


def write_tmatrix_csv(path: str | os.PathLike, data: TMatrixData, metadata: dict | None = None) -> None:
    """Write ``data`` in the format read by :func:`read_tmatrix_csv`.

    Metadata lines are ``data.metadata`` updated by ``metadata``, with
    ``convention = exp(-iwt)`` (how the data are stored). Numbers are written with
    Python's shortest exact repr (at most 17 significant digits), so reading the file
    back gives bit-identical arrays. Values are checked before anything is written; the
    file is written to a temporary file in the same folder and moved into place, so the
    target is either the old file or the complete new one.
    """
    data.check()
    meta = {"convention": CONVENTION}
    meta.update({k: v for k, v in {**data.metadata, **(metadata or {})}.items() if k != "convention"})
    _write_matrix_csv(path, meta, {"Q_W": data.heat_input, "freq_Hz": data.freq}, COEFFICIENTS, data.T, data.sigma)


def _write_matrix_csv(path, meta: dict, leading: dict, entries: dict, M: np.ndarray, sigma) -> None:
    """Metadata lines ``meta``, a header of the ``leading`` {column: (rows,)} columns, the
    (re, im) columns of the 2x2 matrices ``M`` (rows, 2, 2) named by ``entries`` {name:
    (i, j)} and, when ``sigma`` (rows, 2, 2, 2) is given, their ``sigma_*_re/_im``; numbers
    in Python's shortest exact repr; written atomically."""
    out = [_metadata_line(path, k, v) for k, v in meta.items()]
    columns = list(leading) + [f"{e}_{p}" for e in entries for p in ("re", "im")]
    if sigma is not None:
        columns += [f"sigma_{e}_{p}" for e in entries for p in ("re", "im")]
    out.append(",".join(columns))
    for r in range(M.shape[0]):
        row = [v[r] for v in leading.values()]
        row += [part for (i, j) in entries.values() for part in (M[r, i, j].real, M[r, i, j].imag)]
        if sigma is not None:
            row += [sigma[r, i, j, k] for (i, j) in entries.values() for k in (0, 1)]
        out.append(",".join(repr(float(v)) for v in row))
    _atomic_write(path, "\n".join(out) + "\n")


# -- surface impedance -----------------------------------------------------------------
def read_impedance_csv(path: str | os.PathLike) -> ImpedanceData:
    """Read the surface impedance of a rigid-backed layer (docs/formats.md, "Surface impedance: CSV").

    Columns ``freq_Hz`` [Hz], ``Zs_re``, ``Zs_im`` (normalized by rho0 c0). Metadata:
    ``thickness`` [m] (required), ``convention`` (default exp(-iwt); exp(+iwt) is
    conjugated), optional ``T_ambient`` [K] and ``p_ambient`` [Pa]. Optional standard
    deviations ``sigma_Zs`` (both parts) or ``sigma_Zs_re`` and ``sigma_Zs_im``.
    """
    t = _read_table(path, IMPEDANCE_COLUMNS, allowed=lambda c: c in _sigma_columns(("Zs",)))
    conj = _needs_conjugate(t)
    thickness = _meta_float(t, "thickness", "m")
    T_amb = _meta_float(t, "T_ambient", "K", required=False)
    p_amb = _meta_float(t, "p_ambient", "Pa", required=False)
    _check_positive_unique(t, "freq_Hz")
    Zs = _complex(t, "Zs")
    zero = np.flatnonzero(Zs == 0)
    if zero.size:
        raise _fail(
            t.source,
            t.lines[zero[0]],
            "Zs = 0: a rigid-backed layer has |Zs| > 0 (infinite at low frequency); correct or remove the row",
        )
    sigma = _read_sigma(t, ("Zs",))[:, 0] if _has_sigma(t) else None
    Zs = Zs.conj() if conj else Zs
    _check_convention(t, conj, impedance_convention_evidence(t.values["freq_Hz"], Zs))
    return ImpedanceData(
        t.values["freq_Hz"], Zs, thickness, T_amb, p_amb, _converted_metadata(t, conj), t.source, sigma
    )


def write_impedance_csv(path: str | os.PathLike, data: ImpedanceData, metadata: dict | None = None) -> None:
    """Write ``data`` in the format read by :func:`read_impedance_csv` (``thickness``,
    ``T_ambient``, ``p_ambient`` from the data; shortest exact floats; atomically, as
    :func:`write_tmatrix_csv`)."""
    if data.thickness is None:
        raise MeasurementError(f"{path}: the layer's thickness is unknown; the impedance CSV requires it")
    if not (np.all(np.isfinite(data.Zs)) and np.all(np.isfinite(data.freq)) and np.all(data.freq > 0)):
        raise MeasurementError(f"{path}: Zs and freq must be finite, freq > 0")
    if data.sigma is not None and not np.all(np.isfinite(data.sigma) & (data.sigma > 0)):
        raise MeasurementError(f"{path}: sigma must be finite and > 0")
    own = {"convention": CONVENTION, "thickness": repr(float(data.thickness))}
    for key, v in (("T_ambient", data.T_ambient), ("p_ambient", data.p_ambient)):
        if v is not None:
            own[key] = repr(float(v))
    meta = dict(own)
    meta.update({k: v for k, v in {**data.metadata, **(metadata or {})}.items() if k not in own})
    out = [_metadata_line(path, k, v) for k, v in meta.items()]
    columns = ["freq_Hz", "Zs_re", "Zs_im"] + (["sigma_Zs_re", "sigma_Zs_im"] if data.sigma is not None else [])
    out.append(",".join(columns))
    for r in range(len(data)):
        row = [data.freq[r], data.Zs[r].real, data.Zs[r].imag]
        if data.sigma is not None:
            row += list(data.sigma[r])
        out.append(",".join(repr(float(v)) for v in row))
    _atomic_write(path, "\n".join(out) + "\n")


def impedance_convention_evidence(freq, Zs) -> str | None:
    """Why surface impedances ``Zs`` of a rigid-backed layer, taken as exp(-iwt), look
    like exp(+iwt) data, or None. In exp(-iwt) ``Zs = i Zc cot(kd)``: a compliance at low
    frequency (``Im Zs > 0``, infinite as f -> 0), and ``Im Zs`` falls with frequency
    between the half-wave poles (losses round the poles off). The evidence: ``Im Zs < 0``
    at the lowest frequency and rising over most steps of frequency."""
    order = np.argsort(freq)
    im = Zs.imag[order]
    if im.size >= 2 and im[0] < 0 and np.mean(np.diff(im) > 0) > 0.5:
        return (
            f"Im Zs < 0 at {freq[order[0]]:g} Hz, the lowest frequency, and rising with frequency; a "
            "rigid-backed layer has Im Zs > 0 there, falling, in exp(-iwt)"
        )
    return None


# Atalla & Panneton (2005) sample table, transcribed from the data set's README in SI:
# thickness mm -> e-3 m, Lambda um -> e-6 m, T C -> + 273.15 K, P0 bar -> e5 Pa.
_ATALLA_PANNETON = {
    # name: thin, thick, sigma [N s m^-4], phi, alpha_inf, Lambda, Lambda', T, P0, frame
    "foam1": (49.92e-3, 98.7e-3, 4971.0, 0.97, 1.31, 123.19e-6, 289.54e-6, 21.5 + 273.15, 0.992e5, "rigid"),
    "foam2": (34.35e-3, 68.77e-3, 8197.0, 0.95, 1.42, 133.10e-6, 212.65e-6, 24.6 + 273.15, 0.997e5, "rigid"),
    "fibrous1": (23.37e-3, 46.83e-3, 21235.0, 0.94, 1.00, 48.62e-6, 114.39e-6, 22.6 + 273.15, 1.002e5, "limp"),
    # README: the fibrous2 "thick" file behaves like a thinner sample; its thickness is unknown
    "fibrous2": (37.38e-3, None, 50470.0, 0.89, 1.00, 41.51e-6, 114.27e-6, 24.6 + 273.15, 0.977e5, "limp"),
}
_AP_KEYS = (
    "thickness_thin",
    "thickness_thick",
    "sigma",
    "phi",
    "alpha_inf",
    "Lambda",
    "Lambda_prime",
    "T",
    "P0",
    "frame",
)
ATALLA_PANNETON_DIR = Path("data") / "measured" / "atalla_panneton_2005"


def atalla_panneton_samples() -> dict[str, dict]:
    """Sample properties of the Atalla & Panneton (2005) data set, from its README.

    ``{name: {thickness_thin [m], thickness_thick [m] (None for fibrous2: unreliable),
    sigma [N s/m^4], phi [-], alpha_inf [-], Lambda [m], Lambda_prime [m], T [K],
    P0 [Pa], frame ("rigid" | "limp"), files (thin, thick)}}`` for foam1, foam2,
    fibrous1, fibrous2. A fresh dict on every call.
    """
    return {
        name: {**dict(zip(_AP_KEYS, row)), "files": (f"{name}.csv", f"{name}thick.csv")}
        for name, row in _ATALLA_PANNETON.items()
    }


def read_atalla_panneton(
    path: str | os.PathLike, thickness: float | None, T_ambient: float | None = None, p_ambient: float | None = None
) -> ImpedanceData:
    """Read one file of the Atalla & Panneton data set (header ``f,Re,Im,,,``).

    ``f`` [Hz], ``Re``, ``Im`` of ``Zs / (rho0 c0)`` in the paper's ``exp(+jwt)``
    convention; later columns are digitizing leftovers and are ignored. The result is
    conjugated to ``exp(-iwt)``. ``thickness`` [m], ``T_ambient`` [K], ``p_ambient`` [Pa]
    come from :func:`atalla_panneton_samples`, not from the file.
    """
    t = _read_table(path, ("f", "Re", "Im"), ignore_extra=True)
    _check_positive_unique(t, "f")
    Zs = (t.values["Re"] + 1j * t.values["Im"]).conj()  # exp(+jwt) -> exp(-iwt)
    meta = {
        "convention": CONVENTION,
        "original_convention": "exp(+jwt)",
        "origin": "Atalla & Panneton, Canadian Acoustics 33(1) 2005, Fig. 7 (digitized by pyva)",
    }
    return ImpedanceData(t.values["f"], Zs, thickness, T_ambient, p_ambient, meta, t.source)


def _atalla_panneton_folder() -> Path:
    """The copy of the data set bundled with the package (``tawarp/data/measured/``)."""
    return Path(str(resources.files("tawarp") / ATALLA_PANNETON_DIR))


def load_atalla_panneton(name: str, folder: str | os.PathLike | None = None) -> list[ImpedanceData]:
    """``[thin, thick]`` surface impedances of sample ``name`` (foam1, foam2, fibrous1,
    fibrous2), with thickness [m], T_ambient [K], p_ambient [Pa] from the README table.

    ``folder`` defaults to the copy bundled with the package (its README, source and
    licence beside the files); pass another folder to read a copy elsewhere. For fibrous2
    the thick layer's ``thickness`` is None (the README calls that pairing unreliable).
    """
    samples = atalla_panneton_samples()
    if name not in samples:
        raise KeyError(f"unknown Atalla & Panneton sample {name!r}; expected one of {sorted(samples)}")
    folder = Path(folder) if folder is not None else _atalla_panneton_folder()
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: Atalla & Panneton data folder does not exist")
    s = samples[name]
    out = []
    for fname, thickness in zip(s["files"], (s["thickness_thin"], s["thickness_thick"])):
        path = folder / fname
        if not path.is_file():
            raise FileNotFoundError(f"{path}: file of sample {name!r} does not exist")
        d = read_atalla_panneton(path, thickness, s["T"], s["P0"])
        d.metadata["sample"] = name
        if thickness is None:
            d.metadata["note"] = "thickness unknown: the README calls this thick-layer pairing unreliable"
        out.append(d)
    return out


# -- two-port scattering matrix --------------------------------------------------------
#: The four scattering entries and their (row, column) in the 2x2 matrix.
S_ENTRIES = {"S11": (0, 0), "S12": (0, 1), "S21": (1, 0), "S22": (1, 1)}
#: Signed reference-plane keys and the distance keys of the first format (upstream, downstream).
PLANE_KEYS = (("ref_plane_upstream", "ref_upstream", -1.0), ("ref_plane_downstream", "ref_downstream", 1.0))


def _entries(M):
    return M[..., 0, 0], M[..., 0, 1], M[..., 1, 0], M[..., 1, 1]


def _matrix(m11, m12, m21, m22) -> np.ndarray:
    m11, m12, m21, m22 = np.broadcast_arrays(m11, m12, m21, m22)
    return np.stack([np.stack([m11, m12], -1), np.stack([m21, m22], -1)], -2)


def scattering_to_transfer(S, k, Zc, d1=0.0, d2=0.0) -> np.ndarray:
    """Core T-matrix of ``(p, U)`` between the sample faces from a scattering matrix.

    Convention (``exp(-iwt)``): on each side of the sample, plane waves
    ``p = A e^{ikx} + B e^{-ikx}``, ``U = (A e^{ikx} - B e^{-ikx}) / Zc`` (A travels
    downstream, +x), with x measured from that side's reference plane. ``S`` (..., 2, 2)
    maps incoming to outgoing amplitudes at the reference planes,
    ``[B1, A2] = S [A1, B2]`` (side 1 upstream, side 2 downstream). ``k`` [1/m]
    wavenumber (complex for a lossy tube), ``Zc = rho0 c0 / S_tube`` [Pa s/m^3];
    ``d1 = -x_up`` and ``d2 = x_down`` [m], where ``x_up`` is the signed position of the
    upstream reference plane from face x1 and ``x_down`` that of the downstream plane from
    face x6, both positive downstream: ``d1``, ``d2`` >= 0 are the distances of planes
    outside the sample, and any sign is exact (a plane inside the sample's span is a
    place where each side's waves are evaluated, continued as tube waves: planes may
    coincide). All broadcast over the leading axes. Returns ``T`` (..., 2, 2) with
    ``(p, U)(x6) = T (p, U)(x1)``. Needs ``S12 != 0``.
    """
    S = np.asarray(S, dtype=np.complex128)
    k, Zc = np.asarray(k), np.asarray(Zc)
    # amplitudes at the faces: a1 = A1 e^{ik d1}, b1 = B1 e^{-ik d1}, a2 = A2 e^{-ik d2}, b2 = B2 e^{ik d2}
    e1, e2 = np.exp(-1j * k * d1), np.exp(-1j * k * d2)
    s11, s12, s21, s22 = _entries(S)
    s11, s12, s21, s22 = s11 * e1 * e1, s12 * e1 * e2, s21 * e1 * e2, s22 * e2 * e2
    # wave transfer [a2, b2] = W [a1, b1], then T = M W M^-1 with [p, U] = M [a, b]
    w11, w12, w21, w22 = -(s11 * s22 - s12 * s21) / s12, s22 / s12, -s11 / s12, 1 / s12
    return _matrix(
        0.5 * (w11 + w21 + w12 + w22),
        0.5 * Zc * (w11 + w21 - w12 - w22),
        0.5 / Zc * (w11 - w21 + w12 - w22),
        0.5 * (w11 - w21 - w12 + w22),
    )


def transfer_to_scattering(T, k, Zc, d1=0.0, d2=0.0) -> np.ndarray:
    """Inverse of :func:`scattering_to_transfer` (same conventions and arguments)."""
    T = np.asarray(T, dtype=np.complex128)
    k, Zc = np.asarray(k), np.asarray(Zc)
    t11, t12, t21, t22 = _entries(T)
    # W = M^-1 T M
    w11 = 0.5 * (t11 + t12 / Zc + Zc * t21 + t22)
    w12 = 0.5 * (t11 - t12 / Zc + Zc * t21 - t22)
    w21 = 0.5 * (t11 + t12 / Zc - Zc * t21 - t22)
    w22 = 0.5 * (t11 - t12 / Zc - Zc * t21 + t22)
    s11, s12, s21, s22 = -w21 / w22, 1 / w22, (w11 * w22 - w12 * w21) / w22, w12 / w22
    # faces -> reference planes
    e1, e2 = np.exp(1j * k * d1), np.exp(1j * k * d2)
    return _matrix(s11 * e1 * e1, s12 * e1 * e2, s21 * e1 * e2, s22 * e2 * e2)


def propagated_sigma(f, args, sigmas, step: float = 1e-6) -> np.ndarray:
    """Standard deviations (..., 2) of the (re, im) parts of ``f(*args)`` (complex, rows
    first) to first order, from independent errors of the (re, im) parts of each complex
    argument: ``args`` [(rows, ...) complex], ``sigmas`` [(rows, ..., 2) or None: exact].
    ``f`` works row by row; its derivatives are central differences of step ``step`` in
    the arguments (made for dimensionless values of order one, such as S)."""
    var = 0.0
    for a, (x, sx) in enumerate(zip(args, sigmas)):
        if sx is None:
            continue
        for idx in np.ndindex(x.shape[1:]):
            for part, h in ((0, step), (1, 1j * step)):
                lo, hi = [list(args) for _ in range(2)]
                lo[a], hi[a] = x.copy(), x.copy()
                lo[a][(slice(None),) + idx] -= h
                hi[a][(slice(None),) + idx] += h
                d = (f(*hi) - f(*lo)) / (2 * step)
                s = sx[(slice(None),) + idx + (part,)].reshape((-1,) + (1,) * (d.ndim - 1))
                var = var + np.stack([d.real, d.imag], -1) ** 2 * s[..., None] ** 2
    return np.sqrt(var)


@dataclass
class ScatteringData:
    """A four-microphone scattering matrix at its reference planes (before conversion).

    ``freq`` (m,) [Hz]; ``S`` (m, 2, 2) complex in the convention of
    :func:`scattering_to_transfer`, ``exp(-iwt)``; ``sigma`` None or (m, 2, 2, 2) standard
    deviations of the (re, im) parts; ``plane_upstream`` [m] the signed position of the
    upstream reference plane from face x1, ``plane_downstream`` [m] that of the downstream
    plane from face x6, both positive downstream (planes outside the sample:
    ``plane_upstream <= 0 <= plane_downstream``; coinciding planes, e.g. both on the front
    face of a sample of length L: ``0`` and ``-L``); ``tube_radius`` [m], ``T_ambient``
    [K], ``p_ambient`` [Pa], ``gas`` name; ``heat_input`` [W]; ``wavenumber`` None (the
    lossless ``w / c0``) or (m,) complex [1/m] and ``impedance`` None (the lossless
    ``rho0 c0 / S``) or (m,) complex [Pa s/m^3], the tube's own (set by an empty-tube
    calibration, :func:`tawarp.measure.scattering.calibrate_empty_tube`).
    """

    freq: np.ndarray
    S: np.ndarray
    plane_upstream: float
    plane_downstream: float
    tube_radius: float
    T_ambient: float
    p_ambient: float
    gas: str = "air"
    heat_input: float = 0.0
    sigma: np.ndarray | None = None
    wavenumber: np.ndarray | None = None
    metadata: dict[str, str] = field(default_factory=dict)
    source: str = "<data>"
    impedance: np.ndarray | None = None

    def __post_init__(self):
        self.freq = np.asarray(self.freq, dtype=float).reshape(-1)
        self.S = np.asarray(self.S, dtype=np.complex128)
        n = self.freq.size
        if self.S.shape != (n, 2, 2):
            raise MeasurementError(f"{self.source}: S shape {self.S.shape}; expected ({n}, 2, 2)")
        if self.sigma is not None:
            self.sigma = np.asarray(self.sigma, dtype=float)
            if self.sigma.shape != (n, 2, 2, 2):
                raise MeasurementError(f"{self.source}: sigma shape {self.sigma.shape}; expected ({n}, 2, 2, 2)")
        if self.gas not in GASES:
            raise MeasurementError(f"{self.source}: gas = {self.gas!r}; expected one of {sorted(GASES)}")

    def __len__(self) -> int:
        return self.freq.size

    @property
    def sound_speed(self) -> float:
        """c0 = sqrt(gamma R T_ambient) [m/s]."""
        g = GASES[self.gas]
        return math.sqrt(g.gamma * g.R_gas * self.T_ambient)

    @property
    def Zc(self):
        """Characteristic impedance of the tube [Pa s/m^3]: ``impedance`` (m,) if calibrated,
        else the lossless rho0 c0 / (pi radius^2) of the metadata."""
        if self.impedance is not None:
            return self.impedance
        rho0 = self.p_ambient / (GASES[self.gas].R_gas * self.T_ambient)
        return rho0 * self.sound_speed / (math.pi * self.tube_radius**2)

    @property
    def k(self) -> np.ndarray:
        """Wavenumber (m,) [1/m]: ``wavenumber`` if calibrated, else w / c0."""
        return 2 * np.pi * self.freq / self.sound_speed if self.wavenumber is None else self.wavenumber

    def transfer(self, S=None) -> np.ndarray:
        """Core T-matrices (m, 2, 2) [SI] of ``S`` (default the data's) at these planes."""
        return scattering_to_transfer(
            self.S if S is None else S, self.k, self.Zc, -self.plane_upstream, self.plane_downstream
        )

    def to_tmatrix(self) -> TMatrixData:
        """The core T-matrices, sigma propagated to first order (:func:`propagated_sigma`)."""
        sigma = None
        if self.sigma is not None:
            sigma = propagated_sigma(self.transfer, [self.S], [self.sigma])
        meta = dict(self.metadata)
        meta["converted_from"] = "scattering matrix"
        data = TMatrixData(np.full(len(self), self.heat_input), self.freq, self.transfer(), sigma, meta, self.source)
        data.check()  # an overflow of extreme S: named, not NaN data
        return data


def _meta_signed(t: _Table, key: str, unit: str) -> float:
    """Metadata ``key`` as a finite number of any sign [unit]."""
    text = t.meta[key]
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise _fail(t.source, t.meta_line[key], f"metadata {key} = {text!r}: expected a finite number [{unit}]")
    return v


def _reference_plane(t: _Table, signed: str, distance: str, sign: float) -> float:
    """Signed position of one reference plane from ``signed`` or the first format's ``distance``."""
    if signed in t.meta and distance in t.meta:
        raise _fail(
            t.source,
            t.meta_line[distance],
            f"metadata {distance} and {signed} (line {t.meta_line[signed]}) both place the same "
            f"reference plane; give one of them",
        )
    if signed in t.meta:
        return _meta_signed(t, signed, "m")
    if distance in t.meta:
        return sign * _meta_float(t, distance, "m", allow_zero=True)
    raise MeasurementError(
        f"{t.source}: metadata key {signed!r} [m] is missing; add a line '# {signed} = ...' "
        f"(signed position of the reference plane from the sample face, positive downstream) "
        f"or '# {distance} = ...' (its distance from the face, >= 0) before the header"
    )


def read_scattering(path: str | os.PathLike) -> ScatteringData:
    """Read a four-microphone scattering-matrix CSV as it is (no conversion).

    Columns ``freq_Hz`` [Hz], ``S11_re, S11_im, ..., S22_im`` with the convention of
    :func:`scattering_to_transfer`; optional standard deviations ``sigma_S11`` (both parts)
    or ``sigma_S11_re`` and ``sigma_S11_im``, for all four entries or none. Metadata:
    ``tube_radius`` [m], ``T_ambient`` [K], ``p_ambient`` [Pa], required; each reference
    plane either as a signed position, ``ref_plane_upstream`` from face x1 and
    ``ref_plane_downstream`` from face x6 [m], positive downstream (any sign; planes may
    coincide), or as the first format's distance ``ref_upstream`` / ``ref_downstream``
    [m] >= 0 from the face, outside the sample (``ref_plane_upstream = -ref_upstream``,
    ``ref_plane_downstream = ref_downstream``); ``gas`` (default air, one of
    :data:`tawarp.model.gas.GASES`), ``convention`` (default exp(-iwt); exp(+iwt) S is
    conjugated), ``Q_W`` [W] (default 0).
    """
    t = _read_table(path, SCATTERING_COLUMNS, allowed=lambda c: c in _sigma_columns(S_ENTRIES))
    conj = _needs_conjugate(t)
    radius = _meta_float(t, "tube_radius", "m")
    T_amb = _meta_float(t, "T_ambient", "K")
    p_amb = _meta_float(t, "p_ambient", "Pa")
    x_up, x_down = (_reference_plane(t, *keys) for keys in PLANE_KEYS)
    Q = _meta_float(t, "Q_W", "W", required=False, allow_zero=True, default=0.0)
    gas = t.meta.get("gas", "air")
    if gas not in GASES:
        raise _fail(t.source, t.meta_line["gas"], f"gas = {gas!r}; expected one of {sorted(GASES)}")
    _check_positive_unique(t, "freq_Hz")
    S = _matrix(*(_complex(t, e) for e in S_ENTRIES))
    if conj:
        S = S.conj()
    zero = np.flatnonzero(S[:, 0, 1] == 0)
    if zero.size:
        raise _fail(t.source, t.lines[zero[0]], "S12 = 0: no transmission, the T-matrix is undefined")
    sigma = _read_sigma(t, S_ENTRIES).reshape(-1, 2, 2, 2) if _has_sigma(t) else None
    return ScatteringData(
        t.values["freq_Hz"],
        S,
        x_up,
        x_down,
        radius,
        T_amb,
        p_amb,
        gas,
        Q,
        sigma,
        None,
        _converted_metadata(t, conj),
        t.source,
    )


def read_scattering_csv(path: str | os.PathLike) -> TMatrixData:
    """Read a four-microphone scattering matrix (:func:`read_scattering`) and convert it to
    core T-matrices: lossless plane waves ``k = w / c0``, ``c0 = sqrt(gamma R T_ambient)``,
    ``rho0 = p_ambient / (R T_ambient)``, ``Zc = rho0 c0 / (pi tube_radius^2)``; sigma
    propagated to first order. An empty-tube calibration:
    :func:`tawarp.measure.scattering.calibrate_empty_tube`."""
    return read_scattering(path).to_tmatrix()


def write_scattering_csv(path: str | os.PathLike, data: ScatteringData, metadata: dict | None = None) -> None:
    """Write ``data`` in the format read by :func:`read_scattering` (signed plane keys,
    shortest exact floats, atomically as :func:`write_tmatrix_csv`). Calibrated data
    (``wavenumber`` set) have no file form and are refused."""
    if data.wavenumber is not None or data.impedance is not None:
        raise MeasurementError(f"{path}: calibrated scattering data (a fitted tube wavenumber) have no CSV form")
    if not (np.all(np.isfinite(data.S)) and np.all(np.isfinite(data.freq)) and np.all(data.freq > 0)):
        raise MeasurementError(f"{path}: S and freq must be finite, freq > 0")
    own = {
        "convention": CONVENTION,
        "tube_radius": data.tube_radius,
        "T_ambient": data.T_ambient,
        "p_ambient": data.p_ambient,
        "gas": data.gas,
        "Q_W": data.heat_input,
        "ref_plane_upstream": data.plane_upstream,
        "ref_plane_downstream": data.plane_downstream,
    }
    replaced = set(own) | {"ref_upstream", "ref_downstream", "original_convention", "converted_from"}
    meta = {k: repr(float(v)) if isinstance(v, float) else v for k, v in own.items()}
    meta.update({k: v for k, v in {**data.metadata, **(metadata or {})}.items() if k not in replaced})
    _write_matrix_csv(path, meta, {"freq_Hz": data.freq}, S_ENTRIES, data.S, data.sigma)
