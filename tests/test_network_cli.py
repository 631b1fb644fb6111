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
