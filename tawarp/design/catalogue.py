"""Catalogue of stack materials for design search and ranking.

A :class:`Material` holds what the core model needs of a stack material: porosity
``phi`` [-], pore radius [m], tortuosity ``q`` [-], solid conductivity [W/(m K)] and the
lateral heat-exchange coefficient ``h_s`` [W/(m^2 K)], with their uncertainty: either a
full covariance over :data:`PARAMS` or independent standard deviations.

The four materials of the paper (Guedra et al. 2015, Table 1; docs/physics.md) are built in,
with the same values as the bundled cores. Their ``±`` values are the standard
deviations. The paper gives no ``±`` for ``h_s`` (ceramic ``>= 150``, mesh ``≈ 50``,
RVC ``<= 10``, NiCr none); the standard deviations used here are tawarp's choices and are
stated in :data:`PAPER_NOTES`. Solid conductivities are taken as exact (std 0).

A catalogue is extended by the user through TOML files::

    [[material]]
    name = "my_foam"
    porosity = 0.95
    pore_radius = 0.2e-3          # m
    tortuosity = 1.1
    solid_conductivity = 5.0      # W/(m K)
    h_s = 12.0                    # W/(m^2 K)
    std = { porosity = 0.01, h_s = 3.0 }   # optional
    # correlation = [[1, 0.3], [0.3, 1]]   # optional, over the keys of `std` in the order of PARAMS

    [[material]]
    name = "fitted_foam"
    fit = "fit.json"              # a `tawarp fit` result (docs/formats.md); relative to this file
    base = "rvc_foam"             # values of the parameters the fit did not estimate

and by ``fit.json`` files directly (:meth:`Material.from_fit_json`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..model.core import Core, CoreError, check_values
from ..model.fields import field as parameter_field
from ..rng import generator

#: Uncertain parameters of a material, in the order of :attr:`Material.covariance`.
PARAMS = ("porosity", "pore_radius", "tortuosity", "solid_conductivity", "h_s")
#: Core field (``SEGMENT.FIELD``) of each material parameter.
CORE_FIELD = {
    "porosity": "porosity",
    "pore_radius": "pore_radius",
    "tortuosity": "tortuosity",
    "solid_conductivity": "solid_conductivity",
    "h_s": "h",
}
_FIELD_TO_PARAM = {v: k for k, v in CORE_FIELD.items()}


class CatalogueError(ValueError):
    """A material or catalogue file is invalid; the message names the file and key."""


@dataclass(frozen=True)
class Material:
    """A stack material. ``std`` maps parameter -> standard deviation (missing: exact);
    ``correlation`` (len(PARAMS) x len(PARAMS)) completes it to a covariance, identity
    when absent. ``source`` says where the values come from."""

    name: str
    porosity: float
    pore_radius: float
    tortuosity: float
    solid_conductivity: float
    h_s: float
    std: dict = field(default_factory=dict)
    correlation: tuple | None = None
    source: str = "<material>"

    def __post_init__(self):
        where = f"{self.source}: material {self.name!r}"
        try:
            for p in PARAMS:
                check_values(CORE_FIELD[p], getattr(self, p), f"{where}: {p}")
        except CoreError as e:
            raise CatalogueError(str(e)) from None
        bad = set(self.std) - set(PARAMS)
        if bad:
            raise CatalogueError(f"{where}: std for unknown parameter(s) {sorted(bad)}; allowed {PARAMS}")
        for k, v in self.std.items():
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise CatalogueError(f"{where}: std.{k} must be a finite number >= 0, got {v!r}")
        if self.correlation is not None:
            c = np.asarray(self.correlation, dtype=float)
            if (
                c.shape != (len(PARAMS), len(PARAMS))
                or not np.allclose(c, c.T)
                or np.any(np.abs(np.diag(c) - 1) > 1e-9)
            ):
                raise CatalogueError(
                    f"{where}: correlation must be a symmetric {len(PARAMS)}x{len(PARAMS)} matrix "
                    f"with unit diagonal over {PARAMS}"
                )
            object.__setattr__(self, "correlation", tuple(map(tuple, c.tolist())))

    # -- values ------------------------------------------------------------------------
    def values(self) -> np.ndarray:
        """Mean values in the order of :data:`PARAMS`."""
        return np.array([getattr(self, p) for p in PARAMS], dtype=float)

    def std_vector(self) -> np.ndarray:
        return np.array([float(self.std.get(p, 0.0)) for p in PARAMS])

    def covariance(self) -> np.ndarray:
        """(len(PARAMS), len(PARAMS)) covariance: diag(std) C diag(std)."""
        s = self.std_vector()
        c = np.eye(len(PARAMS)) if self.correlation is None else np.asarray(self.correlation)
        return s[:, None] * c * s[None, :]

    def core_params(self, segment: str = "stack") -> dict[str, float]:
        """``{"SEGMENT.FIELD": value}`` that puts this material in ``segment`` of a core."""
        return {f"{segment}.{CORE_FIELD[p]}": getattr(self, p) for p in PARAMS}

    def apply(self, core: Core, segment: str = "stack") -> Core:
        """``core`` with this material in ``segment`` (which must be porous)."""
        if not core.segment(segment).is_porous:
            raise CoreError(f"{core.source}: segment {segment!r} is not porous; a material needs a porous segment")
        return core.replace(**self.core_params(segment))

    def sample(self, n: int, rng: np.random.Generator | int | None = None) -> dict[str, np.ndarray]:
        """n draws from N(mean, covariance), clipped to the ranges a fit may reach (the
        parameter table's ``fit_range``, :mod:`tawarp.model.fields`): {param: (n,)}."""
        rng = generator(rng, "Material.sample", argument="rng")
        cov = self.covariance()
        mean = self.values()
        active = np.flatnonzero(np.diag(cov) > 0)
        x = np.tile(mean, (n, 1))
        if active.size:
            sub = cov[np.ix_(active, active)]
            # eigh tolerates a singular (fully correlated) covariance
            w, v = np.linalg.eigh(sub)
            L = v * np.sqrt(np.clip(w, 0, None))
            x[:, active] += rng.standard_normal((n, active.size)) @ L.T
        out = {}
        for j, p in enumerate(PARAMS):
            lo, hi = parameter_field(CORE_FIELD[p]).fit_range
            out[p] = np.clip(x[:, j], lo, hi)
        return out

    def to_dict(self) -> dict:
        d = {p: getattr(self, p) for p in PARAMS}
        d.update(name=self.name, std=dict(self.std), source=self.source)
        if self.correlation is not None:
            d["correlation"] = [list(r) for r in self.correlation]
        return d

    # -- construction ------------------------------------------------------------------
    @classmethod
    def from_core(
        cls, core: Core, segment: str = "stack", name: str | None = None, std: dict | None = None
    ) -> "Material":
        """The material of porous ``segment`` of ``core``."""
        seg = core.segment(segment)
        if not seg.is_porous:
            raise CoreError(f"{core.source}: segment {segment!r} is not porous")
        return cls(
            name or Path(core.source).stem,
            seg.porosity,
            seg.pore_radius,
            seg.tortuosity,
            seg.solid_conductivity,
            seg.h,
            dict(std or {}),
            None,
            core.source,
        )

    @classmethod
    def from_fit_json(
        cls, path: str | Path, base: "Material | str | None" = None, name: str | None = None, segment: str = "stack"
    ) -> "Material":
        """A material from a ``tawarp fit`` result (docs/formats.md: for each fitted parameter
        ``value`` and ``std``, plus the correlation matrix).

        Accepted layouts: ``{"parameters": {"stack.porosity": {"value", "std"}, ...},
        "correlation": [[...]] | {"names": [...], "matrix": [[...]]}}``, the parameters
        also as a list of ``{"name", "value", "std"}``. Fitted parameters of ``segment``
        (``stack.porosity``, ``stack.pore_radius``, ``stack.tortuosity``,
        ``stack.solid_conductivity``, ``stack.h``) set the material; others (``hot_hx.h``)
        are ignored. A two-step fit's h (one per heat input in ``step2``) gives ``h_s`` by
        :func:`_h_over_heat_inputs`. Unfitted values come from ``base`` (a Material, a catalogue name, or,
        when None, the core named by the file's ``core`` key)."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise
        except (OSError, json.JSONDecodeError) as e:
            raise CatalogueError(f"{path}: not a readable JSON file: {e}") from None
        params = data.get("parameters", data.get("params"))
        if params is None:
            raise CatalogueError(f"{path}: no 'parameters' key (expected the fit.json of docs/formats.md)")
        if isinstance(params, list):
            try:
                params = {p["name"]: p for p in params}
            except (KeyError, TypeError):
                raise CatalogueError(f"{path}: 'parameters' list entries need a 'name'") from None
        names = list(params)
        for k in names:
            entry = params[k]
            if not isinstance(entry, dict) or "value" not in entry:
                raise CatalogueError(f"{path}: parameters.{k} needs 'value' (and 'std')")
        corr = data.get("correlation")
        if isinstance(corr, dict):
            cnames, corr = corr.get("names", names), corr.get("matrix")
        else:
            cnames = names
        C = None
        if corr is not None:
            C = np.asarray(corr, dtype=float)
            if C.shape != (len(cnames), len(cnames)):
                raise CatalogueError(
                    f"{path}: correlation is {C.shape}, expected {len(cnames)}x{len(cnames)} over {cnames}"
                )
        if base is None:
            if "core" not in data:
                raise CatalogueError(f"{path}: give base= (a material) or a 'core' key naming the core that was fitted")
            from ..model.core import load_core

            core_path = Path(data["core"])
            if not core_path.is_absolute() and (path.parent / core_path).exists():
                core_path = path.parent / core_path
            base = cls.from_core(load_core(core_path if core_path.exists() else data["core"]), segment)
        elif isinstance(base, str):
            base = default_catalogue()[base]
        values = {p: getattr(base, p) for p in PARAMS}
        std = {p: s for p, s in base.std.items()}
        order = []
        for k in names:
            seg, _, fld = k.partition(".")
            if seg != segment or fld not in _FIELD_TO_PARAM:
                continue
            p = _FIELD_TO_PARAM[fld]
            values[p] = float(params[k]["value"])
            s = params[k].get("std")
            std[p] = float(s) if s is not None and math.isfinite(float(s)) else 0.0
            order.append((p, k))
        h_key = f"{segment}.h"
        if h_key not in params:
            hv, hs = _h_over_heat_inputs(data.get("step2"), h_key)
            if hv is not None:
                values["h_s"], std["h_s"] = hv, hs
        full = None
        if C is not None and order:
            full = np.eye(len(PARAMS))
            for p1, k1 in order:
                for p2, k2 in order:
                    if k1 in cnames and k2 in cnames:
                        full[PARAMS.index(p1), PARAMS.index(p2)] = C[cnames.index(k1), cnames.index(k2)]
        return cls(name or path.stem, std=std, correlation=full, source=str(path), **values)


def _h_over_heat_inputs(step2, h_key: str) -> tuple[float | None, float]:
    """h of a two-step fit's step 2 (one fit per heat input) as one material value: the
    inverse-variance mean over the heat inputs, with the larger of its standard error and
    the spread over the heat inputs (the paper's h drifts with Q, so the spread is part of
    what is not known about the material). (None, 0) when no step-2 entry fitted it."""
    vals, stds = [], []
    for entry in step2 or ():
        par = (entry.get("parameters") or {}).get(h_key) if isinstance(entry, dict) else None
        if isinstance(par, dict) and par.get("value") is not None and math.isfinite(float(par["value"])):
            vals.append(float(par["value"]))
            s = par.get("std")
            stds.append(float(s) if s is not None and math.isfinite(float(s)) and float(s) > 0 else math.inf)
    if not vals:
        return None, 0.0
    v, s = np.array(vals), np.array(stds)
    w = np.where(np.isfinite(s), 1.0 / s**2, 0.0)
    mean = float(np.sum(w * v) / np.sum(w)) if np.sum(w) > 0 else float(np.mean(v))
    se = float(1.0 / np.sqrt(np.sum(w))) if np.sum(w) > 0 else 0.0
    spread = float(np.std(v, ddof=1)) if len(v) > 1 else 0.0
    return mean, max(se, spread)


#: Where the paper's standard deviations come from, and tawarp's choices where it gives none.
PAPER_NOTES = {
    "ceramic": "Table 1: phi 0.90±0.01, r 0.47±0.05 mm, q 1 (fixed), h_s >= 150; tawarp: h_s 150 ± 30",
    "mesh": "Table 1: phi 0.68±0.01, r 40±4 µm, q 1.06±0.03, h_s ≈ 50; tawarp: h_s 50 ± 10",
    "nicr_foam": "Table 1: phi 0.92±0.01, r 0.31±0.04 mm, q 1.30±0.04, h_s not given; tawarp: h_s 30 ± 10",
    "rvc_foam": "Table 1: phi 0.97±0.01, r 0.17±0.02 mm, q 1.13±0.03, h_s <= 10; tawarp: h_s 8 ± 2",
}

_PAPER = [
    Material(
        "ceramic",
        0.90,
        0.47e-3,
        1.0,
        3.0,
        150.0,
        {"porosity": 0.01, "pore_radius": 0.05e-3, "h_s": 30.0},
        None,
        "paper Table 1",
    ),
    Material(
        "mesh",
        0.68,
        40e-6,
        1.06,
        13.4,
        50.0,
        {"porosity": 0.01, "pore_radius": 4e-6, "tortuosity": 0.03, "h_s": 10.0},
        None,
        "paper Table 1",
    ),
    Material(
        "nicr_foam",
        0.92,
        0.31e-3,
        1.30,
        12.0,
        30.0,
        {"porosity": 0.01, "pore_radius": 0.04e-3, "tortuosity": 0.04, "h_s": 10.0},
        None,
        "paper Table 1",
    ),
    Material(
        "rvc_foam",
        0.97,
        0.17e-3,
        1.13,
        6.3,
        8.0,
        {"porosity": 0.01, "pore_radius": 0.02e-3, "tortuosity": 0.03, "h_s": 2.0},
        None,
        "paper Table 1",
    ),
]


class Catalogue(dict):
    """Materials by name (an ordered dict). :func:`default_catalogue` holds the paper's four;
    :meth:`load` adds the materials of a TOML file or a fit.json."""

    def add(self, material: Material, replace: bool = True) -> None:
        if not replace and material.name in self:
            raise CatalogueError(f"{material.source}: material {material.name!r} already in the catalogue")
        self[material.name] = material

    def load(self, path: str | Path) -> "Catalogue":
        """Add the materials of ``path``: a ``.toml`` catalogue or a ``.json`` fit result."""
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such catalogue file")
        if path.suffix == ".json":
            self.add(Material.from_fit_json(path))
            return self
        try:
            data = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as e:
            raise CatalogueError(f"{path}: not valid TOML: {e}") from None
        unknown = set(data) - {"material"}
        if unknown:
            raise CatalogueError(f"{path}: unknown top-level key(s) {sorted(unknown)}; expected [[material]] tables")
        allowed = set(PARAMS) | {"name", "std", "correlation", "fit", "base"}
        for k, md in enumerate(data.get("material", [])):
            where = f"{path}: material #{k + 1}"
            if "name" not in md:
                raise CatalogueError(f"{where}: missing key 'name'")
            bad = set(md) - allowed
            if bad:
                raise CatalogueError(
                    f"{where} ({md['name']!r}): unknown key(s) {sorted(bad)}; allowed {sorted(allowed)}"
                )
            base = md.get("base")
            if base is not None and base not in self:
                raise CatalogueError(f"{where} ({md['name']!r}): base {base!r} is not in the catalogue {list(self)}")
            if "fit" in md:
                fit = Path(md["fit"])
                fit = fit if fit.is_absolute() else path.parent / fit
                m = Material.from_fit_json(fit, base=self[base] if base else None, name=md["name"])
                over = {p: float(md[p]) for p in PARAMS if p in md}
                self.add(dataclasses.replace(m, **over) if over else m)
                continue
            values = {p: getattr(self[base], p) for p in PARAMS} if base else {}
            std = dict(self[base].std) if base else {}
            for p in PARAMS:
                if p in md:
                    values[p] = md[p]
            missing = [p for p in PARAMS if p not in values]
            if missing:
                raise CatalogueError(f"{where} ({md['name']!r}): missing {missing} (or give base = NAME)")
            if not isinstance(md.get("std", {}), dict):
                raise CatalogueError(f"{where} ({md['name']!r}): std must be a table {{param = value}}")
            std.update(md.get("std", {}))
            corr = md.get("correlation")
            if corr is not None:
                keys = [p for p in PARAMS if p in std]
                C = np.asarray(corr, dtype=float)
                if C.shape != (len(keys), len(keys)):
                    raise CatalogueError(
                        f"{where} ({md['name']!r}): correlation must be {len(keys)}x{len(keys)} over {keys}"
                    )
                full = np.eye(len(PARAMS))
                idx = [PARAMS.index(p) for p in keys]
                full[np.ix_(idx, idx)] = C
                corr = full
            for p in PARAMS:
                if isinstance(values[p], bool) or not isinstance(values[p], (int, float)):
                    raise CatalogueError(f"{where} ({md['name']!r}): {p} must be a number, got {values[p]!r}")
            self.add(
                Material(
                    md["name"], std=std, correlation=corr, source=str(path), **{p: float(values[p]) for p in PARAMS}
                )
            )
        return self


def default_catalogue() -> Catalogue:
    """The paper's four materials (a fresh, modifiable catalogue)."""
    cat = Catalogue()
    for m in _PAPER:
        cat.add(m)
    return cat


def load_catalogue(paths=()) -> Catalogue:
    """The default catalogue extended by TOML catalogue files and fit.json files."""
    cat = default_catalogue()
    for p in paths:
        cat.load(p)
    return cat
