"""The layer model's helpers (tawarp.model.layer): the gas laws read from the kernels and
the Johnson-Champoux-Allard equivalents of the circular-pore parameters."""

import numpy as np

from tawarp import reference
from tawarp.model.gas import GASES
from tawarp.model.layer import gas_transport, jca_equivalent, layer_core


def test_gas_transport_is_the_reference_law():
    T = np.array([200.0, 293.15, 600.0, 1000.0])
    for gas in GASES:
        mu, k = gas_transport(gas, T)
        ref = reference.gas_properties(gas, T, 101325.0)
        assert np.allclose(mu, ref.mu, rtol=1e-14, atol=0) and np.allclose(k, ref.k, rtol=1e-14, atol=0)


def test_jca_equivalent_closed_form():
    # circular pores: Lambda = r / s, Lambda' = ratio r, alpha_inf = q^2, sigma = 8 mu q^2/(phi r^2)
    core = layer_core(0.05, T_ambient=295.0)
    v = {
        "layer.porosity": 0.96,
        "layer.pore_radius": 1.2e-4,
        "layer.tortuosity": 1.2,
        "layer.thermal_radius_ratio": 1.7,
        "layer.viscous_shape_factor": 1.25,
    }
    out = jca_equivalent(v, core)
    mu = float(reference.gas_properties("air", 295.0, core.gas.p_mean).mu)
    assert out["phi"] == 0.96 and abs(out["alpha_inf"] - 1.44) < 1e-15
    assert abs(out["Lambda"] - 1.2e-4 / 1.25) < 1e-18 and abs(out["Lambda_prime"] - 1.7 * 1.2e-4) < 1e-18
    assert abs(out["sigma"] - 8 * mu * 1.44 / (0.96 * 1.2e-4**2)) <= 1e-13 * out["sigma"]
