"""``tawarp onset`` on an engine network: the onset, the followed mode and the profiles."""

from __future__ import annotations

import csv
import json

import numpy as np

from tawarp.cli import main


def test_onset_of_the_traveling_wave_engine_from_the_command_line(tmp_path):
    """The JSON's ratio is T_onset / T_cold, the followed growth rate changes sign around
    T_onset, and the profiles' closed end carries no volume flow (1e-9 of the largest)."""
    out = tmp_path / "tw"
    args = ["onset", "traveling_wave", "--T-max", "700", "--bracket", "6", "--f-max", "120", "-o", str(out)]
    assert main(args + ["--quiet", "--no-plots"]) == 0
    doc = json.loads((out / "onset.json").read_text())
    assert abs(doc["T_ratio"] - doc["T_onset_K"] / doc["T_cold_K"]) < 1e-12
    T, g = np.array(doc["path"]["T_hot_K"]), np.array(doc["path"]["growth_rate_1_per_s"])
    assert np.all(g[T < doc["T_onset_K"]] < 0) and np.all(g[T > doc["T_onset_K"]] > 0)
    assert doc["mode_jumps"] == []
    with (out / "profiles.csv").open() as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    res = [r for r in rows if r["branch"] == "resonator"]
    U = np.array([float(r["U_abs_m3_per_s"]) for r in res])
    assert U[-1] < 1e-9 * U.max()


def test_rank_by_onset_in_a_network_from_the_command_line(tmp_path):
    """``tawarp rank --by onset --engine traveling_wave``: the JSON ranks by the onset ratio,
    its nominal a ratio above 1 where the engine starts; a wrong --segment names the porous ones."""
    out = tmp_path / "rank.json"
    base = ["rank", "--by", "onset", "--engine", "traveling_wave", "--materials", "mesh", "--samples", "2"]
    assert main(base + ["--segment", "regenerator", "--T-max", "1000", "-o", str(out), "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert doc["ranked_by"].startswith("median onset temperature ratio")
    (row,) = doc["ranking"]
    assert row["material"] == "mesh" and 1.0 < row["T_ratio_nominal"] < 1000.0 / 325.0
    assert main(base + ["-o", str(out), "--quiet"]) == 2  # no segment 'stack' in the network
