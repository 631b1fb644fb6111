"""Engine networks batched on Warp: the boundary determinant, complex eigenfrequencies and
onsets of many designs at once (:mod:`tawarp.kernels.network`, one thread per design).

>>> from tawarp.model.network import load_network
>>> from tawarp.model.network_batch import NetworkBatch
>>> net = load_network("traveling_wave")
>>> batch = NetworkBatch(net, {"regenerator.pore_radius": radii}, device="cuda")
>>> res = batch.onset(omega0, T0)        # Newton on (omega, T_hot) from a nearby onset

A design is the network with some segment fields changed (``SEGMENT.FIELD`` as in
:meth:`tawarp.model.network.Network.replace`, numbers only) and ``gas.p_mean``; the topology,
the gas and the temperature names stay those of the file. The NumPy reference
(:mod:`tawarp.model.network_reference`) is the oracle of the tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from ..kernels import network as kn
from ..kernels.pore import PORE_MODELS
from .gas import GASES
from .network import Network
from .network_reference import RADIATION, end_segment

_FIELD_COLUMN = {
    "length": kn.F_LENGTH,
    "porosity": kn.F_POROSITY,
    "pore_radius": kn.F_PORE_RADIUS,
    "tortuosity": kn.F_TORTUOSITY,
    "volume": kn.F_VOLUME,
    "surface_area": kn.F_SURFACE,
}
_KIND = {"duct": 0, "porous": 0, "compliance": 1, "inertance": 2}
#: Magnus cells of a segment with a temperature gradient or a taper (sixth order: 8 cells
#: put the traveling-wave engine's onset 2e-12 from the reference's; the determinant of
#: tests/test_network_batch.py's network at 310 Hz is 3e-8 off with 8 cells, 4e-10 with 16)
DEFAULT_CELLS = 8


def _temperature(t, T_cold: float) -> tuple[float, float]:
    """(a, b) with T = a + b T_hot."""
    if t == "T_hot":
        return 0.0, 1.0
    return (T_cold, 0.0) if t == "T_cold" else (float(t), 0.0)


@dataclass
class BatchOnset:
    """Onsets of a batch: ``omega`` (n,) [rad/s], ``T_hot`` (n,) [K], ``iterations`` (n,)
    Newton steps (-1: not converged)."""

    omega: np.ndarray
    T_hot: np.ndarray
    iterations: np.ndarray


class NetworkBatch:
    """The tables of ``net`` for ``n`` designs (``params``: {name: (n,) values}) on ``device``."""

    def __init__(self, net: Network, params: dict | None = None, device=None, cells: int = DEFAULT_CELLS):
        self.net = net
        self.device = wp.get_device(device)
        self.cells = int(cells)
        params = {k: np.atleast_1d(np.asarray(v, dtype=np.float64)) for k, v in (params or {}).items()}
        n = max([len(v) for v in params.values()], default=1)
        for k, v in params.items():
            if len(v) not in (1, n):
                raise ValueError(f"{k}: {len(v)} values; every parameter needs 1 or {n}")
            # a porosity in (0, 1], a tortuosity >= 1, anything else > 0
            hi, lo, span = (1.0, 0.0, "(0, 1]") if k.endswith(".porosity") else (np.inf, 0.0, "> 0")
            if k.endswith(".tortuosity"):
                lo, span = 1.0, ">= 1"
            bad = np.flatnonzero(~(np.isfinite(v) & (v > 0) & (v >= lo) & (v <= hi)))
            if bad.size:
                raise ValueError(
                    f"{k}[{bad[0]}] = {v[bad[0]]}: expected a finite value {'in ' * (span[0] == '(')}{span}"
                )
        self.n = n
        segs = [s for br in net.branches for s in br.segments]
        if 2 * len(net.branches) > kn.MAX_ROWS:
            raise ValueError(f"{net.source}: {len(net.branches)} branches; the kernel takes at most {kn.MAX_ROWS // 2}")
        index = {s.name: k for k, s in enumerate(segs)}
        table = np.zeros((n, len(segs), kn.N_FIELDS))
        for k, s in enumerate(segs):
            table[:, k, kn.F_LENGTH] = s.length
            table[:, k, kn.F_AREA0] = s.area
            table[:, k, kn.F_AREA1] = s.area_end
            table[:, k, kn.F_POROSITY] = s.porosity
            table[:, k, kn.F_PORE_RADIUS] = s.pore_radius
            table[:, k, kn.F_TORTUOSITY] = s.tortuosity
            table[:, k, kn.F_T0A], table[:, k, kn.F_T0B] = _temperature(s.T_start, net.gas.T_cold)
            table[:, k, kn.F_T1A], table[:, k, kn.F_T1B] = _temperature(s.T_end, net.gas.T_cold)
            table[:, k, kn.F_VOLUME] = s.volume
            table[:, k, kn.F_SURFACE] = s.surface_area
        design = np.zeros((n, kn.N_DESIGN))
        design[:, kn.D_P_MEAN] = net.gas.p_mean
        for name, v in params.items():
            owner, _, fld = name.partition(".")
            if name == "gas.p_mean":
                design[:, kn.D_P_MEAN] = v
            elif owner in index and fld in _FIELD_COLUMN:
                table[:, index[owner], _FIELD_COLUMN[fld]] = v
            elif owner in index and fld in ("area", "radius"):
                a = v if fld == "area" else math.pi * v**2
                s = segs[index[owner]]
                table[:, index[owner], kn.F_AREA0] = a
                if s.area_end == s.area:
                    table[:, index[owner], kn.F_AREA1] = a
            else:
                raise KeyError(
                    f"{name!r}: not a batch parameter; expected gas.p_mean or SEGMENT.FIELD with FIELD in "
                    f"{sorted(_FIELD_COLUMN) + ['area', 'radius']} and SEGMENT in {sorted(index)}"
                )
        g = GASES[net.gas.name]
        # Zs = rho c / S of the first section at T_cold (the reference's reference_impedance)
        first = next(k for k, s in enumerate(segs) if s.kind != "compliance")
        T_c = net.gas.T_cold
        rho = design[:, kn.D_P_MEAN] / (g.R_gas * T_c)
        design[:, kn.D_ZS] = rho * math.sqrt(g.gamma * g.R_gas * T_c) / table[:, first, kn.F_AREA0]
        nodes = net.nodes()
        node_first, inc_b, inc_s, kinds, pars, node_seg = [0], [], [], [], [], []
        starts = np.cumsum([0] + [len(br.segments) for br in net.branches])
        for node, inc in nodes.items():
            for b, side in inc:
                inc_b.append(b)
                inc_s.append(0 if side == "start" else 1)
            node_first.append(len(inc_b))
            if node not in net.ends:
                kinds.append(-1)
                pars.append((0.0, 0.0))
                node_seg.append(0)
                continue
            e = net.ends[node]
            if e.kind == "impedance" and len(e.impedance) > 1:
                raise ValueError(f"{net.source}: end {node!r}: the batched kernel takes a constant impedance only")
            kinds.append(kn.END_KINDS[e.kind])
            pars.append(
                RADIATION[e.flange]
                if e.kind == "open"
                else (e.resistance, e.volume)
                if e.kind == "load"
                else tuple(e.impedance[0, 1:])
                if e.kind == "impedance"
                else (0.0, 0.0)
            )
            b, side = inc[0]
            end_seg = end_segment(net, b, side)
            node_seg.append(int(starts[b]) + list(net.branches[b].segments).index(end_seg))
        dev = self.device
        i32 = {"dtype": wp.int32, "device": dev}
        self.gas = wp.array(g.as_tuple(), dtype=wp.float64, device=dev)
        self.seg = wp.array(table, dtype=wp.float64, device=dev)
        self.design = wp.array(design, dtype=wp.float64, device=dev)
        self.seg_kind = wp.array([_KIND[s.kind] for s in segs], **i32)
        self.seg_model = wp.array([int(PORE_MODELS[s.pore_model]) for s in segs], **i32)
        self.seg_porous = wp.array([int(s.kind == "porous") for s in segs], **i32)
        self.branch_first = wp.array(starts.astype(np.int32), **i32)
        self.node_first = wp.array(node_first, **i32)
        self.inc_branch = wp.array(inc_b, **i32)
        self.inc_side = wp.array(inc_s, **i32)
        self.node_kind = wp.array(kinds, **i32)
        self.node_par = wp.array(np.array(pars, dtype=np.float64).reshape(-1, 2), dtype=wp.float64, device=dev)
        self.node_seg = wp.array(node_seg, **i32)

    def tables(self) -> kn.NetworkTables:
        t = kn.NetworkTables()
        for name in (
            "gas",
            "seg",
            "design",
            "seg_kind",
            "seg_model",
            "seg_porous",
            "branch_first",
            "node_first",
            "inc_branch",
            "inc_side",
            "node_kind",
            "node_par",
            "node_seg",
            "cells",
        ):
            setattr(t, name, getattr(self, name))
        return t

    def _complex(self, z) -> wp.array:
        z = np.ascontiguousarray(np.broadcast_to(np.asarray(z, dtype=complex), (self.n,)))
        return wp.array(z.view(np.float64).reshape(self.n, 2), dtype=wp.vec2d, device=self.device)

    def _real(self, x) -> wp.array:
        x = np.ascontiguousarray(np.broadcast_to(np.asarray(x, dtype=np.float64), (self.n,)))
        return wp.array(x, dtype=wp.float64, device=self.device)

    def determinants(self, omega, T_hot=None) -> np.ndarray:
        """det of every design's boundary matrix at ``omega`` [rad/s] (scalar or (n,), complex)
        and ``T_hot`` [K] (default the file's)."""
        T_hot = self.net.T_hot if T_hot is None else T_hot
        out = wp.empty(self.n, dtype=wp.vec2d, device=self.device)
        wp.launch(
            kn.det_kernel,
            dim=self.n,
            inputs=[self.tables(), self._complex(omega), self._real(np.nan_to_num(T_hot)), out],
            device=self.device,
        )
        return out.numpy().view(np.complex128).ravel()

    def eigenfrequencies(self, guess, T_hot=None, rtol: float = 1e-11, max_iter: int = 60):
        """(omega (n,) complex [rad/s], Muller steps (n,), -1: not converged) of every design at
        ``T_hot`` [K] from ``guess`` (scalar or (n,))."""
        T_hot = self.net.T_hot if T_hot is None else T_hot
        omega = wp.empty(self.n, dtype=wp.vec2d, device=self.device)
        its = wp.empty(self.n, dtype=wp.int32, device=self.device)
        wp.launch(
            kn.eigen_kernel,
            dim=self.n,
            inputs=[
                self.tables(),
                self._complex(guess),
                self._real(np.nan_to_num(T_hot)),
                1e-3,
                float(rtol),
                int(max_iter),
            ]
            + [omega, its],
            device=self.device,
        )
        return omega.numpy().view(np.complex128).ravel(), its.numpy()

    def onset(self, omega0, T0, rtol: float = 1e-10, max_iter: int = 30, T_range=None) -> BatchOnset:
        """Onset of every design by Newton's method on (omega, T_hot) from (``omega0`` [rad/s],
        ``T0`` [K]) (scalars or (n,)): a nearby design's onset, e.g. the nominal one of
        :func:`tawarp.model.network_reference.onset`. An iterate outside ``T_range`` [K]
        (default T_cold to 10 T_cold) or half omega0 away ends a design unconverged."""
        T_lo, T_hi = T_range if T_range is not None else (self.net.gas.T_cold, 10 * self.net.gas.T_cold)
        omega = wp.empty(self.n, dtype=wp.float64, device=self.device)
        T = wp.empty(self.n, dtype=wp.float64, device=self.device)
        its = wp.empty(self.n, dtype=wp.int32, device=self.device)
        wp.launch(
            kn.onset_kernel,
            dim=self.n,
            inputs=[
                self.tables(),
                self._real(omega0),
                self._real(T0),
                float(T_lo),
                float(T_hi),
                float(rtol),
                int(max_iter),
            ]
            + [omega, T, its],
            device=self.device,
        )
        return BatchOnset(omega.numpy(), T.numpy(), its.numpy())

    def followed_onset(
        self, guess, T_max: float, n: int = 12, jump_tol: float = 0.05, halvings: int = 6, rtol: float = 1e-10
    ) -> "FollowedOnset":
        """Onset of every design with its own mode followed from T_cold to ``T_max`` [K] on
        ``n`` hot temperatures, one thread each (:func:`tawarp.kernels.network.followed_onset_kernel`,
        the reference's :func:`tawarp.model.network_reference.onset`): no start near an onset
        needed, only ``guess`` [rad/s] (scalar or (n,), complex) of the mode at T_cold."""
        grid = np.linspace(self.net.gas.T_cold, T_max, n)
        omega = wp.empty(self.n, dtype=wp.vec2d, device=self.device)
        T = wp.empty(self.n, dtype=wp.float64, device=self.device)
        jumps = wp.empty(self.n, dtype=wp.int32, device=self.device)
        status = wp.empty(self.n, dtype=wp.int32, device=self.device)
        wp.launch(
            kn.followed_onset_kernel,
            dim=self.n,
            inputs=[self.tables(), self._complex(guess), wp.array(grid, dtype=wp.float64, device=self.device)]
            + [float(jump_tol), int(halvings), float(rtol), 60, omega, T, jumps, status],
            device=self.device,
        )
        st = status.numpy()
        w = omega.numpy().view(np.complex128).ravel()
        return FollowedOnset(np.where(st == 1, w.real, np.nan), np.where(st == 1, T.numpy(), np.nan), jumps.numpy(), st)


@dataclass
class FollowedOnset:
    """Onsets found by following each design's mode: ``omega`` (n,) [rad/s] and ``T_hot``
    (n,) [K] (NaN without onset), ``jumps`` (n,) mode jumps met on the way, ``status`` (n,):
    1 onset, 0 none up to T_max, -1 a root search failed."""

    omega: np.ndarray
    T_hot: np.ndarray
    jumps: np.ndarray
    status: np.ndarray
