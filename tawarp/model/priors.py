"""Priors of the model parameters: declared in a core file or defaulted from physics.

A :class:`Prior` is a Gaussian in ``ln v`` (``log``: a log-normal, its width relative) or
in ``v`` (width in the field's unit), truncated to a physical range. Every fitted
parameter gets one:

- **declared**: a core file's value written as an inline table (``h = {value = 150,
  rel = 0.2}``, docs/priors.md; parsed by :func:`declared_prior`, stored in ``Core.priors``);
- **defaulted**: :data:`DEFAULT_PRIORS`, a table of physical priors beside the fields
  table (:mod:`tawarp.model.fields`), centred on the core's value, keyed by field and, for
  the heat exchange ``h``, by the segment's role (:func:`segment_role`); any other field a
  broad log-normal (:data:`BROAD`);
- **effects**: :func:`effect_priors`, each effect parameter around its "off" value with
  its typical size as one prior standard deviation.

A fit is then maximum a posteriori: :meth:`Prior.x_moments` gives the prior as a
Gaussian in a :class:`~tawarp.model.effects.Param`'s scaled fit variable x, so that the
prior adds the residual row ``(x - mu_x) / sd_x``; :meth:`Prior.z` is a value's shift from
the prior in prior standard deviations (beyond :data:`TENSION_SD`: prior tension).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from .core import Core, CoreError
from .effects import Effect, Param, stack_and_heater
from .fields import GLOBAL_FIELD_TABLE, Field
from .fields import field as field_spec

#: A parameter further than this many prior standard deviations from its prior is in
#: tension with it (reported by name).
TENSION_SD = 3.0
#: Half-width of a central 95 % interval in standard deviations (the ``range`` syntax).
Z95 = 1.959963984540054


def _log_phi(z: float) -> float:
    """ln of the standard normal density at z."""
    return -0.5 * z * z - 0.5 * math.log(2.0 * math.pi)


def _upper_tail(z: float) -> float:
    """P(Z > z) of a standard normal, accurate far into the tail (erfc, no 1 - Phi)."""
    return 0.5 * math.erfc(z / math.sqrt(2.0))


@dataclass(frozen=True)
class Prior:
    """A prior of one parameter ``v``: Gaussian in ``ln v`` of median ``center`` and width
    ``sd`` (natural-log units: 0.2 is about +-20 %, ln 3 a factor of 3) when ``log``, else
    Gaussian in ``v`` of mean ``center`` and standard deviation ``sd`` (the field's unit);
    truncated to ``[lower, upper]`` (``v``'s unit either way). A ``center`` on a bound makes
    it one-sided (half-normal). ``source`` says where it comes from (not compared)."""

    center: float
    sd: float
    log: bool
    lower: float = -math.inf
    upper: float = math.inf
    source: str = field(default="", compare=False)

    def __post_init__(self):
        for name in ("center", "sd", "lower", "upper"):
            object.__setattr__(self, name, float(getattr(self, name)))
        if not (math.isfinite(self.sd) and self.sd > 0):
            raise ValueError(f"prior sd must be finite and > 0, got {self.sd}")
        if not math.isfinite(self.center):
            raise ValueError(f"prior center must be finite, got {self.center}")
        if not self.lower < self.upper or not self.lower <= self.center <= self.upper:
            raise ValueError(f"prior center {self.center} must lie in [{self.lower}, {self.upper}]")
        if self.log and self.center <= 0:
            raise ValueError(f"a log-normal prior needs a positive center, got {self.center}")

    # -- the prior's own variable y = ln v (log) or v ------------------------------------
    def _y(self, v: float) -> float:
        if not self.log:
            return v
        return math.log(v) if v > 0 else -math.inf

    @property
    def mass(self) -> float:
        """Probability mass of the untruncated Gaussian inside ``[lower, upper]``."""
        mu = self._y(self.center)
        a = (self._y(self.lower) - mu) / self.sd if self.lower > -math.inf else -math.inf
        b = (self._y(self.upper) - mu) / self.sd
        # the center lies inside, so a <= 0 <= b: both tails are <= 1/2 and nothing cancels
        return 1.0 - _upper_tail(-a) - _upper_tail(b)

    def z(self, value: float) -> float:
        """Signed shift of ``value`` from the center in prior standard deviations
        (in ``ln v`` for a log-normal prior; -inf for a value <= 0 there)."""
        return (self._y(float(value)) - self._y(self.center)) / self.sd

    def log_density(self, value: float) -> float:
        """ln of the prior probability density at ``value`` [1/(unit of v)], normalised on
        the truncated range: ``ln N(y; mu, sd) - ln mass`` (a half-normal: ln 2 above
        the Gaussian), minus ``ln v`` for a log-normal (the Jacobian of y = ln v);
        -inf outside ``[lower, upper]``."""
        v = float(value)
        if not self.lower <= v <= self.upper or (self.log and v <= 0):
            return -math.inf
        jacobian = math.log(v) if self.log else 0.0
        return _log_phi(self.z(v)) - math.log(self.sd) - math.log(self.mass) - jacobian

    def log_density_x(self, x: float, par: Param) -> float:
        """ln of the prior density of the fit variable ``x`` of ``par`` (the variable the
        Laplace evidence's covariance is in): :meth:`log_density` at ``par.value(x)`` plus
        ln |dv/dx| (``start e^x`` for a log Param, ``scale`` for a linear one). Exact,
        whatever the two scales."""
        v = float(par.value(x))
        dvdx = v if par.log else par.scale
        return self.log_density(v) + math.log(abs(dvdx))

    def x_moments(self, par: Param) -> tuple[float, float]:
        """``(mu_x, sd_x)``: the prior as a Gaussian in ``par``'s scaled fit variable
        ``x`` (``ln(v/start)`` for a log Param, ``(v - start)/scale`` for a linear one),
        the MAP fit's residual row ``(x - mu_x)/sd_x``. Exact (for the untruncated
        Gaussian) when ``par.log == self.log``; otherwise linearised at the center
        (``ln v ~ ln c + (v - c)/c``), good while ``sd`` is small against the center
        (relative width of a log-normal, sd/center of a normal). Truncation is not in the
        moments: the fit's bounds keep x inside."""
        if self.log == par.log:
            if self.log:
                return math.log(self.center / par.start), self.sd
            return (self.center - par.start) / par.scale, self.sd / par.scale
        if self.log:  # log-normal prior, linear fit variable: v ~ c (1 + u), u ~ N(0, sd)
            return (self.center - par.start) / par.scale, self.center * self.sd / par.scale
        if self.center <= 0:
            raise ValueError(f"{par.label}: a normal prior centred at {self.center} has no ln-scale moments")
        return math.log(self.center / par.start), self.sd / self.center

    def in_scale(self, log: bool) -> Prior:
        """This prior as a Gaussian in the other variable (``log``: ln v, else v), of the
        same center and the width linearised there (sd_v = center sd_ln); itself when
        ``log`` already matches."""
        if log == self.log:
            return self
        sd = self.center * self.sd if self.log else self.sd / self.center
        return Prior(self.center, sd, log, self.lower, self.upper, self.source)

    def describe(self, unit: str = "") -> str:
        """Short text: ``150 W/(m^2 K) x/÷ 3`` (log-normal: a factor per sd) or
        ``0.8 +- 0.1`` (normal), with the bounds that lie within 3 sd."""
        u = f" {unit}" if unit and unit != "-" else ""
        text = (
            f"{self.center:.4g}{u} x/÷ {math.exp(self.sd):.3g}"
            if self.log
            else f"{self.center:.4g} +- {self.sd:.3g}{u}"
        )
        near = [
            (op, b)
            for op, b in ((">=", self.lower), ("<=", self.upper))
            if math.isfinite(self._y(b)) and abs(self.z(b)) <= 3.0
        ]
        return text + "".join(f", {op} {b:.4g}" for op, b in near)

    def toml_entry(self, value: float) -> dict:
        """The inline table of a core file that declares this prior for a field of model
        value ``value`` (docs/priors.md): ``rel`` for a log-normal, ``sd`` for a normal,
        ``center`` when it differs from the value (a fitted core keeps its prior)."""
        out = {"value": float(value)}
        if self.center != float(value):
            out["center"] = self.center
        out["rel" if self.log else "sd"] = self.sd
        return out


# -- declared priors: the core file's syntax --------------------------------------------
DECLARED_KEYS = ("value", "center", "sd", "rel", "range")


def _is_number(v) -> bool:
    """A finite TOML number (a TOML boolean is not one)."""
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


def _number(entry: dict, key: str, where: str) -> float:
    if not _is_number(entry[key]):
        raise CoreError(f"{where}: {key} must be a finite number, got {entry[key]!r}")
    return float(entry[key])


def declared_prior(entry: dict, f: Field, where: str) -> tuple[float, Prior]:
    """``(value, prior)`` of a core file's inline table for field ``f``: ``{value = v,
    sd = s}`` (absolute sd, the field's unit), ``{value = v, rel = r}`` (sd relative to
    the center) or ``{value = v, range = [lo, hi]}`` (the central 95 % interval; its middle
    is the center and ``v`` must lie inside), each optionally with ``center = c`` (the
    prior's center when it is not ``v``: a fitted core written back). The prior is a
    Gaussian in the field's fit scale: log-normal for a log-scaled field (fields table)
    with a positive center (sd converted as sd/center, rel is the width in ln), else
    normal (rel converted as rel |center|); truncated to the field's physical range.
    ``where`` names the file and key in errors (:class:`~tawarp.model.core.CoreError`)."""
    unknown = sorted(set(entry) - set(DECLARED_KEYS))
    if unknown:
        raise CoreError(
            f"{where}: unknown key(s) {unknown} in the inline table; allowed {list(DECLARED_KEYS)}, "
            f"e.g. {{value = 150, rel = 0.2}}"
        )
    if "value" not in entry:
        raise CoreError(f"{where}: an inline table needs value = ..., e.g. {{value = 150, sd = 30}}")
    value = _number(entry, "value", where)
    widths = [k for k in ("sd", "rel", "range") if k in entry]
    if len(widths) != 1:
        raise CoreError(f"{where}: give exactly one of sd, rel, range, got {widths or 'none'}")
    width = widths[0]
    if width == "range":
        if "center" in entry:
            raise CoreError(f"{where}: a range sets the center (its middle); drop center or write sd/rel")
        lo_hi = entry["range"]
        if not isinstance(lo_hi, list) or len(lo_hi) != 2 or not all(map(_is_number, lo_hi)):
            raise CoreError(f"{where}: range must be two finite numbers [low, high], got {lo_hi!r}")
        lo, hi = map(float, lo_hi)
        if not lo < hi:
            raise CoreError(f"{where}: range [{lo}, {hi}] is reversed or empty; write [low, high]")
        if not lo <= value <= hi:
            raise CoreError(f"{where}: value {value} lies outside its range [{lo}, {hi}]")
        if f.log and lo <= 0:
            raise CoreError(
                f"{where}: {f.name} is fitted in ln (log-normal prior): its range must be positive, "
                f"got [{lo}, {hi}]; or write sd = ..."
            )
        if f.log:
            center, sd = math.sqrt(lo * hi), math.log(hi / lo) / (2 * Z95)
        else:
            center, sd = 0.5 * (lo + hi), (hi - lo) / (2 * Z95)
        log = f.log
    else:
        center = _number(entry, "center", where) if "center" in entry else value
        s = _number(entry, width, where)
        if s <= 0:
            raise CoreError(f"{where}: {width} must be > 0, got {s} (a value known exactly belongs in [fit] pinned)")
        log = f.log and center > 0
        if width == "sd":
            sd = s / center if log else s
        else:
            if center == 0:
                raise CoreError(f"{where}: rel is relative to the center, which is 0; write sd = ...")
            sd = s if log else s * abs(center)
    if not f.check(center):
        raise CoreError(f"{where} [{f.unit}]: prior center {center} outside the physical range {f.range_text()}")
    return value, Prior(center, sd, log, f.lower, f.upper, source=f"declared ({where})")


# -- default physical priors --------------------------------------------------------------
@dataclass(frozen=True)
class DefaultPrior:
    """A row of :data:`DEFAULT_PRIORS`: the form of a prior, centred on the core's value
    when used: log-normal of width ``sd`` in ln v when ``log`` (a factor e^sd per sd),
    else normal of ``sd`` in the field's unit; truncated to the field's physical range and
    ``[lower, upper]``. ``reason``: why this width."""

    sd: float
    log: bool
    reason: str
    lower: float = -math.inf
    upper: float = math.inf

    def at(self, center: float, f: Field, source: str) -> Prior:
        """The prior of field ``f`` centred on ``center``. A log-normal form cannot centre
        on a value <= 0: such a field (an ``h`` of 0, a porous sample's unused solid
        conductivity of 0) gets a normal of the field's linear fit scale ``f.scale``
        instead, the same fallback :func:`~tawarp.model.effects.base_params` scales it by."""
        lower, upper = max(self.lower, f.lower), min(self.upper, f.upper)
        if self.log and center <= 0:
            return Prior(center, f.scale, False, lower, upper, source + " (normal: value <= 0)")
        return Prior(center, self.sd, self.log, lower, upper, source)


#: Default physical priors, keyed ``(field name, role)``: role None for every segment,
#: else a :func:`segment_role` (only ``h`` depends on the role). Fields not listed get
#: :data:`BROAD`. Centred on the core file's value; docs/priors.md explains each row.
DEFAULT_PRIORS: dict[tuple[str, str | None], DefaultPrior] = {
    ("h", "buffer_tube"): DefaultPrior(
        1.0,
        True,
        "buffer tube: natural convection inside and conduction through the wall to the room; the paper's "
        "fitted h_a is about 0.2 W/(m^2 K) and a buffer tube's exchange with the room is weak: the order of "
        "magnitude is known, not the value (a factor of e per sd, so a value 20x the file's is 3 sd off)",
    ),
    ("h", "stack"): DefaultPrior(
        math.log(3.0),
        True,
        "stack: the paper only bounds h_s (>= 150 ceramic, about 50 mesh, <= 10 RVC) and notes that lam_s and "
        "h_s are too correlated to fit together: a factor of 3 per sd",
    ),
    ("h", "hot_exchanger"): DefaultPrior(
        math.log(2.0),
        True,
        "hot exchanger: the paper gives h_h = 100 +- 50 W/(m^2 K), a factor of 1.5, widened to 2 per sd for "
        "a core file itself 10-20 % off",
    ),
    ("porosity", None): DefaultPrior(
        0.1,
        False,
        "porosity from a datasheet or a weighing is good to a few hundredths; 0.1 allows for the open vs. "
        "total porosity of foams; truncated to (0, 1]",
    ),
    ("pore_radius", None): DefaultPrior(
        math.log(1.5),
        True,
        "a pore radius follows from a cell count or a fibre diameter through a shape assumption (hydraulic "
        "radius, PPI to pore size): good to some 30-50 %, the paper's +-10 % are fitted values",
    ),
    ("tortuosity", None): DefaultPrior(
        0.2,
        True,
        "q = sqrt(alpha_inf) is 1.0-1.3 for the paper's materials: 0.2 in ln (+-20 %), truncated to q >= 1",
        lower=1.0,
    ),
    ("length", None): DefaultPrior(
        2e-3,
        False,
        "a length is a plane position or a cut: known to a couple of millimetres (microphone spacers, the "
        "sample's faces)",
    ),
    ("T_cold", None): DefaultPrior(5.0, False, "the room or cold-end temperature is known to a few kelvin (+-5 K)"),
    ("p_mean", None): DefaultPrior(0.03, True, "the static pressure from a barometer or the altitude: +-3 %"),
    ("radius", None): DefaultPrior(
        0.02, True, "the tube's bore, measured with calipers or taken from a pipe standard: +-2 %"
    ),
}
#: The prior of a field without a row: broad, a factor of 3 per sd around the core's value.
BROAD = DefaultPrior(math.log(3.0), True, "no physical knowledge stated: a factor of 3 per sd")


def segment_role(core: Core, name: str) -> str | None:
    """Role of segment ``name`` in the heat model: ``hot_exchanger`` (the heater),
    ``stack`` (the porous thermal segment before it, as
    :func:`~tawarp.model.effects.stack_and_heater` finds it), ``buffer_tube`` (the thermal
    duct right after the heater); None for any other segment."""
    stack, heater = stack_and_heater(core)
    if name == heater:
        return "hot_exchanger"
    if name == stack:
        return "stack"
    segs = core.segments
    i = next((k for k, s in enumerate(segs) if s.name == name), None)
    if i is None:
        raise KeyError(f"{core.source}: no segment named {name!r} (have {[s.name for s in segs]})")
    if i > 0 and segs[i - 1].name == heater and segs[i].thermal and not segs[i].is_porous:
        return "buffer_tube"
    return None


def default_prior(name: str, center: float, role: str | None = None) -> Prior:
    """The default prior of field or parameter ``name`` (``tbt.h``, ``porosity``,
    ``gas.T_cold``) in segment role ``role``, centred on ``center``:
    :data:`DEFAULT_PRIORS`, else :data:`BROAD`."""
    f = field_spec(name)
    for key in ((f.name, role), (f.name, None)):
        if key in DEFAULT_PRIORS:
            what = f"{f.name} of a {role.replace('_', ' ')}" if key[1] else f.name
            return DEFAULT_PRIORS[key].at(center, f, f"default: {what}")
    return BROAD.at(center, f, "default")


def prior_for(core: Core, label: str) -> Prior:
    """The prior of parameter ``label`` (``SEGMENT.FIELD``, ``gas.T_cold``, ...) of
    ``core``: the one its file declares (``core.priors``), else the default for that field
    and the segment's role, centred on the core's value. Call it on the core as the user
    gave it: on a fitted copy the defaults would centre on fitted values (declared priors
    keep their center through :meth:`Core.replace`)."""
    if label in core.priors:
        return core.priors[label]
    value = core.get(label)  # validates the name
    owner, _, fld = label.partition(".")
    role = segment_role(core, owner) if label not in GLOBAL_FIELD_TABLE and fld == "h" else None
    return default_prior(label, value, role)


# -- effect priors ------------------------------------------------------------------------
def _frees_base_parameter(par: Param) -> bool:
    """True for a Param that frees one existing parameter of the base model (the plane
    offsets' duct lengths, T_cold, p_mean): a field without an "off" value, set alone."""
    f = field_spec(par.label)
    return par.expand is None and par.targets == (par.label,) and f.neutral is None and f.row >= 0


#: An effect's switch has a prior sd of this many typical sizes: the typical size is where
#: the effect usually sits, not how far it goes (a radiative conductivity of 0.05 W/(m K),
#: 3.7 typical sizes, is a foam at 600 K; a conductivity exponent of 1 is 2.9), and a value
#: a few typical sizes away must not read as prior tension.
EFFECT_WIDTH = 2.0


def effect_priors(effect: Effect, core: Core | None = None) -> dict[str, Prior]:
    """{param label: prior} of ``effect``, each in its Param's own scale (ln for a log
    Param, linear otherwise; a default of the other scale linearised at its center),
    truncated to the field's physical range:

    - a Param that frees a base parameter (plane offsets, ``gas.T_cold``, ``gas.p_mean``):
      that field's default (:func:`default_prior`: +-2 mm, +-5 K, +-3 %) around its start;
    - an effect's switch: centred on "off" (the Param's start) with :data:`EFFECT_WIDTH`
      typical sizes as one sd, the typical size being the largest distance from "off" of
      :attr:`Effect.typical` and of the effect's extra refit ``starts`` (the elastic
      frame's E from 1e4 to 1e7 Pa is such a stated span). "Off" on the field's physical bound (radiation, convection, wall
      conduction, frame mobility >= 0) makes it a half-normal;
    - a Param whose typical value is its start (the ambient exchangers' porosity and pore
      radius, a frame's loss factor and density: shape parameters of an effect another
      Param switches on): its field's default around the start.

    A prior that ``core``'s file declares for the label wins."""
    out = {}
    for par in effect.params:
        if core is not None and par.label in core.priors:
            out[par.label] = core.priors[par.label]
            continue
        f = field_spec(par.label)
        spread = [
            v[par.label] for v in (effect.typical, *effect.starts) if par.label in v and v[par.label] != par.start
        ]
        if spread and not _frees_base_parameter(par):
            sd = EFFECT_WIDTH * max(abs(float(par.x_of(v))) for v in spread) * (1.0 if par.log else par.scale)
            prior = Prior(
                par.start,
                sd,
                par.log,
                f.lower,
                f.upper,
                source=f"effect {effect.name}: off +- {EFFECT_WIDTH:g} typical sizes",
            )
        else:
            prior = default_prior(par.label, par.start)
            if prior.log and not par.log:
                prior = prior.in_scale(False)
        out[par.label] = prior
    return out


def tension(label: str, prior: Prior, value: float, unit: str = "") -> str | None:
    """A one-line report when ``value`` lies more than :data:`TENSION_SD` prior sds from
    ``prior`` (``tbt.h = 8 W/(m^2 K) is 40x its prior 0.2 W/(m^2 K) x/÷ 3 (+3.4 prior
    sd)``; a normal prior: ``... is 5.4 prior sd above its prior 0 +- 1.85 W/(m K), >= 0``),
    else None."""
    z = prior.z(value)
    if abs(z) <= TENSION_SD:
        return None
    u = f" {unit}" if unit and unit != "-" else ""
    if prior.log and value > 0:
        return (
            f"{label} = {value:.4g}{u} is {value / prior.center:.3g}x its prior {prior.describe(unit)} "
            f"({z:+.1f} prior sd)"
        )
    side = "above" if z > 0 else "below"
    return f"{label} = {value:.4g}{u} is {abs(z):.1f} prior sd {side} its prior {prior.describe(unit)}"
