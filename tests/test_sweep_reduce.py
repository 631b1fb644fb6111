"""Reductions of a sweep computed on the device (tawarp.design.reductions) against NumPy's
reductions of the raw values the same sweep wrote: exact for the counts, best values, the
top K and the Pareto front; the quantiles within their bins."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
import xarray as xr

from tawarp.design.reductions import QUANTILES, ordered_keys, parse_reduce
from tawarp.design.samplers import pareto_mask
from tawarp.design.space import DesignSpace, parse_variable
from tawarp.design.sweep import sweep
from tawarp.kernels.reduce import ordered_key
from tawarp.model.core import load_core

ALL = "best,quantiles,histogram,pareto,top=25"
SOBOL = ["material=ceramic,mesh,rvc_foam", "stack.length=0.01:0.08", "stack.porosity=0.7:0.95", "heat_input=1:18:log"]


def _group(path, name):
    with xr.open_dataset(path, engine="h5netcdf", group=name) as ds:
        return ds.load()


@pytest.fixture(scope="module")
def sobol_sweep(tmp_path_factory):
    """3000 Sobol points in chunks of 512 (six chunks: the merges across chunks are
    exercised), raw values and every reduction."""
    path = tmp_path_factory.mktemp("reduce") / "s.nc"
    space = DesignSpace(load_core("rvc_foam"), SOBOL)
    info = sweep(space, path, mode="sobol", n_samples=3000, chunk=512, seed=2, reduce=ALL)
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        raw = ds.load()
    return path, space, info, raw


def test_top_k_and_front_are_numpys(sobol_sweep):
    path, _, info, raw = sobol_sweep
    g = raw.gradient.values.astype(np.float64)
    n = len(g)
    top = _group(path, "top")
    order = np.lexsort((np.arange(n), -g))[:25]  # maximized, ties by index
    np.testing.assert_array_equal(top.point.values, order)
    for k in ("gradient", "T_max", "heat_leak", "stack.length", "heat_input", "material"):
        np.testing.assert_array_equal(
            top[k].values,
            raw[k].values[order]
            if k != "material"
            else np.array(["ceramic", "mesh", "rvc_foam"])[raw.material.values[order]],
        )
    assert info.reductions["best"]["point"] == order[0]
    front = _group(path, "pareto")
    F = np.stack([-g, raw.heat_leak.values.astype(np.float64)], axis=1)
    assert set(front.point.values.tolist()) == set(np.flatnonzero(pareto_mask(F)).tolist())
    np.testing.assert_array_equal(front.heat_leak.values, raw.heat_leak.values[front.point.values])


def test_histograms_and_quantiles_are_numpys(sobol_sweep):
    path, _, _, raw = sobol_sweep
    hist, quant = _group(path, "histogram"), _group(path, "quantiles")
    for o in ("gradient", "T_max", "heat_leak", "T_hot"):
        v = raw[o].values
        ok = ~np.isnan(v)
        bins, counts = np.unique(ordered_keys(v[ok]) >> 12, return_counts=True)  # 20 leading bits
        np.testing.assert_array_equal(hist[f"{o}_count"].values, counts)
        assert int(hist[f"{o}_nan"]) == int((~ok).sum())
        lo, hi = hist[f"{o}_lower"].values, hist[f"{o}_upper"].values
        vv = np.sort(v[ok].astype(np.float64))
        j = np.searchsorted(hi, vv)  # every value inside its bin's edges
        assert np.all((lo[j] <= vv) & (vv <= hi[j]))
        assert np.all(hi / lo - 1 < 2.0**-10)  # equal relative width 2^-11 (one ulp short)
        q = np.quantile(v[ok].astype(np.float64), QUANTILES)
        assert np.all(quant[f"{o}_lower"].values <= q) and np.all(q <= quant[f"{o}_upper"].values)


def test_marginal_best_of_a_sobol_sweep(sobol_sweep):
    """Per variable level (64 bins of each continuous range, of the logarithm for
    heat_input; each material) the best gradient and where it is."""
    path, space, _, raw = sobol_sweep
    best = _group(path, "best")
    g = raw.gradient.values.astype(np.float64)
    for v in space.variables:
        if v.categorical:
            level = raw.material.values.astype(int)
        else:
            x, lo, hi = raw[v.name].values, v.low, v.high
            if v.log:
                x, lo, hi = np.log(x), np.log(lo), np.log(hi)
            level = np.clip(np.floor((x - lo) / (hi - lo) * 64).astype(int), 0, 63)
        for L in range(len(best[f"{v.name}_level"])):
            at = np.flatnonzero(level == L)
            if not at.size:
                assert best[f"{v.name}_point"].values[L] == -1
                continue
            j = at[np.argmax(g[at])]
            assert best[f"{v.name}_point"].values[L] == j and best[f"{v.name}_best"].values[L] == g[j]


def test_marginal_best_of_a_grid_is_the_maximum_over_the_other_axes(tmp_path):
    space = DesignSpace(
        load_core("rvc_foam"),
        [
            parse_variable(s, grid=True)
            for s in ["material=ceramic,rvc_foam", "stack.length=0.01:0.08:7", "heat_input=1:18:5"]
        ],
    )
    sweep(space, tmp_path / "g.nc", chunk=8, reduce="best,top=3")
    with xr.open_dataset(tmp_path / "g.nc", engine="h5netcdf") as ds:
        G = ds.gradient.values
    best = _group(tmp_path / "g.nc", "best")
    for axis, v in enumerate(["material", "stack.length", "heat_input"]):
        np.testing.assert_array_equal(
            best[f"{v}_best"].values, np.moveaxis(G, axis, 0).reshape(G.shape[axis], -1).max(1)
        )
    top = _group(tmp_path / "g.nc", "top")
    flat = np.argsort(-G.ravel().astype(np.float64), kind="stable")[:3]
    np.testing.assert_array_equal(top.point.values, flat)
    at = np.unravel_index(flat, G.shape)
    np.testing.assert_array_equal(top["stack.length"].values, np.linspace(0.01, 0.08, 7)[at[1]])


def test_reductions_without_raw_values_are_the_same(sobol_sweep, tmp_path):
    path, space, _, _ = sobol_sweep
    sweep(space, tmp_path / "r.nc", mode="sobol", n_samples=3000, chunk=1024, seed=2, reduce=ALL, raw=False)
    with xr.open_dataset(tmp_path / "r.nc", engine="h5netcdf") as ds:
        assert "gradient" not in ds and "stack.length" not in ds
    for name in ("top", "pareto", "best", "histogram", "quantiles"):
        a, b = _group(path, name), _group(tmp_path / "r.nc", name)
        if name == "pareto":  # the same front; its order follows the objectives
            assert set(a.point.values.tolist()) == set(b.point.values.tolist())
        else:
            xr.testing.assert_identical(a, b)


def test_candidates_beyond_the_staged_copy_are_read_from_the_device(sobol_sweep, tmp_path, monkeypatch):
    # a chunk's candidates past the STAGED slots copied with its reductions are read from
    # the device: with 2 slots staged (fewer than the top's 25 or the front's candidates)
    # the reductions are the same
    from tawarp.design import reductions

    path, space, _, _ = sobol_sweep
    monkeypatch.setattr(reductions, "STAGED", 2)
    sweep(space, tmp_path / "r.nc", mode="sobol", n_samples=3000, chunk=512, seed=2, reduce=ALL, raw=False)
    xr.testing.assert_identical(_group(path, "top"), _group(tmp_path / "r.nc", "top"))
    a, b = _group(path, "pareto"), _group(tmp_path / "r.nc", "pareto")
    assert set(a.point.values.tolist()) == set(b.point.values.tolist())


def test_histograms_compacted_on_the_device_and_merged_are_numpys():
    """Each output's occupied bins, compacted on the device, and those of two reducers of
    disjoint point ranges merged (Reducer.state, Reducer.merge) equal NumPy's counts of the
    values' 20 leading key bits: values over the whole float32 range (bins in many blocks),
    one bin hit 50 times, NaN counted apart, +-0, +-inf and subnormals."""
    from tawarp.design.reductions import Reducer, ReduceSpec
    from tawarp.kernels.reduce import HIST_OFFSET_BINS

    space = DesignSpace(load_core("rvc_foam"), ["stack.length=0.01:0.08"])
    rng = np.random.default_rng(4)
    x = rng.standard_normal((3, 5000)) * 10.0 ** rng.integers(-44, 38, (3, 5000))
    x = x.astype(np.float32)
    x[:, :50] = 1.5
    x[1, 100:120] = np.nan
    x[2, 200:208] = [0.0, -0.0, np.inf, -np.inf, 1e-45, -1e-45, 3.4028235e38, 2.0**-126]
    outputs = ["gradient", "T_max", "heat_leak"]

    def state(lo, hi, other=None):
        r = Reducer(ReduceSpec(histogram=True), space, "sobol", outputs, [], "cpu", 1000)
        for k, a in enumerate(range(lo, hi, 1000)):
            r.add(k, a, None, wp.array(x[:, a : min(a + 1000, hi)], dtype=wp.float32, device="cpu"))
        if other is not None:
            r.merge(other)
        return r.state()

    whole, merged = state(0, 5000), state(0, 2000, state(2000, 5000))
    for j in range(3):
        ok = ~np.isnan(x[j])
        bins, counts = np.unique((ordered_keys(x[j, ok]) >> 12) + HIST_OFFSET_BINS, return_counts=True)
        for st in (whole, merged):
            np.testing.assert_array_equal(st["histograms"][j][0], bins)
            np.testing.assert_array_equal(st["histograms"][j][1], counts)
            assert st["nan"][j] == np.count_nonzero(~ok)


@wp.kernel
def _keys_of(x: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.int64)):
    i = wp.tid()
    out[i] = ordered_key(x[i])


def test_ordered_key_is_the_bit_pattern():
    """The device's ordering key, computed from the value, equals the float32 bit pattern
    as a signed magnitude (NumPy's view), over the whole range: subnormals, the smallest
    normal, +-0, +-inf, the largest finite, and each value's neighbours."""
    rng = np.random.default_rng(0)
    x = rng.standard_normal(20000) * 10.0 ** rng.integers(-45, 39, 20000)
    special = [0.0, -0.0, np.inf, -np.inf, 1.0, 2.0, 0.5, 3.4028235e38, 1e-45, -1e-45, 2.0**-126, 2.0**-149, 2.0**127]
    x = np.concatenate([x, special]).astype(np.float32)
    with np.errstate(over="ignore"):  # the largest finite's neighbour is inf: kept
        x = np.concatenate([x, np.nextafter(x, np.float32(np.inf)), np.nextafter(x, np.float32(-np.inf))])
    out = wp.zeros(len(x), dtype=wp.int64, device="cpu")
    wp.launch(_keys_of, dim=len(x), inputs=[wp.array(x, dtype=wp.float32, device="cpu"), out], device="cpu")
    np.testing.assert_array_equal(out.numpy(), ordered_keys(x))


def test_vectorized_two_objective_front_is_deb_front():
    """front_2d (the host's merge of front candidates) keeps the rows of rank 0 of Deb's
    sort, ties and duplicates included."""
    from tawarp.design.reductions import front_2d

    rng = np.random.default_rng(1)
    for G in (rng.random((400, 2)), np.round(rng.random((400, 2)) * 12) / 12):
        assert sorted(front_2d(G, np.arange(400)).tolist()) == np.flatnonzero(pareto_mask(G)).tolist()


def test_bad_reductions_are_named():
    with pytest.raises(ValueError, match="top=K"):
        parse_reduce("top=0")
    with pytest.raises(ValueError, match="'median'"):
        parse_reduce("best,median")
    space = DesignSpace(load_core("rvc_foam"), ["stack.length=0.01:0.08"])
    with pytest.raises(ValueError, match="--reduce"):
        sweep(space, "/nonexistent/x.nc", mode="sobol", n_samples=8, raw=False)


def test_command_line_reduced_sweep(tmp_path):
    """tawarp sweep --reduce ... --no-raw: the file holds the groups, the summary the best
    point, which is the top-1 of a raw sweep of the same points."""
    import json

    from tawarp.cli import main

    args = ["sweep", "rvc_foam", "--var", "stack.length=0.01:0.08", "--var", "heat_input=1:18", "--samples", "700"]
    out = tmp_path / "r.nc"
    assert main([*args, "--reduce", "best,top=3,pareto", "--no-raw", "-o", str(out), "--quiet", "--device", "cpu"]) == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["raw"] is False and meta["reductions"]["pareto_points"] == len(_group(out, "pareto").point)
    assert main([*args, "-o", str(tmp_path / "raw.nc"), "--quiet", "--device", "cpu"]) == 0
    with xr.open_dataset(tmp_path / "raw.nc", engine="h5netcdf") as ds:
        j = int(np.argmax(ds.gradient.values))
    assert meta["reductions"]["best"]["point"] == j
    assert main([*args, "--no-raw", "-o", str(tmp_path / "x.nc"), "--quiet", "--device", "cpu"]) == 2


def test_reductions_of_a_host_objective(tmp_path):
    """An output computed on the host (acoustic_loss, minimized) is reduced like a kernel
    column: its top points and histogram are NumPy's of the raw values."""
    space = DesignSpace(load_core("rvc_foam"), ["stack.length=0.01:0.08", "heat_input=1:18"])
    path = tmp_path / "a.nc"
    outputs = ["gradient", "acoustic_loss"]
    sweep(
        space,
        path,
        mode="sobol",
        n_samples=300,
        chunk=128,
        outputs=outputs,
        reduce="top=4,histogram",
        objectives=["acoustic_loss"],
    )
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        a = ds.acoustic_loss.values
    top, hist = _group(path, "top"), _group(path, "histogram")
    np.testing.assert_array_equal(top.point.values, np.lexsort((np.arange(len(a)), a.astype(np.float64)))[:4])
    ok = ~np.isnan(a)
    np.testing.assert_array_equal(
        hist.acoustic_loss_count.values, np.unique(ordered_keys(a[ok]) >> 12, return_counts=True)[1]
    )
