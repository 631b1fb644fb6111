"""The temperature-dependent heat solve with a thread per heat cell
(``ForwardSettings.cell_threads``, a GPU's default: :func:`tawarp.kernels.forward.heat_rows_kernel`
and :func:`tawarp.kernels.forward.picard_kernel`) against a thread per set iterating over its
cells (:func:`tawarp.kernels.heat.solve_heat_nonlinear`, for the wall as a field of its own
:func:`tawarp.kernels.heat.solve_heat_wall`): the same functions on the same
numbers, so on the CPU the excesses and T-matrices are the same bit for bit, whatever the
start, the iteration cap or the mix of sets in the batch (a GPU's compiler may fuse the
stored rows' products differently: rounding)."""

import numpy as np
import pytest
import warp as wp
from test_heat_warm_start import CORES, FREQS, batch

from tawarp.model.core import load_core
from tawarp.model.forward import PICARD_BURST, Engine, ForwardSettings


def contact_core():
    """The ceramic core with a contact resistance between stack and hot exchanger beside the
    buffer tube's convection: the Kirchhoff cells behind a contact."""
    return load_core("ceramic").replace(
        **{"tbt.h_convection": 3.0, "stack.radiative_conductivity": 0.05, "hot_hx.contact_resistance": 2e-4}
    )


ALL = {**CORES, "contact": lambda: (contact_core(), None)}


DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device"))]
#: how far a GPU's two paths may differ (its compiler may contract the stored rows'
#: products differently; on an H200 they were the same bit for bit): rounding
GPU_AGREE = 1e-12


def engines(core, names, device="cpu", **kw):
    """(a thread per set, a thread per cell) engines of ``core`` varying ``names``."""
    return tuple(
        Engine(core, FREQS, names, ForwardSettings(device=device, cells=12, cpu_threads=1, cell_threads=t, **kw))
        for t in (False, True)
    )


def same(a, b, device):
    """Bit for bit on the CPU, to :data:`GPU_AGREE` relative on a GPU."""
    if device == "cpu":
        return np.array_equal(a, b, equal_nan=True)
    return np.allclose(a, b, rtol=GPU_AGREE, atol=GPU_AGREE * np.nanmax(np.abs(b)), equal_nan=True)


def mixed(table):
    """``table`` and beside it: its sets without heat input, and its first set with every
    temperature-dependent field it varies off (a set the heat kernel solves at once)."""
    cold = table.copy()
    cold[0] = 0.0
    return np.concatenate([table, cold], axis=1)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", sorted(ALL))
def test_a_thread_per_cell_gives_the_excesses_of_a_thread_per_set(name, device):
    core, values = ALL[name]()
    eng, table = batch(core, values)
    table = mixed(table)
    per_set, per_cell = engines(core, eng.names, device)
    assert per_cell.cell_threads and not per_set.cell_threads
    a = [x.numpy() for x in per_set.evaluate(table)]
    b = [x.numpy() for x in per_cell.evaluate(table)]
    for x, y in zip(a, b):
        assert same(x, y, device)
    # from a warm start (the point's converged excess) too
    start = np.repeat(a[2][:1], table.shape[1], axis=0)
    start[table[0] == 0.0] = 0.0
    warm = [e.heat(table, start)[1].numpy() for e in (per_set, per_cell)]
    assert same(*warm, device)


@pytest.mark.parametrize("name", ["contact", "wall"])
@pytest.mark.parametrize("most", [1, 2, PICARD_BURST, PICARD_BURST + 1])
def test_a_thread_per_cell_stops_at_the_iteration_cap_of_a_thread_per_set(most, name):
    # a cap below the iterations the sets need stops each set after as many solves in both
    # (the cap across a burst's end too): the same unconverged excess
    core, values = ALL[name]()
    eng, table = batch(core, values)
    per_set, per_cell = engines(core, eng.names, picard_iterations=most)
    full = Engine(core, FREQS, eng.names, ForwardSettings(device="cpu", cells=12, cpu_threads=1))
    theta = [e.heat(table)[1].numpy() for e in (per_set, per_cell, full)]
    assert np.array_equal(theta[0], theta[1])
    assert not np.allclose(theta[0], theta[2], rtol=1e-9, atol=0.0)


def test_a_linear_core_never_takes_a_thread_per_cell():
    # without a temperature-dependent field the solve is one sweep: nothing to iterate
    core = load_core("ceramic")
    eng = Engine(core, FREQS, ["tbt.h"], ForwardSettings(device="cpu", cell_threads=True))
    assert not eng.nonlinear and not eng.cell_threads


@pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device")
def test_a_captured_heat_solve_iterates_in_the_heat_kernel():
    # a CUDA graph being captured (a design search's generation) cannot wait on the count of
    # sets still iterating: under capture the engine leaves the iterations to the heat kernel,
    # and the graph's replay gives the excesses of a thread per set
    core, values = ALL["contact"]()
    eng, table = batch(core, values)
    per_set, per_cell = engines(core, eng.names, "cuda")
    expected = per_set.heat(table)[1].numpy()
    out = per_cell.heat_buffers(table.shape[1])
    varying = wp.array(table, dtype=wp.float64, device="cuda")
    with wp.ScopedCapture("cuda") as capture:
        per_cell.heat(varying, out=out)
    out[1].zero_()
    wp.capture_launch(capture.graph)
    assert same(out[1].numpy(), expected, "cuda")
