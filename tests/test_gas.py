"""Gas constants (tawarp.model.gas) and the kernels' gas laws (kernels/gas.py) against
docs/physics.md's air laws and the ideal gas."""

import numpy as np
import pytest
import warp as wp

from tawarp.kernels import gas as kgas
from tawarp.model.gas import GASES, T_REF

T = np.array([250.0, 293.15, 600.0, 1000.0])


@wp.kernel
def _laws(
    g: wp.array(dtype=wp.float64), T: wp.array(dtype=wp.float64), p: wp.float64, out: wp.array2d(dtype=wp.float64)
):
    i = wp.tid()
    out[i, 0] = kgas.viscosity(g, T[i])
    out[i, 1] = kgas.conductivity(g, T[i])
    out[i, 2] = kgas.density(g, T[i], p)
    out[i, 3] = kgas.sound_speed_squared(g, T[i])


def kernel_laws(name: str, p: float = 101325.0) -> np.ndarray:
    g = wp.array(GASES[name].as_tuple(), dtype=wp.float64, device="cpu")
    out = wp.zeros((T.size, 4), dtype=wp.float64, device="cpu")
    wp.launch(
        _laws, dim=T.size, inputs=[g, wp.array(T, dtype=wp.float64, device="cpu"), wp.float64(p), out], device="cpu"
    )
    return out.numpy()


def test_air_follows_physics_md():
    mu, k, rho, c2 = kernel_laws("air").T
    np.testing.assert_allclose(mu, 1.716e-5 * (T / 273.15) ** 1.5 * 383.55 / (T + 110.4), rtol=1e-14)
    np.testing.assert_allclose(k, 0.0241 * (T / 273.15) ** 1.5 * 467.15 / (T + 194.0), rtol=1e-14)
    np.testing.assert_allclose(rho, 101325.0 / (287.05 * T), rtol=1e-15)
    np.testing.assert_allclose(np.sqrt(c2), np.sqrt(1.4 * 287.05 * T), rtol=1e-15)
    assert np.sqrt(c2[1]) == pytest.approx(343.2, abs=0.05)  # m/s at 20 C


@pytest.mark.parametrize("name", sorted(GASES))
def test_laws_match_the_constants(name):
    """X(T) = X0 (T/T0)^a (1 + S/T0)/(1 + S/T): X0 at T0, and the power law where S = 0."""
    g = GASES[name]
    mu, k, _, _ = kernel_laws(name).T
    law = lambda x0, a, s: x0 * (T / T_REF) ** a * (1 + s / T_REF) / (1 + s / T)  # noqa: E731
    np.testing.assert_allclose(mu, law(g.mu0, g.mu_exponent, g.mu_sutherland), rtol=1e-13)
    np.testing.assert_allclose(k, law(g.k0, g.k_exponent, g.k_sutherland), rtol=1e-13)
    assert g.cp == pytest.approx(g.gamma * g.R_gas / (g.gamma - 1), rel=0.02)  # ideal gas: cp = gamma R/(gamma-1)


def test_monatomic_gases_have_gamma_five_thirds():
    assert GASES["helium"].gamma == GASES["argon"].gamma == pytest.approx(5 / 3, rel=1e-15)
    # Prandtl number of a monatomic gas is close to 2/3 (kinetic theory)
    for name in ("helium", "argon"):
        g = GASES[name]
        assert g.mu0 * g.cp / g.k0 == pytest.approx(2 / 3, rel=0.03)
