"""Scattering data: signed reference planes, sigma columns, the empty-tube
calibration, and the passive end-to-end case (a 3 cm foam in a 100 mm tube, four
microphones) through ``tawarp fit``; data from the independent reference."""

import json
import math

import numpy as np
import pytest

from tawarp import reference
from tawarp.cli import main
from tawarp.measure import (
    MeasurementError,
    calibrate_empty_tube,
    read_scattering,
    read_scattering_csv,
    scattering_to_transfer,
    transfer_to_scattering,
    write_scattering_csv,
)
from tawarp.measure.scattering import microphone_gain, tube_waves
from tawarp.measure.synthetic import scattering_measurement
from tawarp.model.core import dump_core, load_core
from tawarp.model.gas import GASES

FOAM = load_core("foam_sample")
TRUTH = {"foam.porosity": 0.96, "foam.pore_radius": 1.2e-4, "foam.tortuosity": 1.25}
F = np.linspace(100.0, 1600.0, 40)
ZC = 413.0 / (math.pi * 0.05**2)
HEADER = "freq_Hz," + ",".join(f"S{ij}_{p}" for ij in ("11", "12", "21", "22") for p in ("re", "im"))


def duct(k, Zc, length):
    """Lossless duct (p, U)(x + length) = D (p, U)(x), exp(-iwt); a negative length inverts it."""
    c, s = np.cos(k * length), np.sin(k * length)
    return np.stack([np.stack([c, 1j * Zc * s], -1), np.stack([1j * s / Zc, c], -1)], -2)


def foam_T(freqs=F):
    return reference.transfer_matrix(FOAM, freqs)


def scattering_file(path, S, planes: dict, extra=""):
    lines = ["# tube_radius = 0.05", "# T_ambient = 293.15", "# p_ambient = 101325"]
    lines += [f"# {k} = {v!r}" for k, v in planes.items()] + ([extra] if extra else []) + [HEADER]
    lines += [
        f"{float(f)!r}," + ",".join(f"{float(v.real)!r},{float(v.imag)!r}" for v in S[k].reshape(-1))
        for k, f in enumerate(F[: len(S)])
    ]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("x_up, x_down", [(-0.07, 0.05), (0.0, 0.0), (0.0, -0.03), (0.02, -0.01), (0.03, 0.11)])
def test_round_trip_with_any_signed_planes(x_up, x_down):
    # T -> S -> T is exact for any plane positions, lossy (complex) k included
    T = foam_T()
    k = 2 * np.pi * F / 343.0 * (1 + (1 + 1j) * 2e-3)
    S = transfer_to_scattering(T, k, ZC, -x_up, x_down)
    back = scattering_to_transfer(S, k, ZC, -x_up, x_down)
    assert np.max(np.abs(back - T) / np.abs(T).max(axis=(1, 2), keepdims=True)) < 1e-12


@pytest.mark.parametrize("x_up, x_down", [(-0.07, 0.05), (0.0, -0.03), (0.01, 0.02)])
def test_signed_planes_are_sections_of_tube(x_up, x_down):
    # S of the sample at planes (x_up, x_down) is S, at its faces, of the sample with the
    # tube from the upstream plane to x1 and from x6 to the downstream plane (a negative
    # section: the inverse duct), T' = D(x_down) T D(-x_up): the planes' physical meaning
    T = foam_T()
    k = 2 * np.pi * F / 343.0
    S = transfer_to_scattering(T, k, ZC, -x_up, x_down)
    Tp = duct(k, ZC, x_down) @ T @ duct(k, ZC, -x_up)
    S0 = transfer_to_scattering(Tp, k, ZC, 0.0, 0.0)
    assert np.max(np.abs(S - S0)) < 1e-12


def test_coinciding_planes_read_the_sample_and_a_zero_thickness_check(tmp_path):
    # both planes on the front face of the 3 cm foam
    g = GASES["air"]
    k = 2 * np.pi * F / math.sqrt(g.gamma * g.R_gas * 293.15)
    data = read_scattering(
        scattering_file(
            tmp_path / "s.csv",
            np.zeros((F.size, 2, 2)) + [[0, 1], [1, 0]],
            {"ref_plane_upstream": 0.0, "ref_plane_downstream": 0.0},
        )
    )
    T = foam_T()
    S = transfer_to_scattering(T, k, data.Zc, 0.0, -0.03)
    got = read_scattering_csv(
        scattering_file(tmp_path / "f.csv", S, {"ref_plane_upstream": 0.0, "ref_plane_downstream": -0.03})
    )
    assert np.max(np.abs(got.T - T) / np.abs(T).max(axis=(1, 2), keepdims=True)) < 1e-12
    # zero thickness: S = [[0, 1], [1, 0]] at coinciding planes is the identity
    assert np.max(np.abs(data.to_tmatrix().T - np.eye(2))) < 1e-15


def test_first_format_reads_as_before(tmp_path):
    # distances ref_upstream = d1, ref_downstream = d2 are signed planes -d1 and +d2:
    # the same T-matrices bit for bit, those of the conversion with (d1, d2)
    g = GASES["air"]
    k = 2 * np.pi * F / math.sqrt(g.gamma * g.R_gas * 293.15)
    S = transfer_to_scattering(foam_T(), k, ZC, 0.05, 0.04)
    old = read_scattering_csv(scattering_file(tmp_path / "old.csv", S, {"ref_upstream": 0.05, "ref_downstream": 0.04}))
    new = read_scattering_csv(
        scattering_file(tmp_path / "new.csv", S, {"ref_plane_upstream": -0.05, "ref_plane_downstream": 0.04})
    )
    assert np.array_equal(old.T, new.T)
    assert np.array_equal(old.T, scattering_to_transfer(S, k, read_scattering(tmp_path / "old.csv").Zc, 0.05, 0.04))
    # written and read back: the signed form, the same data
    write_scattering_csv(tmp_path / "w.csv", read_scattering(tmp_path / "old.csv"))
    assert "# ref_plane_upstream = -0.05" in (tmp_path / "w.csv").read_text()
    assert np.array_equal(read_scattering_csv(tmp_path / "w.csv").T, old.T)


def test_plane_metadata_errors_name_the_key(tmp_path):
    S = np.zeros((2, 2, 2)) + [[0.1, 0.9], [0.9, 0.1]]
    both = scattering_file(
        tmp_path / "both.csv", S, {"ref_upstream": 0.05, "ref_plane_upstream": -0.05, "ref_downstream": 0.0}
    )
    with pytest.raises(MeasurementError, match=r"both\.csv, line 4: metadata ref_upstream and ref_plane_upstream"):
        read_scattering(both)
    missing = scattering_file(tmp_path / "missing.csv", S, {"ref_plane_upstream": 0.0})
    with pytest.raises(MeasurementError, match=r"missing\.csv: metadata key 'ref_plane_downstream'.*ref_downstream"):
        read_scattering(missing)
    bad = scattering_file(tmp_path / "bad.csv", S, {"ref_plane_upstream": 0.0}, "# ref_plane_downstream = inf")
    with pytest.raises(MeasurementError, match=r"bad\.csv, line 5: metadata ref_plane_downstream = 'inf'"):
        read_scattering(bad)


def test_sigma_columns_propagate_to_the_tmatrix(tmp_path):
    # first-order propagation against a Monte Carlo of the conversion (5 % on the std)
    s = 1e-3
    sample, _ = scattering_measurement(
        foam_T(F[:3]),
        F[:3],
        tube_radius=0.05,
        plane_upstream=-0.05,
        plane_downstream=0.04,
        length=0.03,
        noise=s * math.sqrt(2),
    )
    path = tmp_path / "s.csv"
    write_scattering_csv(path, sample)
    assert "sigma_S11_re" in [ln for ln in path.read_text().splitlines() if ln.startswith("freq_Hz")][0]
    data = read_scattering(path)
    S0 = data.S
    assert np.allclose(data.sigma, s, rtol=1e-12)
    sig = data.to_tmatrix().sigma
    rng = np.random.default_rng(0)
    draws = S0 + s * (rng.standard_normal((4000,) + S0.shape) + 1j * rng.standard_normal((4000,) + S0.shape))
    T = scattering_to_transfer(draws, data.k, data.Zc, 0.05, 0.04)
    mc = np.stack([T.real.std(0), T.imag.std(0)], -1)
    assert np.allclose(sig, mc, rtol=0.05)


def test_impedance_sigma_columns_are_weights(tmp_path):
    from tawarp.measure import ImpedanceKind, load_measurement

    p = tmp_path / "z.csv"
    p.write_text(
        "# thickness = 0.02\nfreq_Hz,Zs_re,Zs_im,sigma_Zs_re,sigma_Zs_im\n100,1,2,0.01,0.02\n200,1.5,-1,0.03,0.04\n"
    )
    kind = load_measurement(p)
    assert isinstance(kind, ImpedanceKind) and kind.has_sigma
    assert np.array_equal(kind.w, 1 / np.array([[0.01, 0.02], [0.03, 0.04]]))
    p.write_text("# thickness = 0.02\nfreq_Hz,Zs_re,Zs_im,sigma_Zs_re\n100,1,2,0.01\n")
    with pytest.raises(MeasurementError, match=r"z\.csv, line 2: sigma for Zs incomplete"):
        load_measurement(p)


def lossy_tube(T_gas=298.15):
    """Wavenumber and characteristic impedance (F,) of the 100 mm tube from the reference's
    lossy duct (full thermoviscous solution) at T_gas [K]: for a 1 cm section,
    cos(k l) = T11 and Zc = T12 / (i sin k l)."""
    D = reference.duct_matrix_omega("air", 101325.0, T_gas, 0.05, 0.01, 2 * np.pi * F)
    k = np.arccos(D[:, 0, 0]) / 0.01
    return k, D[:, 0, 1] / (1j * np.sin(k * 0.01))


def rig(seed, noise=0.003, planes=(-0.05, 0.04)):
    """Foam data with a calibration error: gain and phase of the downstream microphones
    (4 %, 2.9 degrees, growing with frequency) and, for planes 5 cm before and 4 cm after
    the sample, a tube 5 K warmer than T_ambient says, with wall losses (the reference's
    lossy duct). With coinciding planes the empty tube measures no propagation: the tube
    is then as the metadata say (lossless, at T_ambient)."""
    k, Zc = lossy_tube() if planes == (-0.05, 0.04) else (None, None)
    gain = 1.04 * np.exp(0.05j) * (1 + 0.02 * F / 1000.0)
    return scattering_measurement(
        foam_T(),
        F,
        tube_radius=0.05,
        plane_upstream=planes[0],
        plane_downstream=planes[1],
        length=0.03,
        gain=gain,
        tube_wavenumber=k,
        tube_impedance=Zc,
        noise=noise,
        seed=seed,
    )


def test_empty_tube_calibration_removes_gain_and_tube():
    # noiseless: the gain exactly; the tube's sound speed (298.15 K) and losses to the
    # wide-tube law's order eps^2; the T-matrices to 2e-5 (uncalibrated: 5e-2 off)
    sample, empty = rig(0, noise=0.0)
    assert np.allclose(microphone_gain(empty.S), 1.04 * np.exp(0.05j) * (1 + 0.02 * F / 1000.0), rtol=1e-13)
    k, Zc, tube = tube_waves(empty, 0.03)
    k_ref, Zc_ref = lossy_tube()
    g = GASES["air"]
    assert tube["sound_speed"] == pytest.approx(math.sqrt(g.gamma * g.R_gas * 298.15), rel=1e-5)
    assert np.max(np.abs(k / k_ref - 1)) < 3e-5 and np.max(np.abs(Zc / Zc_ref - 1)) < 3e-5  # 3 eps^2 at 100 Hz
    T = foam_T()
    scale = np.abs(T).max(axis=(1, 2), keepdims=True)
    assert np.max(np.abs(calibrate_empty_tube(sample, empty, 0.03).T - T) / scale) < 2e-5
    assert np.max(np.abs(sample.to_tmatrix().T - T) / scale) > 5e-2
    moved = type(empty)(**{**empty.__dict__, "plane_upstream": -0.06})
    with pytest.raises(MeasurementError, match="ref_plane_upstream = -0.06 differs"):
        calibrate_empty_tube(sample, moved, 0.03)
    with pytest.raises(MeasurementError, match="is this the empty-tube measurement"):
        calibrate_empty_tube(sample, sample, 0.03)


@pytest.mark.parametrize(
    "seed, planes", [(0, (-0.05, 0.04)), (1, (-0.05, 0.04)), (2, (-0.05, 0.04)), (3, (0.0, -0.03))]
)
def test_fit_foam_sample_with_empty_tube(tmp_path, seed, planes):
    """Issue 9 item 3 end to end: ``tawarp fit S.csv --core foam_sample --empty-tube E.csv``
    recovers porosity, pore radius and tortuosity within 3 std from a core 10-30 % off;
    without the calibration the fit is grossly inadequate."""
    sample, empty = rig(seed, planes=planes)
    write_scattering_csv(tmp_path / "S.csv", sample)
    write_scattering_csv(tmp_path / "E.csv", empty)
    rng = np.random.default_rng(100 + seed)
    u = rng.uniform(0.1, 0.3, 3)
    start = FOAM.replace(
        **{
            "foam.porosity": 0.96 * (1 - u[0]),
            "foam.tortuosity": 1.25 * (1 + u[2]),
            "foam.pore_radius": 1.2e-4 * (1 + rng.choice([-1, 1]) * u[1]),
        }
    )
    (tmp_path / "start.toml").write_text(dump_core(start))
    fits = {}
    for name, extra in (("calibrated", ["--empty-tube", str(tmp_path / "E.csv")]), ("raw", [])):
        out = tmp_path / f"{name}.json"
        assert (
            main(
                [
                    "fit",
                    str(tmp_path / "S.csv"),
                    "--core",
                    str(tmp_path / "start.toml"),
                    "--device",
                    "cpu",
                    "--quiet",
                    "--no-plots",
                    "-o",
                    str(out),
                ]
                + extra
            )
            == 0
        )
        fits[name] = json.loads(out.read_text())
    cal = fits["calibrated"]["fits"][0]
    assert cal["converged"] and fits["calibrated"]["empty_tube"]["empty_tube"].endswith("E.csv")
    for k, v in TRUTH.items():
        got = cal["parameters"][k]
        assert abs(got["value"] - v) < 3 * got["std"], (k, got, v)
    assert 0.5 < cal["goodness_of_fit"]["reduced_chi2"] < 1.6
    raw = fits["raw"]["fits"][0]
    assert raw["goodness_of_fit"]["reduced_chi2"] > 20 and not raw["goodness_of_fit"]["adequate"]
    assert raw["rms_error"] > 5 * cal["rms_error"]


def test_loop_takes_the_empty_tube(tmp_path):
    # tawarp loop shares --empty-tube with tawarp fit: the calibrated base fit reaches the
    # noise (0.3 % on S), the raw one stays at the calibration error
    sample, empty = rig(0)
    write_scattering_csv(tmp_path / "S.csv", sample)
    write_scattering_csv(tmp_path / "E.csv", empty)
    errors = {}
    for name, extra in (("calibrated", ["--empty-tube", str(tmp_path / "E.csv")]), ("raw", [])):
        assert (
            main(
                [
                    "loop",
                    str(tmp_path / "S.csv"),
                    "--core",
                    "foam_sample",
                    "--device",
                    "cpu",
                    "--quiet",
                    "-o",
                    str(tmp_path / name),
                ]
                + extra
            )
            == 0
        )
        errors[name] = json.loads((tmp_path / name / "report.json").read_text())["error_before"]
    assert errors["calibrated"] < errors["raw"] / 5


def test_synth_writes_a_scattering_pair(tmp_path, capsys):
    # tawarp synth CORE --scattering: the sample's and the empty tube's files, which the
    # calibration turns back into the generating model's T-matrices (no noise) whatever
    # the microphone gain
    from tawarp.measure import load_measurement
    from tawarp.model.forward import transfer_matrices

    out = tmp_path / "S.csv"
    assert (
        main(
            [
                "synth",
                "foam_sample",
                "--scattering=-0.05,0.04",
                "--freqs",
                "100:1600:5",
                "--noise",
                "0",
                "--mic-gain",
                "1.04,3",
                "--cells",
                "8",
                "-o",
                str(out),
                "--device",
                "cpu",
                "--quiet",
            ]
        )
        == 0
    )
    data = read_scattering(out)
    assert (data.plane_upstream, data.plane_downstream, data.metadata["core"]) == (-0.05, 0.04, "foam_sample")
    kind = load_measurement(out, settings=None, empty_tube=tmp_path / "S_empty.csv")
    T = transfer_matrices(FOAM, data.freq, 0.0, device="cpu").T[0]
    assert np.max(np.abs(kind.data.T - T) / np.abs(T).max(axis=(1, 2), keepdims=True)) < 1e-12
    assert np.max(np.abs(read_scattering_csv(out).T - T) / np.abs(T).max(axis=(1, 2), keepdims=True)) > 1e-2
    assert main(["synth", "foam_sample", "--scattering=0,0", "--Q", "0,20", "-o", str(tmp_path / "x.csv")]) == 2
    assert "--Q: a scattering file holds one heat input" in capsys.readouterr().err
