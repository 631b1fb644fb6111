"""Complex eigenfrequencies and onset heat input of engines, batched on Warp.

>>> from tawarp.model.resonator import load_engine
>>> from tawarp.model.onset import eigenfrequencies, onset
>>> eng = load_engine("standing_wave")
>>> eig = eigenfrequencies(eng, heat_input=[0, 20, 40], device="cpu")
>>> eig.frequency, eig.growth_rate          # Hz, 1/s (Im omega; > 0 grows)
>>> res = onset(eng, Q_max=100.0, device="cpu")
>>> res.Q_onset, res.f_onset, res.T_hot      # W, Hz, K

Convention exp(-i omega t): a mode grows when Im omega > 0 (PHYSICS.md, "Onset"). One
kernel thread per (parameter set, heat input) finds omega by Muller's method
(:mod:`tawarp.kernels.onset`); :func:`onset` brackets the heat input where Im omega
changes sign on a grid of Q (one batched launch) and refines it by a bracketed secant
(Illinois) on Q, one batched launch per step for all sets still refining.

Batches: ``params`` as :func:`tawarp.model.forward.transfer_matrices` (``SEGMENT.FIELD``)
plus the resonator's ``engine.left_duct``, ``engine.right_duct`` (lengths [m]),
``engine.left_duct_radius``, ... (:data:`tawarp.model.resonator.RESONATOR_FIELDS`).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from .core import CoreError
from .forward import Engine, ForwardSettings, batch_table
from .gas import GASES
from .resonator import RESONATOR_FIELDS, ThermoacousticEngine
from .validity import check_sets
from ..kernels import layout
from ..kernels import onset as ko

#: Relative spread of Muller's three start points around the guess.
MULLER_SPREAD = 1e-3


@dataclass
class EigenResult:
    """Eigenfrequencies of a batch: ``omega`` (n,) complex [rad/s]; ``heat_input`` (n,)
    [W]; ``T_hot`` (n,) largest steady temperature in the core [K]; ``iterations`` (n,)
    Muller steps (-1: not converged, omega is then the last iterate); ``evaluations`` (n,)
    residual (cascade) evaluations made."""

    omega: np.ndarray
    heat_input: np.ndarray
    T_hot: np.ndarray
    iterations: np.ndarray
    evaluations: np.ndarray

    @property
    def frequency(self) -> np.ndarray:
        """Re omega / 2 pi [Hz]."""
        return self.omega.real / (2 * math.pi)

    @property
    def growth_rate(self) -> np.ndarray:
        """Im omega [1/s]: > 0 the mode grows, < 0 it decays."""
        return self.omega.imag


@dataclass
class OnsetResult:
    """Onset of a batch of n engines: ``Q_onset`` (n,) [W] (NaN where Im omega does not
    cross 0 from below on [0, Q_max]), ``f_onset`` [Hz], ``T_hot`` [K] at onset,
    ``omega_onset`` complex [rad/s]; the bracketing grid ``Q_grid`` (k,) [W] and
    ``omega_grid`` (n, k) complex; ``secant_steps`` the refinement launches; ``evaluations``
    (n,) residual (cascade) evaluations spent on each set."""

    Q_onset: np.ndarray
    f_onset: np.ndarray
    T_hot: np.ndarray
    omega_onset: np.ndarray
    Q_grid: np.ndarray
    omega_grid: np.ndarray
    secant_steps: int
    evaluations: np.ndarray


def _split_names(params: dict | None) -> tuple[dict, dict]:
    core_p, res_p = {}, {}
    for k, v in (params or {}).items():
        if k.startswith("engine."):
            if k[7:] not in RESONATOR_FIELDS:
                raise KeyError(f"{k!r}: not a resonator parameter; expected engine.{{{', '.join(RESONATOR_FIELDS)}}}")
            res_p[k[7:]] = v
        else:
            core_p[k] = v
    return core_p, res_p


class EigenSolver:
    """A compiled engine layout: the core's forward :class:`~tawarp.model.forward.Engine`
    (its heat solve and tables) plus the resonator and ends; :meth:`solve` runs one
    batched launch."""

    def __init__(self, engine: ThermoacousticEngine, names=(), settings: ForwardSettings | None = None):
        self.engine = engine
        self.forward = Engine(engine.core, [1.0], names, settings)
        dev = self.forward.device
        self.ends = wp.array([ko.END_KINDS[engine.left.kind], ko.END_KINDS[engine.right.kind]], dtype=wp.int32,
                             device=dev)
        self.z_left = wp.array(engine.left.table(), dtype=wp.float64, device=dev)
        self.z_right = wp.array(engine.right.table(), dtype=wp.float64, device=dev)

    def lossless_omega(self, params: np.ndarray, resonator: np.ndarray, mode: int) -> np.ndarray:
        """Start value [rad/s] per set: mode ``mode`` of the lossless resonator with the
        same acoustic travel time tau (sum of q L / c at each part's cold temperature):
        n pi / tau between ends of the same kind, (n - 1/2) pi / tau between a closed and
        an open end (an impedance end counts as closed)."""
        core = self.engine.core
        g = GASES[core.gas.name]
        c = np.sqrt(g.gamma * g.R_gas * params[layout.T_COLD])
        tau = resonator[:, ko.R_LEFT_LENGTH] / np.sqrt(g.gamma * g.R_gas * resonator[:, ko.R_LEFT_T])
        tau = tau + resonator[:, ko.R_RIGHT_LENGTH] / np.sqrt(g.gamma * g.R_gas * resonator[:, ko.R_RIGHT_T])
        for s, seg in enumerate(core.segments):
            row = layout.N_GLOBAL + s * layout.N_FIELDS
            q = params[row + layout.TORTUOSITY] if seg.is_porous else 1.0
            tau = tau + q * params[row + layout.LENGTH] / c
        open_ends = (self.engine.left.kind == "open") + (self.engine.right.kind == "open")
        return (mode - 0.5 * (open_ends == 1)) * math.pi / tau

    def solve(self, varying: np.ndarray, resonator: np.ndarray, guess: np.ndarray | None, omega_ref: np.ndarray | None,
              mode: int = 1, tol: float = 1e-13, max_iter: int = 60, hot: bool = True) -> EigenResult:
        """Eigenfrequencies of the (1 + names, n) batch ``varying`` (row 0 heat input [W])
        with resonator rows (n, 6). ``guess`` (n,) complex start [rad/s] and ``omega_ref``
        (n,) [rad/s] for the adaptive cells: None takes the lossless mode ``mode``.
        ``hot``: also the largest temperature (else T_hot is NaN)."""
        fe = self.forward
        dev = fe.device
        params, theta = fe.heat(np.ascontiguousarray(varying, dtype=np.float64))
        n = params.shape[1]
        if guess is None or omega_ref is None:
            w0 = self.lossless_omega(params.numpy(), resonator, mode)
            guess = w0.astype(complex) if guess is None else guess
            omega_ref = w0 if omega_ref is None else omega_ref
        w_guess = wp.array(np.ascontiguousarray(np.broadcast_to(guess, (n,)), dtype=np.complex128).view(np.float64)
                           .reshape(n, 2), dtype=wp.vec2d, device=dev)
        w_ref = wp.array(np.ascontiguousarray(np.broadcast_to(omega_ref, (n,)), dtype=np.float64), dtype=wp.float64,
                         device=dev)
        w_res = wp.array(np.ascontiguousarray(resonator, dtype=np.float64), dtype=wp.float64, device=dev)
        omega = wp.empty(n, dtype=wp.vec2d, device=dev)
        its = wp.empty(n, dtype=wp.int32, device=dev)
        evals = wp.empty(n, dtype=wp.int32, device=dev)
        wp.launch(ko.eigen_kernel, dim=n, device=dev,
                  inputs=[params, fe.flags, fe.gas, theta, fe.seg_cells, float(fe.settings.cell_density), fe.first,
                          fe.heat_cells, w_res, self.ends, self.z_left, self.z_right, w_guess, w_ref,
                          MULLER_SPREAD, float(tol), int(max_iter), omega, its, evals])
        return EigenResult(omega.numpy().view(np.complex128).reshape(n), np.asarray(varying[0]).copy(),
                           self.hot_temperature(params, theta) if hot else np.full(n, np.nan), its.numpy(),
                           evals.numpy())

    def hot_temperature(self, params: wp.array, theta: wp.array) -> np.ndarray:
        """Largest steady temperature [K] in the core per set (:func:`tawarp.kernels.onset.hot_kernel`)."""
        fe = self.forward
        out = wp.empty(params.shape[1], dtype=wp.float64, device=fe.device)
        wp.launch(ko.hot_kernel, dim=params.shape[1], device=fe.device,
                  inputs=[params, fe.flags, fe.gas, theta, fe.first, fe.heat_cells, out])
        return out.numpy()


def prepare(engine: ThermoacousticEngine, heat_input, params: dict | None, settings: ForwardSettings | None, **kw):
    """(solver, varying (1 + names, n), resonator (n, 6)) of a batch, checked."""
    settings = dataclasses.replace(settings or ForwardSettings(), **kw)
    core_p, res_p = _split_names(params)
    arrays = {k: np.atleast_1d(np.asarray(v, dtype=np.float64)) for k, v in res_p.items()}
    q = np.atleast_1d(np.asarray(heat_input, dtype=np.float64))
    n = np.broadcast_shapes(q.shape, *(a.shape for a in arrays.values()),
                            *(np.atleast_1d(np.asarray(v)).shape for v in core_p.values()))[0]
    names, varying = batch_table(engine.core, np.broadcast_to(q, (n,)), core_p)
    resonator = np.tile(engine.resonator_row(), (n, 1))
    for k, a in arrays.items():
        col = RESONATOR_FIELDS.index(k)
        a = np.broadcast_to(a, (n,))
        if not np.all(np.isfinite(a)) or np.any(a < 0) or (not k.endswith("_duct") and np.any(a <= 0)):
            raise CoreError(f"parameter engine.{k}: values must be finite and {'>= 0' if k.endswith('_duct') else '> 0'}")
        resonator[:, col] = a
    check_sets(engine.core, varying[0], dict(zip(names, varying[1:])))
    return EigenSolver(engine, names, settings), varying, resonator


def eigenfrequencies(engine: ThermoacousticEngine, heat_input=0.0, mode: int = 1, params: dict | None = None,
                     guess=None, settings: ForwardSettings | None = None, tol: float = 1e-13, max_iter: int = 60,
                     **kw) -> EigenResult:
    """Complex eigenfrequency of mode ``mode`` (1 = fundamental) for a batch of heat inputs
    [W] and parameter sets (broadcast together, as :func:`~tawarp.model.forward.transfer_matrices`).

    ``guess``: complex start value(s) [rad/s] (default: the lossless resonator's mode
    ``mode``, see :meth:`EigenSolver.lossless_omega`); Muller stops when a step is below
    ``tol`` |omega|. ``settings`` / keywords as :class:`ForwardSettings` (``device=``, ``cells=``).
    Sets that did not converge warn and keep ``iterations == -1``."""
    if int(mode) < 1:
        raise ValueError(f"mode must be >= 1, got {mode}")
    solver, varying, resonator = prepare(engine, heat_input, params, settings, **kw)
    res = solver.solve(varying, resonator, None if guess is None else np.asarray(guess, dtype=complex), None, mode,
                       tol, max_iter)
    _warn_unconverged(res.iterations, res.heat_input)
    return res


def _warn_unconverged(its: np.ndarray, q: np.ndarray) -> None:
    bad = np.flatnonzero(its < 0)
    if bad.size:
        warnings.warn(f"eigenfrequency search did not converge for {bad.size} set(s), first: set {bad[0]} "
                      f"(heat input {q[bad[0]]:g} W); raise max_iter or give a closer guess", RuntimeWarning,
                      stacklevel=3)


def onset(engine: ThermoacousticEngine, Q_max: float, mode: int = 1, params: dict | None = None,
          n_bracket: int = 9, rtol: float = 1e-10, max_steps: int = 100, settings: ForwardSettings | None = None,
          **kw) -> OnsetResult:
    """Onset heat input of mode ``mode`` for a batch of engines (``params`` as
    :func:`eigenfrequencies`).

    Im omega is evaluated on ``n_bracket`` heat inputs evenly spaced on [0, Q_max] [W]
    (each started from the set's unheated eigenfrequency); the first interval where it goes
    from < 0 to >= 0 is refined by the Illinois secant on Q until the bracket is below
    ``rtol`` Q. Returns :class:`OnsetResult`; Q_onset is NaN where there is no such interval
    (already growing at Q = 0, or stable up to Q_max)."""
    if not (Q_max > 0 and math.isfinite(Q_max)):
        raise ValueError(f"Q_max [W] must be finite and > 0, got {Q_max}")
    if n_bracket < 2:
        raise ValueError(f"n_bracket must be >= 2, got {n_bracket}")
    solver, varying, resonator = prepare(engine, 0.0, params, settings, **kw)
    n = varying.shape[1]
    base = solver.solve(varying, resonator, None, None, mode)
    _warn_unconverged(base.iterations, base.heat_input)
    w_ref = base.omega.real.copy()
    guess0 = base.omega
    Qg = np.linspace(0.0, Q_max, n_bracket)

    def at(idx: np.ndarray, Q: np.ndarray, guess: np.ndarray) -> EigenResult:
        v = varying[:, idx].copy()
        v[0] = Q
        r = solver.solve(v, resonator[idx], guess, w_ref[idx], hot=False)
        _warn_unconverged(r.iterations, Q)
        return r

    rep = np.repeat(np.arange(n), n_bracket)
    grid = at(rep, np.tile(Qg, n), guess0[rep])
    wg = grid.omega.reshape(n, n_bracket)
    evals = base.evaluations + grid.evaluations.reshape(n, n_bracket).sum(axis=1)
    g = wg.imag
    up = (g[:, :-1] < 0) & (g[:, 1:] >= 0)
    has = up.any(axis=1)
    j = np.argmax(up, axis=1)
    idx = np.flatnonzero(has)
    q_lo, q_hi = Qg[j[idx]], Qg[j[idx] + 1]
    g_lo, g_hi = g[idx, j[idx]], g[idx, j[idx] + 1]
    w_lo, w_hi = wg[idx, j[idx]], wg[idx, j[idx] + 1]
    Q_on = np.full(n, np.nan)
    w_on = np.full(n, np.nan + 0j)
    T_on = np.full(n, np.nan)
    side = np.zeros(idx.size, dtype=int)       # Illinois: which end was kept last (-1 lo, +1 hi)
    active = np.ones(idx.size, dtype=bool)
    q_prev = np.full(idx.size, np.inf)
    steps = 0
    while active.any() and steps < max_steps:
        a = np.flatnonzero(active)
        t = g_lo[a] / (g_lo[a] - g_hi[a])
        q_new = q_lo[a] + t * (q_hi[a] - q_lo[a])
        r = at(idx[a], q_new, w_lo[a] + t * (w_hi[a] - w_lo[a]))
        steps += 1
        evals[idx[a]] += r.evaluations
        gn = r.omega.imag
        Q_on[idx[a]] = q_new
        w_on[idx[a]] = r.omega
        lo = gn < 0
        al, ah = a[lo], a[~lo]          # the new point replaces the bracket end of its sign
        q_lo[al], g_lo[al], w_lo[al] = q_new[lo], gn[lo], r.omega[lo]
        q_hi[ah], g_hi[ah], w_hi[ah] = q_new[~lo], gn[~lo], r.omega[~lo]
        # Illinois: the end kept twice in a row has its value halved
        g_hi[al[side[al] == -1]] *= 0.5
        g_lo[ah[side[ah] == 1]] *= 0.5
        side[al], side[ah] = -1, 1
        # converged: the bracket, or the secant's own step, below rtol Q
        active[a] = ~((q_hi[a] - q_lo[a] <= rtol * q_new) | (np.abs(q_new - q_prev[a]) <= rtol * q_new) | (gn == 0))
        q_prev[a] = q_new
    if idx.size:
        v = varying[:, idx].copy()
        v[0] = Q_on[idx]
        T_on[idx] = solver.hot_temperature(*solver.forward.heat(v))
    if active.any():
        warnings.warn(f"onset: {int(active.sum())} set(s) not refined to rtol = {rtol} in {max_steps} steps",
                      RuntimeWarning, stacklevel=2)
    return OnsetResult(Q_on, w_on.real / (2 * math.pi), T_on, w_on, Qg, wg, steps, evals)
