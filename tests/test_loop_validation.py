"""The loop on data the model did not make: a reduced version of
``studies/loop_validation.py`` (same cases, same adapter, same scoring), over several seeds.

Data: :mod:`tawarp.reference` (independent NumPy oracle, DOP853 at rtol 1e-12), the core
file 10-30 % off the truth on every parameter of the paper's estimation, noise from the
study's draw. Reduced: the mesh core, 12 frequencies instead of 37, 3 cases of plane
offsets (1-3 mm at each plane, the library's strongest effect at a typical size: 2.3-5.9
noise floors in these cases), fixed fit cells (8). Clean reference data of the mesh core
(no claim, the error at the floor) are test_loop's (three seeds with sigma, three without).

Thresholds: the targets of docs/loop.md scaled to the sample by the rule "allowed failures
= floor((1 - target) n)": the right effect with the error after <= 1.3 x the noise floor in
>= 95 % -> 3 of 3.

Also the study's full cases (37 frequencies) of the hard kinds: two effects that make nearly
the same data (a radiative and a T-dependent conductivity: claimed as a group), an effect of
the noise's size, buffer-tube convection absorbed by the buffer tube's h, a wrong core;
the per-effect scoring of pair cases; the cache of each effect's data alone. And the lab
suite's contact resistance (the reference's own heat physics) on the ceramic core, reduced as
above, over three seeds: named as the library's ``contact_resistance``.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "studies"))
import loop_validation as lv  # noqa: E402

SEEDS = (100, 101, 102)
#: lab-suite seeds of a contact resistance on the ceramic core: R_c 7.8, 8.3, 5.2e-4 m^2 K/W at
#: 0.15, 0.21, 0.11 % noise, 4.8-6.2 noise floors on the reduced case's 12 frequencies
CONTACT_SEEDS = (301, 312, 322)
N_FREQS = 12
CELLS = 8


def allowed_failures(target: float, n: int) -> int:
    """A rate target of docs/loop.md scaled to n cases: floor((1 - target) n) failures."""
    return math.floor((1.0 - target) * n + 1e-9)


def _run(category: str, seed: int, tmp_path: Path) -> dict:
    case = lv.make_case(seed, category=category, material="mesh", n_freqs=N_FREQS)
    return lv.run_case(case, lv.load_or_generate(case, tmp_path), "cpu", base="loop", cells=CELLS)


def test_plane_offsets_over_seeds(tmp_path):
    effect = [_run("effect:plane_offsets", s, tmp_path) for s in SEEDS]
    for r in effect:
        assert r["visibility"] >= lv.VISIBLE, r["visibility"]  # the cases test a visible effect
    wrong = [(r["seed"], lv.outcome_label(r), round(r["ratio_after"], 2)) for r in effect if not r["right"]]
    assert len(wrong) <= allowed_failures(lv.TARGETS["right_effect"], 3), wrong


def test_cache_returns_the_generated_case(tmp_path):
    # the npz cache is keyed by seed and the case description: a second call reads the same arrays
    case = lv.make_case(7, category="clean", material="ceramic", n_freqs=3)
    a = lv.load_or_generate(case, tmp_path)
    b = lv.load_or_generate(case, tmp_path)
    assert len(list(tmp_path.glob(f"case_7_{case.key()}.npz"))) == 1
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    # the noise is what the case says: its rms over the noise-free data, per coefficient
    Y = lv.normalize(a["T"], lv.duct_impedance(lv.load_core("ceramic"))).reshape(a["Y_clean"].shape)
    rel = np.sqrt(np.mean(np.abs(Y - a["Y_clean"]) ** 2, axis=(0, 1)) / np.mean(np.abs(a["Y_clean"]) ** 2, axis=(0, 1)))
    assert np.all(np.abs(rel / case.noise - 1) < 0.6)  # 9 complex draws per coefficient: chi with 18 dof (std 0.17)


def test_prior_is_10_to_30_percent_off_every_parameter():
    for seed in range(20):
        case = lv.make_case(seed)
        truth = case.truth if case.core_material == case.material else None
        assert set(case.prior) == set(lv.paper_names(case.core_material))
        if truth:
            off = [abs(case.prior[k] / truth[k] - 1) for k in case.prior]
            assert min(off) >= 0.1 - 1e-12 and max(off) <= 0.3 + 1e-12, off
        assert 1e-3 <= case.noise <= 1e-2


def test_adapter_reads_the_report_contract():
    report = {
        "error_before": 0.05,
        "error_after": 0.01,
        "noise_floor": None,
        "verdict": "unexplained_residual",
        "accepted_effects": ["T_cold"],
        "accepted_groups": [["T_cold"], ["a", "b"]],
        "indistinguishable": [["a", "b"]],
        "goodness_of_fit_before": {"noise_floor": 0.002},
    }
    got = lv.loop_outcome(report)
    assert got["verdict"] == "unexplained_residual" and got["indistinguishable"] == [["a", "b"]]
    assert got["accepted_effects"] == ["T_cold"] and got["noise_floor"] == 0.002
    assert got["accepted_groups"] == [["T_cold"], ["a", "b"]]


def test_categories_cycle_covers_every_library_effect():
    cats = {lv.make_case(s).category for s in range(len(lv.CATEGORIES))}
    assert cats == set(lv.CATEGORIES)
    assert {f"effect:{e}" for e in lv.EFFECTS} <= cats


@pytest.mark.parametrize("a, b", [(0.04, -0.03)])
def test_calibration_drift_has_zero_mean_over_the_band(a, b):
    f = np.linspace(40.0, 400.0, 37)
    g = lv.calibration_drift(f, a, b)
    assert abs(np.mean(g) - 1) < 1e-15 and np.isclose(g[-1] - g[0], a + 1j * b)


def _pair_record(status_inputs: dict, groups: list, ratio_after: float = 1.05, seed: int = 2) -> dict:
    """A study record of a two-effect case with the given per-effect (visibility, ratio before)
    and the loop's accepted steps ``groups`` (lists of effect names)."""
    case = lv.make_case(seed, category="two", material="mesh")
    per = dict(zip(case.effects, ({"visibility": v, "ratio_before": b} for v, b in status_inputs)))
    outcome = {
        "accepted_groups": groups,
        "accepted_effects": [g[0] for g in groups if len(g) == 1],
        "verdict": "explained" if groups else "adequate",
        "indistinguishable": [],
    }
    rec = {"case": lv.asdict(case), "per_effect": per, "outcome": outcome, "ratio_after": ratio_after}
    return lv.score(rec), case.effects


def test_pair_cases_are_scored_per_effect():
    # n = 8 x 37 x 3 real residuals: the base fit "explains" data up to 1.05 floors (chi^2 at
    # 1 %: (1 + 2.33 sqrt(2/n))^(1/2) = 1.05); visible >= 2 floors, invisible < 0.5
    n = 8 * lv.N_FREQS * 3
    limit = math.sqrt(1 + 2.33 * math.sqrt(2 / n))
    assert lv.effect_status(5.0, 0.99 * limit, n) == "absorbed" and lv.effect_status(5.0, 1.01 * limit, n) == "visible"
    assert lv.effect_status(1.0, 3.0, n) == "marginal" and lv.effect_status(0.4, 3.0, n) == "invisible"
    # A visible, B absorbed by the base fit: the case asks for A only; B may be accepted too (it is true)
    (rec, (a, b)) = _pair_record([(5.0, 3.0), (8.0, 1.0)], [])
    assert rec["expected"]["effects"] == [a] and rec["expected"]["scored"] and not rec["right"]
    assert _pair_record([(5.0, 3.0), (8.0, 1.0)], [[a]])[0]["right"]
    assert _pair_record([(5.0, 3.0), (8.0, 1.0)], [[a], [b]])[0]["right"]
    assert not _pair_record([(5.0, 3.0), (8.0, 1.0)], [[a]], ratio_after=1.4)[0]["right"]  # not at the floor
    assert not _pair_record([(5.0, 3.0), (8.0, 1.0)], [[a], ["radiation"]])[0]["right"]  # a false claim
    # a group the loop cannot split counts only in the group-aware score
    grp = _pair_record([(5.0, 3.0), (8.0, 1.0)], [sorted([a, "radiation"])])[0]
    assert not grp["right"] and grp["right_group"]
    # both visible: both required; both invisible: no claim; one absorbed and nothing visible:
    # scored as absorbed (no false claim; adequate only within the prior); only marginal: not scored
    assert not _pair_record([(5.0, 3.0), (8.0, 3.0)], [[a]])[0]["right"]
    assert _pair_record([(5.0, 3.0), (8.0, 3.0)], [[a], [b]])[0]["right"]
    inv = _pair_record([(0.1, 1.0), (0.2, 1.0)], [])[0]
    assert inv["expected"]["scored"] and inv["expected"]["effects"] == [] and inv["right"]
    absorbed = _pair_record([(1.0, 1.2), (8.0, 1.0)], [])[0]
    assert absorbed["expected"]["verdict"] == "absorbed" and absorbed["expected"]["scored"] and absorbed["right"]
    assert not _pair_record([(1.0, 1.2), (1.5, 1.2)], [])[0]["expected"]["scored"]


def test_pair_cases_cache_each_effect_alone(tmp_path):
    # the data of each effect alone (reference) that the per-effect scoring uses: for two effects
    # in different segments (plane offsets at the ducts, convection in the buffer tube) the
    # transfer matrix is a product, so their changes add to first order: the cross term is
    # second order, below 10 % of the smaller change
    seed = next(s for s in range(100) if lv.make_case(s, category="two").effects == ["plane_offsets", "convection"])
    case = lv.make_case(seed, category="two", material="mesh", n_freqs=4)
    a = lv.load_or_generate(case, tmp_path)
    d = {e: a[f"Y_alone_{e}"] - a["Y_without"] for e in case.effects}
    cross = a["Y_clean"] - a["Y_without"] - sum(d.values())
    size = min(np.sqrt(np.mean(np.abs(v) ** 2)) for v in d.values())
    assert size > 0 and np.sqrt(np.mean(np.abs(cross) ** 2)) < 0.1 * size
    # an older cache without them is completed, not regenerated: the noisy data stay the same
    np.savez(next(tmp_path.glob("case_*.npz")), **{k: v for k, v in a.items() if not k.startswith("Y_alone")})
    b = lv.load_or_generate(case, tmp_path)
    np.testing.assert_array_equal(a["T"], b["T"])
    assert set(b) == set(lv.array_keys(case))


def _full_case(seed: int, tmp_path: Path):
    from tawarp.loop import run_loop
    from tawarp.model.forward import ForwardSettings

    case = lv.make_case(seed)
    arrays = lv.load_or_generate(case, tmp_path)
    prob = lv.TMatrixKind(
        lv.measurement(case, arrays),
        lv.load_core(case.core_material).replace(**case.prior),
        ForwardSettings(device="cpu"),
    )
    return case, arrays, prob, run_loop(prob, drift_h=False)


def test_effects_that_substitute_for_each_other_are_claimed_as_a_group(tmp_path):
    # a radiative conductivity on the NiCr foam (0.12 % noise, no sigma): a T-dependent
    # solid conductivity makes nearly the same data, so the posterior splits between them
    # (neither reaches 0.95 alone) while at least one of them is in the model with
    # probability >= 0.95: the loop claims the pair as a group, neither alone, and the fit
    # reaches the noise floor (1.3 x, the study's yardstick)
    from tawarp.loop import write_report

    case, arrays, prob, rep = _full_case(90, tmp_path)
    assert case.effects == ["radiation"] and case.material == "nicr_foam"
    assert rep["accepted_steps"] == ["conductivity_T+radiation"], (rep["accepted_steps"], rep["verdict"])
    assert rep["accepted_effects"] == [] and rep["chosen_effect"] is None
    inc = rep["inclusion_probabilities"]
    assert inc["radiation"] < 0.95 and inc["conductivity_T"] < 0.95
    assert rep["group_probabilities"]["conductivity_T+radiation"] >= 0.95
    assert rep["verdict"] == "explained" and rep["error_after"] <= 1.3 * lv.noise_floor(arrays, prob.Zc)
    js = write_report(prob, rep, tmp_path)
    assert js["accepted_steps"] == ["conductivity_T+radiation"]
    assert "conductivity_T+radiation" in (tmp_path / "report.md").read_text()


def test_wrong_core_flagged_when_the_data_can_show_it(tmp_path, monkeypatch):
    # a wrong core: the ceramic's data (stack 48 mm, hot exchanger 10 mm) fitted with
    # the NiCr foam's core (40 mm, 13 mm). At its drawn noise (0.8 %) the NiCr core with plane
    # offsets (and a second library effect) makes the noise-free data to within 0.15 (0.10)
    # noise floors (stack geometry
    # (L, q, phi) -> (qL, q/phi) leaves a uniform-temperature segment's 2-port unchanged): no
    # method can flag it, and the study does not score it. The same case at 0.1 % noise (the
    # study's lowest) lies >= 0.5 floors from everything the loop can make of the core: the
    # loop flags it
    case = lv.make_case(69)
    assert (case.category, case.material, case.core_material) == ("wrong_core", "ceramic", "nicr_foam")
    assert case.noise > 0.007
    arrays = lv.load_or_generate(case, tmp_path)
    core = lv.load_core(case.core_material).replace(**case.prior)
    settings = lv.ForwardSettings(device="cpu")
    visibility = lv.wrong_core_visibility(case, arrays, core, settings, None)
    assert visibility < lv.INVISIBLE

    lower = lv.make_case(69, noise=0.001)
    assert lower.prior == case.prior and lower.truth == case.truth and lower.with_sigma == case.with_sigma
    low = lv.load_or_generate(lower, tmp_path)
    # the visibility is the best misfit to the noise-free data (the same at both noise levels;
    # sigma only scales every weight alike) over the case's noise floor: run_case takes the
    # misfit found above rather than repeating its fits
    np.testing.assert_array_equal(low["Y_clean"], arrays["Y_clean"])
    misfit = visibility * lv.noise_floor(arrays, lv.rig_Zc(case))
    monkeypatch.setattr(lv, "wrong_core_visibility", lambda c, a, *_: misfit / lv.noise_floor(a, lv.rig_Zc(c)))
    rec = lv.run_case(lower, low)
    assert rec["visibility"] >= lv.INVISIBLE and rec["expected"]["scored"]
    assert rec["outcome"]["verdict"] in lv.FLAGGED and rec["right"], (rec["outcome"]["verdict"], rec["visibility"])


def test_effect_at_the_noise_size_is_claimed_by_its_evidence(tmp_path):
    # wall conduction on the RVC foam (0.27 % noise, sigma given) leaves the base fit at 1.06
    # noise floors, within chi^2 but not white; the evidence claims it (inclusion >= 0.95) and
    # the fit then passes the posterior predictive checks at the floor
    case, arrays, prob, rep = _full_case(134, tmp_path)
    assert case.effects == ["wall_conduction"] and case.with_sigma
    assert rep["accepted_effects"] == ["wall_conduction"], (rep["accepted_steps"], rep["verdict"])
    assert rep["inclusion_probabilities"]["wall_conduction"] >= 0.95
    assert rep["verdict"] == "explained" and rep["goodness_of_fit_after"]["white"]
    assert rep["error_after"] <= 1.3 * lv.noise_floor(arrays, prob.Zc)


def test_convection_absorbed_by_the_buffer_tube_h_is_named(tmp_path):
    # buffer-tube convection on the RVC foam (0.11 % noise, no sigma): the base fit takes its
    # size into tbt.h, which moves 20x its prior; the model with convection explains the data
    # with tbt.h inside its prior, the loop claims convection and the report names the tension
    # it relieves
    case, arrays, prob, rep = _full_case(161, tmp_path)
    assert case.effects == ["convection"] and not case.with_sigma
    assert rep["accepted_effects"] == ["convection"], (rep["accepted_steps"], rep["verdict"])
    assert rep["inclusion_probabilities"]["convection"] >= 0.95
    base_h = [t for t in rep["prior_tension"] if t["model"] == "base" and t["parameter"] == "tbt.h"]
    assert base_h and base_h[0]["value"] > 10 * base_h[0]["prior_centre"], rep["prior_tension"]
    assert abs(rep["parameters_after"]["tbt.h"]["prior_z"]) < 3
    assert rep["verdict"] == "explained" and rep["error_after"] <= 1.3 * lv.noise_floor(arrays, prob.Zc)


# -- the lab suite (tawarp.reference_effects): generation and scoring ---------------------


def test_lab_suite_prior_is_10_to_20_percent_off_and_sizes_are_typical():
    for seed in range(3 * len(lv.LAB_CATEGORIES)):
        case = lv.make_case(seed, suite="lab")
        assert case.category == lv.LAB_CATEGORIES[seed % len(lv.LAB_CATEGORIES)]
        off = [abs(case.prior[k] / case.truth[k] - 1) for k in case.prior]
        assert min(off) >= 0.1 - 1e-12 and max(off) <= 0.2 + 1e-12, off
        lab = lv.lab_effects(case)
        if case.category == "lab:contact_resistance":
            assert 1e-4 <= lab.contact_resistance <= 1e-3
        elif case.category == "lab:bypass_gap":
            assert 0.1e-3 <= lab.bypass_gap <= 0.5e-3
        elif case.category == "lab:leak":
            assert 0.5e-3 <= lab.leak_diameter <= 1e-3
        elif case.category == "lab:mic_mismatch":
            assert 0.02 <= abs(lab.mic_gain - 1) <= 0.05 and 1.0 <= abs(math.degrees(lab.mic_phase)) <= 3.0
        elif case.category == "lab:porosity_gradient":
            phi = case.truth["stack.porosity"]
            assert abs(lab.porosity_gradient) <= 0.3 and phi * (1 + abs(lab.porosity_gradient) / 2) <= 0.99 + 1e-12
        elif case.category == "lab:wall_field":
            assert case.true_effects() == ["wall_conduction"]
    # a case without lab effects is described (and cached) as before the lab field existed
    case = lv.make_case(5)
    assert (
        case.lab == {}
        and case.key()
        == lv.hashlib.sha1(
            lv.json.dumps({k: v for k, v in lv.asdict(case).items() if k != "lab"}, sort_keys=True).encode()
        ).hexdigest()[:10]
    )


@pytest.mark.parametrize("category", [c for c in lv.LAB_CATEGORIES if c.startswith("lab:")])
def test_lab_categories_generate(category, tmp_path):
    # every lab effect makes data that differ from the reference without it, through the
    # study's own generation (noise, sigma, cache) at two frequencies
    case = lv.make_case(3, category=category, material="mesh", n_freqs=2)
    assert case.lab and not case.effects
    a = lv.load_or_generate(case, tmp_path)
    assert set(a) == set(lv.array_keys(case)) and "Y_without" in a
    assert np.all(np.isfinite(a["T"])) and np.all(np.isfinite(a["Y_clean"]))
    assert lv.rms_error(a["Y_clean"], a["Y_without"]) > 1e-4
    # the data without the effect are the reference's own
    base = lv.normalize(
        lv.reference.transfer_matrix(lv.true_core(case), case.freqs, case.heat_inputs[-1]), lv.rig_Zc(case)
    ).reshape(-1, 4)
    np.testing.assert_allclose(a["Y_without"][-1], base, rtol=1e-12)


def _lab_record(
    category: str, visibility: float, ratio_before: float, report: dict, ratio_after: float = 1.05, seed: int = 1
) -> dict:
    case = lv.make_case(seed, category=category, material="mesh", suite="lab")
    name = (case.effects + list(case.lab))[0] if case.effects or case.lab else None
    per = {name: {"visibility": visibility, "ratio_before": ratio_before}} if name else {}
    report = {"error_before": 0.02, "error_after": 0.01, **report}
    rec = {"case": lv.asdict(case), "per_effect": per, "outcome": lv.loop_outcome(report), "ratio_after": ratio_after}
    return lv.score(rec)


def test_outside_lab_effects_must_be_flagged_not_explained():
    vis, absorbed = (5.0, 3.0), (5.0, 1.0)
    explained = {
        "verdict": "explained",
        "accepted_effects": ["thermal_radius_ratio"],
        "accepted_groups": [["thermal_radius_ratio"]],
    }
    rec = _lab_record("lab:leak", *vis, explained)
    assert rec["expected"]["verdict"] == "unexplained_residual" and not rec["right"]
    assert _lab_record("lab:leak", *vis, {"verdict": "unexplained_residual"})["right"]
    # absorbed by the base fit: a false claim is wrong, flagging is right
    rec = _lab_record("lab:leak", *absorbed, explained)
    assert rec["expected"]["verdict"] == "absorbed" and rec["expected"]["scored"] and not rec["right"]
    assert _lab_record("lab:leak", *absorbed, {"verdict": "unexplained_residual"})["right"]


def test_absorbed_effect_adequate_only_within_the_prior():
    # buffer-tube convection absorbed by tbt.h: "adequate" with tbt.h 30x the core file's
    # value (145 prior sd at 20 %) is wrong; within the prior it is right; the loop's own
    # prior_tension counts too
    case = lv.make_case(1, category="effect:convection", material="mesh", suite="lab")
    far = {k: {"value": v, "std": None} for k, v in case.prior.items()}
    far["tbt.h"]["value"] = 30 * case.prior["tbt.h"]
    rec = _lab_record("effect:convection", 5.0, 1.0, {"verdict": "adequate", "parameters_after": far})
    assert rec["expected"]["verdict"] == "absorbed" and rec["tension"] > 100 and not rec["right"]
    near = {k: v * 1.1 for k, v in case.prior.items()}
    rec = _lab_record("effect:convection", 5.0, 1.0, {"verdict": "adequate", "parameters_after": near})
    assert rec["tension"] == pytest.approx(0.5) and rec["right"]
    rec = _lab_record(
        "effect:convection",
        5.0,
        1.0,
        {"verdict": "adequate", "parameters_after": near, "prior_tension": [{"parameter": "tbt.h", "z": 4.0}]},
    )
    assert not rec["right"]
    named = _lab_record("effect:convection", 5.0, 1.0, {"verdict": "explained", "accepted_steps": ["convection"]})
    assert named["right"]
    # clean data judged adequate in tension are wrong as well
    clean = _lab_record("clean", 0.0, 1.0, {"verdict": "adequate", "parameters_after": {"tbt.h": far["tbt.h"]}})
    assert not clean["right"]


def test_wall_field_is_scored_as_the_library_wall_conduction():
    good = {"verdict": "explained", "accepted_steps": ["wall_conduction"]}
    rec = _lab_record("lab:wall_field", 5.0, 3.0, good)
    assert rec["expected"]["effects"] == ["wall_conduction"] and rec["right"]
    assert not _lab_record("lab:wall_field", 5.0, 3.0, good, ratio_after=1.5)["right"]
    assert not _lab_record("lab:wall_field", 5.0, 3.0, {"verdict": "explained", "accepted_steps": ["radiation"]})[
        "right"
    ]


@pytest.mark.parametrize("seed", CONTACT_SEEDS)
def test_contact_resistance_on_independent_data_is_named(seed, tmp_path):
    # the reference's own contact resistance (a jump in its heat BVP, tawarp.reference_effects)
    # between the ceramic stack and its hot exchanger, R_c 5-8e-4 m^2 K/W, the core file 10-20 %
    # off on every parameter of the paper's estimation, the study's noise draw: the loop names
    # contact_resistance (alone or in a group holding it), claims nothing false, and the error
    # after is within 1.3 noise floors
    case = lv.make_case(seed, category="lab:contact_resistance", material="ceramic", suite="lab", n_freqs=N_FREQS)
    rec = lv.run_case(case, lv.load_or_generate(case, tmp_path), "cpu", base="loop", cells=CELLS)
    assert rec["expected"]["effects"] == ["contact_resistance"], (rec["visibility"], rec["ratio_before"])
    assert rec["right_group"], (lv.outcome_label(rec), rec["outcome"]["inclusion_probabilities"])


def test_contact_resistance_is_scored_as_the_library_contact_resistance():
    # the reference's contact (a jump in its own heat BVP) is the library's contact_resistance:
    # visible, it must be named (alone or in a group with it), not flagged
    good = {"verdict": "explained", "accepted_steps": ["contact_resistance"]}
    rec = _lab_record("lab:contact_resistance", 5.0, 3.0, good)
    assert rec["expected"]["effects"] == ["contact_resistance"] and rec["right"]
    assert not _lab_record("lab:contact_resistance", 5.0, 3.0, {"verdict": "unexplained_residual"})["right"]
    assert not _lab_record(
        "lab:contact_resistance", 5.0, 3.0, {"verdict": "explained", "accepted_steps": ["thermal_radius_ratio"]}
    )["right"]


def test_bypass_gap_is_scored_as_the_library_bypass_gap():
    # the reference's gap (a slit 2-port in parallel with the stack's, joined at its ends) is
    # the library's bypass_gap: visible, it must be named, not flagged nor taken for another
    good = {"verdict": "explained", "accepted_steps": ["bypass_gap"]}
    rec = _lab_record("lab:bypass_gap", 5.0, 3.0, good)
    assert rec["expected"]["effects"] == ["bypass_gap"] and rec["right"]
    assert not _lab_record("lab:bypass_gap", 5.0, 3.0, {"verdict": "unexplained_residual"})["right"]
    assert not _lab_record(
        "lab:bypass_gap", 5.0, 3.0, {"verdict": "explained", "accepted_steps": ["plane_offsets", "square_channels"]}
    )["right"]


def test_inclusion_probabilities_calibration():
    # two effects at >= 0.95: one true (wall conduction in the wall-field case), one not
    # (radiation in clean data): 1 of 2 claims true; the bins count every probability, one
    # summed from model probabilities past 1 by rounding (a record may hold it) in the top bin
    recs = [
        _lab_record(
            "lab:wall_field",
            5.0,
            3.0,
            {
                "verdict": "explained",
                "accepted_steps": ["wall_conduction"],
                "inclusion_probabilities": {"wall_conduction": 1.0000000000000002, "radiation": 0.02},
            },
        ),
        _lab_record(
            "clean",
            0.0,
            1.0,
            {
                "verdict": "explained",
                "accepted_steps": ["radiation"],
                "inclusion_probabilities": {"radiation": 0.97, "T_cold": 0.6},
            },
        ),
    ]
    cal = lv.calibration(recs)
    assert cal["claimed"] == {"n": 2, "k": 1, "rate": 0.5}
    assert [b["n"] for b in cal["bins"]] == [1, 0, 1, 2] and cal["bins"][3]["true"] == 1
    assert cal["groups"] == {"n": 2, "k": 1, "rate": 0.5}


def test_adapter_tolerates_both_report_contracts():
    new = {
        "error_before": 0.05,
        "error_after": 0.01,
        "verdict": "explained",
        "accepted_steps": ["a+b", "c"],
        "inclusion_probabilities": {"a": 0.5, "b": 0.5, "c": 0.99},
        "prior_tension": [{"parameter": "tbt.h", "z": 4.2, "ratio": 40.0}],
        "parameters_after": {"tbt.h": {"value": 8.0, "std": 1.0}},
    }
    got = lv.loop_outcome(new)
    assert got["accepted_groups"] == [["a", "b"], ["c"]] and got["accepted_effects"] == ["c"]
    assert got["prior_tension"] == [{"parameter": "tbt.h", "z": 4.2}] and got["parameters_after"] == {"tbt.h": 8.0}
    old = lv.loop_outcome(
        {
            "error_before": 0.05,
            "error_after": 0.01,
            "verdict": "explained",
            "accepted_steps": ["one of {a, b} (indistinguishable in these data)"],
        }
    )
    assert old["accepted_groups"] == [["a", "b"]] and old["inclusion_probabilities"] == {}
    assert old["prior_tension"] == [] and old["parameters_after"] == {}


def test_held_out_seeds_never_in_a_tuning_run():
    assert lv.study_seeds(0, 3, None, "tuning") == [0, 1, 2]
    assert lv.study_seeds(5, 2, None, "heldout") == [lv.HELDOUT_SEED0 + 5, lv.HELDOUT_SEED0 + 6]
    with pytest.raises(ValueError, match="held out"):
        lv.study_seeds(0, 0, [3, lv.HELDOUT_SEED0], "tuning")
    with pytest.raises(ValueError, match="not held out"):
        lv.study_seeds(0, 0, [3], "heldout")
    assert lv.make_case(lv.HELDOUT_SEED0).held_out and not lv.make_case(0).held_out


def test_report_writes_the_confusion_matrix_and_calibration(tmp_path):
    recs = [
        _lab_record(
            "lab:wall_field",
            5.0,
            3.0,
            {
                "verdict": "explained",
                "accepted_steps": ["wall_conduction"],
                "inclusion_probabilities": {"wall_conduction": 0.99},
            },
        ),
        _lab_record(
            "lab:leak",
            5.0,
            3.0,
            {"verdict": "unexplained_residual", "inclusion_probabilities": {"plane_offsets": 0.3}},
            seed=4,
        ),
        _lab_record(
            "effect:convection",
            5.0,
            1.0,
            {"verdict": "adequate", "prior_tension": [{"parameter": "tbt.h", "z": 40.0}]},
            seed=7,
        ),
    ]
    for r, s in zip(recs, (1, 4, lv.HELDOUT_SEED0)):
        r.update(
            seed=s,
            category=r["case"]["category"],
            material="mesh",
            core="mesh",
            noise=0.003,
            with_sigma=True,
            visibility=5.0,
            ratio_before=1.0,
            wall_s=1.0,
        )
    meta = {"base": "loop", "device": "cpu", "command": "test", "generation_s": 0.0, "cases_per_s": 1.0}
    lv.report(tmp_path, recs, meta, quiet=True)
    s = lv.json.loads((tmp_path / "loop_validation.json").read_text())["summary"]
    assert s["held_out_cases"] == 1 and s["adequate_in_tension"] == 1
    assert s["by_split"]["heldout"]["n_cases"] == 1 and s["by_split"]["heldout"]["adequate_in_tension"] == 1
    assert s["outside_lab_flagged"]["k"] == 1 and s["outside_lab_explained"]["k"] == 0
    assert s["calibration"]["claimed"] == {"n": 1, "k": 1, "rate": 1.0}
    assert s["confusion"]["lab:wall_field"]["wall_conduction"] == 1
    assert s["confusion"]["convection (absorbed)"]["adequate, in tension"] == 1
    md = (tmp_path / "loop_validation.md").read_text()
    assert "Calibration of the inclusion probabilities" in md and "| 0.95-1 | 1 | 0.99 | 1 | 1.00 |" in md
    assert (tmp_path / "confusion.png").exists() and (tmp_path / "calibration.png").exists()
    # an interrupted run's file holds its cases and {"partial": true} alone: rescored, it says so
    lv.report(tmp_path / "partial", recs, {"partial": True}, quiet=True)
    md = (tmp_path / "partial" / "loop_validation.md").read_text()
    assert "the cases an interrupted run finished" in md.splitlines()[0] and "cases per second" not in md


@pytest.mark.parametrize(
    "option, what", [("--workers", "processes"), ("--loop-workers", "processes"), ("--together", "loops")]
)
def test_a_study_without_processes_is_refused_before_any_work(option, what, tmp_path, capsys):
    # no process pool of zero or fewer processes, nor a share of the cores for none, nor a
    # group of no loops: the option named, exit 2 (argparse's), and nothing generated or written
    with pytest.raises(SystemExit) as stop:
        lv.main([option, "0", "--cases", "1", "--out", str(tmp_path / "out")])
    assert stop.value.code == 2
    assert f"{option}: 0; expected a positive number of {what}" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_blocking_waits_without_a_gpu_are_refused_before_any_work(tmp_path, capsys):
    # blocking waits set how a loop process's CUDA context waits: on the CPU the option is
    # refused by name, exit 2, nothing generated or written
    with pytest.raises(SystemExit) as stop:
        lv.main(["--blocking-waits", "--cases", "1", "--out", str(tmp_path / "out")])
    assert stop.value.code == 2
    assert "--blocking-waits: sets how loop processes wait for a GPU; --device is 'cpu'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    "option, text, message",
    [
        ("--rescore", None, "no such file"),
        ("--rescore", "{", "not readable as a study's JSON"),
        ("--append", '{"cases": []}', 'not a study\'s JSON (expected its "meta" and "cases")'),
    ],
)
def test_a_results_file_that_is_not_a_studys_stops_before_any_work(option, text, message, tmp_path, capsys):
    # the option and the file named, exit 2, no reference data made and the file untouched
    out = tmp_path / "out"
    if text is not None:
        out.mkdir()
        (out / "loop_validation.json").write_text(text)
    with pytest.raises(SystemExit) as stop:
        lv.main([option, "--cases", "1", "--out", str(out), "--quiet"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert f"{option}: {out / 'loop_validation.json'}: {message}" in err
    assert not (out / "cache").exists()
    if text is not None:
        assert (out / "loop_validation.json").read_text() == text


def test_cases_run_together_are_scored_as_alone(tmp_path):
    # --together: a plane offset and a clean case of the mesh core, their loops' fits and
    # launches batched (two core files of one structure), each scored as its loop alone
    cases = [
        lv.make_case(SEEDS[0], category=c, material="mesh", n_freqs=N_FREQS) for c in ("effect:plane_offsets", "clean")
    ]
    arrays = [lv.load_or_generate(c, tmp_path) for c in cases]
    alone = [lv.run_case(c, a, "cpu", base="loop", cells=CELLS) for c, a in zip(cases, arrays)]
    together = lv.run_cases(cases, arrays, device="cpu", base="loop", cells=CELLS)
    for a, b in zip(alone, together):
        assert lv.outcome_label(a) == lv.outcome_label(b) and a["right"] == b["right"]
        assert abs(a["ratio_after"] / b["ratio_after"] - 1) < 1e-4


def test_an_interrupt_says_what_its_phase_kept():
    """Ctrl-C inside a phase of the study becomes StudyInterrupted with what the phase had
    written at that moment (asked then, not when the phase began); other errors pass."""
    records = []
    with pytest.raises(lv.StudyInterrupted, match="^2 written$"):
        with lv._kept_on_interrupt(lambda: f"{len(records)} written"):
            records += [1, 2]
            raise KeyboardInterrupt
    with pytest.raises(ValueError):
        with lv._kept_on_interrupt(lambda: "unused"):
            raise ValueError("not an interrupt")
