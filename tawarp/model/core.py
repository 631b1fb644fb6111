"""Description of a thermoacoustic core: gas, tube and segments (docs/formats.md, TOML).

A core is an ordered list of segments from measurement plane x1 to plane x6. Every
numeric quantity is addressable by a *parameter name* ``SEGMENT.FIELD`` (for example
``stack.porosity``), or ``gas.T_cold``, ``gas.p_mean``, ``tube.radius``. The batched
API, the command line and every output use these names.

All values are SI: lengths in m, temperatures in K, pressures in Pa, conductivities in
W/(m K), heat-exchange coefficients in W/(m^2 K).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import tomllib
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np

from .fields import EFFECT_OFF, GLOBAL_FIELD_TABLE, SEGMENT_FIELD_TABLE, SEGMENT_FIELDS, TRUSTED_RANGE, takes
from .fields import field as field_spec
from ..kernels.pore import ASPECT_MAX, PIN_RATIO_MAX, PORE_MODELS as KERNEL_PORE_MODELS
from .gas import GASES, is_mixture, mixture_fractions, mixture_name
from .prior import Prior, PriorError, declared_prior

SEGMENT_KINDS = ("duct", "porous")
PORE_MODELS = tuple(KERNEL_PORE_MODELS)
#: Numeric global fields, addressed as ``gas.T_cold``, ``gas.p_mean``, ``tube.radius``.
GLOBAL_FIELDS = tuple(GLOBAL_FIELD_TABLE)


class CoreError(ValueError):
    """A core description is invalid; the message names the file and key."""


@dataclass(frozen=True)
class Gas:
    """Working gas: ``name`` a pure gas of :data:`tawarp.model.gas.GASES` or a binary mixture
    ("helium=0.7,argon=0.3", a ``[gas.mixture]`` table), mean pressure [Pa], cold temperature [K]."""

    name: str = "air"
    p_mean: float = 101325.0
    T_cold: float = 293.15


@dataclass(frozen=True)
class Segment:
    """One part of the core between two planes.

    A ``duct`` is an empty tube section (porosity 1, pore radius = tube radius,
    tortuosity 1). A ``porous`` segment has ``porosity`` [-], ``pore_radius`` [m]
    (circular pores: radius; ``plates``: half the plate spacing; ``rectangular``: half the
    narrow side, the channel's sides in the ratio ``aspect_ratio`` >= 1; ``pins``: the pin
    radius, each pin's gas cell of outer radius ``outer_radius_ratio`` times it; ``screens``:
    the hydraulic radius of stacked wire screens, whose porosity lies in (0.5, 1); a file may
    give ``wire_diameter`` and ``mesh`` instead, :func:`screen_geometry`), ``tortuosity`` q [-]
    (q^2 = alpha_inf), ``solid_conductivity`` [W/(m K)]. ``h`` [W/(m^2 K)] is the lateral
    heat exchange with the wall, used when ``thermal`` is true (the segment is part of
    the steady heat model). Exactly one thermal segment is the ``heater``. The effect
    fields (:data:`tawarp.model.fields.EFFECT_OFF`) are off by default.
    """

    name: str
    kind: str
    length: float
    pore_model: str = "circular"
    aspect_ratio: float = 1.0
    outer_radius_ratio: float = math.nan
    porosity: float = 1.0
    pore_radius: float = math.nan
    tortuosity: float = 1.0
    solid_conductivity: float = 0.0
    h: float = 0.0
    thermal: bool = False
    heater: bool = False
    thermal_radius_ratio: float = 1.0
    conductivity_exponent: float = 0.0
    radiative_conductivity: float = 0.0
    h_convection: float = 0.0
    wall_conductance: float = 0.0
    wall_resistance: float = 0.0
    frame_mobility: float = 0.0
    viscous_shape_factor: float = 1.0
    end_conductance: float = 0.0
    contact_resistance: float = 0.0
    bypass_gap: float = 0.0
    T_start: float = math.nan
    T_end: float = math.nan

    @property
    def is_porous(self) -> bool:
        return self.kind == "porous"

    @property
    def imposed(self) -> bool:
        """True when the segment's temperatures are imposed (``T_start``, ``T_end``)."""
        return not all(isinstance(t, float) and math.isnan(t) for t in (self.T_start, self.T_end))

    @property
    def pore_shape(self) -> float:
        """The shape number of the pore model (:func:`tawarp.kernels.pore.pore_model_code`):
        a rectangular channel's aspect ratio, a pin array's outer radius ratio, else 1."""
        if self.pore_model == "pins":
            return self.outer_radius_ratio
        return self.aspect_ratio


@dataclass(frozen=True)
class Core:
    """A thermoacoustic core: ``gas``, tube ``radius`` [m] and ``segments`` from x1 to x6;
    ``priors`` {parameter name: :class:`~tawarp.model.prior.Prior`} the uncertainties its
    file declares (docs/priors.md), kept by :meth:`replace` and written back."""

    segments: tuple[Segment, ...]
    gas: Gas = field(default_factory=Gas)
    radius: float = 0.0167
    source: str = "<core>"
    #: parameters the loop's base fit leaves at their core values (the ``[fit] pinned``
    #: list of a core file, docs/formats.md)
    pinned: tuple[str, ...] = ()
    #: declared priors, keyed ``SEGMENT.FIELD``, ``gas.FIELD``, ``tube.radius`` (a dict:
    #: compared, not hashed)
    priors: dict[str, Prior] = field(default_factory=dict, hash=False)

    def __post_init__(self):
        object.__setattr__(self, "segments", tuple(self.segments))
        object.__setattr__(self, "pinned", tuple(self.pinned))
        object.__setattr__(self, "priors", dict(self.priors))
        validate(self)

    # -- structure -------------------------------------------------------------------
    @property
    def area(self) -> float:
        """Tube cross-section S = pi R^2 [m^2]."""
        return math.pi * self.radius**2

    @property
    def thermal_indices(self) -> list[int]:
        return [i for i, s in enumerate(self.segments) if s.thermal]

    @property
    def heater_index(self) -> int:
        for i, s in enumerate(self.segments):
            if s.heater:
                return i
        raise CoreError(f"{self.source}: no segment has heater = true (a passive core has no heat input)")

    def segment(self, name: str) -> Segment:
        for s in self.segments:
            if s.name == name:
                return s
        raise KeyError(f"{self.source}: no segment named {name!r} (have {[s.name for s in self.segments]})")

    def positions(self) -> list[float]:
        """Plane positions [m]: x = 0 at the first plane, one more entry than segments."""
        x = [0.0]
        for s in self.segments:
            x.append(x[-1] + s.length)
        return x

    # -- parameters ------------------------------------------------------------------
    def parameter_names(self) -> list[str]:
        """Every parameter the model uses, ``SEGMENT.FIELD`` or a global name: a duct
        has a length (and ``h`` when thermal), a porous segment all its fields."""
        names = list(GLOBAL_FIELDS)
        for s in self.segments:
            names += [f"{s.name}.{f}" for f in segment_parameter_fields(s)]
        return names

    def get(self, name: str) -> float:
        """Value of parameter ``name`` (``stack.porosity``, ``gas.T_cold``, ...)."""
        owner, fld = _split(name, self.source)
        if owner == "gas" and fld in ("T_cold", "p_mean"):
            return getattr(self.gas, fld)
        if owner == "tube" and fld == "radius":
            return self.radius
        if fld not in SEGMENT_FIELDS:
            raise KeyError(f"{name!r}: unknown field {fld!r}; segment fields are {tuple(SEGMENT_FIELDS)}")
        seg = self.segment(owner)
        value = getattr(seg, fld)
        if fld == "pore_radius" and not seg.is_porous:
            return self.radius
        return value

    def replace(self, **values: float) -> "Core":
        """A copy with parameters changed, keyed by name: ``core.replace(**{"stack.h": 80})``."""
        gas, radius, segs = self.gas, self.radius, {s.name: s for s in self.segments}
        for name, value in values.items():
            owner, fld = _split(name, self.source)
            self.get(name)  # validates the name: an unknown one is a KeyError that names it
            if owner == "gas":
                gas = dataclasses.replace(gas, **{fld: float(value)})
            elif owner == "tube" and fld == "radius":
                radius = float(value)
            else:
                segs[owner] = dataclasses.replace(segs[owner], **{fld: float(value)})
        return Core(tuple(segs[s.name] for s in self.segments), gas, radius, self.source, self.pinned, self.priors)

    def to_dict(self) -> dict:
        """The TOML structure (docs/formats.md) of this core; a field with a declared prior as
        its inline table (:meth:`~tawarp.model.prior.Prior.toml_entry`)."""
        gas = dataclasses.asdict(self.gas)
        if is_mixture(self.gas.name):
            gas.pop("name")
            gas["mixture"] = dict(mixture_fractions(self.gas.name))
        out = {"gas": gas, "tube": {"radius": self.radius}, "segment": []}
        for s in self.segments:
            d = {"name": s.name, "kind": s.kind, "length": s.length}
            if s.is_porous:
                d["pore_model"] = s.pore_model
                if s.pore_model in PORE_SHAPES:
                    d[PORE_SHAPES[s.pore_model][0]] = s.pore_shape
                d.update(
                    porosity=s.porosity,
                    pore_radius=s.pore_radius,
                    tortuosity=s.tortuosity,
                    solid_conductivity=s.solid_conductivity,
                )
            if s.thermal:
                d.update(h=s.h, thermal=True)
            if s.heater:
                d["heater"] = True
            if s.imposed:
                d.update(T_start=s.T_start, T_end=s.T_end)
            d.update({f: getattr(s, f) for f, off in EFFECT_OFF.items() if getattr(s, f) != off})
            out["segment"].append(d)
        tables = {"gas": out["gas"], "tube": out["tube"]} | {s["name"]: s for s in out["segment"]}
        for name, prior in self.priors.items():
            owner, fld = _split(name, self.source)
            tables[owner][fld] = prior.toml_entry(self.get(name))
        if self.pinned:
            out["fit"] = {"pinned": list(self.pinned)}
        return out


def segment_parameter_fields(s: Segment) -> tuple[str, ...]:
    """Fields of segment ``s`` that are parameters, in the table's order
    (:data:`tawarp.model.fields.SEGMENT_FIELD_TABLE`): a duct has its length (and ``h``
    and the thermal effects when thermal), a porous segment its geometry too."""
    return _parameter_fields(s.is_porous, s.thermal, s.imposed)


@functools.lru_cache(maxsize=None)
def _parameter_fields(porous: bool, thermal: bool, imposed: bool) -> tuple[str, ...]:
    # a segment's parameters follow from these three alone; an engine asks for each name
    return tuple(f.name for f in SEGMENT_FIELD_TABLE if takes(f, porous, thermal, imposed))


def _split(name: str, source: str) -> tuple[str, str]:
    owner, dot, fld = name.partition(".")
    if not dot or not owner or not fld:
        raise KeyError(f"{source}: parameter {name!r} is not of the form SEGMENT.FIELD")
    return owner, fld


# -- validation ----------------------------------------------------------------------
def check_values(name: str, values, where: str) -> None:
    """Raise :class:`CoreError` unless every value of field ``name`` (a field or a
    parameter name) is finite and within its physical range
    (:mod:`tawarp.model.fields`); ``where`` names the file/key (or the parameter)."""
    f = field_spec(name)
    lo, hi = TRUSTED_RANGE.get(f.name, (-math.inf, math.inf)) if f.row >= 0 else (-math.inf, math.inf)
    # a batch is a NumPy array; anything else is one value (a string or a list from a
    # TOML file is a wrong value, not a sequence of values)
    batch = getattr(values, "ndim", 0) > 0
    if batch and values.dtype.kind in "iuf":
        # checked in one pass (a per-value loop took 3 s for an onset batch of 1e6 designs);
        # the first bad value, if any, goes through the scalar checks for its message
        bad = np.flatnonzero(~(f.check_array(values) & (values >= lo) & (values <= hi)))
        values = values.ravel()[bad[:1]]
    for value in values if batch else [values]:
        if isinstance(value, bool) or not isinstance(value, (int, float)) and not hasattr(value, "dtype"):
            raise CoreError(f"{where} [{f.unit}]: expected a number, got {value!r}")
        v = float(value)
        if not math.isfinite(v):
            raise CoreError(f"{where} [{f.unit}]: expected a finite number, got {value!r}")
        if not f.check(v):
            raise CoreError(f"{where} [{f.unit}]: must lie in {f.range_text()}, got {v}")
        if not lo <= v <= hi:
            raise CoreError(
                f"{where} [{f.unit}]: {v:g} lies outside the trusted range [{lo:g}, {hi:g}] (docs/trusted_ranges.md)"
            )


#: The shape number of each pore model that takes one: its key, range and meaning.
PORE_SHAPES = {
    "rectangular": ("aspect_ratio", 1.0, ASPECT_MAX, "long side / short side; pore_radius is half the short side"),
    "pins": ("outer_radius_ratio", 1.01, PIN_RATIO_MAX, "gas cell's outer radius / pin radius"),
}
_SHAPE_DEFAULTS = {
    f.name: f.default for f in dataclasses.fields(Segment) if f.name in ("aspect_ratio", "outer_radius_ratio")
}


def _check_pore_shape(s: Segment, where: str) -> None:
    """The shape number of ``s``'s pore model (:data:`PORE_SHAPES`) within its range; the
    other models' shape keys left out."""
    for model, (key, lo, hi, meaning) in PORE_SHAPES.items():
        value, default = getattr(s, key), _SHAPE_DEFAULTS[key]
        if s.pore_model != model:
            if not (value == default or (value != value and default != default)):  # NaN: unset
                raise CoreError(f"{where}: {key} applies only to pore_model = {model!r}")
        elif isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise CoreError(f"{where}: {key} must be a finite number ({meaning}), got {value!r}")
        elif not lo <= value <= hi:
            raise CoreError(f"{where}: {key} = {value} must lie in [{lo:g}, {hi:g}] ({meaning})")


def screen_geometry(wire_diameter: float, mesh: float | None = None, porosity: float | None = None):
    """(porosity, hydraulic radius [m]) of stacked plain square-weave screens of
    ``wire_diameter`` d_w [m] and ``mesh`` m [wires per m] or given ``porosity``:
    phi = 1 - pi m d_w/4 (Swift, "Thermoacoustics", sec. 7.3) and r_h = d_w phi/(4 (1 - phi))
    (the gas volume over the wires' wetted area)."""
    if porosity is None:
        porosity = 1.0 - math.pi * mesh * wire_diameter / 4.0
    return porosity, wire_diameter * porosity / (4.0 * (1.0 - porosity))


def _check_screens(s: Segment, where: str) -> None:
    """A screen stack's porosity within the correlations' reach, and one radius for both
    functions (their heat-transfer correlation carries its own Prandtl number)."""
    if not 0.5 < s.porosity < 1.0:
        raise CoreError(
            f"{where}: porosity = {s.porosity} with pore_model = 'screens': the screens' correlations need "
            f'0.5 < porosity < 1 (fitted on 0.60-0.77; docs/physics.md, "Stacked wire screens")'
        )
    if s.thermal_radius_ratio != 1.0:
        raise CoreError(
            f"{where}: thermal_radius_ratio applies to Rott's pore functions, not to pore_model = 'screens' "
            f"(its heat-transfer correlation is on the hydraulic radius)"
        )


def _screen_keys(table: dict, where: str) -> dict:
    """A [[segment]] table with ``wire_diameter`` [m] and ``mesh`` [1/m] (or ``porosity``) of a
    screen stack replaced by its ``porosity`` and ``pore_radius`` (:func:`screen_geometry`)."""
    out = dict(table)
    if "wire_diameter" not in out and "mesh" not in out:
        return out
    if out.get("pore_model") != "screens":
        raise CoreError(f"{where}: wire_diameter and mesh apply only to pore_model = 'screens'")
    if "pore_radius" in out:
        raise CoreError(f"{where}: give pore_radius (the hydraulic radius) or wire_diameter, not both")
    d_w = out.pop("wire_diameter", None)
    mesh = out.pop("mesh", None)
    if "porosity" in out and mesh is not None:
        raise CoreError(f"{where}: give mesh or porosity with wire_diameter, not both")
    if d_w is None or (mesh is None and "porosity" not in out):
        raise CoreError(f"{where}: a screen stack needs wire_diameter [m] and mesh [1/m] (or porosity)")
    for key, value in (("wire_diameter", d_w), ("mesh", mesh), ("porosity", out.get("porosity"))):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0):
            raise CoreError(f"{where}: {key} must be a positive number (a plain value), got {value!r}")
    porosity, r_h = screen_geometry(float(d_w), mesh, out.get("porosity"))
    if not 0.0 < porosity < 1.0:
        raise CoreError(
            f"{where}: wire_diameter {d_w} m and mesh {mesh} 1/m give porosity {porosity:.4g}, not in (0, 1)"
        )
    out.update(porosity=porosity, pore_radius=r_h)
    return out


def validate(core: Core) -> None:
    """Raise :class:`CoreError` naming the offending key if ``core`` is not physical."""
    src = core.source
    try:
        GASES[core.gas.name]
    except KeyError as e:
        raise CoreError(f"{src}: gas.name: {e.args[0]}") from None
    check_values("p_mean", core.gas.p_mean, f"{src}: gas.p_mean")
    check_values("T_cold", core.gas.T_cold, f"{src}: gas.T_cold")
    check_values("radius", core.radius, f"{src}: tube.radius")
    if not core.segments:
        raise CoreError(f"{src}: no [[segment]] entries")
    names = [s.name for s in core.segments]
    for s in core.segments:
        w = f"{src}: segment {s.name!r}"
        if not isinstance(s.name, str) or not s.name.isidentifier():
            raise CoreError(f"{src}: segment name {s.name!r} must be an identifier (letters, digits, _)")
        if names.count(s.name) > 1:
            raise CoreError(f"{w}: name used twice")
        if s.name in ("gas", "tube"):
            raise CoreError(f"{w}: 'gas' and 'tube' are reserved names")
        if s.kind not in SEGMENT_KINDS:
            raise CoreError(f"{w}: kind = {s.kind!r}; expected one of {SEGMENT_KINDS}")
        check_values("length", s.length, f"{w}: length")
        check_values("h", s.h, f"{w}: h")
        if s.is_porous:
            if s.pore_model not in PORE_MODELS:
                raise CoreError(f"{w}: pore_model = {s.pore_model!r}; expected one of {PORE_MODELS}")
            _check_pore_shape(s, w)
            for fld in ("porosity", "pore_radius", "tortuosity", "solid_conductivity"):
                check_values(fld, getattr(s, fld), f"{w}: {fld}")
            if s.pore_model == "screens":
                _check_screens(s, w)
            if s.pore_radius > core.radius:
                raise CoreError(f"{w}: pore_radius {s.pore_radius} m exceeds the tube radius {core.radius} m")
        if s.imposed:
            for fld in ("T_start", "T_end"):
                check_values(fld, getattr(s, fld), f"{w}: {fld}")
            if s.thermal or s.heater:
                raise CoreError(
                    f"{w}: imposed temperatures (T_start, T_end) and {'heater' if s.heater else 'thermal'} = true: "
                    f"a segment's temperature is imposed or solved by the heat model, not both"
                )
        if s.heater and not s.thermal:
            raise CoreError(f"{w}: heater = true needs thermal = true")
        allowed = segment_parameter_fields(s)
        for fld, off in EFFECT_OFF.items():
            check_values(fld, getattr(s, fld), f"{w}: {fld}")
            if getattr(s, fld) != off and fld not in allowed:
                raise CoreError(
                    f"{w}: {fld} = {getattr(s, fld)} applies only to "
                    f"{SEGMENT_FIELDS[fld].applies.replace('_', ' ')} segments"
                )
        if s.bypass_gap >= core.radius:
            raise CoreError(
                f"{w}: bypass_gap {s.bypass_gap} m must be narrower than the tube radius {core.radius} m "
                f"(the gap is an annulus between the segment and the wall)"
            )
    thermal = core.thermal_indices
    if thermal:
        if thermal != list(range(thermal[0], thermal[-1] + 1)):
            raise CoreError(f"{src}: the thermal = true segments must be contiguous, got {[names[i] for i in thermal]}")
        heaters = [s.name for s in core.segments if s.heater]
        if not heaters:
            raise CoreError(
                f"{src}: segment(s) {[names[i] for i in thermal]} are thermal without imposed temperatures: "
                f"their profile needs the heat model, and then one of them with heater = true; or impose "
                f"their temperatures with T_start and T_end (or T) [K]"
            )
        if len(heaters) != 1:
            raise CoreError(f"{src}: exactly one thermal segment must have heater = true, got {heaters}")


# -- TOML ----------------------------------------------------------------------------
_SEGMENT_KEYS = {f.name for f in dataclasses.fields(Segment)}


def core_from_dict(data: dict, source: str = "<core>") -> Core:
    """Build a :class:`Core` from the TOML structure of docs/formats.md."""
    for key, kind, example in (("gas", dict, "[gas]"), ("tube", dict, "[tube]"), ("segment", list, "[[segment]]")):
        if key in data and not isinstance(data[key], kind):
            raise CoreError(f"{source}: {key!r} must be a table written {example}, got {data[key]!r}")
    if any(not isinstance(sd, dict) for sd in data.get("segment", [])):
        raise CoreError(f"{source}: every 'segment' entry must be a [[segment]] table")
    unknown = set(data) - {"gas", "tube", "segment", "fit"}
    if unknown:
        raise CoreError(f"{source}: unknown top-level key(s) {sorted(unknown)}; expected gas, tube, segment, fit")
    fit = data.get("fit", {})
    if not isinstance(fit, dict) or set(fit) - {"pinned"}:
        raise CoreError(f'{source}: [fit] takes only pinned = ["SEGMENT.FIELD", ...], got {fit!r}')
    pinned = fit.get("pinned", [])
    if not isinstance(pinned, list) or not all(isinstance(n, str) for n in pinned):
        raise CoreError(f"{source}: [fit] pinned must be a list of parameter names, got {pinned!r}")
    priors: dict = {}
    gas_d = dict(data.get("gas", {}))
    if "mixture" in gas_d:
        gas_d["name"] = gas_mixture_name(gas_d, source)
    gas_d = _declared(gas_d, "gas", ("p_mean", "T_cold"), f"{source}: gas", priors)
    bad = set(gas_d) - {"name", "p_mean", "T_cold"}
    if bad:
        raise CoreError(f"{source}: unknown key(s) in [gas]: {sorted(bad)}")
    gas = Gas(**gas_d)
    tube = _declared(dict(data.get("tube", {})), "tube", ("radius",), f"{source}: tube", priors)
    if set(tube) - {"radius"}:
        raise CoreError(f"{source}: unknown key(s) in [tube]: {sorted(set(tube) - {'radius'})}")
    segs = []
    for k, sd in enumerate(data.get("segment", [])):
        where = f"{source}: segment #{k + 1}"
        for key in ("name", "kind", "length"):
            if key not in sd:
                raise CoreError(f"{where}: missing key {key!r}")
        sd = _screen_keys(sd, f"{where} ({sd['name']!r})")
        bad = set(sd) - _SEGMENT_KEYS - {"T"}
        if bad:
            raise CoreError(f"{where} ({sd['name']!r}): unknown key(s) {sorted(bad)}; allowed {sorted(_SEGMENT_KEYS)}")
        sd = _imposed_temperatures(sd, f"{where} ({sd['name']!r})")
        sd = _declared(sd, sd["name"], SEGMENT_FIELDS, f"{where} ({sd['name']!r})", priors)
        if sd["kind"] == "duct":
            extra = (
                {"pore_model", "aspect_ratio"} | {f.name for f in SEGMENT_FIELD_TABLE if "porous" in f.applies}
            ) & set(sd)
            if extra:
                raise CoreError(f"{where} ({sd['name']!r}): a duct takes no {sorted(extra)}; use kind = 'porous'")
        elif "pore_radius" not in sd:
            raise CoreError(f"{where} ({sd['name']!r}): a porous segment needs pore_radius")
        for flag in ("thermal", "heater"):
            if flag in sd and not isinstance(sd[flag], bool):
                raise CoreError(f"{where} ({sd['name']!r}): {flag} must be true or false")
        segs.append(Segment(**sd))
    core = Core(tuple(segs), gas, tube.get("radius", 0.0167), source, tuple(pinned), priors)
    for name in pinned:
        try:
            core.get(name)
        except KeyError as e:
            raise CoreError(f"{source}: [fit] pinned: {e.args[0]}") from None
    unused = sorted(set(priors) - set(core.parameter_names()))
    if unused:
        raise CoreError(
            f"{source}: a prior is declared for {', '.join(unused)}, which the segment does not use "
            f"as a parameter (Core.parameter_names); write a plain value"
        )
    return core


def _imposed_temperatures(table: dict, where: str) -> dict:
    """A [[segment]] table with its imposed temperatures as ``T_start`` and ``T_end``: ``T``
    (uniform) gives both; ``thermal = true`` beside them is dropped (an imposed profile
    replaces the heat model there). Errors name the key."""
    out = dict(table)
    keys = [k for k in ("T", "T_start", "T_end") if k in out]
    if not keys:
        return out
    if "T" in out:
        if len(keys) > 1:
            raise CoreError(f"{where}: T (uniform) and {keys[1]} both given; write T, or T_start and T_end")
        if isinstance(out["T"], dict):
            raise CoreError(f"{where}: T takes a plain value [K]; declare priors on T_start and T_end")
        out["T_start"] = out["T_end"] = out.pop("T")
    elif len(keys) == 1:
        missing = "T_end" if keys[0] == "T_start" else "T_start"
        raise CoreError(f"{where}: {keys[0]} given without {missing}; a linear profile needs both (T: uniform) [K]")
    if out.get("heater") is True:
        raise CoreError(
            f"{where}: heater = true with imposed temperatures; a heater heats the heat model's segments, "
            f"whose temperatures are solved, not imposed"
        )
    out.pop("thermal", None)
    return out


def gas_mixture_name(gas: dict, source: str) -> str:
    """The gas name of a ``[gas.mixture]`` table {gas: mole fraction} (docs/formats.md)."""
    table = gas.pop("mixture")
    if "name" in gas:
        raise CoreError(f"{source}: [gas] has both name and [gas.mixture]; a mixture takes no name")
    if not isinstance(table, dict):
        raise CoreError(f"{source}: [gas.mixture] must be a table of mole fractions, e.g. helium = 0.7, argon = 0.3")
    try:
        return mixture_name(table)
    except ValueError as e:
        raise CoreError(f"{source}: [gas.mixture]: {e}") from None


def _declared(table: dict, owner: str, numeric, where: str, priors: dict) -> dict:
    """``table`` (a [gas], [tube] or [[segment]] table) with every inline table
    ``{value = v, sd | rel | range = ...}`` of a ``numeric`` field replaced by its value
    ``v``, its prior stored in ``priors`` under ``OWNER.FIELD`` (docs/priors.md)."""
    out = dict(table)
    for key, entry in table.items():
        if not isinstance(entry, dict):
            continue
        if key not in numeric:
            raise CoreError(f"{where}: {key} takes a plain value; only numeric fields take {{value = ..., sd = ...}}")
        spec = field_spec(f"{owner}.{key}" if owner in ("gas", "tube") else key)
        try:
            out[key], priors[f"{owner}.{key}"] = declared_prior(entry, spec, f"{where}: {key}")
        except PriorError as e:
            raise CoreError(str(e)) from None
    return out


def load_core(path: str | Path) -> Core:
    """Read and validate a core TOML file (docs/formats.md).

    ``path`` may also name a bundled core: ``ceramic``, ``mesh``, ``nicr_foam``, ``rvc_foam``.
    """
    p, data = read_toml(path, "cores")
    try:
        return core_from_dict(data, str(p))
    except TypeError as e:  # wrong value types reaching the dataclasses
        raise CoreError(f"{p}: {e}") from None


def read_toml(path: str | Path, folder: str) -> tuple[Path, dict]:
    """The path and parsed TOML of a description file; ``path`` may name a file bundled
    in ``tawarp/data/FOLDER`` (without ``.toml``). Errors name the file."""
    p = Path(path)
    if not p.exists() and str(path) in bundled(folder):
        p = Path(str(resources.files("tawarp") / "data" / folder / f"{path}.toml"))
    if not p.exists():
        raise FileNotFoundError(f"{path}: no such file (bundled {folder}: {', '.join(bundled(folder))})")
    try:
        return p, tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise CoreError(f"{p}: not valid TOML: {e}") from None


def bundled(folder: str) -> list[str]:
    """Names of the TOML files shipped in ``tawarp/data/FOLDER``."""
    return sorted(
        f.name[:-5] for f in (resources.files("tawarp") / "data" / folder).iterdir() if f.name.endswith(".toml")
    )


def bundled_cores() -> list[str]:
    """Names of every core shipped with tawarp: the paper-like thermoacoustic cores
    (:func:`paper_cores`) and passive samples (``foam_sample``)."""
    return bundled("cores")


def paper_cores() -> list[str]:
    """Names of the bundled thermoacoustic cores, one per material of the paper (those with
    thermal segments: a heat input means something for them)."""
    return [name for name in bundled_cores() if load_core(name).thermal_indices]


def dump_core(core: Core) -> str:
    """The TOML text of ``core``."""
    lines = []
    d = core.to_dict()
    for table in ("gas", "tube"):
        lines.append(f"[{table}]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in d[table].items()]
        lines.append("")
    for seg in d["segment"]:
        lines.append("[[segment]]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in seg.items()]
        lines.append("")
    if "fit" in d:
        lines += ["[fit]", "pinned = [" + ", ".join(f'"{n}"' for n in d["fit"]["pinned"]) + "]", ""]
    return "\n".join(lines)


def _toml_value(v) -> str:
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + "}"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return f'"{v}"'
    return repr(float(v))
