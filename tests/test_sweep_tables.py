"""Sweep tables built on the device (tawarp.design.space.DeviceTable) against the host's
DesignSpace.varying_table, and whole sweeps against the host path, on the CPU.

Reference: the host path the sweep used before (NumPy grid indices or scipy Sobol points
scaled by DesignSpace.from_unit, DesignSpace.varying_table, Evaluator.evaluate_table).
Sobol points made on the device are scipy's bit for bit (integers times a power of 2).
Grid tables are copies of grid values and material rows: equal bit for bit. Unit points
are scaled by the same float64 operations; the device's exp (log-scale variables) and a
fused multiply-add on a GPU may round differently: 1e-12 relative."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from tawarp.design.evaluate import Evaluator
from tawarp.design.samplers import sobol_directions, sobol_unit
from tawarp.design.space import DesignSpace, DeviceTable, Variable
from tawarp.model.core import load_core

MATERIALS = ("ceramic", "mesh", "nicr_foam", "rvc_foam")
wp.init()
CUDA = pytest.param(
    "cuda",
    marks=[pytest.mark.gpu, pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device: GPU tests skipped")],
)


def _space(rng, grid: bool) -> DesignSpace:
    """A random design space over rvc_foam: a material (2-4 choices, random order), the
    stack length, the hot exchanger's length on a log scale, and, each with probability
    1/2, the stack porosity (overrides the material's), the stack position (the leading
    duct's length) and the heat input; variables in random order, grids of 2-4 values."""
    mats = tuple(rng.permutation(MATERIALS)[: rng.integers(2, 5)])
    specs = [("stack.length", 0.01, 0.08, False), ("hot_hx.length", 0.005, 0.03, True)]
    for extra in (
        ("stack.porosity", 0.6, 0.98, False),
        ("stack.position", 0.01, 0.05, False),
        ("heat_input", 1.0, 30.0, False),
    ):
        if rng.random() < 0.5:
            specs.append(extra)
    variables = [Variable("material", choices=mats)]
    for name, lo, hi, log in specs:
        count = int(rng.integers(2, 5))
        values = tuple((np.geomspace(lo, hi, count) if log else np.linspace(lo, hi, count)).tolist()) if grid else ()
        variables.append(Variable(name, lo, hi, log, values=values))
    order = rng.permutation(len(variables))
    return DesignSpace(load_core("rvc_foam"), [variables[j] for j in order], heat_input=float(rng.uniform(1, 20)))


def _grid_values(space: DesignSpace, lo: int, hi: int) -> dict:
    """The host's design values of grid points lo..hi-1 (C order over space.variables)."""
    shape = tuple(len(v.grid()) for v in space.variables)
    idx = np.unravel_index(np.arange(lo, hi, dtype=np.int64), shape)
    return {
        v.name: (idx[j].astype(np.int64) if v.categorical else np.asarray(v.values)[idx[j]])
        for j, v in enumerate(space.variables)
    }


def _unit_values(space: DesignSpace, u: np.ndarray) -> dict:
    """The host's design values of Sobol points u (continuous columns, then the material)."""
    values = space.from_unit(u[:, : len(space.continuous)])
    k = len(space.material.choices)
    values["material"] = np.minimum((u[:, -1] * k).astype(np.int64), k - 1)
    return values


@pytest.mark.parametrize("device", ["cpu", CUDA])
@pytest.mark.parametrize(("d", "seed", "first"), [(1, 0, 0), (5, 3, 12345), (7, 11, 2**27 + 5)])
def test_device_sobol_points_are_scipys(d, seed, first, device):
    # from the first point (the scrambled shift alone) to past 2^27 (Gray-code bits up to 27)
    from tawarp.kernels.design import sobol_points

    directions, shift, scale = sobol_directions(d, seed)
    u = wp.empty((300, d), dtype=wp.float64, device=device)
    wp.launch(
        sobol_points,
        dim=u.shape,
        device=device,
        inputs=[
            wp.int64(first),
            wp.array(directions, dtype=wp.int64, device=device),
            wp.array(shift, dtype=wp.int64, device=device),
            wp.float64(scale),
            u,
        ],
    )
    np.testing.assert_array_equal(u.numpy(), sobol_unit(300, d, seed, skip=first))


@pytest.mark.parametrize("device", ["cpu", CUDA])
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_device_tables_equal_the_host_tables(seed, device):
    rng = np.random.default_rng(seed)
    space = _space(rng, grid=True)
    tables = DeviceTable(space, device)
    n = int(np.prod([len(v.grid()) for v in space.variables]))
    lo = int(rng.integers(0, n // 2))
    hi = int(rng.integers(lo + 1, n + 1))
    np.testing.assert_array_equal(tables.grid(lo, hi).numpy(), space.varying_table(_grid_values(space, lo, hi)))
    skip = int(rng.integers(0, 1000))
    u = sobol_unit(257, len(tables.names), seed, skip=skip)
    table, values = tables.sobol(skip, skip + 257, seed)  # the points made on the device: scipy's, bit for bit
    host = _unit_values(space, u)
    np.testing.assert_allclose(table.numpy(), space.varying_table(host), rtol=1e-12, atol=0)
    for j, name in enumerate(tables.names):
        np.testing.assert_allclose(values.numpy()[j], host[name], rtol=1e-12, atol=0)
    np.testing.assert_array_equal(values.numpy()[tables.names.index("material")], host["material"])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sweeps_equal_the_host_path(tmp_path, seed):
    """Whole files, chunked so that blocks cut through the dimensions: grid outputs equal
    the host path's float32 values bit for bit; Sobol variables to 1e-12 and outputs to
    the float32 rounding (2^-23 relative: a 1e-16 difference before the cast can move a
    value across a float32 rounding boundary)."""
    import xarray as xr

    from tawarp.design.sweep import sweep

    rng = np.random.default_rng(100 + seed)
    space = _space(rng, grid=True)
    chunk = int(rng.integers(5, 40))
    sweep(space, tmp_path / "grid.nc", chunk=chunk)
    n = int(np.prod([len(v.grid()) for v in space.variables]))
    shape = tuple(len(v.grid()) for v in space.variables)
    host = Evaluator(space).evaluate_table(space.varying_table(_grid_values(space, 0, n)))
    with xr.open_dataset(tmp_path / "grid.nc", engine="h5netcdf") as ds:
        assert ds.gradient.dims == tuple(v.name for v in space.variables)
        for k in ("gradient", "T_max", "heat_leak", "T_hot"):
            assert ds[k].dtype == np.float32
            np.testing.assert_array_equal(ds[k].values, host[k].astype(np.float32).reshape(shape))

    space = _space(rng, grid=False)
    n = int(rng.integers(100, 400))
    sweep(space, tmp_path / "sobol.nc", mode="sobol", n_samples=n, chunk=int(rng.integers(30, 130)), seed=seed)
    u = sobol_unit(n, len(space.continuous) + 1, seed)
    values = _unit_values(space, u)
    host = Evaluator(space).evaluate_table(space.varying_table(values))
    with xr.open_dataset(tmp_path / "sobol.nc", engine="h5netcdf") as ds:
        assert ds["material"].dtype == np.int8
        np.testing.assert_array_equal(ds["material"].values, values["material"])
        for v in space.continuous:
            assert ds[v.name].dtype == np.float64
            np.testing.assert_allclose(ds[v.name].values, values[v.name], rtol=1e-12, atol=0)
        for k in ("gradient", "T_max", "heat_leak", "T_hot"):
            np.testing.assert_allclose(ds[k].values, host[k].astype(np.float32), rtol=2.0**-23, atol=0)


@pytest.mark.gpu
@pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device: GPU tests skipped")
@pytest.mark.parametrize("mode", ["grid", "sobol"])
def test_cuda_sweep_equals_the_cpu_sweep(tmp_path, mode):
    """The overlapped pipeline on CUDA (launch, write the previous chunk, fetch) writes the
    CPU's file: same variables and attributes; design values to 1e-12 (the device's exp
    and fused multiply-adds), outputs to one float32 step (2^-23 relative: the engines
    agree to 1e-12 before the cast)."""
    import xarray as xr

    from tawarp.design.sweep import sweep
    from tawarp.model.forward import ForwardSettings

    space = _space(np.random.default_rng(7), grid=mode == "grid")
    kw = dict(mode=mode, n_samples=1000, chunk=97, seed=5)
    sweep(space, tmp_path / "cpu.nc", settings=ForwardSettings(device="cpu"), **kw)
    sweep(space, tmp_path / "cuda.nc", settings=ForwardSettings(device="cuda"), **kw)
    with (
        xr.open_dataset(tmp_path / "cpu.nc", engine="h5netcdf") as a,
        xr.open_dataset(tmp_path / "cuda.nc", engine="h5netcdf") as b,
    ):
        np.testing.assert_equal(b.attrs, a.attrs)
        assert list(a.variables) == list(b.variables)
        for k in a.variables:
            assert a[k].dtype == b[k].dtype, k
            np.testing.assert_equal(b[k].attrs, a[k].attrs, err_msg=k)  # flag_values: an array
            if a[k].dtype == np.float32:
                np.testing.assert_allclose(b[k].values, a[k].values, rtol=2.0**-23, atol=0, err_msg=k)
            elif a[k].dtype == np.float64:
                np.testing.assert_allclose(b[k].values, a[k].values, rtol=1e-12, atol=0, err_msg=k)
            else:
                np.testing.assert_array_equal(b[k].values, a[k].values, err_msg=k)


def test_device_sampler_coordinates_invert_the_table():
    # the coordinates told to a sampler, made on the device from design values: the host's
    # unit_from_values to rounding (a log variable's logarithm: a few ulp), the material
    # index exact, a one-value range 0; and the unit points the values came from
    space = DesignSpace(
        load_core("rvc_foam"),
        ["material=ceramic,mesh,rvc_foam", "stack.length=0.01:0.08", "heat_input=1:18:log", "hot_hx.length=0.01:0.01"],
    )
    tables = DeviceTable(space, "cpu")
    u = np.random.default_rng(4).random((500, len(tables.names)))
    _, values = tables.unit(u)
    X = tables.coordinates(values).numpy()
    host = dict(zip(tables.names, values.numpy()))
    host["material"] = host["material"].astype(int)
    np.testing.assert_allclose(X, space.unit_from_values(host), rtol=0, atol=4e-16)
    np.testing.assert_allclose(X[:, :2], u[:, :2], rtol=0, atol=4e-16)
    assert not X[:, 2].any() and np.array_equal(X[:, 3], np.floor(u[:, 3] * 3))
    assert np.array_equal(tables.coordinates(values.numpy()).numpy(), X)  # from the host: the same kernel
