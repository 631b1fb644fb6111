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
from dataclasses import dataclass

from .core import Core
from .effects import Effect, Param, stack_and_heater
from .fields import GLOBAL_FIELD_TABLE, Field
from .fields import field as field_spec
from .prior import Z95, Prior


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
    ("wall_resistance", None): DefaultPrior(
        math.log(2.0),
        True,
        "the lateral resistance 1/h_w between the tube wall and the gas of a laminar duct (Nu = 3.66-4.36 over "
        "D: h_w ~ 4 k_gas/D, its gas warmer than T_cold and stirred by convection) or a porous part touching "
        "the wall across a gas film of ~0.1 mm (h_w ~ k_gas/0.1 mm): an order of magnitude known from the "
        "physics, a factor of 2 per sd",
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
    - a log Param with such a span (the layer frame's wave speed, 12-1200 m/s): a scale, not a
      switch (its start is no "off"), whose value is known to decades: log-normal around the
      start with the span as its central 95 % (the ``range`` of a declared prior);
    - a Param whose typical value is its start (the ambient exchangers' porosity and pore
      radius, a frame's loss factor: shape parameters of an effect another
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
        if spread and par.log:
            # a scale, never "off" (x = 0 switches nothing): its stated span is the central 95 %
            sd = max(abs(float(par.x_of(v))) for v in spread) / Z95
            prior = Prior(par.start, sd, True, f.lower, f.upper, source=f"effect {effect.name}: its stated span")
        elif spread and not _frees_base_parameter(par):
            sd = EFFECT_WIDTH * max(abs(float(par.x_of(v))) for v in spread) * par.scale
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
