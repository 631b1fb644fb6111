"""The same kernels on the GPU: results equal the CPU's (skipped without a CUDA device)."""

import numpy as np
import pytest
import warp as wp

from tawarp.model.core import load_core
from tawarp.model.forward import steady_temperature, transfer_matrices

wp.init()
pytestmark = pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device: GPU tests skipped")


@pytest.mark.gpu
@pytest.mark.parametrize("name", ["ceramic", "mesh", "rvc_foam"])
def test_cuda_matches_cpu(name):
    # Same float64 arithmetic in the same order; only libm differences (sin, exp, sqrt
    # rounding) separate the devices: agreement to 1e-12 relative.
    core = load_core(name)
    f = np.linspace(30, 500, 7)
    q = [0.0, 9.0, 18.0]
    cpu = transfer_matrices(core, f, q, device="cpu").dimensionless()
    gpu = transfer_matrices(core, f, q, device="cuda").dimensionless()
    assert np.abs(gpu - cpu).max() / np.abs(cpu).max() < 1e-12
    x = np.linspace(0, core.positions()[-1], 50)
    np.testing.assert_allclose(
        steady_temperature(core, x, q, device="cuda")[0], steady_temperature(core, x, q, device="cpu")[0], rtol=1e-12
    )


@pytest.mark.gpu
@pytest.mark.parametrize("seed", [0, 1])
def test_cuda_onset_matches_cpu(seed):
    # The onset search (grid, Newton on (Re omega, Q), fallback) is host logic around the
    # same kernels: only libm rounding differs, and Q_onset is converged to 1e-10 relative,
    # so the devices agree to 1e-8 on random designs, and on which designs have an onset.
    from tawarp.model.onset import onset
    from tawarp.model.resonator import load_engine

    rng = np.random.default_rng(seed)
    n = 16
    params = {
        "engine.left_duct": rng.uniform(0.5, 0.9, n),
        "stack.length": rng.uniform(0.03, 0.07, n),
        "stack.porosity": rng.uniform(0.85, 0.93, n),
        "stack.h": rng.uniform(100, 200, n),
    }
    eng = load_engine("standing_wave")
    cpu = onset(eng, Q_max=100.0, params=params, device="cpu")
    gpu = onset(eng, Q_max=100.0, params=params, device="cuda")
    assert np.array_equal(np.isnan(cpu.Q_onset), np.isnan(gpu.Q_onset))
    ok = np.isfinite(cpu.Q_onset)
    assert ok.sum() >= n // 2
    np.testing.assert_allclose(gpu.Q_onset[ok], cpu.Q_onset[ok], rtol=1e-8)
    np.testing.assert_allclose(gpu.f_onset[ok], cpu.f_onset[ok], rtol=1e-9)


@pytest.mark.gpu
@pytest.mark.parametrize("heat", [0.0, 40.0])
def test_cuda_tangents_match_cpu(heat):
    # The tangent cascade (Engine.evaluate_tangents) is the same float64 code on both
    # devices: values agree to 1e-12 of their largest entry; the derivatives' seeds are
    # central differences with step 1e-5 of the neighbours' points, which divide the
    # devices' last-bit libm differences (exp, log, pow in the heat solve and gas laws)
    # by 2e-5: 1e-9.
    from tawarp.model.forward import Engine, ForwardSettings

    core = load_core("mesh")
    names = ["stack.porosity", "stack.pore_radius", "stack.h"]
    v = np.array([core.get(k) for k in names])
    rng = np.random.default_rng(3)
    groups = 5
    zs = []
    for _ in range(groups):
        c = v * rng.uniform(0.8, 1.2, 3)
        zs += [c] + [c * (1 + s * 1e-5 * e) for e in np.eye(3) for s in (1, -1)]
    table = np.vstack([np.full(len(zs), heat), np.array(zs).T])
    step = np.full((groups, 3), 1e-5)
    got = {}
    for dev in ("cpu", "cuda"):
        eng = Engine(core, np.linspace(30, 500, 9), names, ForwardSettings(cells=6, device=dev))
        got[dev] = [a.numpy() for a in eng.evaluate_tangents(table, wp.array(step, dtype=wp.float64, device=dev), 3)]
    for (c, g), tol in zip(zip(got["cpu"], got["cuda"]), (1e-12, 1e-9)):
        assert np.abs(g - c).max() < tol * np.abs(c).max()


@pytest.mark.gpu
def test_cuda_design_evaluations_match_cpu():
    # the design kernels (heat solve, metrics) and the device's column copies: float64
    # columns to 1e-12 of the CPU's, float32 columns the float64 ones rounded as NumPy does
    from tawarp.design.evaluate import Evaluator
    from tawarp.design.space import DesignSpace
    from tawarp.model.forward import ForwardSettings

    space = DesignSpace(load_core("rvc_foam"), ["stack.length=0.004:0.1", "heat_input=1:9", "stack.porosity=0.6:0.98"])
    table = space.varying_table(space.from_unit(np.random.default_rng(4).random((257, 3))))
    cpu, gpu = (Evaluator(space, settings=ForwardSettings(device=d)) for d in ("cpu", "cuda"))
    a, b = cpu.evaluate_table(table), gpu.evaluate_table(table)
    assert set(a) == set(b) and all(b[k].flags.c_contiguous for k in b)
    for k in a:
        np.testing.assert_allclose(b[k], a[k], rtol=1e-12, atol=1e-12 * np.abs(a[k]).max())
    f32 = gpu.metric_columns(gpu.evaluate_device(table), gpu.columns).numpy()
    assert np.array_equal(f32, np.array([b[k] for k in gpu.columns], dtype=np.float32))


@pytest.mark.gpu
@pytest.mark.parametrize("fields", [("tbt.h_convection", 3.0), ("tbt.wall_conductance", 2e-3)])
def test_cuda_temperature_dependent_heat_matches_cpu(fields):
    # the iterated heat solve (Kirchhoff cells, and the wall's second field) with its linear
    # cells in the segments without a temperature-dependent field: 1e-12 relative, as above
    core = load_core("ceramic").replace(**{"stack.conductivity_exponent": 0.5, "tbt.h_convection": 3.0})
    core = core.replace(**{fields[0]: fields[1]})
    if fields[0] == "tbt.wall_conductance":
        core = core.replace(**{"tbt.wall_resistance": 0.05})
    f = np.linspace(30, 500, 7)
    q = [0.0, 20.0, 40.0]
    cpu = transfer_matrices(core, f, q, device="cpu", cells=12).dimensionless()
    gpu = transfer_matrices(core, f, q, device="cuda", cells=12).dimensionless()
    assert np.abs(gpu - cpu).max() / np.abs(cpu).max() < 1e-12


def test_blocking_waits_are_set_on_warps_context_and_change_no_number():
    # in a fresh process (the flag stays with its context): Warp's context starts with CUDA's
    # own waits; wait_by_blocking makes it block, and the GPU then computes as the CPU does
    import subprocess
    import sys

    script = """
import numpy as np, warp as wp
from tawarp.distributed import wait_by_blocking, context_waits
from tawarp.model.core import load_core
from tawarp.model.forward import transfer_matrices
wp.config.quiet = True
wp.init()
before = context_waits("cuda")
assert wait_by_blocking("cuda")
core, f = load_core("ceramic"), np.linspace(50.0, 400.0, 5)
gpu = transfer_matrices(core, f, 40.0, device="cuda").dimensionless()
cpu = transfer_matrices(core, f, 40.0, device="cpu").dimensionless()
print(before, context_waits("cuda"), float(np.max(np.abs(gpu - cpu) / np.abs(cpu))))
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    before, after, error = out.stdout.split()[-3:]
    assert before != "blocking" and after == "blocking"
    assert float(error) < 1e-12
