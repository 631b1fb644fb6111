"""Plane waves in the measurement tube: the wavenumber and the characteristic impedance
from the gas's state and the tube's cross-section, in tawarp's ``exp(-i omega t)``
convention (docs/physics.md).

Air (:data:`tawarp.tube.setup.HUMID_AIR`) is humid air: the zero-frequency sound speed
is Cramer's (1993, J. Acoust. Soc. Am. 93, 2510, eq. 15 and Table III, 400 ppm CO2)
with the water-vapour mole fraction from the saturation vapour pressure and the
enhancement factor of Davis (1992, Metrologia 29, 67, the CIPM-81/91 equation), which
also gives the compressibility ``Z`` of the density ``rho = p M / (Z R T)`` with the
molar mass of the mixture ``M = M_a - x_w (M_a - M_w)``. The other gases are tawarp's
ideal dry gases (:mod:`tawarp.model.gas`): ``c = sqrt(gamma R T)``, ``rho = p / (R T)``.

Wall losses are Kirchhoff's wide-tube law (Kirchhoff 1868; Pierce, *Acoustics*, 1989,
sec. 10-5): to first order in the boundary-layer thickness,

    k  = (w / c) (1 + (1 + i) eps),      z0 = rho c (1 + r (1 + i) eps),
    eps = f_loss (1 + (gamma - 1) / sqrt(Pr)) sqrt(nu / (2 w)) / a,
    r   = (1 - (gamma - 1) / sqrt(Pr)) / (1 + (gamma - 1) / sqrt(Pr)),

with ``a = 2 S / P`` (the radius of a circular tube; in a wide tube of any section each
wall element loses as a plane wall does, so the losses per unit length go with the wetted
perimeter ``P`` over the area ``S``; corners add terms of the order of ``eps^2``) and ``f_loss`` = 1 for Kirchhoff's tube (the empty-tube self-calibration fits
it). ``z0`` is the specific characteristic impedance ``p / u`` [Pa s/m] of a plane wave.
"""

from __future__ import annotations

import math

import numpy as np

from dataclasses import dataclass

from ..model.gas import GASES

#: The gas name of air with water vapour (Cramer 1993); the other names are tawarp's dry gases.
HUMID_AIR = "air"


@dataclass(frozen=True)
class Tube:
    """Cross-section of the tube: ``circular`` of ``width`` = diameter [m], or
    ``rectangular`` of ``width`` x ``height`` [m]."""

    shape: str
    width: float
    height: float

    @property
    def area(self) -> float:
        """Cross-section S [m^2]."""
        return math.pi * self.width**2 / 4 if self.shape == "circular" else self.width * self.height

    @property
    def perimeter(self) -> float:
        """Wetted perimeter P [m]."""
        return math.pi * self.width if self.shape == "circular" else 2 * (self.width + self.height)

    @property
    def wall_radius(self) -> float:
        """``2 S / P`` [m]: the radius of a circular tube, ``w h / (w + h)`` of a
        rectangular one; the length that scales its boundary-layer losses."""
        return 2 * self.area / self.perimeter

    @property
    def largest(self) -> float:
        """The diameter, or the largest side [m] (the first cross mode's length)."""
        return max(self.width, self.height)


@dataclass(frozen=True)
class Gas:
    """The tube's gas: ``name`` (``air``, with ``humidity`` [%] relative, or a dry tawarp
    gas), ``temperature`` [K], ``pressure`` [Pa]."""

    name: str = HUMID_AIR
    temperature: float = 293.15
    pressure: float = 101325.0
    humidity: float = 0.0


R_UNIVERSAL = 8.314462618  # J/(mol K)
M_WATER = 0.01801528  # kg/mol
CO2_FRACTION = 400e-6  # mole fraction of CO2 in Cramer's formula
# Cramer (1993), Table III: c0 = a0 + a1 t + a2 t^2 + (a3 + a4 t + a5 t^2) xw + (a6 + a7 t + a8 t^2) p
#   + (a9 + a10 t + a11 t^2) xc + a12 xw^2 + a13 p^2 + a14 xc^2 + a15 xw p xc  (t in deg C, p in Pa)
_CRAMER = (
    331.5024, 0.603055, -0.000528, 51.471935, 0.1495874, -0.000782,
    -1.82e-7, 3.73e-8, -2.93e-10, -85.20931, -0.228525, 5.91e-5,
    -2.835149, -2.15e-13, 29.179762, 0.000486,
)  # fmt: skip
# Davis (1992): saturation vapour pressure, enhancement factor, compressibility
_PSV = (1.2378847e-5, -1.9121316e-2, 33.93711047, -6.3431645e3)
_ENHANCEMENT = (1.00062, 3.14e-8, 5.6e-7)
_COMPRESSIBILITY = (1.58123e-6, -2.9331e-8, 1.1043e-10, 5.707e-6, -2.051e-8, 1.9898e-4, -2.376e-6, 1.83e-11, -0.765e-8)


def water_fraction(gas: Gas) -> float:
    """Mole fraction of water vapour in air of relative humidity ``gas.humidity`` [%]
    (Davis 1992: ``x_w = h f(p, t) p_sv(T) / p``)."""
    T, p, t = gas.temperature, gas.pressure, gas.temperature - 273.15
    a, b, c, d = _PSV
    psv = math.exp(a * T * T + b * T + c + d / T)
    f = _ENHANCEMENT[0] + _ENHANCEMENT[1] * p + _ENHANCEMENT[2] * t * t
    return gas.humidity / 100.0 * f * psv / p


def sound_speed(gas: Gas) -> float:
    """Zero-frequency adiabatic sound speed [m/s] (module doc)."""
    if gas.name != HUMID_AIR:
        g = GASES[gas.name]
        return math.sqrt(g.gamma * g.R_gas * gas.temperature)
    a = _CRAMER
    t, p, xw, xc = gas.temperature - 273.15, gas.pressure, water_fraction(gas), CO2_FRACTION
    return (
        a[0] + a[1] * t + a[2] * t * t
        + (a[3] + a[4] * t + a[5] * t * t) * xw
        + (a[6] + a[7] * t + a[8] * t * t) * p
        + (a[9] + a[10] * t + a[11] * t * t) * xc
        + a[12] * xw * xw + a[13] * p * p + a[14] * xc * xc + a[15] * xw * p * xc
    )  # fmt: skip


def density(gas: Gas) -> float:
    """Density [kg/m^3] (module doc)."""
    g = GASES[gas.name]
    if gas.name != HUMID_AIR:
        return gas.pressure / (g.R_gas * gas.temperature)
    T, p, t = gas.temperature, gas.pressure, gas.temperature - 273.15
    xw = water_fraction(gas)
    a0, a1, a2, b0, b1, c0, c1, d, e = _COMPRESSIBILITY
    Z = (
        1
        - p / T * (a0 + a1 * t + a2 * t * t + (b0 + b1 * t) * xw + (c0 + c1 * t) * xw * xw)
        + (p / T) ** 2 * (d + e * xw * xw)
    )
    M_air = R_UNIVERSAL / g.R_gas
    return p * (M_air - xw * (M_air - M_WATER)) / (Z * R_UNIVERSAL * T)


def plane_waves(freqs, gas: Gas, tube: Tube, loss: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Wavenumber ``k`` [1/m] and specific characteristic impedance ``z0`` [Pa s/m], both
    (nf,) complex in ``exp(-i omega t)``, of plane waves at ``freqs`` [Hz] in ``tube``
    filled with ``gas``; ``loss`` scales Kirchhoff's wall losses (module doc)."""
    from ..model.layer import gas_transport

    f = np.asarray(freqs, dtype=float)
    g = GASES[gas.name]
    c, rho = sound_speed(gas), density(gas)
    mu, lam = (float(v[0]) for v in gas_transport(gas.name, gas.temperature))
    q = (g.gamma - 1) / math.sqrt(mu * g.cp / lam)
    w = 2 * np.pi * f
    with np.errstate(divide="ignore", invalid="ignore"):
        eps = loss * (1 + q) * np.sqrt(mu / rho / (2 * w)) / tube.wall_radius
    eps = np.where(w > 0, eps, 0.0)
    k = w / c * (1 + (1 + 1j) * eps)
    z0 = rho * c * (1 + (1 - q) / (1 + q) * (1 + 1j) * eps)
    return k, z0
