"""Engines: a core closed by resonator ducts and end conditions (docs/formats.md, "Engine TOML").

An engine file is a core file (docs/formats.md) with one more top-level table::

    [engine]
    left = "closed"            # closed | open | impedance
    right = "closed"
    left_duct = 0.87           # resonator duct between the left end and plane x1 [m] (0)
    right_duct = 0.0           # between plane x6 and the right end [m] (0)
    # optional: left_duct_radius / right_duct_radius [m] (the tube's), left_duct_T /
    # right_duct_T [K] (gas.T_cold); for an impedance end, left_impedance = [Z_re, Z_im]
    # [Pa s/m^3] or left_impedance_csv = "file.csv" (freq_Hz,Z_re,Z_im; relative to the file)

The state runs from the left end through the left duct, the core (x1 to x6) and the right
duct to the right end. An impedance Z is that of the termination, p / U with U the volume
velocity flowing out of the resonator into it (exp(-i omega t)); a closed end is Z -> inf,
an ideal open end Z = 0 (no radiation).
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .core import Core, CoreError, bundled, core_from_dict, read_toml

END_KINDS = ("closed", "open", "impedance")
_SIDE_KEYS = ("", "_duct", "_duct_radius", "_duct_T", "_impedance", "_impedance_csv")
_ENGINE_KEYS = {side + k for side in ("left", "right") for k in _SIDE_KEYS}
#: Resonator quantities a batch may vary, as ``engine.NAME`` (tawarp.model.onset).
RESONATOR_FIELDS = ("left_duct", "left_duct_radius", "left_duct_T", "right_duct", "right_duct_radius", "right_duct_T")


@dataclass(frozen=True)
class EndCondition:
    """One end: ``kind`` closed, open or impedance; ``impedance`` (k, 3) rows
    (freq [Hz], Z_re, Z_im [Pa s/m^3]) for an impedance end (one row: a constant)."""

    kind: str = "closed"
    impedance: np.ndarray | None = field(default=None, compare=False)

    def table(self) -> np.ndarray:
        """The impedance rows the kernel reads ((1, 3) zeros when not an impedance end)."""
        return np.zeros((1, 3)) if self.impedance is None else np.ascontiguousarray(self.impedance, dtype=np.float64)


@dataclass(frozen=True)
class ResonatorDuct:
    """An empty resonator duct: ``length`` [m] >= 0; ``radius`` [m] and gas temperature
    ``T`` [K], ``None`` meaning the core's tube radius and T_cold."""

    length: float = 0.0
    radius: float | None = None
    T: float | None = None


@dataclass(frozen=True)
class ThermoacousticEngine:
    """A core between a left and a right resonator duct, each closed by an end condition."""

    core: Core
    left: EndCondition = EndCondition()
    right: EndCondition = EndCondition()
    left_duct: ResonatorDuct = ResonatorDuct()
    right_duct: ResonatorDuct = ResonatorDuct()
    source: str = "<engine>"

    def resonator_row(self) -> np.ndarray:
        """(6,) left (length, radius, T), right (length, radius, T), defaults filled in."""
        out = []
        for d in (self.left_duct, self.right_duct):
            out += [
                d.length,
                self.core.radius if d.radius is None else d.radius,
                self.core.gas.T_cold if d.T is None else d.T,
            ]
        return np.array(out, dtype=np.float64)

    def total_length(self) -> float:
        """Left end to right end [m]."""
        return self.left_duct.length + self.core.positions()[-1] + self.right_duct.length


def read_impedance_csv(path: str | Path) -> np.ndarray:
    """(k, 3) rows freq_Hz, Z_re, Z_im [Pa s/m^3] from a CSV with that header ('#' lines
    skipped); frequencies positive and increasing. Errors name file and line."""
    p = Path(path)
    rows = []
    with p.open(newline="") as fh:
        lines = [(n, line) for n, line in enumerate(fh, 1) if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise CoreError(f"{p}: empty impedance file; expected the header freq_Hz,Z_re,Z_im")
    header = [h.strip() for h in next(csv.reader([lines[0][1]]))]
    if header != ["freq_Hz", "Z_re", "Z_im"]:
        raise CoreError(f"{p}:{lines[0][0]}: header {header}; expected freq_Hz,Z_re,Z_im")
    for n, line in lines[1:]:
        try:
            vals = [float(v) for v in next(csv.reader([line]))]
        except ValueError:
            raise CoreError(f"{p}:{n}: not three numbers: {line.strip()!r}") from None
        if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
            raise CoreError(f"{p}:{n}: expected three finite numbers, got {line.strip()!r}")
        rows.append(vals)
    t = np.array(rows, dtype=np.float64).reshape(-1, 3)
    if len(t) == 0 or np.any(t[:, 0] <= 0) or np.any(np.diff(t[:, 0]) <= 0):
        raise CoreError(f"{p}: frequencies must be positive and strictly increasing")
    return t


def _end(d: dict, side: str, source: str, folder: Path) -> EndCondition:
    kind = d.get(side, "closed")
    if kind not in END_KINDS:
        raise CoreError(f"{source}: [engine] {side} = {kind!r}; expected one of {', '.join(END_KINDS)}")
    given = [k for k in (f"{side}_impedance", f"{side}_impedance_csv") if k in d]
    if kind != "impedance":
        if given:
            raise CoreError(f"{source}: [engine] {given[0]} given but {side} = {kind!r}; use {side} = 'impedance'")
        return EndCondition(kind)
    if len(given) != 1:
        raise CoreError(
            f"{source}: [engine] {side} = 'impedance' needs exactly one of "
            f"{side}_impedance = [Z_re, Z_im] or {side}_impedance_csv = 'file.csv'"
        )
    if given[0].endswith("_csv"):
        return EndCondition(kind, read_impedance_csv(folder / d[given[0]]))
    z = d[given[0]]
    if (
        not isinstance(z, list)
        or len(z) != 2
        or not all(isinstance(v, (int, float)) for v in z)
        or not all(math.isfinite(v) for v in z)
    ):
        raise CoreError(f"{source}: [engine] {given[0]} must be [Z_re, Z_im] in Pa s/m^3, got {z!r}")
    return EndCondition(kind, np.array([[1.0, float(z[0]), float(z[1])]]))


def _duct(d: dict, side: str, source: str) -> ResonatorDuct:
    vals = {}
    for key, name, lo in (("_duct", "length", 0.0), ("_duct_radius", "radius", None), ("_duct_T", "T", None)):
        k = side + key
        if k not in d:
            continue
        v = d[k]
        if (
            isinstance(v, bool)
            or not isinstance(v, (int, float))
            or not math.isfinite(v)
            or (v < 0 if lo is not None else v <= 0)
        ):
            raise CoreError(
                f"{source}: [engine] {k} = {v!r}; expected a finite number "
                f"{'>= 0' if lo is not None else '> 0'} (SI units)"
            )
        vals[name] = float(v)
    return ResonatorDuct(**vals)


def engine_from_dict(data: dict, source: str = "<engine>", folder: Path | None = None) -> ThermoacousticEngine:
    """Build an engine from the TOML structure: ``[engine]`` plus a core (docs/formats.md)."""
    data = dict(data)
    if "engine" not in data:
        raise CoreError(f"{source}: no [engine] table; an engine file is a core file with an [engine] table")
    d = data.pop("engine")
    if not isinstance(d, dict):
        raise CoreError(f"{source}: 'engine' must be a table written [engine]")
    bad = set(d) - _ENGINE_KEYS
    if bad:
        raise CoreError(f"{source}: unknown key(s) in [engine]: {sorted(bad)}; allowed {sorted(_ENGINE_KEYS)}")
    folder = folder or Path(".")
    core = core_from_dict(data, source)
    return ThermoacousticEngine(
        core,
        _end(d, "left", source, folder),
        _end(d, "right", source, folder),
        _duct(d, "left", source),
        _duct(d, "right", source),
        source,
    )


def bundled_engines() -> list[str]:
    """Names of the engines shipped with tawarp."""
    return bundled("engines")


def load_engine(path: str | Path) -> ThermoacousticEngine:
    """Read and validate an engine TOML file; ``path`` may name a bundled engine
    (``standing_wave``)."""
    p, data = read_toml(path, "engines")
    try:
        return engine_from_dict(data, str(p), p.parent)
    except TypeError as e:
        raise CoreError(f"{p}: {e}") from None
