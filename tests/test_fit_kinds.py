"""``tawarp fit`` on a surface-impedance file (a kind with no T-matrix path): data from the
independent NumPy reference with known noise, starts 5-30 % off; and the one result
type's covariance algebra (tawarp.fit.result.FitResult), the same on the kind fit's and the
T-matrix estimator's paths."""

import argparse
import dataclasses
import json

import numpy as np
import pytest

from tawarp import reference
from tawarp.fit.result import FitResult
from tawarp.model.core import load_core
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
    path.write_text(
        "# thickness = 0.05\nfreq_Hz,Zs_re,Zs_im\n"
        + "".join(f"{float(a)!r},{float(z.real)!r},{float(z.imag)!r}\n" for a, z in zip(f, Zs))
    )
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
    r = FitResult(
        names=["a", "b"],
        values=np.array([[1.0, 2.0]]),
        std=np.array([[2.0, 3.0]]),
        covariance=cov.copy(),
        correlation=np.array([[[1.0, 1 / 6], [1 / 6, 1.0]]]),
        condition=np.array([3.0]),
        iterations=np.array([3]),
        converged=np.array([True]),
        reason=np.array(["xtol"]),
        cost=np.array([50.0]),
        rms_error=np.array([0.1]),
        s2=np.array([1.0]),
        dof=48,
        start=np.array([[1.0, 2.0]]),
        problem_warnings=[[]],
        n=50,
    )
    r.add_covariance(np.array([[[5.0, 2.0], [2.0, 7.0]]]))
    assert np.allclose(r.std, [[3.0, 4.0]], rtol=1e-15) and np.allclose(r.std_statistical, [[2.0, 3.0]])
    assert np.isclose(r.correlation[0, 0, 1], 3.0 / 12.0, rtol=1e-15)
    assert np.isclose(r.bic(True), 50.0 + 2 * np.log(50), rtol=1e-15)
    assert np.isclose(r.bic(False), 50 * np.log(1.0) + 2 * np.log(50), rtol=1e-15)
    d = r.problem(0)
    assert d["parameters"]["b"] == {"value": 2.0, "std": 4.0, "start": 2.0, "std_statistical": 3.0}


# -- tawarp fit takes every kind on every core kind; --core and --fit are never ignored ----
def _impedance_file(path, seed=0):
    f = np.linspace(200.0, 1600.0, 36)
    core = layer_core(0.05, TRUTH["layer.porosity"], TRUTH["layer.pore_radius"], TRUTH["layer.tortuosity"])
    Zs = surface_impedance_from_T(reference.transfer_matrix(core, f), core)
    rng = np.random.default_rng(seed)
    Zs = Zs + NOISE * (rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size))
    path.write_text(
        "# thickness = 0.05\nfreq_Hz,Zs_re,Zs_im,sigma_Zs\n"
        + "".join(f"{float(a)!r},{float(z.real)!r},{float(z.imag)!r},{NOISE!r}\n" for a, z in zip(f, Zs))
    )
    return path


def test_impedance_on_a_passive_core_starts_from_it(tmp_path):
    # the core's one porous segment gives the layer's start (10-30 % off the truth); with
    # sigma columns the reduced chi^2 is that of the noise
    from tawarp.cli import main
    from tawarp.model.core import Core, Segment, dump_core

    seg = Segment("foam", "porous", 0.05, porosity=0.9 * 0.8, pore_radius=1.2e-4 * 1.25, tortuosity=1.3 * 1.15)
    (tmp_path / "c.toml").write_text(dump_core(Core((seg,), radius=0.05, source="c")))
    out = tmp_path / "f.json"
    assert (
        main(
            [
                "fit",
                str(_impedance_file(tmp_path / "z.csv")),
                "--core",
                str(tmp_path / "c.toml"),
                "--fit",
                "layer.porosity,layer.pore_radius,layer.tortuosity",
                "--device",
                "cpu",
                "--quiet",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    e = json.loads(out.read_text())["fits"][0]
    assert e["parameters"]["layer.porosity"]["start"] == pytest.approx(0.72)
    for k, v in TRUTH.items():
        assert abs(e["parameters"][k]["value"] - v) < 3 * e["parameters"][k]["std"], k
    assert 0.5 < e["goodness_of_fit"]["reduced_chi2"] < 1.6


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--core", "ceramic"], "--core ceramic: a thermoacoustic core (thermal segments stack, hot_hx, tbt)"),
        (["--core", "foam_sample", "--fit", "layer.porosity,foam.porosity"], "--fit foam.porosity: unknown parameter"),
        (["--fit", "layer.length"], "--fit layer.length: the layer thickness is the file's"),
        (["--empty-tube", "E.csv"], "impedance data take no empty_tube option (it applies to scattering data)"),
        (["--start", "spread"], "--start spread: applies to T-matrix data of a thermoacoustic core"),
    ],
)
def test_impossible_combinations_are_one_line_errors(tmp_path, capsys, argv, message):
    from tawarp.cli import main

    z = _impedance_file(tmp_path / "z.csv")
    assert main(["fit", str(z), "--device", "cpu", "--quiet", "-o", str(tmp_path / "f.json")] + argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err and not (tmp_path / "f.json").exists()


def test_tmatrix_fit_names_are_checked(tmp_path, capsys):
    from tawarp.cli import main
    from tawarp.measure import TMatrixData, write_tmatrix_csv

    f = np.array([100.0, 300.0])
    write_tmatrix_csv(
        tmp_path / "t.csv", TMatrixData(np.zeros(2), f, reference.transfer_matrix(load_core("foam_sample"), f))
    )
    assert (
        main(
            [
                "fit",
                str(tmp_path / "t.csv"),
                "--core",
                "foam_sample",
                "--fit",
                "stack.porosity",
                "--device",
                "cpu",
                "--quiet",
                "-o",
                str(tmp_path / "f.json"),
            ]
        )
        == 2
    )
    err = capsys.readouterr().err
    assert "--fit stack.porosity: unknown parameter for tmatrix data" in err and "foam.porosity" in err


def test_scattering_on_a_thermoacoustic_core(tmp_path):
    # scattering data of a heated core (reference, 0.1 % noise) fitted like its T-matrices,
    # from a core whose stack.h is 27 % off
    from tawarp.cli import main
    from tawarp.measure import write_scattering_csv
    from tawarp.measure.synthetic import scattering_measurement
    from tawarp.model.core import dump_core

    core = load_core("ceramic")
    f = np.linspace(50.0, 200.0, 8)
    s, _ = scattering_measurement(
        reference.transfer_matrix(core, f, 20.0),
        f,
        tube_radius=core.radius,
        plane_upstream=-0.05,
        plane_downstream=0.05,
        length=core.positions()[-1],
        heat_input=20.0,
        noise=1e-3,
        seed=1,
    )
    write_scattering_csv(tmp_path / "s.csv", s)
    (tmp_path / "c.toml").write_text(dump_core(core.replace(**{"stack.h": 110.0})))
    out = tmp_path / "f.json"
    assert (
        main(
            [
                "fit",
                str(tmp_path / "s.csv"),
                "--core",
                str(tmp_path / "c.toml"),
                "--fit",
                "stack.h",
                "--device",
                "cpu",
                "--quiet",
                "--cells",
                "8",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    e = json.loads(out.read_text())["fits"][0]
    h = e["parameters"]["stack.h"]
    assert e["heat_input_W"] == 20.0 and abs(h["value"] - 150.0) < 3 * h["std"], h


def test_loop_takes_impedance_on_a_passive_core(tmp_path):
    # the loop takes the same --core as the fit: the passive core's porous segment starts
    # the layer (10-30 % off the truth) and centres its priors; the data are the circular-pore
    # model plus noise of known sigma, so the base fit reaches the noise and nothing is claimed
    from tawarp.cli import main
    from tawarp.model.core import Core, Segment, dump_core

    seg = Segment("foam", "porous", 0.05, porosity=0.9 * 0.8, pore_radius=1.2e-4 * 1.25, tortuosity=1.3 * 1.15)
    (tmp_path / "c.toml").write_text(dump_core(Core((seg,), radius=0.05, source="c")))
    z = _impedance_file(tmp_path / "z.csv")
    args = ["loop", str(z), "--core", str(tmp_path / "c.toml"), "--device", "cpu", "--quiet", "-o", str(tmp_path / "o")]
    assert main(args) == 0
    rep = json.loads((tmp_path / "o" / "report.json").read_text())
    assert rep["kind"] == "impedance" and rep["noise_source"] == "sigma"
    assert rep["verdict"] == "adequate" and rep["accepted_steps"] == [], (rep["verdict"], rep["accepted_steps"])
    assert rep["error_before"] <= 1.3 * rep["noise_floor"]


def test_loop_refuses_impedance_on_a_thermoacoustic_core(tmp_path, capsys):
    from tawarp.cli import main

    z = _impedance_file(tmp_path / "z.csv")
    assert main(["loop", str(z), "--core", "ceramic", "--device", "cpu", "--quiet", "-o", str(tmp_path / "o")]) == 2
    assert "--core ceramic: a thermoacoustic core" in capsys.readouterr().err


@pytest.mark.parametrize("sigma", [True, False])
def test_tmatrix_fit_has_one_covariance_on_both_paths(sigma):
    # the same T-matrix problem (a passive foam sample: no heat model, so no cell counts
    # differ between the paths) fitted by the kind fit (host LM, forward differences) and by
    # the estimator (reduced on the device, forward differences with the same step in the
    # same scaled variables): the same solution, and the same covariance
    # (tawarp.fit.problem_model), s^2 = 1 with sigma columns (absolute_sigma) and the reduced
    # chi^2 without, to 1e-8 of each entry's scale sqrt(C_ii C_kk)
    from tawarp.fit import estimate
    from tawarp.fit.problems import fit_kind
    from tawarp.measure import TMatrixKind
    from tawarp.measure.synthetic import synthetic_tmatrix
    from tawarp.model.forward import ForwardSettings

    core = load_core("foam_sample")
    truth = {"foam.porosity": 0.95, "foam.pore_radius": 1.1e-4, "foam.tortuosity": 1.3}
    data = synthetic_tmatrix(core, truth, np.linspace(100.0, 1600.0, 30), heat_inputs=(0.0,), noise=0.002, seed=1)
    if not sigma:
        data = dataclasses.replace(data, sigma=None)
    kind = TMatrixKind(data, core, ForwardSettings(device="cpu"))
    assert kind.has_sigma == sigma
    names = kind.default_names()
    a = fit_kind(kind, names, xtol=1e-14, gtol=1e-13, max_iter=200)
    m = kind.freqs.size
    b = estimate.fit(
        core,
        kind.freqs,
        kind.y.reshape(m, 4),
        names,
        start={k: core.get(k) for k in names},
        weights=kind.w.reshape(1, m, 4, 2),
        absolute_sigma=sigma,
        xtol=1e-14,
        gtol=1e-14,
        max_iter=200,
        jacobian="difference",
        settings=ForwardSettings(device="cpu"),
        warn=False,
    )
    assert a.converged[0] and b.converged[0]
    assert np.max(np.abs(a.values - b.values) / np.abs(b.values)) < 1e-8
    assert a.dof == b.dof and np.isclose(a.s2[0], b.s2[0], rtol=1e-8) and (a.s2[0] == 1.0) == sigma
    C = b.covariance[0]
    scale = np.sqrt(np.outer(np.diag(C), np.diag(C)))
    assert np.max(np.abs(a.covariance[0] - C) / scale) < 1e-8
