"""The bundled demo measurement is what the script that makes it writes: a change of the
forward model that moves it is seen here, and the file written again
(``python studies/make_demo_data.py``), not left to drift from its generator."""

import sys
from importlib import resources
from pathlib import Path

import numpy as np

from tawarp.measure.files import read_tmatrix_csv

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "studies"))
import make_demo_data  # noqa: E402


def test_the_bundled_demo_measurement_is_what_its_script_makes(tmp_path):
    out = tmp_path / "demo.csv"
    make_demo_data.main(["--out", str(out)])
    made = read_tmatrix_csv(out)
    bundled = read_tmatrix_csv(resources.files("tawarp") / "data" / "measured" / "ceramic_hidden_effect.csv")
    assert bundled.metadata["generator"] == made.metadata["generator"]
    np.testing.assert_array_equal(bundled.heat_input, made.heat_input)
    np.testing.assert_array_equal(bundled.freq, made.freq)
    np.testing.assert_allclose(bundled.sigma, made.sigma, rtol=1e-12)
    # within a thousandth of the noise: what a change of the model's physics would exceed
    # (the coefficients moved by up to 0.29 noise sd before the file was written again),
    # and not the last bits of another machine's arithmetic
    d = bundled.T - made.T
    assert np.max(np.abs(np.stack([d.real, d.imag], axis=-1)) / bundled.sigma) < 1e-3
