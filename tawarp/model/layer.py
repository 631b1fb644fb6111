"""Surface impedance of a rigid-backed porous layer from the same forward engine.

A layer of thickness L is a one-segment core (one porous, non-thermal segment named
``layer``) at uniform temperature ``T_ambient`` and pressure ``p_ambient``; its two-port
``T`` (front face -> back face) with a rigid backing ``U(L) = 0`` gives the input impedance
``Z = p(0)/U(0) = -Tuu/Tup`` and the specific surface impedance normalized by the air's
characteristic impedance ``Zs = Z S / (rho0 c0)`` (exp(-iwt), as the loaders give it).
The tube radius of the one-segment core is arbitrary (``LAYER_TUBE_RADIUS``): ``S``
cancels.

Circular pores have one radius for viscous and thermal effects: the Johnson-Champoux-
Allard lengths are ``Lambda = Lambda' = r`` and the flow resistivity is
``sigma = 8 mu q^2 / (phi r^2)``. The effect ``layer.thermal_radius_ratio`` gives f_k its
own radius ``Lambda' = ratio * r``; ``layer.viscous_shape_factor`` s sets ``Lambda = r/s``
at the same sigma.
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from ..kernels import lm as klm
from .core import Core, Gas, Segment
from .forward import resolve_device
from .gas import GASES


#: Radius [m] of the one-segment core of a layer (any value: S cancels in Zs).
LAYER_TUBE_RADIUS = 0.05
#: Parameters of the base layer model.
LAYER_BASE = ("layer.porosity", "layer.pore_radius", "layer.tortuosity")


def layer_core(
    thickness: float,
    porosity: float = 0.95,
    pore_radius: float = 1e-4,
    tortuosity: float = 1.0,
    T_ambient: float = 293.15,
    p_ambient: float = 101325.0,
    gas: str = "air",
) -> Core:
    """A core of one porous, non-thermal segment ``layer`` of ``thickness`` [m]."""
    seg = Segment(
        "layer", "porous", float(thickness), porosity=porosity, pore_radius=pore_radius, tortuosity=tortuosity
    )
    return Core((seg,), Gas(gas, float(p_ambient), float(T_ambient)), LAYER_TUBE_RADIUS, "<layer>")


def characteristic_impedance(core: Core) -> float:
    """rho0 c0 [Pa s/m] of the gas at the core's T_cold and p_mean."""
    g = GASES[core.gas.name]
    T, p = core.gas.T_cold, core.gas.p_mean
    return p / (g.R_gas * T) * math.sqrt(g.gamma * g.R_gas * T)


def surface_impedance_from_T(T: np.ndarray, core: Core) -> np.ndarray:
    """``Zs / (rho0 c0) = -Tuu/Tup S / (rho0 c0)`` of T-matrices (..., 2, 2)."""
    return -T[..., 1, 1] / T[..., 1, 0] * core.area / characteristic_impedance(core)


def jca_equivalent(values: dict, core: Core) -> dict:
    """The circular-pore parameters in Johnson-Champoux-Allard terms: phi, alpha_inf = q^2,
    Lambda = r / s (s the viscous shape factor, 1 for circular pores), Lambda' = ratio r,
    sigma = 8 mu q^2 / (phi r^2) [N s/m^4] (mu at T_cold)."""
    phi = values.get("layer.porosity", core.segments[0].porosity)
    r = values.get("layer.pore_radius", core.segments[0].pore_radius)
    q = values.get("layer.tortuosity", core.segments[0].tortuosity)
    ratio = values.get("layer.thermal_radius_ratio", 1.0)
    shape = values.get("layer.viscous_shape_factor", 1.0)
    mu = float(gas_transport(core.gas.name, core.gas.T_cold)[0][0])
    return {
        "phi": phi,
        "alpha_inf": q * q,
        "Lambda": r / shape,
        "Lambda_prime": ratio * r,
        "sigma": 8 * mu * q * q / (phi * r * r),
    }


def gas_transport(gas: str, T) -> tuple[np.ndarray, np.ndarray]:
    """Viscosity mu [Pa s] and conductivity k [W/(m K)] of ``gas`` at temperatures ``T``
    [K], from the kernels' gas laws (:mod:`tawarp.kernels.gas`)."""
    T = np.atleast_1d(np.asarray(T, dtype=float))
    dev = resolve_device("cpu")
    mu = wp.empty(T.size, dtype=wp.float64, device=dev)
    k = wp.empty(T.size, dtype=wp.float64, device=dev)
    wp.launch(
        klm.gas_transport,
        dim=T.size,
        device=dev,
        inputs=[
            wp.array(GASES[gas].as_tuple(), dtype=wp.float64, device=dev),
            wp.array(T.ravel(), dtype=wp.float64, device=dev),
            mu,
            k,
        ],
    )
    return mu.numpy().reshape(T.shape), k.numpy().reshape(T.shape)
