"""The batched network kernels against the NumPy reference (CPU)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tawarp.model import network_reference as nr
from tawarp.model.network import load_network, network_from_dict
from tawarp.model.network_batch import NetworkBatch

AIR_HOT = {"name": "air", "p_mean": 101325.0, "T_cold": 300.0}


def test_determinant_matches_the_reference_on_every_end_and_segment_kind():
    """Ducts, a cone, a porous segment with a gradient, a compliance with surface loss, an
    inertance, a loop, a tee and the four end kinds: the kernel's det equals the reference's
    (DOP853 at 1e-11) at a complex omega to 1e-7 with 8 Magnus cells per graded segment
    (3e-8 at 310 Hz in its 10 cm buffer tube), 1e-9 with 16, converging at sixth order."""
    seg = {"name": "stk", "kind": "porous", "length": 0.05, "radius": 0.02, "porosity": 0.7, "pore_radius": 3e-4}
    d = {
        "gas": {"name": "air", "p_mean": 2e5, "T_cold": 300.0},
        "network": {"T_hot": 500.0},
        "branch": [
            {
                "name": "ring",
                "from": "j",
                "to": "j",
                "segment": [
                    {"name": "d1", "kind": "duct", "length": 0.4, "radius": 0.02},
                    {**seg, "T_start": "T_cold", "T_end": "T_hot"},
                    {
                        "name": "hot",
                        "kind": "porous",
                        "length": 0.01,
                        "radius": 0.02,
                        "porosity": 0.8,
                        "pore_radius": 5e-4,
                        "pore_model": "plates",
                        "T": "T_hot",
                    },
                    {"name": "tbt", "kind": "duct", "length": 0.1, "radius": 0.02, "T_start": "T_hot", "T_end": 300.0},
                    {"name": "neck", "kind": "inertance", "length": 0.05, "radius": 0.01},
                    {"name": "vol", "kind": "compliance", "volume": 2e-4, "surface_area": 0.02},
                ],
            },
            {
                "name": "a",
                "from": "j",
                "to": "tee",
                "segment": [{"name": "cone", "kind": "duct", "length": 0.3, "radius": 0.02, "radius_end": 0.03}],
            },
            {
                "name": "b",
                "from": "tee",
                "to": "open",
                "segment": [{"name": "d2", "kind": "duct", "length": 0.5, "radius": 0.03}],
            },
            {
                "name": "c",
                "from": "load",
                "to": "tee",
                "segment": [{"name": "d3", "kind": "duct", "length": 0.2, "radius": 0.015}],
            },
        ],
        "end": [
            {"name": "open", "kind": "open", "flange": "flanged"},
            {"name": "load", "kind": "load", "resistance": 1e5, "volume": 1e-3},
        ],
    }
    net = network_from_dict(d, "t")
    coarse, fine = NetworkBatch(net, device="cpu", cells=8), NetworkBatch(net, device="cpu", cells=16)
    for w in (2 * math.pi * (120 + 3j), 2 * math.pi * (310 - 5j)):
        ref = nr.determinant(net, w)
        err8 = abs(coarse.determinants(w)[0] / ref - 1)
        err16 = abs(fine.determinants(w)[0] / ref - 1)
        # sixth order: halving the cells divides the error by ~64 (16 allowed)
        assert err8 < 1e-7 and err16 < 1e-9 and err16 < err8 / 16
    d["end"][1] = {"name": "load", "kind": "impedance", "impedance": [3e5, -2e5]}
    net = network_from_dict(d, "t")
    w = 2 * math.pi * (200 + 1j)
    assert abs(NetworkBatch(net, device="cpu", cells=16).determinants(w)[0] / nr.determinant(net, w) - 1) < 1e-9


@pytest.fixture(scope="module")
def tw():
    net = load_network("traveling_wave")
    radii = np.array([60e-6, 84.4e-6, 110e-6])
    return net, radii, NetworkBatch(net, {"regenerator.pore_radius": radii}, device="cpu")


def test_batched_eigenfrequencies_and_onsets_match_the_reference(tw):
    """One thread per design: Muller's eigenfrequency at T_hot = 600 K and Newton's onset from
    the nominal design's agree with the reference's to 1e-10."""
    net, radii, batch = tw
    w, its = batch.eigenfrequencies(2 * math.pi * 86.5, 600.0)
    assert (its > 0).all()
    start = nr.onset(net, 2 * math.pi * 86.5, T_max=700.0, n=8)
    on = batch.onset(start.omega.real, start.T_onset)
    assert (on.iterations > 0).all()
    for k, r in enumerate(radii):
        design = net.replace(**{"regenerator.pore_radius": r})
        assert abs(w[k] / nr.eigenfrequency(design, 2 * math.pi * 86.5, 600.0) - 1) < 1e-10
        w_on, T_on = nr.onset_newton(design, start.omega.real, start.T_onset)
        assert abs(on.omega[k] / w_on - 1) < 1e-10 and abs(on.T_hot[k] / T_on - 1) < 1e-10
    assert abs(on.T_hot[1] / start.T_onset - 1) < 1e-10  # the nominal design is the file's


def test_batch_parameters_are_checked():
    net = load_network("traveling_wave")
    with pytest.raises(KeyError, match=r"'regenerator.colour': not a batch parameter"):
        NetworkBatch(net, {"regenerator.colour": [1.0]}, device="cpu")
    with pytest.raises(ValueError, match=r"regenerator.porosity\[1\] = 1.2: expected a finite value in \(0, 1\]"):
        NetworkBatch(net, {"regenerator.porosity": [0.7, 1.2]}, device="cpu")
    with pytest.raises(ValueError, match=r"regenerator.porosity: 2 values; every parameter needs 1 or 3"):
        NetworkBatch(net, {"regenerator.porosity": [0.7, 0.8], "regenerator.pore_radius": [1e-4] * 3}, device="cpu")


def test_followed_onsets_match_the_reference_without_a_start():
    """Each thread follows its design's mode from T_cold (as the reference's onset does, with
    the same grid, predictor and jump test): onsets agree to 1e-7 (8 Magnus cells: 4e-8 at
    200 um, T_hot = 980 K) from 40 um pores (ratio 1.63) to 200 um (3.02), and 500 um pores
    do not start below 4 T_cold in either."""
    net = load_network("traveling_wave")
    radii = np.array([40e-6, 84.4e-6, 200e-6, 500e-6])
    res = NetworkBatch(net, {"regenerator.pore_radius": radii}, device="cpu").followed_onset(
        2 * math.pi * 86.5, 4 * net.gas.T_cold, n=12
    )
    assert list(res.status) == [1, 1, 1, 0] and (res.jumps == 0).all()
    for k, r in enumerate(radii[:3]):
        ref = nr.onset(net.replace(**{"regenerator.pore_radius": r}), 2 * math.pi * 86.5, 4 * net.gas.T_cold, n=12)
        assert abs(res.T_hot[k] / ref.T_onset - 1) < 1e-7 and abs(res.omega[k] / ref.omega.real - 1) < 1e-7
    assert np.isnan(res.T_hot[3])


def test_an_open_end_radiates_at_the_temperature_of_its_segment():
    """A duct at "T_hot" ending open: the radiation impedance takes the gas at the T_hot of the
    call (not the file's), in the kernel and the reference alike (1e-12); another T_hot moves
    the determinant."""
    d = {
        "gas": AIR_HOT,
        "network": {"T_hot": 400.0},
        "branch": [
            {
                "name": "b",
                "from": "a",
                "to": "o",
                "segment": [{"name": "hot", "kind": "duct", "length": 0.5, "radius": 0.03, "T": "T_hot"}],
            }
        ],
        "end": [{"name": "a", "kind": "closed"}, {"name": "o", "kind": "open"}],
    }
    net = network_from_dict(d, "t")
    batch = NetworkBatch(net, device="cpu")
    w = 2 * math.pi * (200 + 2j)
    for T in (400.0, 700.0):
        assert abs(batch.determinants(w, T)[0] / nr.determinant(net, w, T) - 1) < 1e-12
    assert abs(nr.determinant(net, w, 700.0) / nr.determinant(net, w, 400.0) - 1) > 1e-3
