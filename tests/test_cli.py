"""The command line: outputs readable per FORMATS.md, bad input named, exit codes."""

import numpy as np
import pytest

from tawarp.cli.main import main, parse_list
from tawarp.model.core import load_core
from tawarp.model.forward import transfer_matrices
from tawarp.measure.files import read_tmatrix_csv


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


def test_demo_loop_finds_the_bundled_hidden_effect(tmp_path):
    # The bundled measurement hides natural convection in the buffer tube, tbt.h_convection = 3
    # (studies/make_demo_data.py): the loop must choose it, reach the noise floor (<= 1.5 x),
    # and bring h_s back to the true 150 W/(m^2 K) within 2 std, with less drift of h_s over Q.
    from tawarp.cli.demo import demo_loop

    rep = demo_loop(tmp_path / "loop", device="cpu", quiet=True)
    assert rep["chosen_effect"] == "convection"
    c = rep["parameters_after"]["tbt.h_convection"]
    assert abs(c["value"] - 3.0) < 2 * c["std"]
    assert rep["error_after"] <= 1.5 * rep["noise_floor"] < rep["error_before"] * 1.5
    h = rep["parameters_after"]["stack.h"]
    assert abs(h["value"] - 150.0) < 2 * h["std"]
    assert rep["drift_after"]["relative_spread"]["stack.h"] < rep["drift_before"]["relative_spread"]["stack.h"]
    assert (tmp_path / "loop" / "report.json").exists() and (tmp_path / "loop" / "report.md").exists()
