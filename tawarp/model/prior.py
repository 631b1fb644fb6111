"""One parameter's prior: the distribution (:class:`Prior`), its syntax in a core file
(:func:`declared_prior`) and the report of a value far from it (:func:`tension`).

A :class:`Prior` is a Gaussian in ``ln v`` (``log``: a log-normal, its width relative) or
in ``v`` (width in the field's unit), truncated to a physical range. Where each parameter's
prior comes from (the core file, the documented defaults, an effect's typical size) is
:mod:`tawarp.model.priors`; this module depends on the fields table alone, so that the core
file's reader can parse declared priors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from .fields import Field


class PriorError(ValueError):
    """A declared prior that cannot be read (the core reader names the file and key)."""


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

    def log_density_x(self, x: float, par) -> float:
        """ln of the prior density of the fit variable ``x`` of ``par`` (the variable the
        Laplace evidence's covariance is in): :meth:`log_density` at ``par.value(x)`` plus
        ln |dv/dx| (``start e^x`` for a log Param, ``scale`` for a linear one). Exact,
        whatever the two scales."""
        v = float(par.value(x))
        dvdx = v if par.log else par.scale
        return self.log_density(v) + math.log(abs(dvdx))

    def x_moments(self, par) -> tuple[float, float]:
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
        raise PriorError(f"{where}: {key} must be a finite number, got {entry[key]!r}")
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
    ``where`` names the file and key in errors (:class:`~tawarp.model.core.PriorError`)."""
    unknown = sorted(set(entry) - set(DECLARED_KEYS))
    if unknown:
        raise PriorError(
            f"{where}: unknown key(s) {unknown} in the inline table; allowed {list(DECLARED_KEYS)}, "
            f"e.g. {{value = 150, rel = 0.2}}"
        )
    if "value" not in entry:
        raise PriorError(f"{where}: an inline table needs value = ..., e.g. {{value = 150, sd = 30}}")
    value = _number(entry, "value", where)
    widths = [k for k in ("sd", "rel", "range") if k in entry]
    if len(widths) != 1:
        raise PriorError(f"{where}: give exactly one of sd, rel, range, got {widths or 'none'}")
    width = widths[0]
    if width == "range":
        if "center" in entry:
            raise PriorError(f"{where}: a range sets the center (its middle); drop center or write sd/rel")
        lo_hi = entry["range"]
        if not isinstance(lo_hi, list) or len(lo_hi) != 2 or not all(map(_is_number, lo_hi)):
            raise PriorError(f"{where}: range must be two finite numbers [low, high], got {lo_hi!r}")
        lo, hi = map(float, lo_hi)
        if not lo < hi:
            raise PriorError(f"{where}: range [{lo}, {hi}] is reversed or empty; write [low, high]")
        if not lo <= value <= hi:
            raise PriorError(f"{where}: value {value} lies outside its range [{lo}, {hi}]")
        if f.log and lo <= 0:
            raise PriorError(
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
            raise PriorError(f"{where}: {width} must be > 0, got {s} (a value known exactly belongs in [fit] pinned)")
        log = f.log and center > 0
        if width == "sd":
            sd = s / center if log else s
        else:
            if center == 0:
                raise PriorError(f"{where}: rel is relative to the center, which is 0; write sd = ...")
            sd = s if log else s * abs(center)
    if not f.check(center):
        raise PriorError(f"{where} [{f.unit}]: prior center {center} outside the physical range {f.range_text()}")
    return value, Prior(center, sd, log, f.lower, f.upper, source=f"declared ({where})")


# -- default physical priors --------------------------------------------------------------
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
