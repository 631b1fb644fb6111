"""Property-based tests of the measurement readers: whatever a CSV holds, each
reader returns data or raises MeasurementError naming the file; never another exception."""

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tawarp.measure import MeasurementError, read_impedance_csv, read_scattering_csv, read_tmatrix_csv

TMATRIX = (
    "# convention = exp(-iwt)\nQ_W,freq_Hz,Tpp_re,Tpp_im,Tpu_re,Tpu_im,Tup_re,Tup_im,Tuu_re,Tuu_im\n"
    "0,100,1,0,0,1,0,1e-6,1,0\n0,200,0.9,0,0,2,0,2e-6,0.9,0\n"
)
IMPEDANCE = "# thickness = 0.02\nfreq_Hz,Zs_re,Zs_im\n100,1,2\n200,1.5,-1\n"
SCATTERING = (
    "# tube_radius = 0.05\n# T_ambient = 293.15\n# p_ambient = 101325\n# ref_upstream = 0.1\n"
    "# ref_downstream = 0.1\nfreq_Hz,S11_re,S11_im,S12_re,S12_im,S21_re,S21_im,S22_re,S22_im\n"
    "100,0.1,0,0.9,0,0.9,0,0.1,0\n200,0.1,0,0.9,0,0.9,0,0.1,0\n"
)
TOKENS = ["nan", "inf", "", "abc", "-1", "0", "1e400", ",", "\n", "# x = 1\n", "Q_W", '"', "\t", "\x00", ",,,"]
edit = st.tuples(st.integers(0, 400), st.integers(0, 8), st.sampled_from(TOKENS) | st.text(max_size=3))


def _apply(text, edits):
    for at, width, token in edits:
        at = at % (len(text) + 1)
        text = text[:at] + token + text[at + width :]
    return text


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.sampled_from([TMATRIX, IMPEDANCE, SCATTERING]), st.lists(edit, min_size=1, max_size=4))
def test_any_corruption_reads_or_is_named(tmp_path, base, edits):
    p = tmp_path / "fuzz.csv"
    p.write_text(_apply(base, edits))
    for reader in (read_tmatrix_csv, read_impedance_csv, read_scattering_csv):
        try:
            reader(p)
        except MeasurementError as e:
            assert "fuzz.csv" in str(e)


@pytest.mark.parametrize(
    "base, reader", [(TMATRIX, read_tmatrix_csv), (IMPEDANCE, read_impedance_csv), (SCATTERING, read_scattering_csv)]
)
def test_the_uncorrupted_files_read(tmp_path, base, reader):
    p = tmp_path / "ok.csv"
    p.write_text(base)
    assert len(reader(p)) == 2


# -- signed reference planes, sigma columns and the empty-tube reader -------------------
SIGNED = (
    "# tube_radius = 0.05\n# T_ambient = 293.15\n# p_ambient = 101325\n# ref_plane_upstream = -0.05\n"
    "# ref_plane_downstream = 0.04\nfreq_Hz,S11_re,S11_im,S12_re,S12_im,S21_re,S21_im,S22_re,S22_im,"
    "sigma_S11,sigma_S12,sigma_S21,sigma_S22\n"
    "100,0.1,0,0.9,0,0.9,0,0.1,0,0.01,0.01,0.01,0.01\n200,0.1,0,0.9,0,0.9,0,0.1,0,0.01,0.01,0.01,0.01\n"
)
EMPTY = (
    "# tube_radius = 0.05\n# T_ambient = 293.15\n# p_ambient = 101325\n# ref_plane_upstream = -0.05\n"
    "# ref_plane_downstream = 0.04\nfreq_Hz,S11_re,S11_im,S12_re,S12_im,S21_re,S21_im,S22_re,S22_im\n"
    "100,0.001,0,0.97499,0.21769,0.97499,0.21769,0,0.002\n200,0,0.001,0.90322,0.42449,0.90322,0.42449,0.001,0\n"
)
PLANE_TOKENS = [
    "ref_upstream",
    "ref_plane_upstream",
    "ref_plane_downstream",
    "-",
    "-0",
    "1e-320",
    "sigma_S12",
    "sigma_S11_re",
    "S12_re",
]
plane_edit = st.tuples(
    st.integers(0, 400), st.integers(0, 8), st.sampled_from(TOKENS + PLANE_TOKENS) | st.text(max_size=3)
)


def _load_pair(sample, empty):
    from tawarp.measure import load_measurement

    return load_measurement(sample, "foam_sample", empty_tube=empty)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(plane_edit, min_size=1, max_size=4), st.booleans())
def test_signed_planes_and_empty_tube_corruptions_are_named(tmp_path, edits, corrupt_empty):
    # a corrupted sample (signed planes, sigma columns) or empty-tube file: read and
    # calibrated, or a MeasurementError naming the corrupted file
    s, e = tmp_path / "sample.csv", tmp_path / "empty.csv"
    s.write_text(SIGNED if corrupt_empty else _apply(SIGNED, edits))
    e.write_text(_apply(EMPTY, edits) if corrupt_empty else EMPTY)
    try:
        _load_pair(s, e)
    except MeasurementError as err:
        assert ("empty.csv" if corrupt_empty else "sample.csv") in str(err)


def test_the_uncorrupted_pair_reads(tmp_path):
    s, e = tmp_path / "sample.csv", tmp_path / "empty.csv"
    s.write_text(SIGNED)
    e.write_text(EMPTY)
    kind = _load_pair(s, e)
    assert kind.name == "scattering" and kind.has_sigma and kind.data.metadata["empty_tube"] == str(e)


# -- extreme values in a T-matrix file, loaded and predicted --------------------------------
# In a child process: one frequency of 1e300 Hz ended ``tawarp fit`` with SIGSEGV (the
# cascade's cell count overflowed); a crash is then an exit code that fails this test, with
# the example printed just before it.
_LOAD_FUZZ = r"""
import math, sys, tempfile, warnings
from pathlib import Path
import numpy as np
from hypothesis import HealthCheck, given, settings, strategies as st
from tawarp.measure import MeasurementError, load_measurement
from tawarp.model.core import load_core

CORE = load_core("ceramic")
HEADER = "Q_W,freq_Hz,Tpp_re,Tpp_im,Tpu_re,Tpu_im,Tup_re,Tup_im,Tuu_re,Tuu_im"
ROWS = [[0, 100, 1, 0, 0, 4e4, 0, 1e-6, 1, 0], [0, 200, 0.9, 0, 0, 8e4, 0, 2e-6, 0.9, 0],
        [40, 100, 1, 0, 0, 4e4, 0, 1e-6, 1, 0], [40, 200, 0.9, 0, 0, 8e4, 0, 2e-6, 0.9, 0]]
magnitude = st.builds(lambda sign, e: sign * 10.0 ** e, st.sampled_from([1.0, -1.0]), st.floats(-320, 308))
values = st.one_of(magnitude, st.sampled_from([0.0, math.inf, math.nan, 5e-324, 1.7e308]))
edits = st.lists(st.tuples(st.integers(0, 3), st.integers(0, 9), values), min_size=1, max_size=3)
folder = Path(tempfile.mkdtemp())


@settings(max_examples=int(sys.argv[1]), deadline=None, derandomize=True, database=None,
          suppress_health_check=list(HealthCheck))
@given(edits)
def load(edits):
    rows = [list(r) for r in ROWS]
    for i, j, v in edits:
        rows[i][j] = v
    print(rows, flush=True)
    path = folder / "fuzz.csv"
    path.write_text("# convention = exp(-iwt)\n" + HEADER + "\n" + "".join(",".join(map(repr, r)) + "\n" for r in rows))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            kind = load_measurement(path, CORE)
            Y = kind.predict({}, 1)
    except MeasurementError as e:
        assert "fuzz.csv" in str(e), e
        return
    assert np.all(np.isfinite(Y)), Y
    assert np.all(np.isfinite(kind.y))


load()
print("done")
"""


def test_extreme_values_in_a_data_file_load_or_are_named():
    """One to three cells of a T-matrix file (frequencies, heat inputs, coefficients) set
    to any magnitude and sign, inf or NaN: a MeasurementError naming the file, or data
    whose model prediction is finite."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", _LOAD_FUZZ, "300"], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0 and run.stdout.rstrip().endswith("done"), (
        f"rc {run.returncode}; last example: {run.stdout.strip().splitlines()[-1:]}\n{run.stderr[-3000:]}"
    )
