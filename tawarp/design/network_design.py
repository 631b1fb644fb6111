"""Design search on an engine network: the lowest onset temperature ratio T_hot / T_cold over
a box of segment fields (``tawarp design NETWORK.toml --var regenerator.pore_radius=...``).

Every generation draws ``batch`` designs in the box (uniform, or log-uniform where asked);
after the first quarter of the trials, half of each generation is drawn around the best
design so far (a Gaussian of a tenth of the box, clipped to it). Each design's onset is
Newton's method on (omega, T_hot) on the device (:meth:`tawarp.model.network_batch.NetworkBatch.onset`),
started from the onset of the nearest design already solved (in the box's unit coordinates;
at first the file's own, found by following its mode from T_cold on the host), so that the
search walks away from the file's design by continuation. A design Newton loses follows its
own mode from T_cold (:meth:`~tawarp.model.network_batch.NetworkBatch.followed_onset`); one
that does not start up to T_max is counted as without onset.
"""

from __future__ import annotations

import time

import numpy as np

from ..model import network_reference as nr
from ..model.network import Network
from ..model.network_batch import NetworkBatch
from ..rng import generator


def _unit(variables, x: np.ndarray) -> np.ndarray:
    """Box coordinates in [0, 1] (log ones in log)."""
    out = np.empty_like(x)
    for k, v in enumerate(variables):
        lo, hi = (np.log(v.low), np.log(v.high)) if v.log else (v.low, v.high)
        val = np.log(x[:, k]) if v.log else x[:, k]
        out[:, k] = (val - lo) / (hi - lo) if hi > lo else 0.0
    return out


def _values(variables, u: np.ndarray) -> np.ndarray:
    out = np.empty_like(u)
    for k, v in enumerate(variables):
        if v.log:
            out[:, k] = np.exp(np.log(v.low) + u[:, k] * (np.log(v.high) - np.log(v.low)))
        else:
            out[:, k] = v.low + u[:, k] * (v.high - v.low)
    return out


def search_network(
    net: Network,
    variables,
    n_trials: int = 4096,
    batch: int = 256,
    seed: int = 0,
    T_max: float | None = None,
    device=None,
    segment: str | None = None,
    amplitude: float = 1e5,
    keep: int = 20,
) -> dict:
    """Search ``variables`` (:class:`tawarp.design.space.Variable` ranges named
    ``SEGMENT.FIELD`` or ``gas.p_mean``) for the lowest onset T_hot / T_cold of ``net``'s
    lowest mode (module docstring). Returns the report: the ``keep`` best designs (their
    values, T_ratio, f_onset_Hz, and, with ``segment``, the acoustic power it produces at
    onset with |p| = ``amplitude`` [Pa] at the network's first end), the counts and the timing."""
    if batch < 1 or n_trials < 1:
        raise ValueError("batch and n_trials must be >= 1")
    rng = generator(seed, "search_network")
    for v in variables:
        if v.choices or (v.log and v.low <= 0):
            raise ValueError(f"--var {v.name}: a network design takes numeric ranges (log ones > 0)")
        NetworkBatch(net, {v.name: [v.low]}, device="cpu")  # a KeyError naming a wrong name
    T_max = 4.0 * net.gas.T_cold if T_max is None else T_max
    names = [v.name for v in variables]
    t0 = time.perf_counter()
    (w_cold, *_) = nr.real_axis_modes(net, 1.0, 2e3, 400, T_hot=net.gas.T_cold)
    home = nr.onset(net, w_cold, T_max=T_max, n=12)
    if not np.isfinite(home.T_onset):
        raise ValueError(
            f"{net.source}: the file's design does not start up to T_max = {T_max:g} K; raise --T-ratio-max"
        )
    x_home = np.array([[net.gas.p_mean if n == "gas.p_mean" else _field(net, n) for n in names]])
    archive_u = _unit(variables, x_home)
    archive = [(home.omega.real, home.T_onset)]
    done_x, done_T, done_w = [], [], []
    evaluated = without = 0
    while evaluated < n_trials:
        m = min(batch, n_trials - evaluated)
        u = rng.uniform(size=(m, len(names)))
        if done_T and evaluated >= n_trials // 4:
            best = _unit(variables, done_x[int(np.argmin(done_T))][None, :])[0]
            h = m // 2
            u[:h] = np.clip(best + 0.1 * rng.standard_normal((h, len(names))), 0.0, 1.0)
        x = _values(variables, u)
        nearest = np.argmin(((u[:, None, :] - archive_u[None, :, :]) ** 2).sum(axis=2), axis=1)
        starts = np.array([archive[k] for k in nearest])
        batch_x = NetworkBatch(net, {n: x[:, k] for k, n in enumerate(names)}, device=device)
        res = batch_x.onset(starts[:, 0], starts[:, 1], T_range=(net.gas.T_cold, T_max))
        w_on, T_on, ok = res.omega, res.T_hot, res.iterations > 0
        if not ok.all():
            # the designs Newton lost follow their own modes from T_cold (one more launch)
            lost = np.flatnonzero(~ok)
            sub = NetworkBatch(net, {n: x[lost, k] for k, n in enumerate(names)}, device=device)
            fol = sub.followed_onset(w_cold, T_max, n=12)
            found = fol.status == 1
            w_on[lost[found]], T_on[lost[found]] = fol.omega[found], fol.T_hot[found]
            ok[lost[found]] = True
        without += int((~ok).sum())
        evaluated += m
        archive_u = np.concatenate([archive_u, u[ok]])
        archive += list(zip(w_on[ok], T_on[ok], strict=True))
        done_x += list(x[ok])
        done_T += list(T_on[ok])
        done_w += list(w_on[ok])
    seconds = time.perf_counter() - t0
    order = np.argsort(done_T)[:keep]
    b, s = net.segment(segment) if segment else (None, None)
    node = next(iter(net.ends)) if net.ends else net.branches[0].start
    best = []
    for k in order:
        d = net.replace(**{n: float(done_x[k][j]) for j, n in enumerate(names)})
        row = {
            "params": {n: float(done_x[k][j]) for j, n in enumerate(names)},
            "T_ratio": float(done_T[k] / net.gas.T_cold),
            "T_onset_K": float(done_T[k]),
            "f_onset_Hz": float(done_w[k] / (2 * np.pi)),
        }
        if segment:
            w, T = done_w[k], done_T[k]
            p_in, U_in = nr.segment_entry(d, segment, w, T, nr.mode_start_states(d, w, T, node) * amplitude)
            row["Edot_produced_W"] = nr.power_budget(d, d.branches[b].segments[s], w, T, p_in, U_in).total
        best.append(row)
    return {
        "engine": str(net.source),
        "objective": "onset T_hot / T_cold of the lowest mode (lower first)",
        "variables": [{"name": v.name, "low": v.low, "high": v.high, "log": v.log} for v in variables],
        "T_max_K": T_max,
        "file_design": {"T_ratio": home.ratio, "f_onset_Hz": home.frequency},
        "evaluated": evaluated,
        "with_onset": len(done_T),
        "without_onset": without,
        "seconds": seconds,
        "designs_per_minute": 60.0 * evaluated / seconds,
        "amplitude_Pa": amplitude if segment else None,
        "amplitude_at": node if segment else None,
        "best": best,
    }


def _field(net: Network, name: str) -> float:
    """The file's value of ``SEGMENT.FIELD`` (``radius`` from the area)."""
    owner, _, fld = name.partition(".")
    b, s = net.segment(owner)
    seg = net.branches[b].segments[s]
    if fld == "radius":
        return float(np.sqrt(seg.area / np.pi))
    return float(getattr(seg, fld))
