"""Rank stack materials by the temperature gradient they reach, or by the heat input at
which they start an engine, with uncertainty.

Each material of a :class:`tawarp.design.catalogue.Catalogue` is put in the stack of one
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

:func:`rank_by_onset` puts each material in the stack of a reference engine (default the
bundled ``standing_wave``: the ceramic core in a closed-closed resonator) and draws its
parameters the same way; the onset of every (material, draw) is found in one batched
:func:`tawarp.model.onset.onset` call (each grid point and Newton step is one launch for
all draws). Reported per material: the nominal onset heat input Q_onset [W], its median,
5, 90 (the robust value) and 95 % points over the draws, the onset frequency and the
onset temperature ratio T_hot / T_cold (medians), the fraction of draws that do not start
by ``Q_max``, and the probability that it starts at a lower heat input than each other
material (draws paired by index; a draw that does not start counts as Q_onset = inf).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .catalogue import CORE_FIELD, PARAMS, Catalogue, Material, default_catalogue
from ..model.core import Core, load_core
from .evaluate import Evaluator
from .objectives import DEFAULT_T_LIMIT
from ..model.forward import ForwardSettings
from ..model.resonator import ThermoacousticEngine, load_engine
from ..rng import generator


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
        return {
            "core": self.core,
            "heat_inputs_W": self.heat_inputs,
            "materials": self.materials,
            "n_samples": self.n_samples,
            "gradient_definition": "(T(x3) - T(x2)) / l_s [K/m]",
            "ranking": self.table,
        }


def _materials(materials, catalogue: Catalogue | None) -> list[Material]:
    cat = catalogue if catalogue is not None else default_catalogue()
    if materials is None:
        materials = list(cat.values())
    mats = [cat[m] if isinstance(m, str) else m for m in materials]
    if not mats:
        raise ValueError("no material to rank")
    return mats


def draw_parameter_sets(
    materials, n_samples: int, seed: int | np.random.Generator | None = 0, segment: str = "stack"
) -> dict[str, np.ndarray]:
    """``{"SEGMENT.FIELD": (M, n_samples + 1)}``: per material, column 0 its nominal values
    and columns 1.. ``n_samples`` draws from N(mean, covariance) (:meth:`Material.sample`:
    a fit.json's covariance, clipped to the fit ranges), one generator for all materials."""
    rng = generator(seed, "draw_parameter_sets")
    out = {f"{segment}.{CORE_FIELD[p]}": np.empty((len(materials), n_samples + 1)) for p in PARAMS}
    for i, m in enumerate(materials):
        draws = m.sample(n_samples, rng)
        for p in PARAMS:
            out[f"{segment}.{CORE_FIELD[p]}"][i] = np.concatenate([[getattr(m, p)], draws[p]])
    return out


def rank_materials(
    materials=None,
    heat_inputs=(9.0,),
    core: Core | str = "rvc_foam",
    segment: str = "stack",
    n_samples: int = 2000,
    seed: int = 0,
    T_limit: float = DEFAULT_T_LIMIT,
    catalogue: Catalogue | None = None,
    settings: ForwardSettings | None = None,
) -> RankResult:
    """Rank ``materials`` (Material objects or catalogue names; default: the whole catalogue)
    at each heat input [W]; see the module docstring."""
    rng = generator(seed, "rank_materials")
    mats = _materials(materials, catalogue)
    if isinstance(core, str):
        core = load_core(core)
    qs = np.atleast_1d(np.asarray(heat_inputs, dtype=float))
    if np.any(~np.isfinite(qs)) or np.any(qs < 0):
        raise ValueError(f"heat inputs [W] must be finite and >= 0, got {qs}")
    if n_samples < 2:
        raise ValueError("n_samples must be >= 2")
    if not (math.isfinite(T_limit) and T_limit > 0):
        raise ValueError(f"T_limit [K] must be finite and > 0, got {T_limit}")
    seg_names = [s.name for s in core.segments]
    if segment not in seg_names:
        raise KeyError(f"{core.source}: no segment {segment!r} for the materials; one of {', '.join(seg_names)}")
    stack_index = seg_names.index(segment)
    M, Nq, N = len(mats), len(qs), n_samples
    # one batch: material-major, then heat input, then draw; draw 0 is the nominal material
    sets = draw_parameter_sets(mats, N, rng, segment)
    names = list(sets)
    Q = np.broadcast_to(qs[None, :, None], (M, Nq, N + 1))
    table = np.stack([Q.ravel()] + [np.broadcast_to(sets[n][:, None, :], (M, Nq, N + 1)).ravel() for n in names])
    ev = Evaluator(None, core=core, names=names, stack_index=stack_index, settings=settings)
    out = {}
    chunk = ev.settings.chunk
    for lo in range(0, table.shape[1], chunk):
        part = ev.evaluate_table(table[:, lo : lo + chunk])
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
            rows.append(
                {
                    "material": m.name,
                    "Q_W": float(q),
                    "rank": int(rank[i]),
                    "gradient_nominal_K_per_m": float(g[i, j, 0]),
                    "gradient_mean_K_per_m": float(means[i]),
                    "gradient_std_K_per_m": float(draws[i].std(ddof=1)),
                    "gradient_p025_K_per_m": float(np.percentile(draws[i], 2.5)),
                    "gradient_p975_K_per_m": float(np.percentile(draws[i], 97.5)),
                    "p_best": float(np.mean(best == i)),
                    "T_max_mean_K": float(tmax[i, j, 1:].mean()),
                    "p_T_max_over_limit": float(np.mean(tmax[i, j, 1:] > T_limit)),
                    "T_limit_K": float(T_limit),
                }
            )
            samples[(m.name, float(q))] = draws[i]
    rows.sort(key=lambda r: (r["Q_W"], r["rank"]))
    return RankResult(str(core.source), [float(q) for q in qs], [m.name for m in mats], N, rows, samples)


def _none_if_inf(x: float):
    return float(x) if np.isfinite(x) else None


def _onset_statistics(draws: np.ndarray, names: list[str]) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """Of ``draws`` (materials x draws, lower is better, inf where no onset): each material's
    median, rank by it (1 = lowest) and its shares ``p_no_onset``, ``p_best`` (lowest of its
    draw, a draw where none starts counting for none) and ``p_beats`` {other: P(lower)}."""
    M = len(names)
    median = np.median(draws, axis=1)
    rank = np.empty(M, int)
    rank[np.argsort(median, kind="stable")] = np.arange(1, M + 1)
    best = np.argmin(draws, axis=0)
    all_inf = ~np.isfinite(draws).any(axis=0)
    shares = [
        {
            "p_no_onset": float(np.mean(~np.isfinite(draws[i]))),
            "p_best": float(np.mean((best == i) & ~all_inf)),
            "p_beats": {o: float(np.mean(draws[i] < draws[k])) for k, o in enumerate(names) if k != i},
        }
        for i in range(M)
    ]
    return median, rank, shares


@dataclass
class OnsetRankResult:
    """``table``: rows per material (rank by median Q_onset, nominal / median / p05 / p90 /
    p95 Q_onset [W] (None: above Q_max), median f_onset [Hz] and T_hot / T_cold,
    ``p_no_onset``, ``p_best``, ``p_beats`` {other: P(Q_onset < other's)});
    ``samples``: {material: (n_samples,) Q_onset draws [W], inf where no onset}."""

    engine: str
    Q_max: float
    materials: list
    n_samples: int
    table: list
    samples: dict

    def ordering(self) -> list[str]:
        """Materials from the lowest median onset heat input to the highest."""
        return [r["material"] for r in sorted(self.table, key=lambda r: r["rank"])]

    def to_dict(self) -> dict:
        return {
            "engine": self.engine,
            "Q_max_W": self.Q_max,
            "materials": self.materials,
            "n_samples": self.n_samples,
            "ranked_by": "median onset heat input Q_onset [W] (lower first)",
            "ranking": self.table,
        }


def rank_by_onset(
    materials=None,
    engine: ThermoacousticEngine | str = "standing_wave",
    segment: str = "stack",
    n_samples: int = 200,
    seed: int = 0,
    Q_max: float = 200.0,
    n_bracket: int = 9,
    catalogue: Catalogue | None = None,
    settings: ForwardSettings | None = None,
) -> OnsetRankResult:
    """Rank ``materials`` by the onset heat input of ``engine`` with each in ``segment``;
    see the module docstring. ``Q_max`` [W] and ``n_bracket``: :func:`tawarp.model.onset.onset`."""
    from ..model.onset import onset

    rng = generator(seed, "rank_by_onset")
    mats = _materials(materials, catalogue)
    eng = load_engine(engine) if isinstance(engine, str) else engine
    if not eng.core.segment(segment).is_porous:
        raise ValueError(f"{eng.source}: segment {segment!r} is not porous; a material needs a porous segment")
    if n_samples < 2:
        raise ValueError("n_samples must be >= 2")
    M, N = len(mats), n_samples
    sets = draw_parameter_sets(mats, N, rng, segment)
    res = onset(
        eng, Q_max=Q_max, params={k: v.ravel() for k, v in sets.items()}, n_bracket=n_bracket, settings=settings
    )
    Q = np.where(np.isfinite(res.Q_onset), res.Q_onset, np.inf).reshape(M, N + 1)
    f = res.f_onset.reshape(M, N + 1)
    ratio = (res.T_hot / eng.core.gas.T_cold).reshape(M, N + 1)
    draws = Q[:, 1:]
    with np.errstate(invalid="ignore"):  # inf - inf between two draws without onset: the point is inf
        p05, p90, p95 = np.percentile(draws, [5, 90, 95], axis=1)
    median, rank, shares = _onset_statistics(draws, [m.name for m in mats])
    rows, samples = [], {}
    for i, m in enumerate(mats):
        ok = np.isfinite(draws[i])
        rows.append(
            {
                "material": m.name,
                "rank": int(rank[i]),
                "Q_onset_nominal_W": _none_if_inf(Q[i, 0]),
                "Q_onset_median_W": _none_if_inf(median[i]),
                "Q_onset_p05_W": _none_if_inf(p05[i]),
                "Q_onset_p90_W": _none_if_inf(p90[i]),
                "Q_onset_p95_W": _none_if_inf(p95[i]),
                "f_onset_median_Hz": float(np.median(f[i, 1:][ok])) if ok.any() else None,
                "T_ratio_median": float(np.median(ratio[i, 1:][ok])) if ok.any() else None,
                **shares[i],
            }
        )
        samples[m.name] = draws[i]
    rows.sort(key=lambda r: r["rank"])
    return OnsetRankResult(str(eng.source), float(Q_max), [m.name for m in mats], N, rows, samples)


@dataclass
class NetworkRankResult:
    """Ranking in an engine network (:func:`rank_by_network_onset`). ``table``: rows per
    material (rank by median onset ratio T_hot / T_cold, nominal / median / p05 / p95 ratio
    (None: no onset up to T_max), median f_onset [Hz], the acoustic power produced in the
    nominal segment at onset with |p| = ``amplitude`` at ``node`` [W], ``p_no_onset``, ``p_best``,
    ``p_beats``); ``samples``: {material: (n_samples,) ratio draws, inf where no onset}."""

    engine: str
    segment: str
    amplitude: float
    node: str
    materials: list
    n_samples: int
    table: list
    samples: dict

    def ordering(self) -> list[str]:
        """Materials from the lowest median onset ratio to the highest."""
        return [r["material"] for r in sorted(self.table, key=lambda r: r["rank"])]

    def to_dict(self) -> dict:
        return {
            "engine": self.engine,
            "segment": self.segment,
            "amplitude_Pa": self.amplitude,
            "amplitude_at": self.node,
            "materials": self.materials,
            "n_samples": self.n_samples,
            "ranked_by": "median onset temperature ratio T_hot / T_cold (lower first)",
            "ranking": self.table,
        }


def rank_by_network_onset(
    materials=None,
    engine="traveling_wave",
    segment: str = "regenerator",
    n_samples: int = 30,
    seed: int = 0,
    T_max: float | None = None,
    amplitude: float = 1e5,
    catalogue: Catalogue | None = None,
    device=None,
) -> NetworkRankResult:
    """Rank ``materials`` by the onset temperature ratio of the network ``engine`` (a
    :class:`~tawarp.model.network.Network` or a file / bundled name) with each in its porous
    ``segment`` (porosity, pore radius, tortuosity, solid conductivity; a network segment has
    no lateral h). Each material's parameters are drawn ``n_samples`` times from its
    N(mean, covariance) (:func:`draw_parameter_sets`); every draw (and the nominal) follows
    its lowest mode from T_cold up to ``T_max`` (default 4 T_cold), all at once on ``device``,
    one thread each (:meth:`tawarp.model.network_batch.NetworkBatch.followed_onset`); a draw
    without onset up to T_max counts as ratio = inf. Also reported: the acoustic
    power the segment produces at the nominal onset, |p| = ``amplitude`` [Pa] at the
    network's first end (Edot out minus in, :func:`tawarp.model.network_reference.power_budget`)."""
    from ..model import network_reference as nr
    from ..model.network import load_network
    from ..model.network_batch import NetworkBatch

    rng = generator(seed, "rank_by_network_onset")
    net = load_network(engine) if isinstance(engine, str) else engine
    b, s = net.segment(segment)
    if net.branches[b].segments[s].kind != "porous":
        raise ValueError(f"{net.source}: segment {segment!r} is not porous; a material needs a porous segment")
    if n_samples < 2:
        raise ValueError("n_samples must be >= 2")
    T_max = 4.0 * net.gas.T_cold if T_max is None else T_max
    node = next(iter(net.ends)) if net.ends else net.branches[0].start
    mats = _materials(materials, catalogue)
    M, N = len(mats), n_samples
    sets = draw_parameter_sets(mats, N, rng, segment)
    fields = [k for k in sets if not k.endswith(".h")]
    w_cold = nr.real_axis_modes(net, 1.0, 2e3, 400, T_hot=net.gas.T_cold)[0]
    ratio = np.full((M, N + 1), np.inf)
    freq = np.full((M, N + 1), np.nan)
    edot = np.full(M, np.nan)
    # with imposed temperatures the solid's conductivity enters Htot only, not the onset
    acoustic = [k for k in fields if not k.endswith(".solid_conductivity")]
    for i in range(M):
        res = NetworkBatch(net, {k: sets[k][i] for k in acoustic}, device=device).followed_onset(w_cold, T_max, n=12)
        ok = res.status == 1
        ratio[i, ok] = res.T_hot[ok] / net.gas.T_cold
        freq[i, ok] = res.omega[ok] / (2 * np.pi)
        if ok[0]:
            nom = net.replace(**{k: float(sets[k][i, 0]) for k in fields})
            w, T = res.omega[0], res.T_hot[0]
            p_in, U_in = nr.segment_entry(nom, segment, w, T, nr.mode_start_states(nom, w, T, node) * amplitude)
            edot[i] = nr.power_budget(nom, nom.branches[b].segments[s], w, T, p_in, U_in).total
    draws = ratio[:, 1:]
    with np.errstate(invalid="ignore"):
        p05, p95 = np.percentile(draws, [5, 95], axis=1)
    median, rank, shares = _onset_statistics(draws, [m.name for m in mats])
    rows, samples = [], {}
    for i, m in enumerate(mats):
        ok = np.isfinite(draws[i])
        rows.append(
            {
                "material": m.name,
                "rank": int(rank[i]),
                "T_ratio_nominal": _none_if_inf(ratio[i, 0]),
                "T_ratio_median": _none_if_inf(median[i]),
                "T_ratio_p05": _none_if_inf(p05[i]),
                "T_ratio_p95": _none_if_inf(p95[i]),
                "f_onset_median_Hz": float(np.median(freq[i, 1:][ok])) if ok.any() else None,
                "Edot_produced_nominal_W": None if np.isnan(edot[i]) else float(edot[i]),
                **shares[i],
            }
        )
        samples[m.name] = draws[i]
    rows.sort(key=lambda r: r["rank"])
    return NetworkRankResult(str(net.source), segment, float(amplitude), node, [m.name for m in mats], N, rows, samples)
