"""The command line: outputs readable per FORMATS.md, bad input named, exit codes."""

import numpy as np
import pytest

from tawarp.cli import main, parse_list
from tawarp.core import load_core
from tawarp.forward import transfer_matrices
from tawarp.measurements import read_tmatrix_csv


def test_list_options():
    np.testing.assert_allclose(parse_list("30:500:100"), np.linspace(30, 500, 100))
    np.testing.assert_allclose(parse_list("30,100,250"), [30, 100, 250])
    with pytest.raises(Exception, match="start:stop:count"):
        parse_list("30:500")


def test_forward_writes_measurement_csv(tmp_path):
    out = tmp_path / "T.csv"
    assert main(["forward", "mesh", "--freqs", "40,200", "--Q", "0,20", "-o", str(out), "--device", "cpu",
                 "--quiet"]) == 0
    data = read_tmatrix_csv(out)
    expected = transfer_matrices(load_core("mesh"), [40.0, 200.0], [0.0, 20.0], device="cpu").T
    # rows are (Q, freq) in Q-major order; repr() round trip is exact
    np.testing.assert_array_equal(data.T, expected.reshape(-1, 2, 2))
    np.testing.assert_array_equal(data.heat_input, [0, 0, 20, 20])
    assert (tmp_path / "T_coefficients.png").stat().st_size > 0
    assert (tmp_path / "T_temperature.png").stat().st_size > 0


def test_bad_core_exit_code_names_key(tmp_path, capsys):
    core = tmp_path / "bad.toml"
    text = (load_core("ceramic").source and open(load_core("ceramic").source).read()).replace("porosity = 0.9\n", "porosity = 1.3\n", 1)
    core.write_text(text)
    assert main(["forward", str(core), "--freqs", "50", "-o", str(tmp_path / "T.csv"), "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert "bad.toml" in err and "porosity" in err
    assert not (tmp_path / "T.csv").exists()  # nothing half-written
