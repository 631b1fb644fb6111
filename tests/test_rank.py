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
