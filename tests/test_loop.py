"""Closing the loop (issue #4): data made with an undeclared effect are given to the loop,
which must name that effect, bring the error to the noise floor and the base parameters
back; no effect and an effect outside the library give no claim; on the measured foams
(Atalla & Panneton) the loop lowers the error of the circular-pore model."""

import json

import numpy as np
import pytest

from tawarp.model.core import load_core
from tawarp.model.forward import ForwardSettings
from shared_data import measured_folder
from tawarp.loop import NOISE_FACTOR, default_base_params, impedance_loop, run_loop, write_report
from tawarp.measure import TMatrixKind, atalla_panneton_samples, load_atalla_panneton, load_measurement, write_tmatrix_csv
from tawarp.measure.synthetic import synthetic_tmatrix

CORE = load_core("ceramic")
BASE = ("stack.porosity", "stack.pore_radius", "stack.h", "hot_hx.h")
#: noise realizations every loop test runs on (the same seeds for every case, none picked)
SEEDS = (0, 1, 2)
SEED = SEEDS[0]
WALL = {f"{s}.wall_conductance": 0.3 for s in ("stack", "hot_hx", "tbt")}
CASES = [
    ("plane_offsets", {"duct_left.length": 0.033}, None),
    ("T_cold", {"gas.T_cold": 297.15}, None),
    ("p_mean", {"gas.p_mean": 99000.0}, None),
    ("thermal_radius_ratio", {"stack.thermal_radius_ratio": 1.6}, None),
    ("conductivity_T", {"stack.conductivity_exponent": 1.0}, None),
    ("convection", {"tbt.h_convection": 3.0}, None),
    ("wall_conduction", WALL, None),
    ("ambient_exchangers", {}, {}),   # the effect's typical exchangers
]


#: Effects that the loop may report as indistinguishable from another library effect.
TIES = {"conductivity_T"}


#: Noise per case (default 0.2 %): T-dependent conductivity at b = 1 moves the T-matrices by
#: about 3e-3 relative, so it is measured at 0.05 % noise to be visible above it.
NOISE = {"conductivity_T": 5e-4}


def loop_on(truth, ambient=None, seed=SEED, noise=0.002):
    data = synthetic_tmatrix(CORE, truth, seed=seed, ambient_exchangers=ambient, noise=noise)
    prob = TMatrixKind(data, CORE, ForwardSettings(device="cpu", cells=8))
    return prob, run_loop(prob)


@pytest.mark.parametrize("effect, truth, ambient", CASES, ids=[c[0] for c in CASES])
def test_loop_finds_undeclared_effect(effect, truth, ambient):
    # every seed: the right effect, the error down to the noise, less drift of h with Q.
    # z-scores of the fitted values are standard normal draws, so they are judged as a rate
    # over the seeds: of the 12 base-parameter z-scores (4 parameters x 3 seeds) at most 2
    # beyond 2 (P(>= 3 of 12) = 1.5 % for a standard normal), none beyond 4; the effect's own
    # parameter(s) beyond 3 in at most one seed, never beyond 4. (Seen: p_mean, seed 0 has
    # stack.porosity at z = 3.04 and gas.p_mean at z = 3.24, every other run within 2.)
    z_base, z_effect = [], []
    for seed in SEEDS:
        prob, rep = loop_on(truth, ambient, seed, NOISE.get(effect, 0.002))
        # the right effect, or (T^b conductivity against T^3 radiation: BIC within 0.1 at 0.2 %
        # noise) a tie reported as indistinguishable, the right effect among the named
        assert rep["chosen_effect"] == effect or (effect in rep["indistinguishable"] and effect in TIES), (
            seed, [(c["effect"], c["score"], c.get("checks")) for c in rep["candidates"]])
        assert rep["error_before"] > 1.2 * rep["noise_floor"]  # the effect is visible in the data
        assert rep["error_after"] <= NOISE_FACTOR * rep["noise_floor"]
        # on a tie the right effect's own refit carries its values
        after = (rep["parameters_after"] if rep["chosen_effect"] == effect else
                 next(c["fitted"] for c in rep["candidates"] if c["effect"] == effect))
        z_base += [(after[name]["value"] - CORE.get(name)) / after[name]["std"] for name in BASE]
        # the effect's own parameter comes back too
        for name, v in truth.items():
            key = "wall_conductance" if name.endswith("wall_conductance") else name
            z_effect.append((after[key]["value"] - v) / after[key]["std"])
        # the drift of the fitted h's with Q shrinks once the effect is in the model
        db, da = rep["drift_before"], rep["drift_after"]
        assert da["relative_spread"]["hot_hx.h"] <= max(db["relative_spread"]["hot_hx.h"], 0.01)
    z = np.abs(z_base)
    assert np.sum(z > 2) <= 2 and np.all(z < 4), np.round(z_base, 2)
    ze = np.abs(np.reshape(z_effect, (len(SEEDS), -1)))
    assert np.sum(np.any(ze > 3, axis=1)) <= 1 and np.all(ze < 4), np.round(ze, 2)


@pytest.mark.parametrize("seed", SEEDS)
def test_no_effect_no_claim(seed):
    prob, rep = loop_on({}, seed=seed)
    assert rep["chosen_effect"] is None
    assert rep["error_after"] == rep["error_before"] <= NOISE_FACTOR * rep["noise_floor"]


OUTSIDE = [{"stack.tortuosity": 1.1}, {"stack.tortuosity": 1.05}, {"hot_hx.thermal_radius_ratio": 1.8}]


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("truth", OUTSIDE, ids=["tortuosity_1.1", "tortuosity_1.05", "hx_thermal_radius"])
def test_effect_outside_library_no_false_claim(truth, seed):
    # the stack's tortuosity is fixed at 1 in the paper's ceramic model, and neither it nor the
    # hot exchanger's thermal radius is in the library. tortuosity 1.05 is close to a plane
    # offset: that candidate takes the error from 4.1 to 1.3 noise floors, and only the
    # chi^2 test (the residual after must be noise) stops the claim.
    prob, rep = loop_on(truth, seed=seed)
    assert rep["chosen_effect"] is None
    assert rep["error_before"] > 3 * rep["noise_floor"]
    assert rep["error_after"] == rep["error_before"]


def test_loop_cli_writes_report(tmp_path):
    import argparse

    from tawarp.cli.loop import add_loop_parser

    data = synthetic_tmatrix(CORE, {"gas.T_cold": 297.15}, seed=SEED)
    csv = tmp_path / "data.csv"
    write_tmatrix_csv(csv, data)
    parser = argparse.ArgumentParser()
    add_loop_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["loop", str(csv), "--core", "ceramic", "-o", str(tmp_path / "out"), "--device", "cpu",
                              "--cells", "8", "--quiet"])
    assert args.func(args) == 0
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    for key in ("error_before", "error_after", "chosen_effect", "candidates", "parameters_before", "parameters_after",
                "drift_before", "drift_after"):
        assert key in rep
    assert rep["chosen_effect"] == "T_cold"
    assert (tmp_path / "out" / "report.md").read_text().startswith("# tawarp loop report")
    assert (tmp_path / "out" / "residuals.png").stat().st_size > 1000


def _foam(name):
    data = load_atalla_panneton(name, measured_folder("atalla_panneton_2005"))
    s = atalla_panneton_samples()[name]
    return data, {k: s[k] for k in ("phi", "alpha_inf", "Lambda", "Lambda_prime", "sigma")}


@pytest.mark.parametrize("name", ["foam1", "foam2"])
def test_loop_lowers_error_on_measured_foams(name, tmp_path):
    data, ref = _foam(name)
    prob, rep = impedance_loop(data, ref)
    assert rep["chosen_effect"] is not None
    assert rep["error_after"] < 0.95 * rep["error_before"]
    js = write_report(prob, rep, tmp_path)
    assert js["comparison"]["phi"]["reference"] == ref["phi"]
    if name == "foam2":
        # what the circular-pore model lacks here is the separate thermal radius
        assert rep["chosen_effect"] == "thermal_radius_ratio"
        c = js["comparison"]
        assert 1.2 < c["Lambda_prime"]["after"] / c["Lambda"]["after"] < 2.4
        assert abs(c["phi"]["after"] - ref["phi"]) < abs(c["phi"]["before"] - ref["phi"])


def test_loop_on_scattering_matrix_with_misplaced_reference_plane(tmp_path):
    # four-microphone data (Q = 0) whose upstream reference plane is 2 mm further than
    # declared: the converted T-matrices carry 2 mm of extra duct, a plane offset
    from tawarp.model.coefficients import duct_impedance
    from tawarp.model.forward import transfer_matrices
    from tawarp.model.gas import GASES
    from tawarp.measure import ScatteringKind, transfer_to_scattering

    f = np.linspace(50.0, 500.0, 24)
    T = transfer_matrices(CORE, f, 0.0, params={"duct_left.length": 0.032}, device="cpu", cells=8).T[0]
    g = GASES["air"]
    Tc, p0 = CORE.gas.T_cold, CORE.gas.p_mean
    c0 = np.sqrt(g.gamma * g.R_gas * Tc)
    S = transfer_to_scattering(T, 2 * np.pi * f / c0, duct_impedance(CORE), 0.05, 0.05)
    rng = np.random.default_rng(SEED)
    S = S + 0.002 * (rng.standard_normal(S.shape) + 1j * rng.standard_normal(S.shape))
    lines = [f"# tube_radius = {CORE.radius}", f"# T_ambient = {Tc}", f"# p_ambient = {p0}", "# ref_upstream = 0.05",
             "# ref_downstream = 0.05", "freq_Hz," + ",".join(f"S{ij}_{p}" for ij in ("11", "12", "21", "22")
                                                              for p in ("re", "im"))]
    for k in range(len(f)):
        vals = [S[k, 0, 0], S[k, 0, 1], S[k, 1, 0], S[k, 1, 1]]
        lines.append(f"{float(f[k])!r}," + ",".join(f"{float(v.real)!r},{float(v.imag)!r}" for v in vals))
    path = tmp_path / "S.csv"
    path.write_text("\n".join(lines) + "\n")
    prob = load_measurement(path, CORE, ForwardSettings(device="cpu", cells=8))
    assert isinstance(prob, ScatteringKind)
    rep = run_loop(prob, default_base_params(prob, ["stack.porosity", "stack.pore_radius"]))
    assert rep["chosen_effect"] == "plane_offsets"
    assert rep["error_after"] < 0.5 * rep["error_before"]
    dl = rep["parameters_after"]["duct_left.length"]
    assert abs(dl["value"] - 0.032) < 3 * dl["std"] + 2e-4


def test_loop_reports_its_progress(monkeypatch):
    """tawarp loop ran up to 400 s silent (issue 10 item 13): its bar passes every stage in order."""
    import tawarp.loop.run as run

    seen = []

    class Bar:
        def set_postfix_str(self, name):
            seen.append(name)

        def update(self, k):
            pass

        def close(self):
            seen.append("closed")

    monkeypatch.setattr(run, "progress_bar", lambda total, desc, enabled, unit: Bar())
    loop_on({}, seed=SEED)
    assert seen == list(run.STAGES) + ["closed"]
