"""Engine networks: branches of segments joined at junctions, closed by ends (docs/formats.md,
"Engine network TOML"; docs/engines.md).

A network is what DeltaEC users build: segments in sequence (DeltaEC's DUCT, STKSCREEN, HX,
COMPLIANCE, ...), T-junctions that split the volume flow (TBRANCH/UNION), closed loops (a
traveling-wave engine's torus) and ends (HARDEND, an open end radiating, an impedance, an
RC load). Here a network is a graph:

* a **branch** is an ordered list of segments from a node ``from`` to a node ``to``; the
  state ``(p, U)`` (pressure [Pa], volume flow [m^3/s], positive from ``from`` to ``to``)
  runs along it;
* a **node** named by an ``[[end]]`` table is an end (exactly one branch touches it);
  any other node is a **junction**: every branch end that touches it has the same pressure
  and the volume flows into it sum to zero. A loop is a cycle of branches (a branch may go
  from a junction back to itself);
* every segment has an imposed temperature: uniform ``T`` or linear ``T_start`` ->
  ``T_end`` [K]; each is a number or the name ``"T_cold"`` / ``"T_hot"``. ``T_cold`` is
  ``[gas] T_cold``, ``T_hot`` the network's hot temperature (``[network] T_hot``), which the
  onset search varies (:mod:`tawarp.model.network_reference`).

Convention exp(-i omega t), as everywhere in tawarp.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .core import CoreError, Gas, gas_mixture_name, bundled, check_values, read_toml
from .gas import GASES
from .resonator import read_impedance_csv

SEGMENT_KINDS = ("duct", "porous", "compliance", "inertance")
PORE_MODELS = ("circular", "plates")
END_KINDS = ("closed", "open", "impedance", "load")
FLANGES = ("unflanged", "flanged")
TEMPERATURE_NAMES = ("T_cold", "T_hot")

#: keys each segment kind takes (besides name, kind), with what they mean (docs/formats.md)
_KIND_KEYS = {
    "duct": {"length", "radius", "area", "radius_end", "area_end", "T", "T_start", "T_end"},
    "porous": {
        "length",
        "radius",
        "area",
        "porosity",
        "pore_model",
        "pore_radius",
        "tortuosity",
        "solid_conductivity",
        "T",
        "T_start",
        "T_end",
    },
    "compliance": {"volume", "surface_area", "T"},
    "inertance": {"length", "radius", "area", "T"},
}
_END_KEYS = {
    "closed": {"name", "kind"},
    "open": {"name", "kind", "flange"},
    "impedance": {"name", "kind", "impedance", "impedance_csv"},
    "load": {"name", "kind", "resistance", "volume"},
}

Temperature = float | str


@dataclass(frozen=True)
class NetworkSegment:
    """One segment of a branch.

    ``kind``: ``duct`` (an empty tube, a cone when its end area differs), ``porous`` (a stack,
    regenerator or heat exchanger: ``porosity`` [-], ``pore_radius`` [m] of ``pore_model``
    circular pores (radius) or plates (half spacing), ``tortuosity`` [-],
    ``solid_conductivity`` [W/(m K)] for the total power's conduction term), ``compliance``
    (a lumped volume [m^3], optional inner ``surface_area`` [m^2] for its thermal-relaxation
    loss), ``inertance`` (a lumped short tube: length and area, viscous loss of a circular
    tube). ``area`` [m^2] is the cross-section at the start (the housing's for a porous
    segment), ``area_end`` at the end (a cone; ``area`` when equal). Temperatures
    ``T_start``, ``T_end`` [K] or the names ``T_cold``, ``T_hot``.
    """

    name: str
    kind: str
    length: float = 0.0
    area: float = math.nan
    area_end: float = math.nan
    porosity: float = 1.0
    pore_model: str = "circular"
    pore_radius: float = math.nan
    tortuosity: float = 1.0
    solid_conductivity: float = 0.0
    volume: float = 0.0
    surface_area: float = 0.0
    T_start: Temperature = "T_cold"
    T_end: Temperature = "T_cold"

    @property
    def lumped(self) -> bool:
        """Compliance and inertance have no length along which a profile runs."""
        return self.kind in ("compliance", "inertance")

    @property
    def extent(self) -> float:
        """Length along the branch's x [m] (a compliance has none)."""
        return 0.0 if self.kind == "compliance" else self.length

    def temperatures(self, T_cold: float, T_hot: float) -> tuple[float, float]:
        """(T_start, T_end) [K] with the names resolved."""
        names = {"T_cold": T_cold, "T_hot": T_hot}
        return tuple(float(names[t]) if isinstance(t, str) else float(t) for t in (self.T_start, self.T_end))

    def uses_T_hot(self) -> bool:
        return "T_hot" in (self.T_start, self.T_end)


@dataclass(frozen=True)
class Branch:
    """Segments in sequence from node ``start`` to node ``end`` (the file's ``from``/``to``)."""

    name: str
    start: str
    end: str
    segments: tuple[NetworkSegment, ...]

    def length(self) -> float:
        """Sum of the segments' extents [m]."""
        return sum(s.extent for s in self.segments)


@dataclass(frozen=True)
class NetworkEnd:
    """An end node: ``kind`` closed (U = 0), open (radiation of an ``unflanged`` or ``flanged``
    pipe end into free space), impedance (rows (freq [Hz], Z_re, Z_im [Pa s/m^3]), one row:
    constant) or load (``resistance`` [Pa s/m^3] in series with a closed ``volume`` [m^3]:
    DeltaEC's RC load). Z is p / U with U flowing out of the network into the end."""

    name: str
    kind: str
    flange: str = "unflanged"
    impedance: np.ndarray | None = field(default=None, compare=False)
    resistance: float = 0.0
    volume: float = 0.0


@dataclass(frozen=True)
class Network:
    """An engine network: ``gas``, ``branches``, ``ends`` {name: end}, the hot temperature
    ``T_hot`` [K] named by segments (the onset search varies it)."""

    gas: Gas
    branches: tuple[Branch, ...]
    ends: dict = field(default_factory=dict, hash=False)
    T_hot: float = math.nan
    source: str = "<network>"

    def __post_init__(self):
        object.__setattr__(self, "branches", tuple(self.branches))
        check_graph(self)

    def nodes(self) -> dict[str, list[tuple[int, str]]]:
        """{node: [(branch index, "start" | "end"), ...]} in branch order."""
        out: dict[str, list[tuple[int, str]]] = {}
        for b, br in enumerate(self.branches):
            out.setdefault(br.start, []).append((b, "start"))
            out.setdefault(br.end, []).append((b, "end"))
        return out

    def junctions(self) -> list[str]:
        return [n for n in self.nodes() if n not in self.ends]

    def segment(self, name: str) -> tuple[int, int]:
        """(branch index, segment index) of the segment ``name``."""
        for b, br in enumerate(self.branches):
            for s, seg in enumerate(br.segments):
                if seg.name == name:
                    return b, s
        raise KeyError(f"{self.source}: no segment named {name!r}")

    def uses_T_hot(self) -> bool:
        return any(s.uses_T_hot() for br in self.branches for s in br.segments)

    def replace(self, **values) -> "Network":
        """A copy with segment fields changed, keyed ``SEGMENT.FIELD`` (``regenerator.porosity``),
        or ``network.T_hot``, ``gas.p_mean``, ``gas.T_cold``."""
        gas, T_hot = self.gas, self.T_hot
        branches = [list(br.segments) for br in self.branches]
        for name, value in values.items():
            owner, _, fld = name.partition(".")
            if owner == "gas":
                gas = dataclasses.replace(gas, **{fld: float(value)})
            elif owner == "network" and fld == "T_hot":
                T_hot = float(value)
            else:
                b, s = self.segment(owner)
                if fld not in {f.name for f in dataclasses.fields(NetworkSegment)} - {"name", "kind"}:
                    raise KeyError(f"{name!r}: unknown segment field {fld!r}")
                branches[b][s] = dataclasses.replace(branches[b][s], **{fld: value})
        new = tuple(
            Branch(br.name, br.start, br.end, tuple(segs)) for br, segs in zip(self.branches, branches, strict=True)
        )
        return Network(gas, new, self.ends, T_hot, self.source)


# -- graph ---------------------------------------------------------------------------
def check_graph(net: Network) -> None:
    """Raise :class:`CoreError` unless every end is touched by exactly one branch end, every
    junction by at least two, and the network is one connected piece."""
    src = net.source
    if not net.branches:
        raise CoreError(f"{src}: no [[branch]] tables; a network needs at least one branch")
    names = [br.name for br in net.branches]
    for n in names:
        if names.count(n) > 1:
            raise CoreError(f"{src}: branch name {n!r} used twice")
    segs = [s.name for br in net.branches for s in br.segments]
    for n in segs:
        if segs.count(n) > 1:
            raise CoreError(f"{src}: segment name {n!r} used twice (segment names are global)")
    nodes = net.nodes()
    for end in net.ends:
        if end not in nodes:
            raise CoreError(f"{src}: [[end]] {end!r} is not the from/to of any branch")
        if len(nodes[end]) != 1:
            touching = [net.branches[b].name for b, _ in nodes[end]]
            raise CoreError(
                f"{src}: end {end!r} is touched by {len(touching)} branch ends ({touching}); an end closes exactly one"
            )
    for node, inc in nodes.items():
        if node not in net.ends and len(inc) < 2:
            b = net.branches[inc[0][0]].name
            raise CoreError(
                f"{src}: branch {b!r} {'starts' if inc[0][1] == 'start' else 'ends'} at {node!r}, which nothing "
                f"else touches; add an [[end]] named {node!r} or connect another branch there"
            )
    # connected: one piece (a second piece would be a separate device)
    seen, todo = set(), [next(iter(nodes))]
    while todo:
        n = todo.pop()
        if n in seen:
            continue
        seen.add(n)
        for b, _ in nodes[n]:
            todo += [net.branches[b].start, net.branches[b].end]
    if len(seen) != len(nodes):
        raise CoreError(f"{src}: the network falls into separate pieces; nodes {sorted(set(nodes) - seen)} are cut off")
    if net.uses_T_hot() and not (math.isfinite(net.T_hot) and net.T_hot > 0):
        raise CoreError(f"{src}: a segment names 'T_hot' but [network] T_hot is not given (a temperature [K] > 0)")


# -- TOML ----------------------------------------------------------------------------
def _number(v, where: str, positive: bool = True, allow_zero: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise CoreError(f"{where}: expected a finite number, got {v!r}")
    if positive and (v < 0 or (v == 0 and not allow_zero)):
        raise CoreError(f"{where}: must be {'>= 0' if allow_zero else '> 0'}, got {v!r}")
    return float(v)


def _temperature(v, where: str) -> Temperature:
    if isinstance(v, str):
        if v not in TEMPERATURE_NAMES:
            raise CoreError(f"{where}: {v!r}; expected a temperature [K] or one of {', '.join(TEMPERATURE_NAMES)}")
        return v
    return _number(v, where + " [K]")


def _area(d: dict, base: str, where: str) -> float:
    given = [k for k in (base.replace("area", "radius"), base) if k in d]
    if len(given) > 1:
        raise CoreError(f"{where}: give {given[0]} or {given[1]}, not both")
    if not given:
        return math.nan
    v = _number(d[given[0]], f"{where}: {given[0]} [m{'^2' if 'area' in given[0] else ''}]")
    return v if "area" in given[0] else math.pi * v**2


def segment_from_dict(d: dict, where: str) -> NetworkSegment:
    """One ``[[branch.segment]]`` table; errors name ``where`` and the key."""
    if not isinstance(d, dict):
        raise CoreError(f"{where}: every segment must be a [[branch.segment]] table")
    for key in ("name", "kind"):
        if key not in d:
            raise CoreError(f"{where}: missing key {key!r}")
    name, kind = d["name"], d["kind"]
    if not isinstance(name, str) or not name.isidentifier() or name in ("gas", "network"):
        raise CoreError(f"{where}: name {name!r} must be an identifier (letters, digits, _), not gas or network")
    where = f"{where} ({name!r})"
    if kind not in SEGMENT_KINDS:
        raise CoreError(f"{where}: kind = {kind!r}; expected one of {', '.join(SEGMENT_KINDS)}")
    bad = set(d) - {"name", "kind"} - _KIND_KEYS[kind]
    if bad:
        raise CoreError(f"{where}: a {kind} takes no {sorted(bad)}; allowed {sorted(_KIND_KEYS[kind])}")
    v: dict = {"name": name, "kind": kind}
    if kind == "compliance":
        if "volume" not in d:
            raise CoreError(f"{where}: a compliance needs volume [m^3]")
        v["volume"] = _number(d["volume"], f"{where}: volume [m^3]")
        if "surface_area" in d:
            v["surface_area"] = _number(d["surface_area"], f"{where}: surface_area [m^2]", allow_zero=True)
    else:
        if "length" not in d:
            raise CoreError(f"{where}: missing key 'length' [m]")
        v["length"] = _number(d["length"], f"{where}: length [m]")
        v["area"] = _area(d, "area", where)
        if not math.isfinite(v["area"]):
            raise CoreError(f"{where}: give its cross-section: radius [m] or area [m^2]")
        end_area = _area(d, "area_end", where) if kind == "duct" else math.nan
        v["area_end"] = end_area if math.isfinite(end_area) else v["area"]
    if kind == "porous":
        if "pore_radius" not in d:
            raise CoreError(f"{where}: a porous segment needs pore_radius [m] (plates: half the spacing)")
        v["pore_radius"] = _number(d["pore_radius"], f"{where}: pore_radius [m]")
        model = d.get("pore_model", "circular")
        if model not in PORE_MODELS:
            raise CoreError(f"{where}: pore_model = {model!r}; expected one of {', '.join(PORE_MODELS)}")
        v["pore_model"] = model
        v["porosity"] = _number(d.get("porosity", 1.0), f"{where}: porosity [-]")
        if v["porosity"] > 1:
            raise CoreError(f"{where}: porosity [-] must lie in (0, 1], got {v['porosity']}")
        v["tortuosity"] = _number(d.get("tortuosity", 1.0), f"{where}: tortuosity [-]")
        if v["tortuosity"] < 1:
            raise CoreError(f"{where}: tortuosity [-] must be >= 1, got {v['tortuosity']}")
        v["solid_conductivity"] = _number(
            d.get("solid_conductivity", 0.0), f"{where}: solid_conductivity [W/(m K)]", allow_zero=True
        )
        if v["pore_radius"] ** 2 * math.pi > v["area"]:
            raise CoreError(f"{where}: pore_radius {v['pore_radius']} m is wider than the segment's cross-section")
    if "T" in d and ("T_start" in d or "T_end" in d):
        raise CoreError(f"{where}: give T (uniform) or T_start and T_end (linear), not both")
    if "T" in d:
        v["T_start"] = v["T_end"] = _temperature(d["T"], f"{where}: T")
    elif ("T_start" in d) != ("T_end" in d):
        raise CoreError(f"{where}: a linear profile needs both T_start and T_end")
    elif "T_start" in d:
        v["T_start"] = _temperature(d["T_start"], f"{where}: T_start")
        v["T_end"] = _temperature(d["T_end"], f"{where}: T_end")
    return NetworkSegment(**v)


def _end_from_dict(d: dict, where: str, folder: Path) -> NetworkEnd:
    if not isinstance(d, dict) or "name" not in d or "kind" not in d:
        raise CoreError(f"{where}: an [[end]] table needs name and kind")
    kind = d["kind"]
    where = f"{where} ({d['name']!r})"
    if kind not in END_KINDS:
        raise CoreError(f"{where}: kind = {kind!r}; expected one of {', '.join(END_KINDS)}")
    bad = set(d) - _END_KEYS[kind]
    if bad:
        raise CoreError(f"{where}: a {kind} end takes no {sorted(bad)}; allowed {sorted(_END_KEYS[kind] - {'name'})}")
    if kind == "open":
        flange = d.get("flange", "unflanged")
        if flange not in FLANGES:
            raise CoreError(f"{where}: flange = {flange!r}; expected one of {', '.join(FLANGES)}")
        return NetworkEnd(d["name"], kind, flange=flange)
    if kind == "impedance":
        given = [k for k in ("impedance", "impedance_csv") if k in d]
        if len(given) != 1:
            raise CoreError(f"{where}: an impedance end needs exactly one of impedance = [Z_re, Z_im] or impedance_csv")
        if given[0] == "impedance_csv":
            return NetworkEnd(d["name"], kind, impedance=read_impedance_csv(folder / d["impedance_csv"]))
        z = d["impedance"]
        if not isinstance(z, list) or len(z) != 2:
            raise CoreError(f"{where}: impedance must be [Z_re, Z_im] in Pa s/m^3, got {z!r}")
        zr, zi = (_number(x, f"{where}: impedance", positive=False) for x in z)
        return NetworkEnd(d["name"], kind, impedance=np.array([[1.0, zr, zi]]))
    if kind == "load":
        for k in ("resistance", "volume"):
            if k not in d:
                raise CoreError(f"{where}: a load needs resistance [Pa s/m^3] and volume [m^3]")
        return NetworkEnd(
            d["name"],
            kind,
            resistance=_number(d["resistance"], f"{where}: resistance [Pa s/m^3]", allow_zero=True),
            volume=_number(d["volume"], f"{where}: volume [m^3]"),
        )
    return NetworkEnd(d["name"], kind)


def network_from_dict(data: dict, source: str = "<network>", folder: Path | None = None) -> Network:
    """A :class:`Network` from the TOML structure (docs/formats.md, "Engine network TOML")."""
    folder = folder or Path(".")
    unknown = set(data) - {"gas", "network", "branch", "end"}
    if unknown:
        raise CoreError(f"{source}: unknown top-level key(s) {sorted(unknown)}; expected gas, network, branch, end")
    gas_d = data.get("gas", {})
    if not isinstance(gas_d, dict) or set(gas_d) - {"name", "p_mean", "T_cold", "mixture"}:
        raise CoreError(f"{source}: [gas] takes name (or a [gas.mixture] table), p_mean, T_cold; got {gas_d!r}")
    gas_d = dict(gas_d)
    if "mixture" in gas_d:
        gas_d["name"] = gas_mixture_name(gas_d, source)
    gas = Gas(**gas_d)
    if not isinstance(gas.name, str) or gas.name not in GASES:
        raise CoreError(f"{source}: gas.name = {gas.name!r}; expected one of {sorted(GASES)}")
    check_values("p_mean", gas.p_mean, f"{source}: gas.p_mean")
    check_values("T_cold", gas.T_cold, f"{source}: gas.T_cold")
    net_d = data.get("network", {})
    if not isinstance(net_d, dict) or set(net_d) - {"T_hot"}:
        raise CoreError(f"{source}: [network] takes only T_hot = temperature [K]; got {net_d!r}")
    T_hot = _number(net_d["T_hot"], f"{source}: [network] T_hot [K]") if "T_hot" in net_d else math.nan
    branches = []
    for k, bd in enumerate(data.get("branch", [])):
        where = f"{source}: branch #{k + 1}"
        if not isinstance(bd, dict):
            raise CoreError(f"{where}: every branch must be a [[branch]] table")
        for key in ("name", "from", "to"):
            if not isinstance(bd.get(key), str):
                raise CoreError(f"{where}: missing key {key!r} (a name)")
        bad = set(bd) - {"name", "from", "to", "segment"}
        if bad:
            raise CoreError(f"{where} ({bd['name']!r}): unknown key(s) {sorted(bad)}; allowed name, from, to, segment")
        sds = bd.get("segment", [])
        if not isinstance(sds, list) or not sds:
            raise CoreError(f"{where} ({bd['name']!r}): no [[branch.segment]] tables")
        segs = tuple(segment_from_dict(sd, f"{where} ({bd['name']!r}) segment #{j + 1}") for j, sd in enumerate(sds))
        branches.append(Branch(bd["name"], bd["from"], bd["to"], segs))
    ends = {}
    for k, ed in enumerate(data.get("end", [])):
        e = _end_from_dict(ed, f"{source}: end #{k + 1}", folder)
        if e.name in ends:
            raise CoreError(f"{source}: end name {e.name!r} used twice")
        ends[e.name] = e
    return Network(gas, tuple(branches), ends, T_hot, source)


def is_network_file(data: dict) -> bool:
    """True for a network file (``[[branch]]`` tables), False for a core-based engine file."""
    return "branch" in data


def load_network(path: str | Path) -> Network:
    """Read and validate a network TOML file; ``path`` may name a bundled engine
    (``traveling_wave``, ``refrigerator``)."""
    p, data = read_toml(path, "engines")
    if not is_network_file(data):
        raise CoreError(f"{p}: no [[branch]] tables; a core-based engine file is read with load_engine")
    try:
        return network_from_dict(data, str(p), p.parent)
    except TypeError as e:
        raise CoreError(f"{p}: {e}") from None


def bundled_networks() -> list[str]:
    """Names of the bundled engine files that are networks."""
    return [n for n in bundled("engines") if is_network_file(read_toml(n, "engines")[1])]


def network_from_engine(engine) -> Network:
    """The network of a core-based engine (:class:`tawarp.model.resonator.ThermoacousticEngine`)
    whose temperatures are all imposed: one branch from the left end through the left duct,
    the core's segments and the right duct to the right end. An imposed temperature equal to
    the engine's highest is named ``"T_hot"`` (the onset search varies it), one equal to
    T_cold ``"T_cold"``; any other stays a number. Refused: segments the heat model solves,
    and effects a network segment does not have (the fields of
    :data:`tawarp.model.fields.EFFECT_OFF` away from their off values), impedance ends given
    as tables."""
    from .fields import EFFECT_OFF

    core, src = engine.core, engine.source
    T_c = core.gas.T_cold
    hot = max([T_c] + [t for s in core.segments if s.imposed for t in (s.T_start, s.T_end)])

    def name(t: float):
        return "T_hot" if t == hot and hot != T_c else "T_cold" if t == T_c else float(t)

    segs = []
    row = engine.resonator_row()
    for side, (L, R, T) in (("left", row[:3]), ("core", (0.0, 0.0, 0.0)), ("right", row[3:])):
        if side == "core":
            for s in core.segments:
                if s.thermal and not s.imposed:
                    raise CoreError(
                        f"{src}: segment {s.name!r} is solved by the heat model; a network needs T_start, T_end"
                    )
                on = [f for f, off in EFFECT_OFF.items() if getattr(s, f) != off]
                if on:
                    raise CoreError(f"{src}: segment {s.name!r} has {on}, which a network segment does not take")
                T0, T1 = (s.T_start, s.T_end) if s.imposed else (T_c, T_c)
                kw = {"pore_model": s.pore_model, "porosity": s.porosity, "pore_radius": s.pore_radius}
                kw |= {"tortuosity": s.tortuosity, "solid_conductivity": s.solid_conductivity}
                segs.append(
                    NetworkSegment(
                        s.name,
                        s.kind,
                        s.length,
                        core.area,
                        core.area,
                        T_start=name(T0),
                        T_end=name(T1),
                        **(kw if s.is_porous else {}),
                    )
                )
        elif L > 0:
            area = math.pi * R * R
            segs.append(NetworkSegment(f"{side}_duct", "duct", L, area, area, T_start=name(T), T_end=name(T)))
    ends = {}
    for side, e in (("left", engine.left), ("right", engine.right)):
        if e.kind == "impedance" and len(e.impedance) > 1:
            raise CoreError(f"{src}: the {side} end's impedance is a table; a network end takes [Z_re, Z_im]")
        if e.kind == "open":  # the engine's ideal open end: p = 0
            ends[f"{side}_end"] = NetworkEnd(f"{side}_end", "impedance", impedance=np.array([[1.0, 0.0, 0.0]]))
        else:
            ends[f"{side}_end"] = NetworkEnd(f"{side}_end", e.kind, impedance=e.impedance)
    branch = Branch("resonator", "left_end", "right_end", tuple(segs))
    return Network(core.gas, (branch,), ends, hot if hot != T_c else math.nan, src)
