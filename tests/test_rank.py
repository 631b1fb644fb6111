"""Material ranking with uncertainty (tawarp.design.rank), on the CPU."""

from __future__ import annotations

import numpy as np
import pytest

PAPER = ("ceramic", "mesh", "nicr_foam", "rvc_foam")


def test_rank_the_paper_materials_at_9_W():
    """At Q = 9 W in the same core the RVC foam reaches the highest gradient, as the paper
    concludes, and the stainless-steel mesh the lowest. The hot end temperature is set by
    the heat the stack draws, G_s theta3 with G_s = S sqrt(2 h_s lam_s / R) tanh(k L), in
    parallel with the hot exchanger's own losses, and the fraction of it across the stack
    is 1 - sech(k L). RVC has the smallest h_s lam_s (8 x 0.21); the mesh the largest
    (50 x 4.3: steel at porosity 0.68) and the shortest k L (1.5). Ceramic (150 x 0.32,
    kL 9.4) comes before NiCr (30 x 0.98, kL 2.4; its h_s = 30 is tawarp's choice)."""
    from tawarp.design.rank import rank_materials

    res = rank_materials(PAPER, [9.0], n_samples=400, seed=1)
    assert res.ordering(9.0) == ["rvc_foam", "ceramic", "nicr_foam", "mesh"]
    rows = {r["material"]: r for r in res.table}
    for r in rows.values():
        assert np.isfinite(r["gradient_std_K_per_m"]) and r["gradient_std_K_per_m"] > 0
        assert r["gradient_p025_K_per_m"] < r["gradient_mean_K_per_m"] < r["gradient_p975_K_per_m"]
    assert rows["rvc_foam"]["p_best"] > 0.9
    assert sum(r["p_best"] for r in rows.values()) == pytest.approx(1.0)


def _fit_json(tmp_path, std, corr):
    """A fit.json as ``tawarp fit`` writes it (docs/formats.md): ceramic stack parameters with
    standard deviations and their correlation."""
    import json

    names = ["stack.porosity", "stack.pore_radius", "stack.h"]
    values = [0.9, 0.47e-3, 150.0]
    d = {
        "core": "ceramic",
        "parameters": {k: {"value": v, "std": s} for k, v, s in zip(names, values, std)},
        "correlation": {"names": names, "matrix": corr},
    }
    p = tmp_path / "fit.json"
    p.write_text(json.dumps(d))
    return p, names, np.array(values), np.array(std)[:, None] * np.array(corr) * np.array(std)[None, :]


def test_drawn_sets_match_the_fit_covariance(tmp_path):
    """Parameter sets drawn for a material read from a fit.json have the fit's mean and
    covariance within sampling error: 20000 draws, mean within 4 standard errors, each
    covariance entry within 5 of its standard errors (var of s_ij: (S_ii S_jj + S_ij^2)/N);
    column 0 is the nominal material. The stds are small enough that clipping never acts."""
    from tawarp.design.catalogue import Material
    from tawarp.design.rank import draw_parameter_sets

    corr = [[1.0, -0.6, 0.3], [-0.6, 1.0, 0.5], [0.3, 0.5, 1.0]]
    path, names, mean, cov = _fit_json(tmp_path, [0.01, 0.03e-3, 20.0], corr)
    m = Material.from_fit_json(path)
    N = 20000
    sets = draw_parameter_sets([m], N, seed=5)
    X = np.stack([sets[k][0] for k in names])
    assert np.array_equal(X[:, 0], mean)
    d = X[:, 1:]
    se = np.sqrt(np.diag(cov) / N)
    assert np.all(np.abs(d.mean(axis=1) - mean) < 4 * se)
    S = np.cov(d)
    se_cov = np.sqrt((np.outer(np.diag(cov), np.diag(cov)) + cov**2) / N)
    assert np.all(np.abs(S - cov) < 5 * se_cov)
    # unfitted parameters keep the base values, without spread
    assert np.all(sets["stack.tortuosity"] == 1.0) and np.all(sets["stack.solid_conductivity"] == 3.0)


def test_onset_ranking_with_zero_covariance_is_the_point_prediction(tmp_path):
    """A fit with zero standard deviations: every draw's onset equals the point prediction,
    i.e. onset() of the engine with the fitted values (batch = single run to 1e-12), and the
    5-95 % interval collapses onto it."""
    from tawarp.design.catalogue import Material
    from tawarp.design.rank import rank_by_onset
    from tawarp.model.onset import onset
    from tawarp.model.resonator import load_engine

    path, names, mean, _ = _fit_json(tmp_path, [0.0, 0.0, 0.0], np.eye(3).tolist())
    m = Material.from_fit_json(path, name="zero")
    res = rank_by_onset([m], n_samples=3, Q_max=80.0)
    point = onset(load_engine("standing_wave"), Q_max=80.0, params=m.core_params()).Q_onset[0]
    row = res.table[0]
    assert np.all(np.abs(res.samples["zero"] - point) <= 1e-12 * point)
    for k in ("nominal", "median", "p05", "p90", "p95"):
        assert abs(row[f"Q_onset_{k}_W"] - point) <= 1e-12 * point


def test_rank_by_onset_probabilities(tmp_path):
    """Four materials in the standing-wave engine at 10 bar (gas.p_mean = 1e6): each row's
    nominal onset is that of a single onset() run with the material in the stack (1e-12);
    P(a beats b) and P(best) are the fractions of paired draws; the 40 um mesh pores
    (r / delta_kappa ~ 0.6 at 10 bar, 150 Hz) are too narrow for a standing-wave stack: no
    onset up to Q_max, and it beats nobody. The command line writes the same table."""
    import dataclasses
    import json

    from tawarp.cli import main
    from tawarp.design.catalogue import default_catalogue
    from tawarp.design.rank import rank_by_onset
    from tawarp.model.onset import onset
    from tawarp.model.resonator import load_engine

    base = load_engine("standing_wave")
    eng = dataclasses.replace(base, core=base.core.replace(**{"gas.p_mean": 1e6}))
    res = rank_by_onset(PAPER, eng, n_samples=24, seed=2, Q_max=120.0)
    rows = {r["material"]: r for r in res.table}
    cat = default_catalogue()
    for name in ("ceramic", "nicr_foam", "rvc_foam"):
        one = onset(eng, Q_max=120.0, params=cat[name].core_params(), n_bracket=9).Q_onset[0]
        assert abs(rows[name]["Q_onset_nominal_W"] - one) <= 1e-12 * one
        assert rows[name]["Q_onset_p05_W"] <= rows[name]["Q_onset_median_W"] <= rows[name]["Q_onset_p95_W"]
    assert rows["mesh"]["p_no_onset"] == 1.0 and rows["mesh"]["Q_onset_median_W"] is None
    assert all(v == 0.0 for v in rows["mesh"]["p_beats"].values())
    s = res.samples
    assert rows["rvc_foam"]["p_beats"]["ceramic"] == pytest.approx(np.mean(s["rvc_foam"] < s["ceramic"]), abs=0)
    best = np.argmin(np.stack([s[m] for m in PAPER]), axis=0)
    assert [rows[m]["p_best"] for m in PAPER] == [np.mean(best == k) for k in range(4)]
    assert res.ordering()[-1] == "mesh"
    out = tmp_path / "r.json"
    assert (
        main(
            [
                "rank",
                "--by",
                "onset",
                "--samples",
                "24",
                "--seed",
                "2",
                "--Q-max",
                "120",
                "--set",
                "gas.p_mean=1e6",
                "-o",
                str(out),
                "--device",
                "cpu",
                "--quiet",
            ]
        )
        == 0
    )
    assert json.loads(out.read_text())["ranking"] == json.loads(json.dumps(res.to_dict()["ranking"]))
