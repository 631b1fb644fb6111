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
    np.testing.assert_allclose(steady_temperature(core, x, q, device="cuda")[0],
                               steady_temperature(core, x, q, device="cpu")[0], rtol=1e-12)
