"""The library of effects the paper's model lacks (docs/physics.md, "Effects the
paper's model lacks").

Every effect is an optional term of the *same* forward model: a few named parameters
(``SEGMENT.FIELD`` or ``gas.*``) that are off at their start value, evaluated in the same
kernels. A :class:`Param` may set several model parameters to one value (``targets``):
the wall conductance of all thermal segments; or map its value to several (``expand``).
Two kinds of effect change the core's structure. :func:`with_ambient_exchangers` inserts
two non-thermal porous segments (taking their length from the end ducts, so every plane
stays where it was), and the effect's parameter is their length: at 0 the base model bit
for bit, so it is nested in the augmented one like every other effect. The stack's pore
shape (:func:`pore_geometry_effects`) is not nested: the swap has no parameter of its own.

Libraries: :func:`tmatrix_library` (plane offsets, T_cold, p_mean, thermal radius ratio,
T-dependent conductivity, radiation, the stack's pore shape, convection in the buffer tube,
wall conduction, ambient exchangers, a contact resistance between stack and hot exchanger, a
porosity gradient, a bypass gap) and :func:`impedance_library` (thermal radius ratio, viscous shape
factor, thickness offset, limp frame, elastic frame, T_cold, p_mean).

The kernel-level fields are documented at :data:`tawarp.model.fields.EFFECT_OFF`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .biot import FRAME_POISSON_RATIO
from .core import Core, Segment
from .gas import GASES
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
            return (
                math.log(lo / self.start) if lo > 0 else -np.inf,
                math.log(hi / self.start) if math.isfinite(hi) else np.inf,
            )
        return ((lo - self.start) / self.scale, (hi - self.start) / self.scale)

    def with_start(self, v: float) -> "Param":
        return dataclasses.replace(self, start=float(v))


def base_params(core: Core, names, ties: dict | None = None) -> list[Param]:
    """:class:`Param` of each model parameter ``names`` starting at the core's value, its
    scaling and bounds from :mod:`tawarp.model.fields`: log fields fitted as ln(v/start)
    within their ``fit_range`` and 1e-3..1e3 times the start, the others as
    (v - start)/``scale`` within ``fit_range``. ``ties`` {name: [model parameters]}: those
    set to the value of ``name`` too (:func:`same_material_ties`)."""
    out = []
    ties = ties or {}
    for name in names:
        v = core.get(name)
        f = field_spec(name)
        lo, hi = f.fit_range
        targets = (name, *ties.get(name, ()))
        if f.log and v > 0:
            out.append(Param(name, targets, v, 1.0, max(lo, v * 1e-3), min(hi, v * 1e3), log=True))
        else:
            out.append(Param(name, targets, v, f.scale, lo, hi))
    return out


@dataclass(frozen=True)
class Effect:
    """A candidate effect: ``params`` added to the base fit; ``transform`` changes the core's
    structure (None for a field of the existing segments); ``typical`` {param label: value}
    a physically typical size of the effect (the validation study injects it there; the
    params' ``start`` values are the effect's "off"); ``starts`` further {param label:
    value} points a refit should also start from, for an effect whose fit from "off" stays
    in a local minimum at its bound (the elastic frame: a frame resonance inside the band
    is not reached by descending from an infinitely stiff frame); ``mechanism``: the physical
    degree of freedom the effect models, shared by alternative models of it (the frame's
    motion: :data:`FRAME_MOTION`): a model holds at most one effect per mechanism."""

    name: str
    description: str
    params: tuple[Param, ...]
    transform: Callable[[Core], Core] | None = field(default=None, compare=False)
    typical: dict = field(default_factory=dict, compare=False)
    starts: tuple = field(default=(), compare=False)
    mechanism: str | None = field(default=None, compare=False)

    def model_values(self, values: dict | None = None) -> dict:
        """Model parameters {name: value} of the effect at ``values`` {param label: value}
        (labels left out: their start, i.e. off; default: :attr:`typical`)."""
        values = self.typical if values is None else values
        out: dict = {}
        for par in self.params:
            par.assign(values.get(par.label, par.start), out)
        return out


def with_ambient_exchangers(
    core: Core, length: float = 1e-3, porosity: float = 0.8, pore_radius: float = 1e-3, tortuosity: float = 1.0
) -> Core:
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


#: The fields that make a porous segment's material: a core file that gives the stack and
#: the hot exchanger the same values of all of them describes one material in both.
MATERIAL_FIELDS = ("porosity", "pore_radius", "tortuosity", "solid_conductivity")


def same_material_ties(core: Core, fields=("porosity", "pore_radius", "tortuosity")) -> dict[str, list[str]]:
    """{stack field: [the hot exchanger's field]} of ``fields`` where the core file gives
    the stack and a porous hot exchanger one material (every :data:`MATERIAL_FIELDS`
    equal, as the paper's ceramic core): a fit of the stack's geometry moves the
    exchanger's with it, as the paper's first step does; else {}."""
    stack, heater = stack_and_heater(core)
    if stack is None or heater is None:
        return {}
    s, h = core.segment(stack), core.segment(heater)
    if not h.is_porous or any(getattr(s, f) != getattr(h, f) for f in MATERIAL_FIELDS):
        return {}
    return {f"{stack}.{f}": [f"{heater}.{f}"] for f in fields}


#: Wall of the typical wall-conduction effect: 1 mm of stainless steel, 15 W/(m K).
WALL_THICKNESS, WALL_CONDUCTIVITY = 1e-3, 15.0
#: Typical open-cell foam: Rosseland conductivity at T_cold [W/(m K)] that gives 0.11 W/(m K)
#: at 600 K (16 sigma_SB T^3 / (3 beta), extinction beta = 4.4 (1 - phi)/d_p ~ 570 1/m for a
#: NiCr foam of porosity 0.92 and pore diameter 0.62 mm, scaled by (293/600)^3).
TYPICAL_RADIATIVE_CONDUCTIVITY = 0.0134
#: Laminar natural convection about a horizontal cylinder, h = 1.32 (dT/D)^(1/4) W/(m^2 K)
#: (D the tube diameter): h_convection = 1.32 D^(-1/4) [W/(m^2 K^1.25)].
CONVECTION_COEFFICIENT = 1.32
#: Typical thermal contact of an ambient exchanger [W/(m^2 K)]: gas-side h ~ Nu k/(2 r) ~ 50 W/(m^2 K)
#: in 1 mm pores over the wetted area 2 phi l / r ~ 16 per section area (10 mm, porosity 0.8):
#: about 1e3, tenfold the conductance lam_s / L of a stack, so the end is nearly held at T_cold.
TYPICAL_END_CONDUCTANCE = 1e3
#: Typical thermal contact resistance of a stack pressed against its hot exchanger [m^2 K/W]:
#: Incropera, DeWitt, Bergman & Lavine, Fundamentals of Heat and Mass Transfer (6th ed.,
#: Wiley 2007), Table 3.1: 0.6-25e-4 for metallic interfaces in vacuum at 1e5-1e7 Pa of
#: contact pressure, 2.75e-4 for aluminium at 1e5 Pa with air in the gaps. A ceramic or foam
#: stack held by a light axial load against a metal exchanger sits in that band.
TYPICAL_CONTACT_RESISTANCE = 3e-4
#: Typical porosity gradient g along a stack (phi(x) = phi (1 + g (x/L - 1/2))): a wound or
#: stacked-screen stack compressed unevenly, a foam's density varying along its rise, 10 %
#: end to end.
TYPICAL_POROSITY_GRADIENT = 0.1
#: Parts of a graded stack (:func:`graded_parts`): the porosity piecewise constant, the
#: 2-port's error second order in the parts' size (2.5 % of a g = 0.2 gradient's effect).
GRADED_PARTS = 8
#: Typical annular bypass gap between a stack and its tube [m]: a ceramic or foam stack cut,
#: or a screen stack punched or wound, 0.1-0.5 mm under the tube's diameter (a stack sliding
#: into its tube needs that clearance; a stack pressed or glued in has none).
TYPICAL_BYPASS_GAP = 2e-4
#: The widest of those clearances [m], a further start of the gap's refits: the slit's flow
#: grows as g^3 and its section share as g, so the misfit is far from quadratic in g, and a
#: descent from below a wide gap (from "off" or the typical size) can stop at a small g where
#: the share alone compensates the base fit's error (an RVC foam with a 0.39 mm gap: 0.14 mm
#: at 26 noise floors); from above, the flow term leads it down to the gap.
WIDE_BYPASS_GAP = 5e-4
#: Names of the 2-port calibration effect (not kernel fields: the T-matrix kind applies them).
CALIBRATION_GAIN, CALIBRATION_PHASE = "calibration.gain", "calibration.phase"


def _field_effect(name: str, description: str, targets, typical: float, label: str | None = None) -> Effect:
    """An effect of one table field set to one value in all ``targets`` (start: its neutral
    value; scale and bounds: the fields table)."""
    targets = tuple(targets)
    f = field_spec(targets[0])
    label = label or targets[0]
    lo, hi = f.fit_range
    return Effect(name, description, (Param(label, targets, f.neutral, f.scale, lo, hi),), typical={label: typical})


def plane_offsets_effect(core: Core) -> Effect:
    """Both end ducts' lengths free: the measurement planes off by millimetres (typical: 2 mm
    further out on each side)."""
    a, b = core.segments[0], core.segments[-1]
    return Effect(
        "plane_offsets",
        "measurement planes off by millimetres (end duct lengths)",
        (
            Param(f"{a.name}.length", (f"{a.name}.length",), a.length, 1e-3, 1e-4, 10.0),
            Param(f"{b.name}.length", (f"{b.name}.length",), b.length, 1e-3, 1e-4, 10.0),
        ),
        typical={f"{a.name}.length": a.length + 2e-3, f"{b.name}.length": b.length + 2e-3},
    )


def ambient_effects(
    core: Core, T_bounds: tuple[float, float] | None = None, p_bounds: tuple[float, float] | None = None
) -> list[Effect]:
    """T_cold and p_mean not as assumed (typical: +5 K, -2 %); bounds default to the fields
    table's fit range."""
    T0, p0 = core.gas.T_cold, core.gas.p_mean
    Tlo, Thi = T_bounds or field_spec("gas.T_cold").fit_range
    plo, phi = p_bounds or field_spec("gas.p_mean").fit_range
    return [
        Effect(
            "T_cold",
            "cold-end (room) temperature not as assumed",
            (Param("gas.T_cold", ("gas.T_cold",), T0, 1.0, Tlo, Thi),),
            typical={"gas.T_cold": T0 + 5.0},
        ),
        Effect(
            "p_mean",
            "static pressure not as assumed",
            (Param("gas.p_mean", ("gas.p_mean",), p0, 1e3, plo, phi),),
            typical={"gas.p_mean": 0.98 * p0},
        ),
    ]


def calibration_effect() -> Effect:
    """A 4-microphone calibration error: a constant complex gain ``g = gain exp(i phase)``
    of the downstream microphone pair relative to the upstream one. It multiplies the
    downstream wave amplitudes (A2, B2) by g, so the scattering matrix ``[B1, A2] = S [A1, B2]``
    becomes ``S11, S12/g, g S21, S22`` (the transmissions), and the T-matrix
    ``(p, U)(x6) = T (p, U)(x1)``, whose left side is measured downstream, becomes
    ``g T``: all four coefficients (:func:`tawarp.measure.files.scattering_to_transfer`:
    T = M W M^-1 with the wave transfer W scaled by g). Off at gain 1, phase 0; typical
    1.02 at 2 degrees."""
    return Effect(
        "calibration",
        "downstream/upstream microphone calibration off by a constant gain and phase (measured T = g T)",
        (
            Param(CALIBRATION_GAIN, (CALIBRATION_GAIN,), 1.0, 0.01, 0.5, 2.0),
            Param(CALIBRATION_PHASE, (CALIBRATION_PHASE,), 0.0, 0.01, -0.5, 0.5),
        ),
        typical={CALIBRATION_GAIN: 1.02, CALIBRATION_PHASE: math.radians(2.0)},
    )


def porous_layer_effects(
    names: list[str], frame: bool = True, thermal: list[str] | None = None, stiffness: str | None = None
) -> list[Effect]:
    """Effects of the porous segments ``names`` (all together): a separate thermal length
    (typical Lambda'/Lambda = 1.8; of the segments ``thermal``, default ``names``: wire
    screens have none), a viscous shape factor (typical 1.5), a limp frame (typical frame
    bulk density 30 kg/m^3; one model of the frame's motion, :data:`FRAME_MOTION`), which
    sets the elastic frame's field ``stiffness`` (a wave speed or modulus whose start is not
    0) to 0."""
    thermal = names if thermal is None else thermal
    out = (
        [
            _field_effect(
                "thermal_radius_ratio",
                "separate thermal and viscous pore radii (JCA Lambda'/Lambda)",
                [f"{n}.thermal_radius_ratio" for n in thermal],
                1.8,
            )
        ]
        if thermal
        else []
    )
    out.append(
        _field_effect(
            "viscous_shape_factor",
            "viscous length Lambda = r/s apart from the resistivity radius r (shape factor)",
            [f"{n}.viscous_shape_factor" for n in names],
            1.5,
        )
    )
    if frame:
        limp = _field_effect(
            "limp_frame",
            "non-rigid (limp) frame moving with the air; parameter 1/(frame bulk density)",
            [f"{n}.frame_mobility" for n in names],
            1.0 / TYPICAL_FRAME["rho_1"],
        )
        if stiffness is not None:
            # a limp frame is an elastic frame without stiffness: 0 in its own sets, whatever
            # an elastic frame fitted beside it in one batch starts from
            (par,) = limp.params
            zero = [f"{n}.{stiffness}" for n in names]

            def without_stiffness(v, targets=par.targets):
                return {**{t: v for t in targets}, **{t: 0.0 * v for t in zero}}

            limp = dataclasses.replace(
                limp, params=(dataclasses.replace(par, targets=par.targets + tuple(zero), expand=without_stiffness),)
            )
        # a limp frame's descent from "off" can stay there: starts at a light and a typical
        # frame, none beyond the typical 1/30 m^3/kg (the starts also set the prior's width,
        # tawarp.model.priors.effect_priors)
        starts = tuple({limp.params[0].label: 1.0 / rho} for rho in (100.0, TYPICAL_FRAME["rho_1"]))
        out.append(dataclasses.replace(limp, mechanism=FRAME_MOTION, starts=starts))
    return out


def with_pore_model(core: Core, segment: str, pore_model: str, aspect_ratio: float = 1.0) -> Core:
    """``core`` with the pores of ``segment`` of ``pore_model`` (rectangular channels of
    ``aspect_ratio``), every value kept."""
    segs = tuple(
        dataclasses.replace(s, pore_model=pore_model, aspect_ratio=aspect_ratio) if s.name == segment else s
        for s in core.segments
    )
    return Core(segs, core.gas, core.radius, core.source, core.pinned, core.priors)


def pore_geometry_effects(core: Core, stack: str) -> list[Effect]:
    """The stack's pores of another shape than the core file's circular ones, as structural
    alternatives without parameters of their own (the base fit's porosity, pore radius and
    tortuosity are refitted in each; :func:`tawarp.loop.evidence.effect_columns` takes the
    residual change of the swap at the base solution): square channels (Stinson; half the
    side a = r keeps the hydraulic radius r/2 and the flow resistivity within 12 %) and
    parallel plates (half-spacing y0 = r/2 has the circular pore's hydraulic radius: the fit
    moves the pore radius by that factor 2, 1.7 sd of its default prior). Their prior is the
    model prior alone, as likely as any other single effect. Left out: pins (the pore radius
    becomes the pin radius, another length) and wire screens (correlations fitted on
    porosities 0.60-0.77 with a friction factor of their own: a stack is screens by its
    construction, which the core file states)."""
    if core.segment(stack).pore_model != "circular":
        return []
    return [
        Effect(
            "square_channels",
            "the stack's pores are square channels (pore_radius half the side), not circular",
            (),
            transform=lambda c: with_pore_model(c, stack, "rectangular", 1.0),
        ),
        Effect(
            "plate_pores",
            "the stack is parallel plates (pore_radius half the spacing), not circular pores",
            (),
            transform=lambda c: with_pore_model(c, stack, "plates"),
        ),
    ]


def tmatrix_library(core: Core) -> list[Effect]:
    """Candidate effects for 2-port (T-matrix or scattering) data of ``core``: plane
    offsets, T_cold, p_mean, the calibration gain; for a heated core (docs/physics.md's list)
    the stack's thermal radius ratio, T-dependent conductivity, radiation, its pores as
    square channels or plates (:func:`pore_geometry_effects`), convection in
    the buffer tube, wall conduction, the ambient exchangers' acoustics and their thermal
    role, a thermal contact resistance between stack and hot exchanger
    (:func:`contact_effect`), a porosity gradient along the stack and an annular bypass
    gap around it (:func:`bypass_gap_effect`); for a passive core (no thermal stack) the porous-layer effects of its porous
    segments, an elastic frame when it has one porous segment, and T_cold and p_mean
    within room conditions (+-15 K, +-5 %)."""
    segs = core.segments
    stack, heater = stack_and_heater(core)
    thermal = [core.segments[i] for i in core.thermal_indices]
    buffer = next((s.name for s in thermal if not s.is_porous), None)
    ducts = segs[0].kind == "duct" and segs[-1].kind == "duct" and len(segs) >= 2
    lib = [plane_offsets_effect(core)] if ducts else []
    T0, p0 = core.gas.T_cold, core.gas.p_mean
    # a passive sample is measured at room conditions, known to +-15 K and +-5 % (as a layer's)
    lib += ambient_effects(core) if stack else ambient_effects(core, (T0 - 15, T0 + 15), (0.95 * p0, 1.05 * p0))
    lib.append(calibration_effect())
    # wire screens have no thermal radius of their own (their heat-transfer correlation is on
    # the hydraulic radius, and A takes their Prandtl number from the two radii)
    if stack and core.segment(stack).pore_model != "screens":
        lib.append(
            _field_effect(
                "thermal_radius_ratio",
                "separate thermal and viscous pore radii in the stack (Lambda'/Lambda)",
                [f"{stack}.thermal_radius_ratio"],
                1.8,
            )
        )
    if stack:
        # stainless steel: 14.9 W/(m K) at 300 K, 19 at 600 K: b = ln(19/14.9)/ln 2 = 0.35
        lib.append(
            _field_effect(
                "conductivity_T",
                "temperature-dependent stack conductivity lam (T/T_cold)^b",
                [f"{stack}.conductivity_exponent"],
                0.35,
            )
        )
        lib.append(
            _field_effect(
                "radiation",
                "radiative conductivity in the porous stack (prop. T^3)",
                [f"{stack}.radiative_conductivity"],
                TYPICAL_RADIATIVE_CONDUCTIVITY,
            )
        )
        lib += pore_geometry_effects(core, stack)
    else:
        porous = [s.name for s in segs if s.is_porous]
        if porous:
            lib += porous_layer_effects(
                porous, thermal=[s.name for s in segs if s.is_porous and s.pore_model != "screens"]
            )
        if len(porous) == 1:
            lib.append(two_port_frame_effect(porous[0]))
    if buffer:
        lib.append(
            _field_effect(
                "convection",
                "natural convection in the buffer tube, h = h_a + h_c theta^(1/4)",
                [f"{buffer}.h_convection"],
                CONVECTION_COEFFICIENT * (2 * core.radius) ** -0.25,
            )
        )
    if thermal:
        lib.append(wall_conduction_effect(core))
    if ducts and stack and min(segs[0].length, segs[-1].length) > AMBIENT_HX_MIN_DUCT:
        lib.append(ambient_exchanger_effect(core))
    if stack:
        ends = dict.fromkeys((thermal[0].name, thermal[-1].name))  # the heat model's two ends
        lib.append(
            _field_effect(
                "ambient_exchanger_thermal",
                "ambient exchangers drawing heat H theta at both ends "
                "of the heat model toward T_cold (H = 0: adiabatic)",
                [f"{n}.end_conductance" for n in ends],
                TYPICAL_END_CONDUCTANCE,
                label="ambient_hx.end_conductance",
            )
        )
        contact = contact_effect(core)
        if contact is not None:
            lib.append(contact)
        lib.append(porosity_gradient_effect(stack))
        lib.append(bypass_gap_effect(core, stack))
    return lib


#: Laminar Nusselt number h_w D / k_gas of the gas in a thermal duct (the buffer tube)
#: against its wall: fully developed pipe flow has 3.66 at a wall of uniform temperature and
#: 4.36 at a uniform wall flux (Incropera et al., Fundamentals of Heat and Mass Transfer, 6th
#: ed., Eqs. 8.55 and 8.53); the mean of the two.
WALL_NUSSELT = 4.0
#: Gas film [m] between a porous part (stack, exchanger) and its tube wall: a part that slides
#: into its tube touches the wall at points across a clearance of about 0.1 mm (the bypass
#: gap's order, :data:`TYPICAL_BYPASS_GAP`), h_w ~ k_gas / film ~ 260 W/(m^2 K) in air.
WALL_FILM = 1e-4


def wall_conduction_effect(core: Core) -> Effect:
    """Axial conduction in the tube wall along the thermal parts, the wall a temperature
    field of its own (:mod:`tawarp.kernels.heat`, :func:`~tawarp.kernels.heat.solve_heat_wall`):
    its conductance ``wall_conductance`` lam_w A_w / S [W/(m K)] in every thermal segment
    (the switch: off at 0, bit for bit; typical a 1 mm steel wall) and the lateral
    resistance ``wall_resistance`` R_w = 1/h_w [m^2 K/W] between the wall and the porous
    parts (one value for all of them, labelled by the first) and between the wall and the gas
    of the thermal ducts (the buffer tube; labelled by the first). The resistances are log
    Params whose start is the physical value: the ducts' laminar conduction
    D / (:data:`WALL_NUSSELT` k_gas), the porous parts' gas film :data:`WALL_FILM` / k_gas
    (k_gas at T_cold), each with the default prior of the field
    (:data:`tawarp.model.priors.DEFAULT_PRIORS`, a factor 2 per sd): shape parameters
    of the effect that ``wall_conductance`` switches on. The buffer tube's coupling length
    sqrt(lam_w R / (2 h_w)) (about 4 cm, as long as the tube) is why the wall is a field and
    not an added conductivity (its R_w -> 0 limit); the porous parts' (5-10 mm at
    h_w ~ 100-500) is that of the hot exchanger, so theirs is finite as well."""
    thermal = [core.segments[i] for i in core.thermal_indices]
    R = core.radius
    wall = WALL_CONDUCTIVITY * ((R + WALL_THICKNESS) ** 2 - R * R) / (R * R)
    k_gas = float(GASES[core.gas.name].transport(core.gas.T_cold)[1])
    f = field_spec("wall_conductance")
    params = [
        Param(
            "wall_conductance", tuple(f"{s.name}.wall_conductance" for s in thermal), f.neutral, f.scale, *f.fit_range
        )
    ]
    for names, start in (
        ([s.name for s in thermal if s.is_porous], WALL_FILM / k_gas),
        ([s.name for s in thermal if not s.is_porous], 2.0 * R / (WALL_NUSSELT * k_gas)),
    ):
        if names:
            targets = tuple(f"{n}.wall_resistance" for n in names)
            params.append(Param(targets[0], targets, start, 1.0, start * 1e-3, start * 1e3, log=True))
    return Effect(
        "wall_conduction",
        "axial heat conduction in the tube wall (all thermal parts), the wall a temperature field coupled "
        "laterally by h_w = 1/wall_resistance",
        tuple(params),
        # the couplings sit at their physical values: the typical wall is the 1 mm steel one
        typical={"wall_conductance": wall, **{p.label: p.start for p in params[1:]}},
    )


def bypass_gap_effect(core: Core, stack: str) -> Effect:
    """An annular gap of width g [m] between ``stack`` and the tube wall
    (``STACK.bypass_gap``, a field of the kernels): a parallel-plate slit of spacing g and
    section share x = g (2R - g)/R^2 beside the pores (which keep phi (1 - x) of the
    section), at the stack's temperature, joined to them at the stack's two end planes,
    where their admittance matrices add (:func:`tawarp.kernels.acoustics.parallel2`); its
    gas replaces that share of the stack's solid in the heat model. Off at 0, exactly (no
    gap: the same arithmetic as without the field). Typical :data:`TYPICAL_BYPASS_GAP`,
    refitted from :data:`WIDE_BYPASS_GAP` too (its prior spans that: :func:`tawarp.model.priors.effect_priors`);
    bounded by the fields table's fit range and half the tube radius (a wider gap is a
    missing stack, not a clearance)."""
    label = f"{stack}.bypass_gap"
    f = field_spec(label)
    lo, hi = f.fit_range
    return Effect(
        "bypass_gap",
        "an annular gap between the stack and the tube wall (a slit of width g beside the pores)",
        (Param(label, (label,), 0.0, f.scale, lo, min(hi, 0.5 * core.radius)),),
        typical={label: TYPICAL_BYPASS_GAP},
        starts=({label: WIDE_BYPASS_GAP},),
    )


def porosity_gradient_effect(stack: str) -> Effect:
    """The porosity of ``stack`` varying linearly along it, phi(x) = phi (1 + g (x/L - 1/2))
    (``STACK.porosity_gradient`` g, a host field: :func:`graded_parts` splits the stack into
    :data:`GRADED_PARTS` parts of their own porosity, pore radius and tortuosity held, in the
    acoustics and in the heat model's conductivity phi lam_gas + (1 - phi) lam_solid). Off at
    g = 0, exactly: the stack is then not split. Typical :data:`TYPICAL_POROSITY_GRADIENT`."""
    label = f"{stack}.porosity_gradient"
    f = field_spec(label)
    return Effect(
        "porosity_gradient",
        "the stack's porosity varying linearly along it (g end to end)",
        (Param(label, (label,), 0.0, f.scale, *f.fit_range),),
        transform=graded_structure,
        typical={label: TYPICAL_POROSITY_GRADIENT},
    )


def graded_structure(core: Core) -> Core:
    """The structure of a graded stack's models: the core as it stands, its stack split
    into parts by the T-matrix kind per set's gradient (:func:`graded_parts`). Declared a
    structure so that its fits launch apart: a launch on the split stack costs 4x the
    stack's cells, which the models without the gradient then do not pay. A model holds at
    most one structure, so the gradient is not combined with the pore shapes or the
    ambient exchangers' acoustics."""
    return core


def _log_mean(a, b):
    """(b - a) / ln(b / a), a where a = b: the harmonic mean of a quantity linear between a
    and b, as a x / ln(1 + x) with x = (b - a)/a (the same x above and below: no cancellation
    when b is close to a)."""
    a, b = np.broadcast_arrays(np.asarray(a, dtype=float), np.asarray(b, dtype=float))
    x = (b - a) / a
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(x == 0.0, a, a * x / np.log1p(x))


def graded_parts(core: Core, values: dict, n: int, parts: int = GRADED_PARTS) -> tuple[Core, dict]:
    """``core`` and the model values ``values`` {name: scalar or (n,)} of ``n`` sets with every
    segment ``SEG`` whose ``SEG.porosity_gradient`` g is in ``values`` and not 0 in every set
    split into ``parts`` parts ``SEG_part1`` ..., each with every value of SEG (the contact
    resistance at its start on the first part only) but three:

    - length: the parts' ends step the law's conductivity phi lam_gas + (1 - phi) lam_s
      (linear in x, gas at T_cold) geometrically from one end to the other: where it is
      small the temperature turns within a short length, and the parts are short there (a
      ceramic stack of porosity 0.9 with g = 0.2 conducts ten times less at its open end);
    - porosity: the law's value at the part's middle (clipped to [1e-3, 0.999]);
    - solid conductivity: such that the part's conductivity is the harmonic mean of the
      law's over the part (its thermal resistance exact).

    Against the independent reference's graded stack (tawarp.reference_effects) the
    T-matrix's error falls as parts^-2: 4 % of the effect with 6 parts, 1 % with 12
    (tests/test_effects_library.py). The gradient keys are removed; where g is 0 in every
    set the segment stays whole (the model bit for bit)."""
    values = dict(values)
    grads = {
        k.rpartition(".")[0]: np.broadcast_to(np.asarray(values.pop(k), dtype=float), (n,))
        for k in [k for k in values if k.endswith(".porosity_gradient")]
    }
    split = []
    for seg in core.segments:
        g = grads.get(seg.name)
        if g is None or not np.any(g):
            continue
        split.append(seg.name)
        if seg.heater or not seg.is_porous:
            raise ValueError(f"{core.source}: a porosity gradient needs a porous segment that is not the heater")
        own = {k.partition(".")[2]: values.pop(k) for k in [k for k in values if k.partition(".")[0] == seg.name]}
        phi = np.asarray(own.pop("porosity", seg.porosity), dtype=float)
        length = np.asarray(own.pop("length", seg.length), dtype=float)
        lam_s = np.asarray(own.pop("solid_conductivity", seg.solid_conductivity), dtype=float)
        k_gas = GASES[core.gas.name].transport(values.get("gas.T_cold", core.gas.T_cold))[1]

        def porosity(t):
            return np.clip(phi * (1.0 + g * (t - 0.5)), 1e-3, 0.999)

        def lam(t):
            return porosity(t) * k_gas + (1.0 - porosity(t)) * lam_s

        # part ends t_j (x/L): the conductivity in geometric steps from one end to the other
        # (where it is small the profile turns within a short length: the parts are short);
        # every part's values at once, (parts + 1 or parts, n): a part at a time cost a launch
        # of a graded fit more host work than its table
        log_ratio = np.log(lam(1.0) / lam(0.0))
        small = np.abs(log_ratio) < 1e-9
        safe = np.where(small, 1.0, log_ratio)
        k = np.arange(parts + 1)[:, None]
        ends = np.where(small, k / parts, np.expm1(safe * k / parts) / np.expm1(safe))
        phis = porosity(0.5 * (ends[:-1] + ends[1:]))
        at_ends = lam(ends)
        lams = _log_mean(at_ends[:-1], at_ends[1:])
        lam_s_parts = (lams - phis * k_gas) / (1.0 - phis)
        lengths = length * (ends[1:] - ends[:-1])
        for j in range(parts):
            name = f"{seg.name}_part{j + 1}"
            first = j == 0
            values[f"{name}.porosity"] = phis[j]
            values[f"{name}.solid_conductivity"] = lam_s_parts[j]
            values[f"{name}.length"] = lengths[j]
            for fld, v in own.items():
                values[f"{name}.{fld}"] = v if (first or fld != "contact_resistance") else 0.0 * np.asarray(v)
    if not split:
        return core, values
    return split_core(core, tuple(split), parts), values


@functools.lru_cache(maxsize=64)
def split_core(core: Core, names: tuple[str, ...], parts: int) -> Core:
    """``core`` with each segment of ``names`` split into ``parts`` parts ``SEG_part1`` ...
    of equal length, each with every value of SEG (the contact resistance on the first part
    only): :func:`graded_parts`' structure, whose own values set the parts' lengths and
    fields. Kept per (core, names, parts): a fit's every launch asks for the same one, and a
    core's checks cost more than its launch's host work."""
    segs = []
    for seg in core.segments:
        if seg.name not in names:
            segs.append(seg)
            continue
        for j in range(parts):
            segs.append(
                dataclasses.replace(
                    seg,
                    name=f"{seg.name}_part{j + 1}",
                    length=seg.length / parts,
                    contact_resistance=seg.contact_resistance * (j == 0),
                )
            )
    return Core(tuple(segs), core.gas, core.radius, core.source, core.pinned, core.priors)


def graded_cells(cells: dict, core: Core) -> dict:
    """Fixed Magnus cells {segment: count} (:class:`tawarp.model.forward.ForwardSettings`)
    for ``core`` split by :func:`graded_parts`: a part ``SEG_partJ`` gets a quarter of the
    count of the whole ``SEG`` (at least 1), twice the stack's cells over its 8 parts: the
    parts are an eighth of its length on average, but the short ones sit where its
    conductivity is smallest and the heat decay rate sqrt(2 h/(R lam)) largest (3x the whole
    stack's at g = 0.2 on the ceramic). The split stack's Magnus error then stays below the
    whole stack's at its own count (tests/test_effects_library.py): each further cell costs
    every heated column of a graded fit, the loop's most expensive ones."""
    out = {}
    for seg in core.segments:
        whole = seg.name.rpartition("_part")[0]
        if seg.name in cells:
            out[seg.name] = cells[seg.name]
        elif whole in cells:
            out[seg.name] = max(1, -(-int(cells[whole]) // 4))
    return out


def contact_effect(core: Core) -> Effect | None:
    """A thermal contact resistance R_c [m^2 K/W] between the stack and the hot exchanger
    (``contact_resistance`` of whichever of the two comes second in the heat model, at its
    start, :mod:`tawarp.kernels.heat`): the temperature jumps by R_c times the heat flux
    density crossing the interface. Off at 0 (perfect contact, bit for bit); typical
    :data:`TYPICAL_CONTACT_RESISTANCE` (Incropera et al., Table 3.1). None when the two are
    not adjacent thermal segments."""
    stack, heater = stack_and_heater(core)
    names = [core.segments[i].name for i in core.thermal_indices]
    if stack is None or heater is None or abs(names.index(stack) - names.index(heater)) != 1:
        return None
    second = names[max(names.index(stack), names.index(heater))]
    return _field_effect(
        "contact_resistance",
        "thermal contact resistance between the stack and the hot exchanger (temperature jump R_c q)",
        [f"{second}.contact_resistance"],
        TYPICAL_CONTACT_RESISTANCE,
    )


#: Typical ambient exchangers: 10 mm long, porosity 0.8, pore radius 1 mm (a copper fin
#: or screen exchanger); end ducts must be longer than this to hold one.
AMBIENT_HX = {"length": 0.010, "porosity": 0.8, "pore_radius": 1e-3}
AMBIENT_HX_MIN_DUCT = 2e-3


def ambient_exchanger_effect(core: Core) -> Effect:
    """The ambient exchangers' acoustics as an effect, their geometry free: two non-thermal
    porous segments (:func:`with_ambient_exchangers`) of length ``ambient_hx.length`` taken
    from the end ducts (the planes stay), porosity ``ambient_hx.porosity`` and pore radius
    ``ambient_hx.pore_radius``, the same on both sides. Off at length 0, exactly: a segment
    of zero length is the identity matrix (its propagation exponential is exp(0)) and the
    ducts keep their lengths, so the T-matrix is the base model's bit for bit whatever the
    porosity and pore radius (which the data then do not determine)."""
    a, b = core.segments[0], core.segments[-1]
    La, Lb = a.length, b.length

    def lengths(v):
        return {
            "ambient_hx_left.length": v,
            "ambient_hx_right.length": v,
            f"{a.name}.length": La - v,
            f"{b.name}.length": Lb - v,
        }

    upper = min(La, Lb) - 1e-4
    return Effect(
        "ambient_exchangers",
        "acoustics of the two ambient heat exchangers (length, porosity, pore radius free; off at length 0)",
        (
            Param(
                "ambient_hx.length",
                ("ambient_hx_left.length", "ambient_hx_right.length", f"{a.name}.length", f"{b.name}.length"),
                0.0,
                1e-3,
                0.0,
                upper,
                expand=lengths,
            ),
            Param(
                "ambient_hx.porosity",
                ("ambient_hx_left.porosity", "ambient_hx_right.porosity"),
                AMBIENT_HX["porosity"],
                0.5,
                0.05,
                1.0,
            ),
            Param(
                "ambient_hx.pore_radius",
                ("ambient_hx_left.pore_radius", "ambient_hx_right.pore_radius"),
                AMBIENT_HX["pore_radius"],
                1.0,
                1e-5,
                core.radius,
                log=True,
            ),
        ),
        transform=lambda c: with_ambient_exchangers(
            c, AMBIENT_HX_MIN_DUCT / 2, AMBIENT_HX["porosity"], AMBIENT_HX["pore_radius"]
        ),
        typical={
            "ambient_hx.length": AMBIENT_HX["length"],
            "ambient_hx.porosity": AMBIENT_HX["porosity"],
            "ambient_hx.pore_radius": AMBIENT_HX["pore_radius"],
        },
    )


#: Names of the elastic-frame effect of a layer: the limp frame's kernel field (1/rho_1) and
#: the host-side fields of the frame's stiffness (:data:`tawarp.model.fields.HOST_FIELD_TABLE`).
FRAME_MOBILITY, FRAME_WAVE_SPEED, FRAME_LOSS_FACTOR = (
    "layer.frame_mobility",
    "layer.frame_wave_speed",
    "layer.frame_loss_factor",
)
#: Typical foam frame: E = 2e5 Pa, loss factor 0.1, bulk density 30 kg/m^3.
TYPICAL_FRAME = {"E": 2e5, "eta": 0.1, "rho_1": 30.0}
#: P-wave modulus over Young's modulus, (1 - nu)/((1 + nu)(1 - 2 nu)), at the frame's fixed
#: Poisson ratio nu: normal incidence sees P = E times this alone.
P_WAVE_FACTOR = (1 - FRAME_POISSON_RATIO) / ((1 + FRAME_POISSON_RATIO) * (1 - 2 * FRAME_POISSON_RATIO))
#: In-vacuo compressional wave speed sqrt(P / rho_1) of foam and fibre frames [m/s]: Young's
#: moduli from 1e4 Pa (soft fibres) to 1e7 Pa (a stiff foam's apparent modulus in a tube,
#: its edge held by the wall; Allard & Atalla,
#: *Propagation of Sound in Porous Media*, 2nd ed., the materials of ch. 6 and 11) over frame
#: densities of 100 to 10 kg/m^3: two decades, the central 95 % of the layer frame's prior.
FRAME_WAVE_SPEED_RANGE = (math.sqrt(1e4 * P_WAVE_FACTOR / 100.0), math.sqrt(1e7 * P_WAVE_FACTOR / 10.0))
#: The one physical mechanism of both frame models: a model holds at most one of them.
FRAME_MOTION = "frame motion"


def elastic_frame_effect() -> Effect:
    """An elastic frame (Biot-Allard, :mod:`tawarp.model.biot`) of a rigid-backed layer, the
    frame bonded to the backing: its mobility ``layer.frame_mobility`` m = 1/rho_1 [m^3/kg]
    (the limp frame's field), its in-vacuo compressional wave speed ``layer.frame_wave_speed``
    c = sqrt(P / rho_1) [m/s] (P = E (1 - nu)/((1 + nu)(1 - 2 nu)), the only modulus normal
    incidence sees; Poisson ratio fixed) and loss factor ``layer.frame_loss_factor`` eta.

    **Why these parameters.** m = 0 is an infinitely heavy frame, which does not move
    whatever its stiffness: exactly the rigid model (the kernels' layer, bit for bit, as
    "off" must be). Frame densities of foams and fibres lie within a decade (10-100
    kg/m^3), so a half-normal from "off" of twice the typical 1/30 m^3/kg, the limp frame's
    own prior, is a fair prior of m. At fixed c, m moves the frame's coupling to the air and
    not its resonances (c / 4d for a layer of thickness d): a fit that lowers m to shrink a
    misplaced resonance does not move it, and one that moves c does not switch the frame
    off, unlike (1/E, rho_1) or (m, E), where the way to the rigid model also shifts the
    resonance. The wave speed is no switch but a scale over two decades
    (:data:`FRAME_WAVE_SPEED_RANGE`): a log Param, its prior log-normal with that span as
    the central 95 % (:func:`tawarp.model.priors.effect_priors`), even per decade. It is
    also what such data fix: a resonance's frequency, E and rho_1 apart far less
    (correlation 0.995 in ``docs/elastic_frame.md``). A switch on the compliance 1/E would
    need a half-normal on 1/E reaching the softest frames: its density per decade of E
    falls as 1/E, and a foam of 3e6 Pa would pay about 4 units of ln Z for its stiffness
    alone, enough to lose a frame resonance that a coarse grid samples twice (foam2 at every
    8th frequency, docs/loop.md).

    **One frame per model.** The limp frame is this frame's c -> 0 end (Biot's frame without
    stiffness, ``tests/test_effects_library.py``), which a log-normal prior does not hold at
    a finite value; so the limp frame stays its own effect, an alternative model of the
    same mechanism (:data:`FRAME_MOTION`), never combined with this one
    (:func:`tawarp.loop.evidence.subsets`): both set the frame's mobility, and a layer has
    one frame. Where the data cannot tell a limp from a stiff frame, the inclusion splits
    between the two and the comparison names the frame's motion as their group."""
    fm, fc, fe = (field_spec(n) for n in (FRAME_MOBILITY, FRAME_WAVE_SPEED, FRAME_LOSS_FACTOR))
    lo, hi = FRAME_WAVE_SPEED_RANGE
    frame = {FRAME_MOBILITY: 1.0 / TYPICAL_FRAME["rho_1"], FRAME_LOSS_FACTOR: TYPICAL_FRAME["eta"]}
    return Effect(
        "elastic_frame",
        "elastic frame (Biot-Allard): frame resonance; 1/frame density, frame wave speed, loss factor",
        (
            Param(FRAME_MOBILITY, (FRAME_MOBILITY,), fm.neutral, fm.scale, *fm.fit_range),
            Param(FRAME_WAVE_SPEED, (FRAME_WAVE_SPEED,), math.sqrt(lo * hi), 1.0, *fc.fit_range, log=True),
            Param(FRAME_LOSS_FACTOR, (FRAME_LOSS_FACTOR,), TYPICAL_FRAME["eta"], fe.scale, *fe.fit_range),
        ),
        typical={**frame, FRAME_WAVE_SPEED: math.sqrt(TYPICAL_FRAME["E"] * P_WAVE_FACTOR / TYPICAL_FRAME["rho_1"])},
        # the span of c, one start per factor sqrt(10) (a frame resonance's basin is narrow)
        starts=tuple({**frame, FRAME_WAVE_SPEED: c} for c in np.geomspace(lo, hi, 5)),
        mechanism=FRAME_MOTION,
    )


def two_port_frame_effect(sample: str) -> Effect:
    """An elastic frame (Biot-Allard) of the porous segment ``sample`` of a passive core
    measured as a 2-port, the frame sliding freely at the tube wall (1-D; a frame clamped or
    glued at its edge bends and is not modelled): the limp frame (``SAMPLE.frame_mobility``
    1/rho_1 [m^3/kg], the kernels' field) given a Young's modulus ``SAMPLE.frame_modulus``
    E [Pa] and loss factor ``SAMPLE.frame_loss_factor``. A free frame of infinite stiffness
    still moves as a rigid body, so "off" is infinite frame density, mobility 0 (exact);
    E = 0 is exactly the limp frame, :func:`porous_layer_effects`' ``limp_frame``: the two
    model one mechanism (:data:`FRAME_MOTION`) and a model holds at most one of them.
    :class:`tawarp.measure.tmatrix.TMatrixKind` evaluates the Biot 2-port where both are > 0."""
    m, E, eta = (f"{sample}.{f}" for f in ("frame_mobility", "frame_modulus", "frame_loss_factor"))
    fm, fE, fe = field_spec(m), field_spec(E), field_spec(eta)
    typical = {m: 1.0 / TYPICAL_FRAME["rho_1"], E: TYPICAL_FRAME["E"], eta: TYPICAL_FRAME["eta"]}
    return Effect(
        "elastic_frame",
        "elastic frame (Biot-Allard, frame sliding at the wall): 1/frame density, Young's modulus, loss factor",
        (
            Param(m, (m,), fm.neutral, fm.scale, *fm.fit_range),
            Param(E, (E,), 0.0, fE.scale, *fE.fit_range),
            Param(eta, (eta,), TYPICAL_FRAME["eta"], fe.scale, *fe.fit_range),
        ),
        typical=typical,
        starts=tuple({**typical, E: v} for v in (1e4, 1e5, 1e6, 1e7)),
        mechanism=FRAME_MOTION,
    )


def impedance_library(core: Core) -> list[Effect]:
    """Candidate effects for the surface impedance of a rigid-backed layer: the porous-layer
    effects, an elastic frame, a thickness offset (typical 0.5 mm), and T_cold and p_mean
    within what a room's are known to (+-15 K, +-5 %)."""
    off = field_spec("layer.length_offset")
    T0, p0 = core.gas.T_cold, core.gas.p_mean
    return (
        porous_layer_effects(["layer"], stiffness=FRAME_WAVE_SPEED.partition(".")[2])
        + [elastic_frame_effect()]
        + [
            Effect(
                "thickness_offset",
                "layer thicknesses off by a common offset (measurement plane)",
                (Param("layer.length_offset", ("layer.length_offset",), off.neutral, off.scale, *off.fit_range),),
                typical={"layer.length_offset": 5e-4},
            )
        ]
        + ambient_effects(core, (T0 - 15, T0 + 15), (0.95 * p0, 1.05 * p0))
    )


def library_for_core(core: Core, kind_name: str) -> list[Effect]:
    """The candidate effects for data of kind ``kind_name`` on ``core``: 2-port data
    (``tmatrix``, ``scattering``) :func:`tmatrix_library`, a rigid-backed layer's surface
    impedance (``impedance``) :func:`impedance_library`; none for other kinds."""
    if kind_name in ("tmatrix", "scattering"):
        return tmatrix_library(core)
    if kind_name == "impedance":
        return impedance_library(core)
    return []
