"""Material catalogue (tawarp.design.catalogue), on the CPU."""

from __future__ import annotations

import json
import textwrap

import numpy as np
import pytest

from tawarp.design.catalogue import (
    CORE_FIELD,
    PARAMS,
    Catalogue,
    CatalogueError,
    Material,
    default_catalogue,
    load_catalogue,
)
from tawarp.model.core import load_core
from tawarp.model.fields import field

PAPER = ("ceramic", "mesh", "nicr_foam", "rvc_foam")


def test_paper_materials_match_bundled_cores():
    cat = default_catalogue()
    assert list(cat) == list(PAPER)
    for name in PAPER:
        ref = Material.from_core(load_core(name))
        m = cat[name]
        for p in PARAMS:
            assert getattr(m, p) == pytest.approx(getattr(ref, p)), (name, p)
        # Table 1 uncertainties: porosity ± 0.01 for all four
        assert m.std["porosity"] == 0.01
        cov = m.covariance()
        assert cov.shape == (len(PARAMS), len(PARAMS)) and np.all(np.linalg.eigvalsh(cov) >= -1e-18)


def test_fit_json_and_toml_catalogue(tmp_path):
    fit = {
        "parameters": {
            "stack.porosity": {"value": 0.95, "std": 0.005},
            "stack.h": {"value": 12.0, "std": 3.0},
            "hot_hx.h": {"value": 90.0, "std": 20.0},
        },
        "correlation": [[1.0, 0.6, 0.1], [0.6, 1.0, 0.0], [0.1, 0.0, 1.0]],
        "converged": True,
        "iterations": 7,
        "cost": 1e-3,
        "rms_error": 0.01,
    }
    (tmp_path / "fit.json").write_text(json.dumps(fit))
    m = Material.from_fit_json(tmp_path / "fit.json", base="rvc_foam", name="fitted")
    assert m.porosity == 0.95 and m.h_s == 12.0 and m.pore_radius == default_catalogue()["rvc_foam"].pore_radius
    cov = m.covariance()
    ip, ih = PARAMS.index("porosity"), PARAMS.index("h_s")
    assert cov[ip, ih] == pytest.approx(0.6 * 0.005 * 3.0)
    draws = m.sample(20000, 1)
    assert np.corrcoef(draws["porosity"], draws["h_s"])[0, 1] == pytest.approx(0.6, abs=0.03)
    (tmp_path / "cat.toml").write_text(
        textwrap.dedent("""
        [[material]]
        name = "my_foam"
        base = "rvc_foam"
        h_s = 5.0
        std = { h_s = 1.0 }

        [[material]]
        name = "from_fit"
        fit = "fit.json"
        base = "nicr_foam"
    """)
    )
    cat = load_catalogue([tmp_path / "cat.toml"])
    assert cat["my_foam"].h_s == 5.0 and cat["my_foam"].porosity == 0.97 and cat["my_foam"].std["h_s"] == 1.0
    assert cat["from_fit"].porosity == 0.95 and cat["from_fit"].solid_conductivity == 12.0
    (tmp_path / "bad.toml").write_text('[[material]]\nname = "x"\nporosity = 0.5\ncolour = "red"\n')
    with pytest.raises(CatalogueError, match="bad.toml.*colour"):
        Catalogue().load(tmp_path / "bad.toml")
    (tmp_path / "bad2.toml").write_text(
        '[[material]]\nname = "x"\nporosity = 1.5\npore_radius = 1e-4\n'
        "tortuosity = 1.0\nsolid_conductivity = 1.0\nh_s = 1.0\n"
    )
    with pytest.raises(CatalogueError, match="bad2.toml.*porosity"):
        Catalogue().load(tmp_path / "bad2.toml")


def test_draws_are_clipped_to_the_fit_ranges_of_the_parameter_table():
    """Draws near the bounds: every draw lies in the parameter table's fit range, and the
    share clipped to a bound is the normal tail beyond it (to 0.01 with 40000 draws)."""
    from scipy.stats import norm

    m = Material(
        "wide",
        porosity=0.995,
        pore_radius=2e-4,
        tortuosity=1.02,
        solid_conductivity=1.0,
        h_s=5.0,
        std={"porosity": 0.01, "tortuosity": 0.02},
    )
    d = m.sample(40000, 3)
    for p in PARAMS:
        lo, hi = field(CORE_FIELD[p]).fit_range
        assert np.all((lo <= d[p]) & (d[p] <= hi)), p
    # porosity upper bound 1.0: P(x > 1) = 1 - Phi(0.5) = 0.3085; tortuosity lower 1.0: Phi(-1) = 0.1587
    assert np.mean(d["porosity"] == 1.0) == pytest.approx(1 - norm.cdf(0.5), abs=0.01)
    assert np.mean(d["tortuosity"] == 1.0) == pytest.approx(norm.cdf(-1.0), abs=0.01)


def test_fit_json_of_a_two_step_fit_carries_h_from_every_heat_input(tmp_path):
    # tawarp fit's two-step output holds the stack's h per heat input (step2): the material's
    # h_s is their inverse-variance mean, its std the larger of the standard error and the
    # spread over the heat inputs (closed form below)
    hs, sd = np.array([48.0, 50.0, 55.0]), np.array([1.0, 2.0, 2.0])
    fit = {
        "core": "mesh",
        "parameters": {"stack.porosity": {"value": 0.7, "std": 0.01}},
        "correlation": {"names": ["stack.porosity"], "matrix": [[1.0]]},
        "step2": [
            {"heat_input_W": q, "parameters": {"stack.h": {"value": h, "std": s}, "tbt.h": {"value": 0.2, "std": 0.01}}}
            for q, h, s in zip((10.0, 20.0, 40.0), hs, sd)
        ],
    }
    (tmp_path / "fit.json").write_text(json.dumps(fit))
    m = Material.from_fit_json(tmp_path / "fit.json")
    w = 1 / sd**2
    assert m.h_s == pytest.approx(np.sum(w * hs) / np.sum(w), rel=1e-12)
    assert m.std["h_s"] == pytest.approx(max(1 / np.sqrt(w.sum()), np.std(hs, ddof=1)), rel=1e-12)
    assert m.porosity == 0.7
