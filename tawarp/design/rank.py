"""Rank stack materials by the temperature gradient they reach, with uncertainty.

Each material of a :class:`tawarp.catalogue.Catalogue` is put in the stack of one
reference core (default: the bundled ``rvc_foam`` layout: 4 cm stack, 1.3 cm hot
exchanger, 10 cm buffer tube, so that only the material differs). Its uncertain
parameters (porosity, pore radius, tortuosity, solid conductivity, h_s) are drawn
``n_samples`` times from N(mean, covariance) (clipped to physical ranges); every
(material, heat input, draw) is one parameter set of a single batch: one heat-solve
launch for the whole ranking.

The gradient is ``(T(x3) - T(x2)) / l_s`` [K/m] (see :mod:`tawarp.design`). Reported per
material and heat input: the nominal gradient (at the mean values), the mean, standard
deviation and 2.5-97.5 % interval over the draws, the probability of being the best
material (draws paired by index across materials, which are independent), the mean
maximum temperature and the probability that it exceeds ``T_limit``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .catalogue import CORE_FIELD, PARAMS, Catalogue, Material, default_catalogue
from ..model.core import Core, load_core
from .evaluate import Evaluator
from .objectives import DEFAULT_T_LIMIT
from ..model.forward import ForwardSettings


@dataclass
class RankResult:
    """``table``: list of rows (material, Q_W, rank, nominal, mean, std, p025, p975,
    p_best, T_max_mean, p_over_T_limit); ``samples``: {(material, Q): gradient draws}."""

    core: str
    heat_inputs: list
    materials: list
    n_samples: int
    table: list
    samples: dict

    def ordering(self, heat_input: float) -> list[str]:
        """Materials from the highest mean gradient to the lowest at ``heat_input``."""
        rows = [r for r in self.table if r["Q_W"] == float(heat_input)]
        return [r["material"] for r in sorted(rows, key=lambda r: r["rank"])]

    def to_dict(self) -> dict:
        return {"core": self.core, "heat_inputs_W": self.heat_inputs, "materials": self.materials,
                "n_samples": self.n_samples, "gradient_definition": "(T(x3) - T(x2)) / l_s [K/m]",
                "ranking": self.table}


def rank_materials(materials=None, heat_inputs=(9.0,), core: Core | str = "rvc_foam", segment: str = "stack",
                   n_samples: int = 2000, seed: int = 0, T_limit: float = DEFAULT_T_LIMIT,
                   catalogue: Catalogue | None = None, settings: ForwardSettings | None = None) -> RankResult:
    """Rank ``materials`` (Material objects or catalogue names; default: the whole catalogue)
    at each heat input [W]; see the module docstring."""
    cat = catalogue if catalogue is not None else default_catalogue()
    if materials is None:
        materials = list(cat.values())
    mats: list[Material] = [cat[m] if isinstance(m, str) else m for m in materials]
    if not mats:
        raise ValueError("no material to rank")
    if isinstance(core, str):
        core = load_core(core)
    qs = np.atleast_1d(np.asarray(heat_inputs, dtype=float))
    if np.any(~np.isfinite(qs)) or np.any(qs < 0):
        raise ValueError(f"heat inputs [W] must be finite and >= 0, got {qs}")
    if n_samples < 2:
        raise ValueError("n_samples must be >= 2")
    seg_names = [s.name for s in core.segments]
    stack_index = seg_names.index(segment)
    names = [f"{segment}.{CORE_FIELD[p]}" for p in PARAMS]
    rng = np.random.default_rng(seed)
    M, Nq, N = len(mats), len(qs), n_samples
    # one batch: material-major, then heat input, then draw; draw 0 is the nominal material
    cols = {n: np.empty((M, Nq, N + 1)) for n in names}
    for i, m in enumerate(mats):
        draws = m.sample(N, rng)
        for p in PARAMS:
            col = np.concatenate([[getattr(m, p)], draws[p]])
            cols[f"{segment}.{CORE_FIELD[p]}"][i] = col[None, :]
    Q = np.broadcast_to(qs[None, :, None], (M, Nq, N + 1))
    table = np.stack([Q.ravel()] + [cols[n].ravel() for n in names])
    ev = Evaluator(None, core=core, names=names, stack_index=stack_index, settings=settings)
    out = {}
    chunk = ev.settings.chunk
    for lo in range(0, table.shape[1], chunk):
        part = ev.evaluate_table(table[:, lo:lo + chunk])
        for k, v in part.items():
            out.setdefault(k, []).append(v)
    res = {k: np.concatenate(v).reshape(M, Nq, N + 1) for k, v in out.items()}
    g, tmax = res["gradient"], res["T_max"]
    rows, samples = [], {}
    for j, q in enumerate(qs):
        draws = g[:, j, 1:]
        best = np.argmax(draws, axis=0)
        means = draws.mean(axis=1)
        order = np.argsort(-means, kind="stable")
        rank = np.empty(M, int)
        rank[order] = np.arange(1, M + 1)
        for i, m in enumerate(mats):
            rows.append({"material": m.name, "Q_W": float(q), "rank": int(rank[i]),
                         "gradient_nominal_K_per_m": float(g[i, j, 0]),
                         "gradient_mean_K_per_m": float(means[i]),
                         "gradient_std_K_per_m": float(draws[i].std(ddof=1)),
                         "gradient_p025_K_per_m": float(np.percentile(draws[i], 2.5)),
                         "gradient_p975_K_per_m": float(np.percentile(draws[i], 97.5)),
                         "p_best": float(np.mean(best == i)),
                         "T_max_mean_K": float(tmax[i, j, 1:].mean()),
                         "p_T_max_over_limit": float(np.mean(tmax[i, j, 1:] > T_limit)),
                         "T_limit_K": float(T_limit)})
            samples[(m.name, float(q))] = draws[i]
    rows.sort(key=lambda r: (r["Q_W"], r["rank"]))
    return RankResult(str(core.source), [float(q) for q in qs], [m.name for m in mats], N, rows, samples)
