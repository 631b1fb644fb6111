"""``tawarp fit`` on a surface-impedance file (a kind with no T-matrix path): data from the
independent NumPy reference with known noise, starts 5-30 % off; and the one result
type's covariance algebra (tawarp.fit.result.FitResult)."""

import argparse
import json

import numpy as np
import pytest

from tawarp import reference
from tawarp.fit.result import FitResult
from tawarp.model.layer import layer_core, surface_impedance_from_T

TRUTH = {"layer.porosity": 0.9, "layer.pore_radius": 1.2e-4, "layer.tortuosity": 1.3}  # start 0.95, 1.5e-4, 1.1
NOISE = 0.01


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fit_command_on_surface_impedance(tmp_path, seed):
    from tawarp.cli.fit import add_fit_parser

    f = np.linspace(200.0, 1600.0, 36)
    core = layer_core(0.05, TRUTH["layer.porosity"], TRUTH["layer.pore_radius"], TRUTH["layer.tortuosity"])
    Zs = surface_impedance_from_T(reference.transfer_matrix(core, f), core)
    rng = np.random.default_rng(seed)
    Zs = Zs + NOISE * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
    path = tmp_path / "zs.csv"
    path.write_text("# thickness = 0.05\nfreq_Hz,Zs_re,Zs_im\n"
                    + "".join(f"{float(a)!r},{float(z.real)!r},{float(z.imag)!r}\n" for a, z in zip(f, Zs)))
    parser = argparse.ArgumentParser()
    add_fit_parser(parser.add_subparsers(dest="command"))
    out = tmp_path / "fit.json"
    args = parser.parse_args(["fit", str(path), "-o", str(out), "--device", "cpu", "--quiet"])
    assert args.func(args) == 0
    js = json.loads(out.read_text())
    assert js["kind"] == "impedance"
    e = js["fits"][0]
    assert e["converged"]
    for k, v in TRUTH.items():
        got = e["parameters"][k]
        assert abs(got["value"] - v) < 3 * got["std"], (k, got, v)
    # unit weights: s^2 = cost/dof estimates the noise, so the error is the noise's share
    # of rms|Zs| (complex noise of std NOISE per part: sqrt(2) NOISE)
    rms = np.sqrt(np.mean(np.abs(Zs) ** 2))
    assert 0.7 < e["rms_error"] / (np.sqrt(2) * NOISE / rms) < 1.3


def test_add_covariance_and_bic():
    cov = np.array([[[4.0, 1.0], [1.0, 9.0]]])
    r = FitResult(names=["a", "b"], values=np.array([[1.0, 2.0]]), std=np.array([[2.0, 3.0]]), covariance=cov.copy(),
                  correlation=np.array([[[1.0, 1 / 6], [1 / 6, 1.0]]]), condition=np.array([3.0]),
                  iterations=np.array([3]), converged=np.array([True]), reason=np.array(["xtol"]),
                  cost=np.array([50.0]), rms_error=np.array([0.1]), s2=np.array([1.0]), dof=48,
                  start=np.array([[1.0, 2.0]]), problem_warnings=[[]], n=50)
    r.add_covariance(np.array([[[5.0, 2.0], [2.0, 7.0]]]))
    assert np.allclose(r.std, [[3.0, 4.0]], rtol=1e-15) and np.allclose(r.std_statistical, [[2.0, 3.0]])
    assert np.isclose(r.correlation[0, 0, 1], 3.0 / 12.0, rtol=1e-15)
    assert np.isclose(r.bic(True), 50.0 + 2 * np.log(50), rtol=1e-15)
    assert np.isclose(r.bic(False), 50 * np.log(1.0) + 2 * np.log(50), rtol=1e-15)
    d = r.problem(0)
    assert d["parameters"]["b"] == {"value": 2.0, "std": 4.0, "start": 2.0, "std_statistical": 3.0}
