"""The CSV tables of every measurement file (docs/formats.md): ``# key = value`` metadata
lines, one header, numeric rows; the time convention; errors that name the file, the line
or the metadata key; atomic writes. The kinds' readers (:mod:`.files`) build on it."""

from __future__ import annotations

import contextlib
import csv
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

CONVENTION = "exp(-iwt)"
# Accepted spellings (after removing blanks, lower case); i and j both name sqrt(-1).
_MINUS = {"exp(-iwt)", "exp(-jwt)"}
_PLUS = {"exp(+iwt)", "exp(iwt)", "exp(+jwt)", "exp(jwt)"}


class MeasurementError(ValueError):
    """A measurement file or data set is invalid; the message names the file and line or key."""


# -- generic CSV reading ---------------------------------------------------------------
@dataclass
class _Table:
    source: str
    meta: dict[str, str]
    meta_line: dict[str, int]  # line of each metadata key
    header_line: int
    columns: list[str]
    values: dict[str, np.ndarray]  # column name -> floats
    lines: np.ndarray  # file line of each data row


def number(v) -> str:
    """A value of a file or data set as messages show it: ``-50.0`` (round-trip exact), not
    NumPy's ``np.float64(-50.0)``, which ``!r`` gives for an element of an array."""
    return repr(float(v))


def _fail(source, line, what) -> MeasurementError:
    return MeasurementError(f"{source}, line {line}: {what}")


def _read_table(path, required, allowed=lambda name: False, ignore_extra=False) -> _Table:
    """Parse ``# key = value`` lines, a header naming ``required`` columns (any order;
    others must satisfy ``allowed`` unless ``ignore_extra``) and numeric, finite rows.

    The file is streamed: data lines are parsed in blocks of :data:`_BLOCK` lines into
    float arrays, so memory stays near the size of the numbers (8 bytes each), not of the
    text; a block that the fast parser refuses is parsed line by line to name the line."""
    src = str(path)
    meta, meta_line = {}, {}
    header, header_line, used, width = None, 0, {}, 0
    blocks, line_blocks, lines, numbers = [], [], [], []
    for n, line in text_lines(path):
        if header is not None and not line.startswith("#"):
            lines.append(line)
            numbers.append(n)
            if len(lines) == _BLOCK:
                blocks.append(_parse_rows(src, lines, numbers, used, width, header_line, ignore_extra))
                line_blocks.append(np.array(numbers, dtype=np.int64))
                lines, numbers = [], []
            continue
        if line.startswith("#"):
            if header is not None:
                raise _fail(
                    src, n, "comment or metadata line after the header; '# key = value' lines must come before it"
                )
            key, eq, value = line[1:].partition("=")
            if eq:  # '# key = value'; a comment without '=' is free text
                key = key.strip()
                if not key:
                    raise _fail(src, n, "metadata line without a key; expected '# key = value'")
                if key in meta:
                    raise _fail(src, n, f"metadata key {key!r} given twice (first on line {meta_line[key]})")
                meta[key], meta_line[key] = value.strip(), n
            continue
        header, header_line = _split(src, n, line), n
        used = _check_header(src, n, header, required, allowed, ignore_extra)
        width = max(used.values()) + 1 if ignore_extra else len(header)
    if lines:
        blocks.append(_parse_rows(src, lines, numbers, used, width, header_line, ignore_extra))
        line_blocks.append(np.array(numbers, dtype=np.int64))
    del lines, numbers
    if header is None:
        raise _fail(src, 1, f"empty file (no header line); expected a header with columns {','.join(required)}")
    if not blocks:
        raise _fail(src, header_line, "header but no data rows after it")
    arr = np.concatenate(blocks) if len(blocks) > 1 else blocks[0]
    del blocks
    values = {name: arr[:, k] for k, name in enumerate(used)}
    return _Table(src, meta, meta_line, header_line, list(used), values, np.concatenate(line_blocks))


#: Data lines parsed at once (a few MB of text at most).
_BLOCK = 8192

#: The byte-order mark; spreadsheets write it at the start of a file, and files joined
#: by hand carry it to the start of a line.
_BOM = "\ufeff"


def text_lines(path):
    """``(line number, text)`` of the lines of the measurement file ``path`` that are not
    blank, stripped of blanks and of byte-order marks. A file that is not UTF-8 text (an
    image, a spreadsheet) or cannot be read raises :class:`MeasurementError` naming it."""
    src = str(path)
    n = 0
    try:
        with open(path, encoding="utf-8", newline=None) as f:
            for n, raw in enumerate(f, start=1):
                line = raw.replace(_BOM, "").strip()
                if line:
                    yield n, line
    except UnicodeDecodeError as e:
        byte = e.object[e.start : e.start + 1].hex()
        raise MeasurementError(
            f"{src}: not a text file (byte 0x{byte} on line {n + 1} is not UTF-8); give the "
            "measurement CSV, saved as UTF-8 text (docs/formats.md)"
        ) from None
    except OSError as e:
        raise MeasurementError(f"{src}: cannot read ({e.strerror})") from None


def _split(src, n, line: str) -> list[str]:
    """The stripped fields of line ``n`` of ``src`` (quotes as the csv module reads them)."""
    try:
        return [f.strip() for f in next(csv.reader([line]))]
    except csv.Error as e:  # e.g. a field over csv.field_size_limit() (128 kB): no number is that long
        raise _fail(
            src, n, f"not a CSV line of numbers ({e}); a measurement CSV holds one number per field (docs/formats.md)"
        ) from None


def _parse_rows(src, lines, numbers, used, width, header_line, ignore_extra) -> np.ndarray:
    """Floats (len(lines), len(used)) of the data ``lines`` (file lines ``numbers``): NumPy's
    parser when every line is plain (no quotes, ``width`` fields), else, or when it
    refuses a value, line by line with an error naming the line and column."""
    cols = list(used.values())
    commas = width - 1
    plain = not any('"' in s for s in lines) and all(
        (s.count(",") >= commas) if ignore_extra else (s.count(",") == commas) for s in lines
    )
    if plain:
        try:
            arr = np.loadtxt(
                lines, delimiter=",", usecols=cols, dtype=np.float64, comments=None, ndmin=2, quotechar=None
            )
        except ValueError:
            arr = None
        if arr is not None and arr.shape == (len(lines), len(cols)) and np.isfinite(arr).all():
            return arr
    out = np.empty((len(lines), len(cols)))
    for r, (line, n) in enumerate(zip(lines, numbers)):
        fields = _split(src, n, line)
        if len(fields) < width or (not ignore_extra and len(fields) != width):
            raise _fail(src, n, f"{len(fields)} fields; expected {width} as in the header (line {header_line})")
        for k, (name, j) in enumerate(used.items()):
            try:
                v = float(fields[j])
            except ValueError:
                raise _fail(src, n, f"column {name!r}: expected a number, got {fields[j]!r}") from None
            if not math.isfinite(v):
                raise _fail(src, n, f"column {name!r}: expected a finite number, got {fields[j]!r}")
            out[r, k] = v
    return out


def _check_header(src, n, header, required, allowed, ignore_extra) -> dict[str, int]:
    """Map each used column name to its field index, or raise naming what is wrong."""
    expected = f"expected a header with columns {','.join(required)}"
    numeric = 0
    for f in header:
        with contextlib.suppress(ValueError):
            float(f)
            numeric += 1
    if numeric == len(header):
        raise _fail(src, n, f"missing header line (got numbers); {expected}")
    named = [f for f in header if f]
    dup = sorted({f for f in named if named.count(f) > 1})
    if dup:
        raise _fail(src, n, f"column(s) {dup} appear twice in the header")
    missing = [c for c in required if c not in header]
    if missing:
        raise _fail(src, n, f"missing column(s) {missing}; {expected}")
    unknown = [f for f in header if f not in required and not allowed(f)]
    if unknown and not ignore_extra:
        raise _fail(src, n, f"unknown column(s) {unknown}; {expected} (and optional sigma_* columns where allowed)")
    return {f: j for j, f in enumerate(header) if f in required or (f and allowed(f))}


def _needs_conjugate(t: _Table) -> bool:
    """True if the file says ``convention = exp(+iwt)`` (default ``exp(-iwt)``)."""
    value = t.meta.get("convention", CONVENTION)
    key = "".join(value.split()).lower().replace("ω", "w")
    if key in _MINUS:
        return False
    if key in _PLUS:
        return True
    raise _fail(
        t.source, t.meta_line["convention"], f"convention = {value!r}; expected 'exp(-iwt)' (default) or 'exp(+iwt)'"
    )


def _check_convention(t: _Table, conjugated: bool, evidence: str | None) -> None:
    """Refuse data whose values, read in the convention the file declares (``conjugated``:
    declared exp(+iwt)), have the signs that passive data take in the other convention
    (``evidence``: which signs, or None when they are those of the declared one)."""
    if evidence is None:
        return
    other = CONVENTION if conjugated else "exp(+iwt)"
    if "convention" in t.meta:
        raise _fail(
            t.source,
            t.meta_line["convention"],
            f"this file looks like {other} data ({evidence}), yet declares convention = "
            f"{t.meta['convention']!r}; correct the line to '# convention = {other}'",
        )
    raise MeasurementError(
        f"{t.source}: this file looks like {other} data ({evidence}); add a line "
        f"'# convention = {other}' before the header"
    )


def _meta_float(t: _Table, key: str, unit: str, required=True, allow_zero=False, default=None):
    """Metadata ``key`` as a finite number > 0 (>= 0 with ``allow_zero``) [unit]."""
    if key not in t.meta:
        if required:
            raise MeasurementError(
                f"{t.source}: metadata key {key!r} [{unit}] is missing; add a line '# {key} = ...' before the header"
            )
        return default
    text = t.meta[key]
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and (v >= 0 if allow_zero else v > 0)):
        raise _fail(
            t.source,
            t.meta_line[key],
            f"metadata {key} = {text!r}: expected a number {'>=' if allow_zero else '>'} 0 [{unit}]",
        )
    return v


def _check_positive_unique(t: _Table, col: str, others=()) -> None:
    """Column ``col`` > 0; rows unique in (others..., col). Errors name the line: the
    first row (in file order) that repeats an earlier one, and that earlier row. One
    stable sort of the keys, so linear-logarithmic in the rows and no per-row objects."""
    bad = np.flatnonzero(t.values[col] <= 0)
    if bad.size:
        raise _fail(t.source, t.lines[bad[0]], f"{col} = {number(t.values[col][bad[0]])}: expected a number > 0")
    keys = [t.values[c] for c in (*others, col)]
    order = np.lexsort(keys[::-1])  # stable: equal keys stay in file order
    same = np.ones(order.size - 1, dtype=bool)
    for k in keys:
        same &= k[order[1:]] == k[order[:-1]]
    if same.any():
        first = order[np.r_[0, np.flatnonzero(~same) + 1]]  # first row of each run of equal keys
        run = np.cumsum(np.r_[True, ~same]) - 1  # run of each sorted position
        dup = order[1:][same]
        i = int(dup.min())  # earliest repeat in the file
        j = int(first[run[1:][same][np.argmin(dup)]])
        names = ", ".join(f"{c} = {float(t.values[c][i])!r}" for c in (*others, col))
        raise _fail(t.source, t.lines[i], f"duplicate row ({names}), first on line {t.lines[j]}")


def _complex(t: _Table, name: str) -> np.ndarray:
    return t.values[f"{name}_re"] + 1j * t.values[f"{name}_im"]


def _converted_metadata(t: _Table, conjugated: bool) -> dict[str, str]:
    """File metadata, with ``convention`` describing the data as stored (exp(-iwt))."""
    meta = dict(t.meta)
    if conjugated:
        meta["original_convention"] = meta["convention"]
    meta["convention"] = CONVENTION
    return meta


def _metadata_line(path, key, value) -> str:
    key, value = str(key).strip(), str(value).strip()
    if not key or "=" in key or any(ch in key + value for ch in "\r\n"):
        raise MeasurementError(f"{path}: metadata {key!r} = {value!r}: keys need no '=' and neither may span lines")
    return f"# {key} = {value}"


def _atomic_write(path, text: str) -> None:
    """Write ``text`` to ``path`` via a temporary file in the same folder and ``os.replace``
    (atomic on POSIX and Windows for one filesystem)."""
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path}: folder {path.parent} does not exist")
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        # mkstemp makes the file 0600; give it the mode a plain open() would
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
