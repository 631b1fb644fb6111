"""The one table of model parameters: every numeric field a segment or the core has.

Each row says, for one field: its row in the kernels' parameter table
(:mod:`tawarp.kernels.layout`), unit, physical range (validation of cores and batches),
which segments take it, its neutral value (an effect is off there and the model is
then the base model bit for bit), whether it makes the heat model nonlinear, and how a
fit treats it: log or linear scale, the typical size of a linear step, the bounds a
fit is projected onto, and the range a spread of starts is drawn from.

Adding a segment field: one row here and one row constant in ``kernels/layout.py``
(the kernels read it by that constant). Everything else (validation, the TOML keys,
parameter names, bounds, scaling, starts) reads this table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ..kernels import layout

if TYPE_CHECKING:  # numpy is imported where an array is made
    import numpy as np

#: Which segments take a field: every segment, porous ones, thermal ones, thermal porous ones,
#: those with imposed temperatures.
APPLIES = ("all", "porous", "thermal", "thermal_porous", "imposed")


@dataclass(frozen=True)
class Field:
    """One numeric model parameter (see the module doc).

    ``lower``/``upper``/``lower_open``: physical range; ``neutral``: value at which an
    optional effect is off (None for a field of the paper's base model); ``log``: fitted
    as ln(v/start) (positive quantities that can start away from 0), else as
    (v - start)/``scale`` with ``scale`` of the size of the field's values (the damped LM
    step ``(H + mu I) dz = -g`` treats all unit steps alike: porosity at 0.05 instead of 0.5
    takes the paper's geometry fits from 6 to 10 iterations); ``fit_range``: bounds a fit is projected onto (natural units);
    ``prior``: range of a spread of starts (None: the core's value +-20 %).
    """

    name: str
    row: int
    unit: str
    lower: float
    upper: float
    lower_open: bool
    applies: str = "all"
    neutral: float | None = None
    nonlinear: bool = False
    log: bool = True
    scale: float = 1.0
    fit_range: tuple[float, float] = (-math.inf, math.inf)
    prior: tuple[float, float] | None = None
    description: str = ""
    upper_open: bool = False

    @property
    def is_effect(self) -> bool:
        return self.neutral is not None

    def check(self, value: float) -> bool:
        """True when ``value`` lies in the physical range."""
        return not (
            value < self.lower
            or (self.lower_open and value == self.lower)
            or value > self.upper
            or (self.upper_open and value == self.upper)
        )

    def check_array(self, values) -> "np.ndarray":
        """Element-wise :meth:`check` of an array (non-finite values fail)."""
        import numpy as np

        a = np.asarray(values, dtype=float)
        ok = np.isfinite(a) & (a >= self.lower) & (a <= self.upper)
        if self.lower_open:
            ok &= a != self.lower
        if self.upper_open:
            ok &= a != self.upper
        return ok

    def range_text(self) -> str:
        hi = f"{self.upper}]" if math.isfinite(self.upper) and not self.upper_open else f"{self.upper})"
        return f"{'(' if self.lower_open else '['}{self.lower}, {hi}"


_INF = math.inf
#: Segment fields in the order they are listed as parameters (``Core.parameter_names``).
SEGMENT_FIELD_TABLE: tuple[Field, ...] = (
    Field("length", layout.LENGTH, "m", 0.0, _INF, True, fit_range=(1e-4, 10.0), description="segment length"),
    Field(
        "porosity",
        layout.POROSITY,
        "-",
        0.0,
        1.0,
        True,
        "porous",
        log=False,
        scale=0.5,
        fit_range=(1e-2, 1.0),
        prior=(0.3, 0.99),
        description="open fraction of the cross-section",
    ),
    Field(
        "pore_radius",
        layout.PORE_RADIUS,
        "m",
        0.0,
        _INF,
        True,
        "porous",
        fit_range=(1e-7, 0.1),
        prior=(1e-5, 2e-3),
        description="pore radius (plates: half the spacing; rectangular: half the narrow side)",
    ),
    Field(
        "tortuosity",
        layout.TORTUOSITY,
        "-",
        1.0,
        _INF,
        False,
        "porous",
        log=False,
        scale=1.0,
        fit_range=(1.0, 10.0),
        prior=(1.0, 2.0),
        description="q, with q^2 = alpha_inf",
    ),
    Field(
        "solid_conductivity",
        layout.SOLID_CONDUCTIVITY,
        "W/(m K)",
        0.0,
        _INF,
        False,
        "porous",
        fit_range=(1e-4, 1e4),
        prior=(0.3, 50.0),
        description="conductivity of the solid matrix",
    ),
    Field(
        "h",
        layout.H,
        "W/(m^2 K)",
        0.0,
        _INF,
        False,
        "thermal",
        fit_range=(1e-4, 1e5),
        prior=(0.05, 500.0),
        description="lateral heat exchange with the wall",
    ),
    Field(
        "thermal_radius_ratio",
        layout.THERMAL_RADIUS_RATIO,
        "-",
        0.0,
        _INF,
        True,
        "porous",
        neutral=1.0,
        log=False,
        scale=0.2,
        fit_range=(0.1, 10.0),
        description="Lambda'/Lambda: f_k uses ratio * pore_radius",
    ),
    Field(
        "frame_mobility",
        layout.FRAME_MOBILITY,
        "m^3/kg",
        0.0,
        _INF,
        False,
        "porous",
        neutral=0.0,
        log=False,
        scale=0.01,
        fit_range=(0.0, 10.0),
        description="1/(frame bulk density): > 0 makes the frame limp",
    ),
    Field(
        "viscous_shape_factor",
        layout.VISCOUS_SHAPE_FACTOR,
        "-",
        0.0,
        _INF,
        True,
        "porous",
        neutral=1.0,
        log=False,
        scale=0.2,
        fit_range=(0.2, 5.0),
        description="s = r/Lambda (circular pores: 1)",
    ),
    Field(
        "conductivity_exponent",
        layout.CONDUCTIVITY_EXPONENT,
        "-",
        -10.0,
        10.0,
        False,
        "thermal",
        neutral=0.0,
        nonlinear=True,
        log=False,
        scale=0.5,
        fit_range=(-3.0, 3.0),
        description="b in lam (T/T_cold)^b (heat model)",
    ),
    Field(
        "radiative_conductivity",
        layout.RADIATIVE_CONDUCTIVITY,
        "W/(m K)",
        0.0,
        _INF,
        False,
        "thermal_porous",
        neutral=0.0,
        nonlinear=True,
        log=False,
        scale=0.1,
        fit_range=(0.0, 100.0),
        description="Rosseland conductivity at T_cold, added as c (T/T_cold)^3",
    ),
    Field(
        "h_convection",
        layout.H_CONVECTION,
        "W/(m^2 K^1.25)",
        0.0,
        _INF,
        False,
        "thermal",
        neutral=0.0,
        nonlinear=True,
        log=False,
        scale=1.0,
        fit_range=(0.0, 1e3),
        description="natural convection: h_eff = h + h_conv theta^(1/4)",
    ),
    Field(
        "wall_conductance",
        layout.WALL_CONDUCTANCE,
        "W/(m K)",
        0.0,
        _INF,
        False,
        "thermal",
        neutral=0.0,
        log=False,
        scale=0.1,
        fit_range=(0.0, 1e3),
        description="axial conduction of the tube wall, lam_wall A_wall/S",
    ),
    Field(
        "wall_resistance",
        layout.WALL_RESISTANCE,
        "m^2 K/W",
        0.0,
        _INF,
        False,
        "thermal",
        neutral=0.0,
        log=False,
        scale=0.1,
        fit_range=(0.0, 1e3),
        description="lateral thermal resistance 1/h_w between the gas/solid and the tube wall per wall area: > 0 "
        "with a wall_conductance makes the wall a temperature field of its own (0: perfect contact, the wall at "
        "the gas temperature, its conductance added to the segment's)",
    ),
    Field(
        "end_conductance",
        layout.END_CONDUCTANCE,
        "W/(m^2 K)",
        0.0,
        _INF,
        False,
        "thermal",
        neutral=0.0,
        log=False,
        scale=100.0,
        fit_range=(0.0, 1e5),
        description="heat flux H theta per section area drawn to T_cold at the heat model's end that lies in this "
        "segment (the ambient exchangers' thermal contact; 0: adiabatic end, inf: held at T_cold)",
    ),
    Field(
        "contact_resistance",
        layout.CONTACT_RESISTANCE,
        "m^2 K/W",
        0.0,
        _INF,
        False,
        "thermal",
        neutral=0.0,
        log=False,
        scale=1e-4,
        fit_range=(0.0, 0.1),
        description="thermal contact resistance at the segment's start against the previous thermal segment: "
        "theta jumps by R_c times the heat flux density there (0: perfect contact; no effect on the first)",
    ),
    Field(
        "bypass_gap",
        layout.BYPASS_GAP,
        "m",
        0.0,
        _INF,
        False,
        "porous",
        neutral=0.0,
        log=False,
        scale=1e-4,
        fit_range=(0.0, 5e-3),
        description="width g of an annular gap between the segment and the tube wall: a parallel-plate channel "
        "of spacing g beside the pores, area share g (2R - g)/R^2 (0: none; below the tube radius)",
    ),
    Field(
        "T_start",
        layout.T_START,
        "K",
        0.0,
        _INF,
        True,
        "imposed",
        fit_range=(1.0, 1e4),
        description="imposed temperature at the segment's start (a linear profile to T_end)",
    ),
    Field(
        "T_end",
        layout.T_END,
        "K",
        0.0,
        _INF,
        True,
        "imposed",
        fit_range=(1.0, 1e4),
        description="imposed temperature at the segment's end",
    ),
)
#: Core-wide fields, addressed ``gas.T_cold``, ``gas.p_mean``, ``tube.radius``.
GLOBAL_FIELD_TABLE: dict[str, Field] = {
    "gas.T_cold": Field(
        "T_cold",
        layout.T_COLD,
        "K",
        0.0,
        _INF,
        True,
        fit_range=(150.0, 500.0),
        description="cold-end (ambient) temperature",
    ),
    "gas.p_mean": Field(
        "p_mean", layout.P_MEAN, "Pa", 0.0, _INF, True, fit_range=(1e3, 1e8), description="mean pressure"
    ),
    "tube.radius": Field(
        "radius", layout.RADIUS, "m", 0.0, _INF, True, fit_range=(1e-4, 10.0), description="tube radius"
    ),
}

#: Fields the kernels do not read (``row`` -1): effects a measurement kind applies on the
#: host, addressed ``layer.FIELD`` (the elastic frame of :mod:`tawarp.model.biot`, the
#: thickness offset of :mod:`tawarp.measure.impedance`) or by their full name (the 2-port
#: calibration of :mod:`tawarp.measure.tmatrix`).
HOST_FIELD_TABLE: dict[str, Field] = {
    "frame_wave_speed": Field(
        "frame_wave_speed",
        -1,
        "m/s",
        0.0,
        _INF,
        False,
        "porous",
        fit_range=(0.0, 1e4),
        description="in-vacuo compressional wave speed of a layer's elastic frame, sqrt(P-wave modulus / rho_1) "
        "(Biot): the frame's resonances",
    ),
    "frame_modulus": Field(
        "frame_modulus",
        -1,
        "Pa",
        0.0,
        _INF,
        False,
        "porous",
        log=False,
        scale=1e5,
        fit_range=(0.0, 1e8),
        description="Young's modulus E of the elastic frame (real part of E (1 - i eta)); 0: a limp frame",
    ),
    "frame_loss_factor": Field(
        "frame_loss_factor",
        -1,
        "-",
        0.0,
        _INF,
        False,
        "porous",
        log=False,
        scale=0.05,
        fit_range=(0.0, 1.0),
        description="eta of the frame modulus E (1 - i eta)",
    ),
    "frame_density": Field(
        "frame_density",
        -1,
        "kg/m^3",
        0.0,
        _INF,
        True,
        "porous",
        fit_range=(1.0, 1e3),
        description="frame bulk density rho_1 (frame mass per layer volume)",
    ),
    "porosity_gradient": Field(
        "porosity_gradient",
        -1,
        "-",
        -2.0,
        2.0,
        True,
        "porous",
        neutral=0.0,
        log=False,
        scale=0.1,
        fit_range=(-1.0, 1.0),
        upper_open=True,
        description="g in phi(x) = phi (1 + g (x/L - 1/2)) along a thermal stack (its parts' porosities, "
        "tawarp.model.effects.graded_parts)",
    ),
    "poisson_ratio": Field(
        "poisson_ratio",
        -1,
        "-",
        -1.0,
        0.5,
        True,
        "porous",
        log=False,
        scale=0.1,
        fit_range=(0.0, 0.49),
        upper_open=True,
        description="Poisson ratio nu of the frame",
    ),
    "length_offset": Field(
        "length_offset",
        -1,
        "m",
        -_INF,
        _INF,
        False,
        "porous",
        neutral=0.0,
        log=False,
        scale=1e-3,
        fit_range=(-0.01, 0.01),
        description="offset added to every layer thickness",
    ),
    "calibration.gain": Field(
        "gain",
        -1,
        "-",
        0.0,
        _INF,
        True,
        neutral=1.0,
        log=False,
        scale=0.01,
        fit_range=(0.5, 2.0),
        description="|g| of the 2-port calibration gain g (measured T = g T)",
    ),
    "calibration.phase": Field(
        "phase",
        -1,
        "rad",
        -math.pi,
        math.pi,
        False,
        neutral=0.0,
        log=False,
        scale=0.01,
        fit_range=(-0.5, 0.5),
        description="arg g of the 2-port calibration gain",
    ),
}

#: Trusted range (lowest, highest) of each kernel field, inside its physical range: the
#: values at which the kernels' float64 arithmetic was checked against the independent
#: reference (tawarp/reference.py) and by tests/test_fuzz_core.py. A value outside is
#: refused before any kernel launch (:func:`tawarp.model.core.check_values`);
#: docs/trusted_ranges.md gives the reasons.
TRUSTED_RANGE: dict[str, tuple[float, float]] = {
    "T_cold": (1.0, 1e4),
    "p_mean": (1.0, 1e9),
    "radius": (1e-6, 10.0),
    "length": (1e-9, 100.0),
    "porosity": (1e-12, 1.0),
    "pore_radius": (1e-9, 10.0),
    "tortuosity": (1.0, 1e3),
    "solid_conductivity": (0.0, 1e5),
    "h": (0.0, 1e7),
    "thermal_radius_ratio": (1e-6, 1e6),
    "frame_mobility": (0.0, 1e6),
    "viscous_shape_factor": (1e-3, 1e3),
    "conductivity_exponent": (-10.0, 10.0),
    "radiative_conductivity": (0.0, 1e4),
    "h_convection": (0.0, 1e5),
    "wall_conductance": (0.0, 1e4),
    "wall_resistance": (0.0, 1e6),
    "end_conductance": (0.0, 1e9),
    "contact_resistance": (0.0, 1.0),
    "bypass_gap": (0.0, 10.0),
    "T_start": (1.0, 1e4),
    "T_end": (1.0, 1e4),
}

SEGMENT_FIELDS: dict[str, Field] = {f.name: f for f in SEGMENT_FIELD_TABLE}
assert sorted(f.row for f in SEGMENT_FIELD_TABLE) == list(range(layout.N_FIELDS)), "kernels/layout.py rows"
#: Effect fields and their neutral ("off") values.
EFFECT_OFF = {f.name: f.neutral for f in SEGMENT_FIELD_TABLE if f.is_effect}
#: Fields evaluated at the local temperature: they make the heat solve iterate.
NONLINEAR_FIELDS = tuple(f.name for f in SEGMENT_FIELD_TABLE if f.nonlinear)


def field(name: str) -> Field:
    """The table row of a parameter name: ``SEGMENT.FIELD``, a bare field name, a
    global (``gas.T_cold``, ``gas.p_mean``, ``tube.radius``) or a host field
    (:data:`HOST_FIELD_TABLE`)."""
    if name in GLOBAL_FIELD_TABLE:
        return GLOBAL_FIELD_TABLE[name]
    if name in HOST_FIELD_TABLE:
        return HOST_FIELD_TABLE[name]
    fld = name.rpartition(".")[2]
    if fld in SEGMENT_FIELDS:
        return SEGMENT_FIELDS[fld]
    if fld in HOST_FIELD_TABLE and "." not in fld:
        return HOST_FIELD_TABLE[fld]
    for f in GLOBAL_FIELD_TABLE.values():
        if f.name == fld:
            return f
    raise KeyError(
        f"{name!r}: unknown field {fld!r}; segment fields are {tuple(SEGMENT_FIELDS)}, globals "
        f"{tuple(GLOBAL_FIELD_TABLE)}"
    )


def takes(f: Field, porous: bool, thermal: bool, imposed: bool = False) -> bool:
    """True when a segment of that structure has field ``f``."""
    return {
        "all": True,
        "porous": porous,
        "thermal": thermal,
        "thermal_porous": porous and thermal,
        "imposed": imposed,
    }[f.applies]
