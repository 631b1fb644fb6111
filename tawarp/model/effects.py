"""The library of effects the paper's model lacks (issue #4, PHYSICS.md "Effects the
paper's model lacks").

Every effect is an optional term of the *same* forward model: a few named parameters
(``SEGMENT.FIELD`` or ``gas.*``) that are off at their start value, evaluated in the same
kernels. A :class:`Param` may set several model parameters to one value (``targets``):
the wall conductance of all thermal segments; or map its value to several (``expand``).
Only the ambient heat exchangers change the core's structure: :func:`with_ambient_exchangers`
inserts two non-thermal porous segments (taking their length from the end ducts, so every
plane stays where it was), and the effect's one parameter is their *presence* s in [0, 1]
(:func:`ambient_presence`): at s = 0 they are exactly empty duct (porosity 1, pore radius =
tube radius), so the base model is nested in the augmented one like for every other effect.

Libraries: :func:`tmatrix_library` (plane offsets, T_cold, p_mean, thermal radius ratio,
T-dependent conductivity, radiation, convection in the buffer tube, wall conduction,
ambient exchangers) and :func:`impedance_library` (thermal radius ratio, viscous shape
factor, thickness offset, limp frame, T_cold, p_mean).

The kernel-level fields are documented at :data:`tawarp.model.fields.EFFECT_OFF`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .core import Core, Segment
from .fields import field as field_spec


@dataclass(frozen=True)
class Param:
    """One fitted parameter. ``targets``: the model parameters it sets (all to the same
    value); ``start``: its start (for an effect: its "off") value; the fit variable is
    ``x = ln(v / start)`` when ``log`` (positive quantities) else ``x = (v - start) / scale``;
    ``lower``/``upper``: physical bounds."""

    label: str
    targets: tuple[str, ...]
    start: float
    scale: float = 1.0
    lower: float = -math.inf
    upper: float = math.inf
    log: bool = False
    #: optional map value -> {model parameter: values} (default: every target = value)
    expand: Callable | None = field(default=None, compare=False)

    def assign(self, v, out: dict) -> None:
        """Write the model parameters of value(s) ``v`` into ``out``."""
        if self.expand is not None:
            out.update(self.expand(np.asarray(v, dtype=float)))
        else:
            for t in self.targets:
                out[t] = v

    def value(self, x):
        x = np.asarray(x, dtype=float)
        return self.start * np.exp(x) if self.log else self.start + self.scale * x

    def x_of(self, v):
        v = np.asarray(v, dtype=float)
        return np.log(v / self.start) if self.log else (v - self.start) / self.scale

    def bounds_x(self) -> tuple[float, float]:
        lo, hi = self.lower, self.upper
        if self.log:
            return (math.log(lo / self.start) if lo > 0 else -np.inf, math.log(hi / self.start) if math.isfinite(hi) else np.inf)
        return ((lo - self.start) / self.scale, (hi - self.start) / self.scale)

    def with_start(self, v: float) -> "Param":
        return dataclasses.replace(self, start=float(v))


def base_params(core: Core, names) -> list[Param]:
    """:class:`Param` of each model parameter ``names`` starting at the core's value, its
    scaling and bounds from :mod:`tawarp.model.fields`: log fields fitted as ln(v/start)
    within their ``fit_range`` and 1e-3..1e3 times the start, the others as
    (v - start)/``scale`` within ``fit_range``."""
    out = []
    for name in names:
        v = core.get(name)
        f = field_spec(name)
        lo, hi = f.fit_range
        if f.log and v > 0:
            out.append(Param(name, (name,), v, 1.0, max(lo, v * 1e-3), min(hi, v * 1e3), log=True))
        else:
            out.append(Param(name, (name,), v, f.scale, lo, hi))
    return out


@dataclass(frozen=True)
class Effect:
    """A candidate effect: ``params`` added to the base fit; ``transform`` changes the core's
    structure (None for a field of the existing segments)."""

    name: str
    description: str
    params: tuple[Param, ...]
    transform: Callable[[Core], Core] | None = field(default=None, compare=False)


def with_ambient_exchangers(core: Core, length: float = 0.005, porosity: float = 0.7, pore_radius: float = 0.5e-3,
                            tortuosity: float = 1.0) -> Core:
    """``core`` with two ambient heat exchangers: non-thermal porous segments
    ``ambient_hx_left`` (after the first segment, a duct) and ``ambient_hx_right`` (before
    the last), each of ``length`` [m] taken from that duct so that the planes do not move."""
    segs = list(core.segments)
    if len(segs) < 3 or segs[0].kind != "duct" or segs[-1].kind != "duct":
        raise ValueError(f"{core.source}: ambient exchangers need ducts as first and last segments")
    if not (segs[0].length > length and segs[-1].length > length):
        raise ValueError(f"{core.source}: end ducts shorter than the exchangers ({length} m)")
    hx = dict(kind="porous", length=length, porosity=porosity, pore_radius=pore_radius, tortuosity=tortuosity)
    left = dataclasses.replace(segs[0], length=segs[0].length - length)
    right = dataclasses.replace(segs[-1], length=segs[-1].length - length)
    out = [left, Segment("ambient_hx_left", **hx)] + segs[1:-1] + [Segment("ambient_hx_right", **hx), right]
    return Core(tuple(out), core.gas, core.radius, core.source)


def stack_and_heater(core: Core) -> tuple[str | None, str | None]:
    thermal = [core.segments[i] for i in core.thermal_indices]
    heater = next((s.name for s in thermal if s.heater), None)
    stack = next((s.name for s in thermal if s.is_porous and not s.heater), None)
    return stack, heater


def tmatrix_library(core: Core) -> list[Effect]:
    """Candidate effects for core T-matrix data (PHYSICS.md's list)."""
    segs = core.segments
    stack, heater = stack_and_heater(core)
    thermal = [core.segments[i] for i in core.thermal_indices]
    buffer = next((s.name for s in thermal if not s.is_porous), None)
    lib = []
    if segs[0].kind == "duct" and segs[-1].kind == "duct":
        lib.append(Effect("plane_offsets", "measurement planes off by millimetres (end duct lengths)",
                          (Param(f"{segs[0].name}.length", (f"{segs[0].name}.length",), segs[0].length, 1e-3, 1e-4, 10.0),
                           Param(f"{segs[-1].name}.length", (f"{segs[-1].name}.length",), segs[-1].length, 1e-3, 1e-4, 10.0))))
    lib.append(Effect("T_cold", "cold-end (room) temperature not as assumed",
                      (Param("gas.T_cold", ("gas.T_cold",), core.gas.T_cold, 1.0, 150.0, 500.0),)))
    lib.append(Effect("p_mean", "static pressure not as assumed",
                      (Param("gas.p_mean", ("gas.p_mean",), core.gas.p_mean, 1e3, 1e3, 1e8),)))
    if stack:
        lib.append(Effect("thermal_radius_ratio", "separate thermal and viscous pore radii in the stack (Lambda'/Lambda)",
                          (Param(f"{stack}.thermal_radius_ratio", (f"{stack}.thermal_radius_ratio",), 1.0, 0.2, 0.1, 10.0),)))
        lib.append(Effect("conductivity_T", "temperature-dependent stack conductivity lam (T/T_cold)^b",
                          (Param(f"{stack}.conductivity_exponent", (f"{stack}.conductivity_exponent",), 0.0, 0.5, -3.0, 3.0),)))
        lib.append(Effect("radiation", "radiative conductivity in the porous stack (prop. T^3)",
                          (Param(f"{stack}.radiative_conductivity", (f"{stack}.radiative_conductivity",), 0.0, 0.1, 0.0, 100.0),)))
    if buffer:
        lib.append(Effect("convection", "natural convection in the buffer tube, h = h_a + h_c theta^(1/4)",
                          (Param(f"{buffer}.h_convection", (f"{buffer}.h_convection",), 0.0, 1.0, 0.0, 1e3),)))
    if thermal:
        lib.append(Effect("wall_conduction", "axial heat conduction in the tube wall (all thermal parts)",
                          (Param("wall_conductance", tuple(f"{s.name}.wall_conductance" for s in thermal), 0.0, 0.1, 0.0, 1e3),)))
    if segs[0].kind == "duct" and segs[-1].kind == "duct" and min(segs[0].length, segs[-1].length) > AMBIENT_HX["length"]:
        lib.append(ambient_exchanger_effect(core))
    return lib


#: Ambient exchangers of the library: 5 mm of porosity 0.7, pore radius 0.5 mm at full presence.
AMBIENT_HX = {"length": 0.005, "porosity": 0.7, "pore_radius": 0.5e-3}


def ambient_presence(core: Core, s, hx: dict = AMBIENT_HX) -> dict:
    """Parameters of both ambient exchangers at presence ``s`` in [0, 1]: porosity
    ``1 - s (1 - phi_hx)``, pore radius ``R (r_hx/R)^s``. At s = 0 the exchangers are exactly
    empty duct (porosity 1, pore radius = tube radius R, tortuosity 1): the effect is nested."""
    s = np.asarray(s, dtype=float)
    phi = 1.0 - s * (1.0 - hx["porosity"])
    r = core.radius * (hx["pore_radius"] / core.radius) ** s
    return {f"ambient_hx_{side}.{f}": v for side in ("left", "right") for f, v in (("porosity", phi), ("pore_radius", r))}


def ambient_exchanger_effect(core: Core, hx: dict = AMBIENT_HX) -> Effect:
    """The ambient exchangers as an effect: the structure of :func:`with_ambient_exchangers`
    with their presence s (0 = absent) as the one parameter."""
    return Effect("ambient_exchangers",
                  f"acoustic presence of the two ambient heat exchangers ({hx['length'] * 1e3:g} mm, porosity "
                  f"{hx['porosity']:g}, pore radius {hx['pore_radius'] * 1e3:g} mm at presence 1)",
                  (Param("ambient_hx.presence", ("ambient_hx_left.porosity", "ambient_hx_right.porosity",
                                                 "ambient_hx_left.pore_radius", "ambient_hx_right.pore_radius"),
                         0.0, 0.2, 0.0, 1.0, expand=lambda s: ambient_presence(core, s, hx)),),
                  transform=lambda c: with_ambient_exchangers(c, hx["length"], 1.0, c.radius))


def impedance_library(core: Core) -> list[Effect]:
    """Candidate effects for the surface impedance of a rigid-backed layer."""
    return [
        Effect("thermal_radius_ratio", "separate thermal radius Lambda' = ratio Lambda (JCA)",
               (Param("layer.thermal_radius_ratio", ("layer.thermal_radius_ratio",), 1.0, 0.2, 0.1, 10.0),)),
        Effect("viscous_shape_factor", "viscous length Lambda = r/s apart from the resistivity radius r (shape factor)",
               (Param("layer.viscous_shape_factor", ("layer.viscous_shape_factor",), 1.0, 0.2, 0.2, 5.0),)),
        Effect("thickness_offset", "layer thicknesses off by a common offset (measurement plane)",
               (Param("layer.length_offset", ("layer.length_offset",), 0.0, 1e-3, -0.01, 0.01),)),
        Effect("limp_frame", "non-rigid (limp) frame moving with the air; parameter 1/(frame bulk density)",
               (Param("layer.frame_mobility", ("layer.frame_mobility",), 0.0, 0.01, 0.0, 10.0),)),
        # a room's temperature and pressure are known to +-15 K and +-5 %
        Effect("T_cold", "ambient temperature not as assumed (within 15 K)",
               (Param("gas.T_cold", ("gas.T_cold",), core.gas.T_cold, 1.0, core.gas.T_cold - 15, core.gas.T_cold + 15),)),
        Effect("p_mean", "static pressure not as assumed (within 5 %)",
               (Param("gas.p_mean", ("gas.p_mean",), core.gas.p_mean, 1e3, 0.95 * core.gas.p_mean, 1.05 * core.gas.p_mean),)),
    ]
