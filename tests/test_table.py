"""The CSV machinery under every measurement reader (tawarp.measure.table): large files
read in memory proportional to their numbers, the fast block parser agrees with
Python's float() bit for bit, and errors in any block name the file line."""

import tracemalloc

import numpy as np
import pytest

from tawarp.measure import MeasurementError, read_tmatrix_csv
from tawarp.measure.table import _BLOCK

HEADER = "Q_W,freq_Hz,Tpp_re,Tpp_im,Tpu_re,Tpu_im,Tup_re,Tup_im,Tuu_re,Tuu_im"
META_LINES = 2  # '# convention' and the header


def _rows(n: int, seed: int = 0) -> tuple[list[str], np.ndarray]:
    """n data lines with distinct (Q, f) and random 17-digit values, and those values."""
    rng = np.random.default_rng(seed)
    v = rng.standard_normal((n, 10)) * 10.0 ** rng.integers(-8, 4, (n, 10))
    v[:, 0] = np.repeat(np.arange(n // 4 + 1), 4)[:n] * 0.5  # Q: 4 frequencies each
    v[:, 1] = np.tile([50.0, 100.0, 150.0, 200.0], n // 4 + 1)[:n]
    return [",".join(repr(float(x)) for x in row) for row in v], v


def _write(path, lines):
    path.write_text("# convention = exp(-iwt)\n" + HEADER + "\n" + "\n".join(lines) + "\n")


def test_large_file_read_in_memory_a_fraction_of_its_size(tmp_path):
    """A 10 MB file: what the read allocates at its peak (tracemalloc: Python objects and
    NumPy arrays) stays below the file's size; the whole text or a list of its lines
    (4.2 x the file before) would not."""
    lines, _ = _rows(60_000)
    p = tmp_path / "big.csv"
    _write(p, lines)
    size = p.stat().st_size
    assert size > 9e6
    del lines
    tracemalloc.start()
    data = read_tmatrix_csv(p)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert len(data) == 60_000
    assert peak < 1.0 * size, f"peak {peak / 1e6:.1f} MB for a {size / 1e6:.1f} MB file"


def test_block_parser_equals_float_bit_for_bit_across_blocks(tmp_path):
    """Rows over three blocks, one block with a quoted field (parsed line by line) and
    blanks, spaces and CRLF endings: every value equals Python's float() of its text."""
    n = 2 * _BLOCK + 100
    lines, v = _rows(n, seed=1)
    f = lines[_BLOCK + 7].split(",")
    f[2] = f'"{f[2]}"'
    lines[_BLOCK + 7] = ",".join(f)
    k = lines[5].index(",")
    lines[5] = lines[5][:k] + " , " + lines[5][k + 1 :]
    text = (
        "# convention = exp(-iwt)\r\n"
        + HEADER
        + "\r\n"
        + "\r\n".join(lines[:10])
        + "\r\n\r\n"
        + "\r\n".join(lines[10:])
        + "\r\n"
    )
    p = tmp_path / "mixed.csv"
    p.write_bytes(text.encode())
    data = read_tmatrix_csv(p)
    assert np.array_equal(data.heat_input, v[:, 0]) and np.array_equal(data.freq, v[:, 1])
    T = data.T.reshape(n, 4)
    got = np.stack([T.real, T.imag], axis=-1).reshape(n, 8)
    assert np.array_equal(got, v[:, 2:])


@pytest.mark.parametrize(
    "bad, what",
    [
        ("abc", "expected a number, got 'abc'"),
        ("1e400", "expected a finite number"),
        ("nan", "expected a finite number"),
    ],
)
def test_error_in_a_late_block_names_its_line(tmp_path, bad, what):
    lines, _ = _rows(_BLOCK + 50, seed=2)
    i = _BLOCK + 20  # in the second block
    f = lines[i].split(",")
    f[6] = bad
    lines[i] = ",".join(f)
    p = tmp_path / "late.csv"
    _write(p, lines)
    with pytest.raises(MeasurementError, match=rf"late\.csv, line {i + 1 + META_LINES}: column 'Tup_re': {what}"):
        read_tmatrix_csv(p)


def test_missing_field_in_a_late_block_names_its_line(tmp_path):
    lines, _ = _rows(_BLOCK + 50, seed=3)
    i = _BLOCK + 33
    lines[i] = lines[i].rsplit(",", 1)[0]
    p = tmp_path / "short.csv"
    _write(p, lines)
    with pytest.raises(MeasurementError, match=rf"short\.csv, line {i + 1 + META_LINES}: 9 fields; expected 10"):
        read_tmatrix_csv(p)


def test_duplicate_names_the_first_repeat_and_its_original(tmp_path):
    """Rows 3 and 9000 repeat row 1's (Q, f) and row 20 repeats row 10's: the error names
    the earliest repeat in the file (row 3) and its first occurrence (row 1)."""
    lines, v = _rows(_BLOCK + 900, seed=4)
    for dst, src in ((9000, 1), (3, 1), (20, 10)):
        f = lines[dst].split(",")
        f[:2] = lines[src].split(",")[:2]
        lines[dst] = ",".join(f)
    p = tmp_path / "dup.csv"
    _write(p, lines)
    with pytest.raises(
        MeasurementError,
        match=rf"dup\.csv, line {3 + 1 + META_LINES}: duplicate row "
        rf"\(Q_W = {float(v[1, 0])!r}, freq_Hz = {float(v[1, 1])!r}\), first on line "
        rf"{1 + 1 + META_LINES}",
    ):
        read_tmatrix_csv(p)
