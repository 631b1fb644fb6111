"""``tawarp onset`` on an engine network: the onset, the followed mode and the profiles."""

from __future__ import annotations

import csv
import json

import numpy as np

from tawarp.cli import main


def test_onset_of_the_traveling_wave_engine_from_the_command_line(tmp_path):
    """The JSON's ratio is T_onset / T_cold, the followed growth rate changes sign around
    T_onset, and the profiles' closed end carries no volume flow (1e-9 of the largest); a
    --var design's onset (followed on the device) is the reference's Newton onset of that
    design (1e-9)."""
    from tawarp.model import network_reference as nr
    from tawarp.model.network import load_network

    out = tmp_path / "tw"
    args = ["onset", "traveling_wave", "--T-ratio-max", "2.15", "--bracket", "6", "--f-max", "120", "-o", str(out)]
    assert main(args + ["--var", "regenerator.pore_radius=7e-5,9e-5", "--device", "cpu", "--quiet", "--no-plots"]) == 0
    doc = json.loads((out / "onset.json").read_text())
    net = load_network("traveling_wave")
    for s in doc["sets"]:
        design = net.replace(**s["params"])
        _, T = nr.onset_newton(design, 2 * np.pi * doc["f_onset_Hz"], doc["T_onset_K"])
        assert abs(s["T_ratio"] / (T / net.gas.T_cold) - 1) < 1e-9
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
    assert main(base + ["--segment", "regenerator", "--T-ratio-max", "3.0", "-o", str(out), "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert doc["ranked_by"].startswith("median onset temperature ratio")
    (row,) = doc["ranking"]
    assert row["material"] == "mesh" and 1.0 < row["T_ratio_nominal"] < 3.0
    assert main(base + ["-o", str(out), "--quiet"]) == 2  # no segment 'stack' in the network


def test_design_on_a_network_lowers_the_onset_ratio(tmp_path):
    """``tawarp design traveling_wave --var regenerator.length=...``: the search's best onset
    ratio is at most the file's (a box holding the file's 7.3 cm), and each kept design's
    ratio is the followed onset of the network with its values (1e-8)."""
    from tawarp.model import network_reference as nr
    from tawarp.model.network import load_network

    out = tmp_path / "d"
    args = ["design", "traveling_wave", "--var", "regenerator.length=0.04:0.09", "--trials", "48", "--batch", "16"]
    assert (
        main(args + ["--segment", "regenerator", "--keep", "2", "--T-ratio-max", "2.77", "-o", str(out), "--quiet"])
        == 0
    )
    doc = json.loads((out / "design.json").read_text())
    best = doc["best"][0]
    assert best["T_ratio"] <= doc["file_design"]["T_ratio"] + 1e-9
    net = load_network("traveling_wave").replace(**best["params"])
    (w0, *_) = nr.real_axis_modes(net, 40.0, 130.0, 90, T_hot=net.gas.T_cold)
    assert abs(nr.onset(net, w0, T_max=2.77 * 325.0, n=8).ratio / best["T_ratio"] - 1) < 1e-8
    assert best["Edot_produced_W"] > 0


def test_onset_of_a_network_without_T_hot_reports_its_mode(tmp_path):
    """The refrigerator names no T_hot: ``tawarp onset`` reports its lowest mode, which lies
    within 1 % of the 500 Hz at which DeltaEC's hofler1 drives it, decaying (a passive
    resonator), and writes its profiles."""
    out = tmp_path / "rf"
    assert main(["onset", "refrigerator", "-o", str(out), "--quiet", "--no-plots"]) == 0
    doc = json.loads((out / "onset.json").read_text())
    assert abs(doc["f_Hz"] / 500.0 - 1) < 0.01 and doc["growth_rate_1_per_s"] < 0 and doc["T_onset_K"] is None
    assert (out / "profiles.csv").stat().st_size > 0
