"""Complex eigenfrequencies and onset heat input or hot temperature of engines, batched on Warp.

>>> from tawarp.model.resonator import load_engine
>>> from tawarp.model.onset import eigenfrequencies, onset
>>> eng = load_engine("standing_wave")
>>> eig = eigenfrequencies(eng, heat_input=[0, 20, 40], device="cpu")
>>> eig.frequency, eig.growth_rate          # Hz, 1/s (Im omega; > 0 grows)
>>> res = onset(eng, Q_max=100.0, device="cpu")
>>> res.Q_onset, res.f_onset, res.T_hot      # W, Hz, K

An engine whose temperatures are imposed (segments with ``T_start``/``T_end``, docs/formats.md)
has its onset in the hot temperature instead: ``onset(eng, T_ratio_max=3.0)`` scales every
imposed temperature's excess over T_cold together, T_hot / T_cold from 1 to 3
(:class:`TemperatureSearch`), and reports ``res.ratio_onset``.

Convention exp(-i omega t): a mode grows when Im omega > 0 (docs/physics.md, "Onset"). One
kernel thread per (parameter set, heat input) finds omega by Muller's method
(:mod:`tawarp.kernels.onset`); :func:`onset` brackets the heat input where Im omega
changes sign on a grid of Q (one batched launch per grid point for the sets still
marching) and refines it by Newton's method on (Re omega, Q), with the bracketed Illinois
secant on Q as fallback: one batched launch per step for all sets still refining.

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
    """Onset of a batch of n engines in the searched quantity (``searched``: "heat_input",
    or "T_ratio" for imposed temperatures, :func:`onset`): ``Q_onset`` (n,) [W] (NaN where Im
    omega does not cross 0 from below on the searched range, and for a search in the hot
    temperature), ``ratio_onset`` (n,) T_hot / T_cold at onset, ``f_onset`` [Hz], ``T_hot``
    [K] at onset, ``omega_onset`` complex [rad/s]; the bracketing ``grid`` (k,) of the
    searched quantity (W, or T_hot / T_cold) and ``omega_grid`` (n, k) complex (NaN where
    not computed, see :func:`onset`); ``refine_steps`` the refinement launches (Newton and
    fallback secant steps); ``evaluations`` (n,) residual (cascade) evaluations spent on each
    set; ``fallback`` the sets refined by the secant fallback instead of Newton."""

    Q_onset: np.ndarray
    f_onset: np.ndarray
    T_hot: np.ndarray
    omega_onset: np.ndarray
    grid: np.ndarray
    omega_grid: np.ndarray
    refine_steps: int
    evaluations: np.ndarray
    fallback: np.ndarray
    ratio_onset: np.ndarray
    searched: str = "heat_input"

    @property
    def Q_grid(self) -> np.ndarray:
        """The heat inputs of the bracketing grid [W] (NaN for a search in the hot temperature)."""
        return self.grid if self.searched == "heat_input" else np.full(self.grid.shape, np.nan)

    @property
    def mean_evaluations(self) -> float:
        """Residual (cascade) evaluations per onset, mean over the batch."""
        return float(np.mean(self.evaluations))


class HeatSearch:
    """Onset searched in the heat input Q [W] (row 0 of a batch table), from 0."""

    name = "heat_input"
    start = 0.0

    def set(self, varying: np.ndarray, x: np.ndarray) -> None:
        """Put the searched values ``x`` (one per column) into the batch table ``varying``."""
        varying[0] = x


class TemperatureSearch:
    """Onset searched in the hot temperature of an engine whose temperatures are imposed:
    at ratio x = T_hot / T_cold every imposed temperature T_k of the file becomes
    T_cold (1 + e_k (x - 1)), e_k = (T_k - T_cold) / (T_hot - T_cold) its place in the file's
    own profile (T_hot the file's largest imposed temperature, T_cold its gas.T_cold), so
    that the largest is x T_cold; a set's own T_cold when the batch varies gas.T_cold. From
    x = 1 (every part at T_cold)."""

    name = "T_ratio"
    start = 1.0

    def __init__(self, engine: ThermoacousticEngine, params: dict):
        core = engine.core
        self.names = [f"{s.name}.{f}" for s in core.segments if s.imposed for f in ("T_start", "T_end")]
        if not self.names:
            raise CoreError(
                f"{core.source}: onset in the hot temperature needs imposed temperatures (T_start, T_end or T "
                f"on a [[segment]]); this engine has none (search in the heat input: Q_max)"
            )
        given = sorted(set(self.names) & set(params))
        if given:
            raise CoreError(
                f"onset in the hot temperature sets the imposed temperatures itself; {given[0]} cannot vary in the batch"
            )
        values = np.array([core.get(k) for k in self.names])
        t_cold = core.gas.T_cold
        if not values.max() > t_cold:
            raise CoreError(
                f"{core.source}: no imposed temperature lies above gas.T_cold = {t_cold:g} K: the hot "
                f"temperature has no profile to scale"
            )
        self.t_cold = t_cold
        self.shape = (values - t_cold) / (values.max() - t_cold)
        self.rows: np.ndarray | None = None
        self.t_cold_row: int | None = None

    def bind(self, names: list[str]) -> None:
        """Rows of the batch table (row 0 heat input, then ``names``) the search writes and reads."""
        self.rows = np.array([1 + names.index(k) for k in self.names])
        self.t_cold_row = 1 + names.index("gas.T_cold") if "gas.T_cold" in names else None

    def set(self, varying: np.ndarray, x: np.ndarray) -> None:
        t_cold = varying[self.t_cold_row] if self.t_cold_row is not None else self.t_cold
        varying[self.rows] = t_cold * (1 + self.shape[:, None] * (np.asarray(x) - 1))


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


def _complex(z, device) -> wp.array:
    """Complex values ``z`` (n,) as the kernels' (re, im) vectors on ``device``."""
    z = np.ascontiguousarray(z, dtype=np.complex128)
    return wp.array(z.view(np.float64).reshape(-1, 2), dtype=wp.vec2d, device=device)


def _real(x, device) -> wp.array:
    """``x`` (any shape) as a float64 array on ``device``."""
    return wp.array(np.ascontiguousarray(x, dtype=np.float64), dtype=wp.float64, device=device)


def heated_core(fe: Engine, params: wp.array, theta: wp.array) -> ko.HeatedCore:
    """The complex-frequency kernels' :class:`tawarp.kernels.onset.HeatedCore` of the batch
    ``params`` (rows, n) whose heat solve on ``fe`` gave ``theta`` (:meth:`Engine.heat`)."""
    core = ko.HeatedCore()
    core.sets = fe._sets(params)
    core.theta = theta
    core.first = fe.first
    core.heat_cells = fe.heat_cells
    core.seg_cells = fe.seg_cells
    core.cell_density = float(fe.settings.cell_density)
    return core


class EigenSolver:
    """A compiled engine layout: the core's forward :class:`~tawarp.model.forward.Engine`
    (its heat solve and tables) plus the resonator and ends; :meth:`solve` runs one
    batched launch."""

    def __init__(self, engine: ThermoacousticEngine, names=(), settings: ForwardSettings | None = None):
        self.engine = engine
        self.forward = Engine(engine.core, [1.0], names, settings)
        dev = self.forward.device
        self.ends = wp.array(
            [ko.END_KINDS[engine.left.kind], ko.END_KINDS[engine.right.kind]], dtype=wp.int32, device=dev
        )
        self.z_left = wp.array(engine.left.table(), dtype=wp.float64, device=dev)
        self.z_right = wp.array(engine.right.table(), dtype=wp.float64, device=dev)

    def resonator(self, ducts: np.ndarray) -> ko.Resonator:
        """The kernels' :class:`tawarp.kernels.onset.Resonator` of the engine's ends with the
        duct rows ``ducts`` (n, 6)."""
        res = ko.Resonator()
        res.ducts = _real(ducts, self.forward.device)
        res.ends = self.ends
        res.z_left = self.z_left
        res.z_right = self.z_right
        return res

    def lossless_omega(self, params: np.ndarray, resonator: np.ndarray, mode: int) -> np.ndarray:
        """Start value [rad/s] per set: mode ``mode`` of the lossless resonator with the
        same acoustic travel time tau (sum of q L / c at each part's cold or imposed temperature):
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
            if seg.imposed:  # int dx / c over a linear T(x): 2 L / (c(T_start) + c(T_end))
                ends = np.sqrt(g.gamma * g.R_gas * params[row + layout.T_START])
                ends = ends + np.sqrt(g.gamma * g.R_gas * params[row + layout.T_END])
                tau = tau + 2 * q * params[row + layout.LENGTH] / ends
            else:
                tau = tau + q * params[row + layout.LENGTH] / c
        open_ends = (self.engine.left.kind == "open") + (self.engine.right.kind == "open")
        return (mode - 0.5 * (open_ends == 1)) * math.pi / tau

    def solve(
        self,
        varying: np.ndarray,
        resonator: np.ndarray,
        guess: np.ndarray | None,
        omega_ref: np.ndarray | None,
        mode: int = 1,
        tol: float = 1e-13,
        max_iter: int = 60,
        hot: bool = True,
    ) -> EigenResult:
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
        omega = wp.empty(n, dtype=wp.vec2d, device=dev)
        its = wp.empty(n, dtype=wp.int32, device=dev)
        evals = wp.empty(n, dtype=wp.int32, device=dev)
        wp.launch(
            ko.eigen_kernel,
            dim=n,
            device=dev,
            inputs=[
                heated_core(fe, params, theta),
                self.resonator(resonator),
                _complex(np.broadcast_to(guess, (n,)), dev),
                _real(np.broadcast_to(omega_ref, (n,)), dev),
                MULLER_SPREAD,
                float(tol),
                int(max_iter),
                omega,
                its,
                evals,
            ],
        )
        return EigenResult(
            omega.numpy().view(np.complex128).reshape(n),
            np.asarray(varying[0]).copy(),
            self.hot_temperature(params, theta) if hot else np.full(n, np.nan),
            its.numpy(),
            evals.numpy(),
        )

    def residuals(
        self, varying: np.ndarray, resonator: np.ndarray, omega_ref: np.ndarray, column: np.ndarray, omega: np.ndarray
    ) -> np.ndarray:
        """Residuals (complex, n_points) of the end condition: point j at complex ``omega[j]``
        [rad/s] for set ``column[j]`` of the (1 + names, n) batch ``varying`` (row 0 heat input
        [W]), its resonator row (n, 6) and reference frequency ``omega_ref`` (n,) [rad/s]."""
        fe = self.forward
        dev = fe.device
        params, theta = fe.heat(np.ascontiguousarray(varying, dtype=np.float64))
        k = omega.size
        out = wp.empty(k, dtype=wp.vec2d, device=dev)
        wp.launch(
            ko.residual_kernel,
            dim=k,
            device=dev,
            inputs=[
                heated_core(fe, params, theta),
                self.resonator(resonator),
                wp.array(np.asarray(column, dtype=np.int32), dtype=wp.int32, device=dev),
                _complex(omega, dev),
                _real(omega_ref, dev),
                out,
            ],
        )
        return out.numpy().view(np.complex128).reshape(k)

    def hot_temperature(self, params: wp.array, theta: wp.array) -> np.ndarray:
        """Largest steady temperature [K] in the core per set (:func:`tawarp.kernels.onset.hot_kernel`)."""
        fe = self.forward
        out = wp.empty(params.shape[1], dtype=wp.float64, device=fe.device)
        wp.launch(ko.hot_kernel, dim=params.shape[1], device=fe.device, inputs=[heated_core(fe, params, theta), out])
        return out.numpy()


def prepare(engine: ThermoacousticEngine, heat_input, params: dict | None, settings: ForwardSettings | None, **kw):
    """(solver, varying (1 + names, n), resonator (n, 6)) of a batch, checked."""
    settings = dataclasses.replace(settings or ForwardSettings(), **kw)
    core_p, res_p = _split_names(params)
    arrays = {k: np.atleast_1d(np.asarray(v, dtype=np.float64)) for k, v in res_p.items()}
    q = np.atleast_1d(np.asarray(heat_input, dtype=np.float64))
    n = np.broadcast_shapes(
        q.shape, *(a.shape for a in arrays.values()), *(np.atleast_1d(np.asarray(v)).shape for v in core_p.values())
    )[0]
    names, varying = batch_table(engine.core, np.broadcast_to(q, (n,)), core_p)
    resonator = np.tile(engine.resonator_row(), (n, 1))
    for k, a in arrays.items():
        col = RESONATOR_FIELDS.index(k)
        a = np.broadcast_to(a, (n,))
        if not np.all(np.isfinite(a)) or np.any(a < 0) or (not k.endswith("_duct") and np.any(a <= 0)):
            raise CoreError(
                f"parameter engine.{k}: values must be finite and {'>= 0' if k.endswith('_duct') else '> 0'}"
            )
        resonator[:, col] = a
    check_sets(engine.core, varying[0], dict(zip(names, varying[1:])))
    return EigenSolver(engine, names, settings), varying, resonator


def eigenfrequencies(
    engine: ThermoacousticEngine,
    heat_input=0.0,
    mode: int = 1,
    params: dict | None = None,
    guess=None,
    settings: ForwardSettings | None = None,
    tol: float = 1e-13,
    max_iter: int = 60,
    **kw,
) -> EigenResult:
    """Complex eigenfrequency of mode ``mode`` (1 = fundamental) for a batch of heat inputs
    [W] and parameter sets (broadcast together, as :func:`~tawarp.model.forward.transfer_matrices`).

    ``guess``: complex start value(s) [rad/s] (default: the lossless resonator's mode
    ``mode``, see :meth:`EigenSolver.lossless_omega`); Muller stops when a step is below
    ``tol`` |omega|. ``settings`` / keywords as :class:`ForwardSettings` (``device=``, ``cells=``).
    Sets that did not converge warn and keep ``iterations == -1``."""
    if int(mode) < 1:
        raise ValueError(f"mode must be >= 1, got {mode}")
    solver, varying, resonator = prepare(engine, heat_input, params, settings, **kw)
    res = solver.solve(
        varying, resonator, None if guess is None else np.asarray(guess, dtype=complex), None, mode, tol, max_iter
    )
    _warn_unconverged(res.iterations, res.heat_input)
    return res


def _warn_unconverged(its: np.ndarray, q: np.ndarray, searched: str = HeatSearch.name) -> None:
    bad = np.flatnonzero(its < 0)
    if bad.size:
        at = f"heat input {q[bad[0]]:g} W" if searched == HeatSearch.name else f"T_hot/T_cold {q[bad[0]]:g}"
        warnings.warn(
            f"eigenfrequency search did not converge for {bad.size} set(s), first: set {bad[0]} "
            f"({at}); raise max_iter or give a closer guess",
            RuntimeWarning,
            stacklevel=3,
        )


def onset(
    engine: ThermoacousticEngine,
    Q_max: float | None = None,
    mode: int = 1,
    params: dict | None = None,
    n_bracket: int = 9,
    rtol: float = 1e-10,
    max_steps: int = 100,
    settings: ForwardSettings | None = None,
    grid_tol: float = 1e-6,
    newton_steps: int = 12,
    curve: bool = False,
    T_ratio_max: float | None = None,
    **kw,
) -> OnsetResult:
    """Onset of mode ``mode`` for a batch of engines (``params`` as :func:`eigenfrequencies`)
    in the heat input on [0, ``Q_max``] [W] or, for an engine with imposed temperatures, in
    the hot temperature T_hot / T_cold on [1, ``T_ratio_max``] (:class:`TemperatureSearch`):
    give one of the two. Below, Q is the searched quantity.

    1. Bracket: Im omega on ``n_bracket`` values of Q evenly spaced on its range,
       marched from its start (the unheated mode), each point a Muller search to ``grid_tol``
       started from the linear extrapolation of the two before; a set stops at its first
       interval where Im omega goes from < 0 to >= 0 (``curve``: every set runs the whole
       grid, for the growth-rate curve).
    2. Refinement: at onset omega is real, so the complex residual R(omega, Q) = 0 is solved
       for (Re omega, Q) by Newton's method (:func:`_newton_onset`) from the linear
       interpolation of the bracket, until a step is below ``rtol`` in Q and in omega.
    3. Fallback: a set whose Newton step leaves the bracket, whose |R| does not decrease, or
       that is not converged in ``newton_steps`` steps (0: every set) is refined by the
       Illinois secant on Q (a Muller search to 1e-13 per step, at most ``max_steps``).

    Returns :class:`OnsetResult`; its onset (Q_onset, or ratio_onset in the hot temperature) is
    NaN where there is no such interval (already growing at the start, or stable up to the end). ``omega_grid`` holds the grid's eigenfrequencies
    to ``grid_tol`` |omega|; NaN past a set's bracket unless ``curve``."""
    if int(mode) < 1:
        raise ValueError(f"mode must be >= 1, got {mode}")
    search, upper, params = _search(engine, Q_max, T_ratio_max, params)
    if n_bracket < 2:
        raise ValueError(f"n_bracket must be >= 2, got {n_bracket}")
    solver, varying, resonator = prepare(engine, 0.0, params, settings, **kw)
    if isinstance(search, TemperatureSearch):
        search.bind(solver.forward.names)
    search.set(varying, search.start)
    n = varying.shape[1]
    base = solver.solve(varying, resonator, None, None, mode, tol=grid_tol, hot=False)
    _warn_unconverged(base.iterations, base.heat_input)
    # one real reference frequency per set fixes its adaptive cell counts: every residual of
    # the set (grid, Newton, secant) is then one analytic function of (omega, Q)
    w_ref = base.omega.real.copy()
    evals = base.evaluations.astype(np.int64)
    Qg = np.linspace(search.start, upper, n_bracket)

    def at(idx: np.ndarray, Q: np.ndarray, guess: np.ndarray, tol: float) -> EigenResult:
        v = varying[:, idx].copy()
        search.set(v, Q)
        r = solver.solve(v, resonator[idx], guess, w_ref[idx], tol=tol, hot=False)
        _warn_unconverged(r.iterations, np.broadcast_to(Q, idx.shape), search.name)
        evals[idx] += r.evaluations
        return r

    wg = np.full((n, n_bracket), np.nan + 0j)
    wg[:, 0] = base.omega
    j = np.full(n, -1)  # the first crossing lies in (Qg[j], Qg[j + 1])
    march = np.arange(n)
    for k in range(1, n_bracket):
        if not curve:
            march = march[j[march] < 0]
        if not march.size:
            break
        guess = wg[march, 0] if k == 1 else 2 * wg[march, k - 1] - wg[march, k - 2]
        wg[march, k] = at(march, np.full(march.size, Qg[k]), guess, grid_tol).omega
        up = (j[march] < 0) & (wg[march, k - 1].imag < 0) & (wg[march, k].imag >= 0)
        j[march[up]] = k - 1
    idx = np.flatnonzero(j >= 0)
    br = _Bracket(Qg[j[idx]], Qg[j[idx] + 1], wg[idx, j[idx]], wg[idx, j[idx] + 1])
    Q_on = np.full(n, np.nan)
    w_on = np.full(n, np.nan + 0j)
    T_on = np.full(n, np.nan)
    q, w, ok, steps = _newton_onset(
        solver, search, varying, resonator, w_ref, idx, br, rtol, newton_steps, grid_tol, evals
    )
    Q_on[idx[ok]], w_on[idx[ok]] = q[ok], w[ok]
    fb = np.flatnonzero(~ok)
    if fb.size:
        q, w, active, secant = _illinois(at, idx[fb], br.subset(fb), rtol, max_steps)
        Q_on[idx[fb]], w_on[idx[fb]] = q, w
        steps += secant
        if active.any():
            warnings.warn(
                f"onset: {int(active.sum())} set(s) not refined to rtol = {rtol} in {max_steps} steps",
                RuntimeWarning,
                stacklevel=2,
            )
    ratio = np.full(n, np.nan)
    if idx.size:
        v = varying[:, idx].copy()
        search.set(v, Q_on[idx])
        table, theta = solver.forward.heat(v)
        T_on[idx] = solver.hot_temperature(table, theta)
        ratio[idx] = T_on[idx] / table.numpy()[layout.T_COLD]
    if isinstance(search, TemperatureSearch):
        Q_on = np.full(n, np.nan)
    return OnsetResult(Q_on, w_on.real / (2 * math.pi), T_on, w_on, Qg, wg, steps, evals, idx[fb], ratio, search.name)


def _search(engine: ThermoacousticEngine, Q_max, T_ratio_max, params: dict | None):
    """(search, its upper end, the batch's params) of :func:`onset`, checked."""
    params = dict(params or {})
    if (Q_max is None) == (T_ratio_max is None):
        raise ValueError("onset: give Q_max [W] (search in the heat input) or T_ratio_max (in T_hot/T_cold), one")
    if Q_max is not None:
        if not (Q_max > 0 and math.isfinite(Q_max)):
            raise ValueError(f"Q_max [W] must be finite and > 0, got {Q_max}")
        return HeatSearch(), float(Q_max), params
    if not (T_ratio_max > 1 and math.isfinite(T_ratio_max)):
        raise ValueError(f"T_ratio_max (T_hot/T_cold) must be finite and > 1, got {T_ratio_max}")
    search = TemperatureSearch(engine, params)
    # the imposed temperatures vary with the search: rows of the batch table
    params.update({k: engine.core.get(k) for k in search.names})
    return search, float(T_ratio_max), params


@dataclass
class _Bracket:
    """Per set: heat inputs q_lo < q_hi [W] with Im omega < 0 at q_lo and >= 0 at q_hi, and
    the eigenfrequencies w_lo, w_hi [rad/s] there."""

    q_lo: np.ndarray
    q_hi: np.ndarray
    w_lo: np.ndarray
    w_hi: np.ndarray

    def subset(self, k: np.ndarray) -> "_Bracket":
        return _Bracket(self.q_lo[k].copy(), self.q_hi[k].copy(), self.w_lo[k].copy(), self.w_hi[k].copy())

    def interpolate(self) -> tuple[np.ndarray, np.ndarray]:
        """Linear interpolation where Im omega crosses 0: (Q [W], omega [rad/s])."""
        g_lo, g_hi = self.w_lo.imag, self.w_hi.imag
        t = g_lo / (g_lo - g_hi)
        return self.q_lo + t * (self.q_hi - self.q_lo), self.w_lo + t * (self.w_hi - self.w_lo)


#: Relative finite-difference steps of the Newton Jacobian, in omega and in Q (of the
#: bracket's upper end): the truncation error (~ step) and the rounding of the residual
#: (~ 1e-14 / step) are both ~1e-7 relative, which only slows Newton's last step by that factor.
FD_STEP = 1e-7
#: Newton keeps its Jacobian (one evaluation per step instead of three) once a step is below
#: this relative size: the Jacobian is then off by about that much, and each step contracts
#: the error by that factor (chord method).
CHORD_STEP = 1e-4


def _newton_onset(
    solver: EigenSolver,
    search,
    varying: np.ndarray,
    resonator: np.ndarray,
    w_ref: np.ndarray,
    idx: np.ndarray,
    br: _Bracket,
    rtol: float,
    max_steps: int,
    grid_tol: float,
    evals: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Onset of sets ``idx`` by Newton's method on the real unknowns (w = Re omega, Q, the
    quantity ``search`` puts into the batch, :class:`HeatSearch` or :class:`TemperatureSearch`): the
    complex residual R of :func:`tawarp.kernels.onset.engine_residual` is zero at real omega
    exactly at onset, two real equations. Jacobian: dR/dw (R is analytic in omega, a real
    step gives the complex derivative) and dR/dQ (a heat solve at Q + dQ) by forward
    differences (:data:`FD_STEP`), kept once steps are small (:data:`CHORD_STEP`).

    Start: the bracket's linear interpolation. A set converges when its step is below
    ``rtol`` in Q and in w; the returned point is one step beyond, so its error is that of
    the next step (quadratic, or contracted by CHORD_STEP), far below rtol. It fails (for the
    secant fallback) when a step leaves the bracket, |R| does not decrease, the Jacobian is
    singular, or ``max_steps`` steps do not converge. The bracket is widened by 10 times the
    heat input in which Im omega moves by the grid's tolerance: a grid sign is uncertain that
    close to onset. ``evals[idx]`` counts the evaluations.
    Returns (Q [W], omega [rad/s], converged mask, launches)."""
    m = idx.size
    Q, w0 = br.interpolate()
    w = w0.real.copy()
    slope = (br.w_hi.imag - br.w_lo.imag) / (br.q_hi - br.q_lo)
    margin = 10 * grid_tol * np.abs(br.w_lo) / slope
    J = np.full((m, 2, 2), np.nan)
    R_prev = np.full(m, np.inf)
    last = np.full(m, np.inf)  # relative size of the last step
    Q_out, w_out = np.full(m, np.nan), np.full(m, np.nan)
    done = np.zeros(m, dtype=bool)
    failed = np.zeros(m, dtype=bool)
    launches = 0
    for _ in range(max_steps):
        a = np.flatnonzero(~done & ~failed)
        if not a.size:
            break
        launches += 1
        need = last[a] > CHORD_STEP
        an = a[need]
        dQ = FD_STEP * br.q_hi[an]
        dw = FD_STEP * w[an]
        # heat solves at Q (all) and Q + dQ (new Jacobians); points: R(w, Q), R(w + dw, Q), R(w, Q + dQ)
        cols = np.concatenate([idx[a], idx[an]])
        v = varying[:, cols].copy()
        search.set(v, np.concatenate([Q[a], Q[an] + dQ]))
        col = np.concatenate([np.arange(a.size), np.flatnonzero(need), a.size + np.arange(an.size)])
        pts = np.concatenate([w[a], w[an] + dw, w[an]]).astype(complex)
        out = solver.residuals(v, resonator[cols], w_ref[cols], col, pts)
        evals[idx[a]] += 1 + 2 * need
        R = out[: a.size]
        dR_dw = (out[a.size : a.size + an.size] - R[need]) / dw
        dR_dQ = (out[a.size + an.size :] - R[need]) / dQ
        J[an] = np.stack([np.stack([dR_dw.real, dR_dQ.real], -1), np.stack([dR_dw.imag, dR_dQ.imag], -1)], -2)
        Ja = J[a]
        det = Ja[:, 0, 0] * Ja[:, 1, 1] - Ja[:, 0, 1] * Ja[:, 1, 0]
        sw = -(Ja[:, 1, 1] * R.real - Ja[:, 0, 1] * R.imag) / det
        sq = -(Ja[:, 0, 0] * R.imag - Ja[:, 1, 0] * R.real) / det
        q_new, w_new = Q[a] + sq, w[a] + sw
        bad = ~(np.abs(R) < R_prev[a]) | ~np.isfinite(sw) | ~np.isfinite(sq)
        bad |= ~((q_new >= br.q_lo[a] - margin[a]) & (q_new <= br.q_hi[a] + margin[a]))
        conv = ~bad & (np.abs(sq) <= rtol * np.abs(q_new)) & (np.abs(sw) <= rtol * np.abs(w_new))
        failed[a[bad]] = True
        done[a[conv]] = True
        Q_out[a[conv]], w_out[a[conv]] = q_new[conv], w_new[conv]
        R_prev[a], Q[a], w[a] = np.abs(R), q_new, w_new
        last[a] = np.maximum(np.abs(sq) / np.abs(q_new), np.abs(sw) / np.abs(w_new))
    return Q_out, w_out + 0j, done, launches


def _illinois(at, idx: np.ndarray, br: _Bracket, rtol: float, max_steps: int):
    """Onset of sets ``idx`` by the Illinois secant on Q in their brackets: each step a Muller
    search to 1e-13 at the secant's Q (``at(idx, Q, guess, tol)``), started from the omega
    interpolated alongside. Returns (Q [W], omega [rad/s], still active mask, steps)."""
    q_lo, q_hi, w_lo, w_hi = br.q_lo, br.q_hi, br.w_lo, br.w_hi
    g_lo, g_hi = w_lo.imag.copy(), w_hi.imag.copy()
    Q_on = np.full(idx.size, np.nan)
    w_on = np.full(idx.size, np.nan + 0j)
    side = np.zeros(idx.size, dtype=int)  # Illinois: which end was kept last (-1 lo, +1 hi)
    active = np.ones(idx.size, dtype=bool)
    q_prev = np.full(idx.size, np.inf)
    steps = 0
    while active.any() and steps < max_steps:
        a = np.flatnonzero(active)
        t = g_lo[a] / (g_lo[a] - g_hi[a])
        q_new = q_lo[a] + t * (q_hi[a] - q_lo[a])
        r = at(idx[a], q_new, w_lo[a] + t * (w_hi[a] - w_lo[a]), 1e-13)
        steps += 1
        gn = r.omega.imag
        Q_on[a] = q_new
        w_on[a] = r.omega
        lo = gn < 0
        al, ah = a[lo], a[~lo]  # the new point replaces the bracket end of its sign
        q_lo[al], g_lo[al], w_lo[al] = q_new[lo], gn[lo], r.omega[lo]
        q_hi[ah], g_hi[ah], w_hi[ah] = q_new[~lo], gn[~lo], r.omega[~lo]
        # Illinois: the end kept twice in a row has its value halved
        g_hi[al[side[al] == -1]] *= 0.5
        g_lo[ah[side[ah] == 1]] *= 0.5
        side[al], side[ah] = -1, 1
        # converged: the bracket, or the secant's own step, below rtol Q
        active[a] = ~((q_hi[a] - q_lo[a] <= rtol * q_new) | (np.abs(q_new - q_prev[a]) <= rtol * q_new) | (gn == 0))
        q_prev[a] = q_new
    return Q_on, w_on, active, steps
