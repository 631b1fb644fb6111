"""Batched Levenberg-Marquardt estimation on the device (paper Sect. 4).

>>> from tawarp import load_core
>>> from tawarp.fit.estimate import fit
>>> core = load_core("mesh")
>>> res = fit(core, freqs, Y, ["stack.porosity", "stack.pore_radius", "stack.tortuosity"],
...           start={"stack.porosity": 0.7, "stack.pore_radius": 5e-5, "stack.tortuosity": 1.1})
>>> res.values, res.std, res.correlation, res.converged

A *batch* is one core structure (same segments), one frequency grid ``freqs`` (m,) and
N independent problems. Each problem has its own measured dimensionless coefficients
``Y`` (N, m, 4) complex (``Tpp, Tpu/Zc, Tup*Zc, Tuu``, :func:`tawarp.model.coefficients.normalize`
with :func:`tawarp.model.coefficients.duct_impedance` of the core), weights, heat input, fixed
parameter values (``fixed={"hot_hx.length": (N,)}``) and start values for the p free
parameters ``names`` (``SEGMENT.FIELD``).

Method
------
*Cost.* ``F = sum over frequencies, coefficients, re/im of (w (Y_model - Y_meas))^2`` with
``w`` = 1 / sigma of the dimensionless value (or 1).

*Scaled variables* (the one scheme of the package, :class:`tawarp.model.effects.Param`
likewise). LM works on z: ``v = s exp(z)`` for positive parameters (radii, lengths,
conductivities, heat-exchange coefficients, T_cold, p_mean: the ``log`` column of
:mod:`tawarp.model.fields`) with s the start value, ``v = v0 + scale z`` for porosity,
tortuosity and the other linear fields, v0 the start value and ``scale`` the field's (0.05
for porosity, 0.1 for tortuosity). After each step z is projected onto each field's
``fit_range`` (porosity in [0.01, 1], tortuosity in [1, 10], h in [1e-4, 1e5], pore radius
in [1e-7, 0.1] m, ...: they keep runs from a poor start from drifting to 0 or infinity;
``bounds=`` for others). Both choices make a unit step mean "a relative change of order
one" or "one typical step of the field", so the damped update ``(H + mu I) dz = -g``
treats r ~ 1e-4 m and h ~ 1e2 W/(m^2 K) alike.

*Q = 0 batches* (every heat input 0, no h free or fixed) evaluate the core with its
thermal segments at uniform temperature in closed form (:func:`cold_batch`): the same
model to rounding, without the Magnus cascade.

*One iteration = one forward launch* per active problem. The default where the problems
cascade, ``jacobian="broyden"``, evaluates the trial point alone (one cascade) and moves
the problem's Jacobian by Broyden's rank-one update along the step (a secant method:
Broyden 1965; Madsen, Nielsen & Tingleff 2004, Sect. 3.4); the T-matrices and Jacobian of
every problem stay on the device between iterations (:class:`tawarp.kernels.lm.Secant`).
Forward differences (p cascades beside the point's, step 1e-6 in z, towards the interior at
a bound; ~1e-6) make the Jacobian at the start (once for problems that start from the same
set: a batch with one start shares the evaluation), after a rejected secant step, and at
every solution: the covariance is computed from a fresh forward-difference Jacobian, never
a secant one, and a solution found on secant steps stands only where the Gauss-Newton step
from that fresh Jacobian is below xtol and under 0.1 standard deviations long
(:data:`tawarp.fit.lm.SECANT_CONFIRM`), else the problem iterates on from it. A start
shared by many problems also gets its second derivatives (forward second differences,
step :data:`SECOND_STEP`, p + p (p + 1) / 2 cascades once), which give each problem's
first step a geodesic acceleration (Transtrum & Sethna 2012) and its Jacobian at the
first trial a Taylor update. The heat workload of ``bench/fit.py`` takes 6.2 cascades per
fit this way (64 problems; 6.0 for 1e5) and 3 iterations, instead of 20 and 4.
``jacobian="difference"`` (the default at Q = 0 on a GPU, where the closed form makes an
evaluation cheap and the secant's extra iterations cost more) evaluates each trial with
its forward-difference Jacobian, ``1 + p`` cascades per problem; with
``jacobian="tangent"`` (the default at Q = 0 on the CPU) the Jacobian is carried through
the cascade with the value (:meth:`tawarp.model.forward.Engine.evaluate_tangents`): each
problem's point and its 2p neighbours z +- 1e-5 e_a (1e-4 when the heat solve iterates)
get their heat solve and Gauss-point coefficients, whose central differences seed the
tangents of one cascade per frequency (the pore functions are shared; exact to ~1e-10
against a converged central difference of the whole model). Measured: bench/README.md,
section "tawarp/fit/estimate.py". With both, an accepted trial's Jacobian is already
there; a rejected trial wastes its Jacobian but no launch. :mod:`tawarp.kernels.lm` builds
the sets from z on the device and reduces the T-matrices to ``F``, ``g = J^T r`` and
``H = J^T J`` per problem, which stay there: the damped solves (Cholesky), acceptance,
damping updates and stopping tests run on the device too (:mod:`tawarp.kernels.lm_step`),
and the trial points are not read back: an iteration's one host round trip reads the
problems' done flags (beside the cascade's own read of its largest point count).

*Damping.* ``damping="nielsen"`` (default): mu *= max(1/3, 1 - (2 rho - 1)^3) on success,
mu *= nu, nu *= 2 on failure (Nielsen 1999; Madsen, Nielsen & Tingleff 2004).
``damping="paper"``: mu halved on success, doubled on failure (the paper's rule). Both
start at ``mu = 1e-3 max diag H``.

*Stopping* (per problem, paper's rule first): an accepted step changes every parameter
by less than ``xtol`` = 0.1 % (relative, natural units) -> ``"xtol"``; the gradient test
``max_a |g_a| / sqrt(H_aa F) <= gtol`` (cosine between the residual and each Jacobian
column, MINPACK's test) -> ``"gtol"``; all components at a bound pushing outward ->
``"bound"``; ``max_iter`` iterations -> ``"max_iterations"`` (not converged); the damping
grows past 1e16 without a decrease -> ``"stalled"`` (converged only if the gradient
cosine is below 1e-4). Converged problems leave the active set: later launches contain
only the problems still iterating.

*Uncertainty.* The covariance of every fit of the package
(:class:`tawarp.fit.problem_model.ProblemModel`, here without priors): ``cov_z = s^2 H^-1``
at the solution with ``s^2 = F / (8 m - p)`` (the reduced chi^2: the weights are taken as
relative; ``absolute_sigma=True`` takes s^2 = 1, for weights that are true 1/sigma),
transformed to natural units by the delta method, ``cov_v = D cov_z D`` with
``D = diag(dv/dz)`` (= v for log parameters, the field's scale for linear ones). ``std`` is its diagonal's
root, ``correlation`` the normalised matrix, ``condition`` the 2-norm condition number of H
in the scaled variables. A warning names the parameter pairs with |correlation| above
``corr_limit`` (0.95) and the dominant parameters of the least determined direction when
the condition number exceeds ``cond_limit`` (1e8).

*Restarts* (``restarts=k``): k extra problems per problem start from the solution with
every parameter moved by ±``restart_spread`` (20 %) and run as one more batch; with no
start (``start=None``) a spread of ``n_starts`` Sobol points inside each field's ``prior`` range (:mod:`tawarp.model.fields`)
is run first. The lowest-cost solution is reported; ``distinct_minima`` flags problems
where a converged restart (±20 %) ended more than ``max(1 std, 10 xtol |v|)`` away from it,
or a converged run from the spread did so at a cost the data cannot tell apart from the
best (``(cost - best) / s^2 < 25``); spread runs stuck in clearly worse local minima are
only counted (``local_minima``).
"""

from __future__ import annotations

import dataclasses
import time
import warnings as _warnings

import numpy as np
import warp as wp

from ..model.coefficients import duct_impedance
from ..model.core import GLOBAL_FIELDS, Core
from ..model.fields import field as field_spec
from ..model.forward import ForwardSettings, parameter_row
from ..kernels import covariance as kcov
from ..kernels import eigen as keigen
from ..kernels import lm as klm
from ..measure.kind import get_engine, smooth_settings  # noqa: F401 (smooth_settings: public API)
from ..rng import checked_seed, generator
from .lm import levenberg_marquardt, measured, normal_equations, scaling, slots
from .problem_model import ProblemModel, noise_variance
from .result import FitResult, ProblemWarnings

#: Forward-difference step in the scaled variable z (``jacobian="difference"``).
FD_STEP = 1e-6
#: Step in z of the second differences at a start shared by many problems
#: (``jacobian="broyden"``): truncation ~1e-4 relative, rounding ~1e-16 / 1e-8.
SECOND_STEP = 1e-4
#: Margin on the heat model's decay rate k of the fixed cells :func:`fit` sizes at the
#: starts (:func:`smooth_settings`): 1.25 leaves room for h to grow 1.56x; the counts are
#: checked at the solutions, and problems re-run from them where the solutions need more
#: (:func:`_cells_at_solutions`). Measured: bench/README.md, section "tawarp/fit/estimate.py".
FIT_K_FACTOR = 1.25
REASONS = ("xtol", "gtol", "bound", "stalled", "max_iterations", "invalid")


class FitWarning(UserWarning):
    """A fit is ill-conditioned, has inseparable parameters, did not converge, or its
    restarts found different minima."""


def field_of(name: str) -> str:
    return name.partition(".")[2]


def is_log(name: str) -> bool:
    """True if ``name`` is fitted in log scale (:mod:`tawarp.model.fields`)."""
    return field_spec(name).log


def cold_batch(heat_input, names) -> bool:
    """True when every problem is unheated and no h is involved: the temperature is then
    T_cold everywhere and the thermal segments can use the closed form."""
    return bool(np.all(np.asarray(heat_input) == 0)) and not any(field_of(k) == "h" for k in names)


def _cold_core(core: Core) -> Core:
    """The same core with no thermal segment: at Q = 0 the temperature is uniform, so
    every segment's matrix is the exact exp(A L) instead of a Magnus cascade (identical to
    rounding; the parameter table keeps its layout)."""
    return Core(
        tuple(dataclasses.replace(s, thermal=False, heater=False) for s in core.segments),
        core.gas,
        core.radius,
        core.source,
    )


class Problems:
    """Everything that fixes a batch of least-squares problems, on the device.

    ``core``, ``freqs`` (m,), ``Y`` (N, m, 4) complex, ``names`` (p free parameters),
    ``heat_input`` (N,), ``fixed`` {name: (N,)}, ``weights`` None, (N, m, 4) or
    (N, m, 4, 2) (re, im), ``ties`` {free name: [other names set to the same value]},
    ``bounds`` {name: (lo, hi)} natural units, ``scale`` (N, p) reference (start) values of z
    (:meth:`set_scale`).
    """

    def __init__(
        self,
        core: Core,
        freqs,
        Y,
        names,
        *,
        heat_input=0.0,
        fixed=None,
        weights=None,
        ties=None,
        bounds=None,
        settings: ForwardSettings | None = None,
        device=None,
        scale=None,
        jacobian: str = "auto",
    ):
        self.core = core
        self.freqs = np.atleast_1d(np.asarray(freqs, dtype=float))
        m = self.freqs.size
        Y = np.asarray(Y, dtype=np.complex128)
        if Y.ndim == 2:
            Y = Y[None]
        if Y.ndim != 3 or Y.shape[1:] != (m, 4):
            raise ValueError(f"Y: shape {Y.shape}; expected (N, {m}, 4) dimensionless coefficients")
        self.N = N = Y.shape[0]
        self.Y = Y
        self.names = list(names)
        if not self.names or len(set(self.names)) != len(self.names):
            raise ValueError(f"names: expected distinct parameter names, got {self.names}")
        if len(self.names) > 8:
            raise ValueError(f"at most 8 free parameters per problem, got {len(self.names)}")
        self.p = len(self.names)
        for k in self.names:
            parameter_row(core, k)
        self.ties = {k: list(v) for k, v in (ties or {}).items()}
        for k, others in self.ties.items():
            if k not in self.names:
                raise KeyError(f"ties: {k!r} is not a free parameter ({self.names})")
            for o in others:
                parameter_row(core, o)
                if field_of(o) != field_of(k):
                    raise ValueError(f"ties: {k!r} and {o!r} are different fields")
        tied = [o for v in self.ties.values() for o in v]
        fixed = {k: np.broadcast_to(np.asarray(v, dtype=float), (N,)).copy() for k, v in (fixed or {}).items()}
        clash = (set(fixed) & (set(self.names) | set(tied))) | (set(self.names) & set(tied))
        if clash or len(tied) != len(set(tied)):
            raise ValueError(f"parameters both free/tied/fixed: {sorted(clash) or tied}")
        for k in fixed:
            parameter_row(core, k)
        self.fixed = fixed
        q = np.broadcast_to(np.asarray(heat_input, dtype=float), (N,)).copy()
        if not np.all(np.isfinite(q)) or np.any(q < 0):
            raise ValueError("heat_input [W]: must be finite and >= 0")
        self.heat_input = q
        # Engine rows: free, tied, fixed; the fixed table has heat input first
        engine_names = self.names + tied + list(fixed)
        row_src = [-1] + list(range(self.p)) + [self.names.index(k) for k, v in self.ties.items() for _ in v]
        row_src += [-2 - j for j in range(len(fixed))]
        self.settings = (
            dataclasses.replace(settings or ForwardSettings(), device=device)
            if device is not None
            else (settings or ForwardSettings())
        )
        #: every problem unheated: the closed form instead of the cascade (:func:`cold_batch`)
        self.cold = cold_batch(q, engine_names)
        self.engine = get_engine(_cold_core(core) if self.cold else core, self.freqs, engine_names, self.settings)
        self.device = self.engine.device
        dev = self.device
        fixed_table = np.stack([q] + [fixed[k] for k in fixed])
        # weights -> (N, m, 8), or (1, m, 8) when every problem has the same: a batch of
        # 1e4 problems then uploads one row instead of 64 MB (the kernel reads row 0)
        if weights is None:
            W = np.ones((1, m, 8))
        else:
            w = np.asarray(weights, dtype=float)
            pair = w.ndim >= 3 and w.shape[-2:] == (4, 2)  # else (.., m, 4): the same for re and im
            w = np.broadcast_to(w, (N, m, 4, 2) if pair else (N, m, 4))
            if w.strides[0] == 0:  # a broadcast: one row for all problems
                w = w[:1]
            if not np.all(np.isfinite(w)) or np.any(w < 0):
                raise ValueError("weights: must be finite and >= 0")
            W = np.empty(w.shape[:3] + (2,))
            W[...] = w if pair else w[..., None]
            W = W.reshape(-1, m, 8)
        self.W = W
        # duct impedance per problem (fixed globals change it)
        glob = [k for k in fixed if k in GLOBAL_FIELDS]
        if glob:
            zc = np.array([duct_impedance(core.replace(**{k: fixed[k][i] for k in glob})) for i in range(N)])
        else:
            zc = np.full(N, duct_impedance(core))
        self.zc = zc
        self.kind = np.array([1 if is_log(k) else 0 for k in self.names], dtype=np.int32)
        #: step of a linear parameter per unit z (:mod:`tawarp.model.fields`)
        self.step = np.array([field_spec(k).scale for k in self.names])
        lo, hi = np.full(self.p, -np.inf), np.full(self.p, np.inf)
        bounds = dict(bounds or {})
        for a, k in enumerate(self.names):
            b = bounds.get(k, field_spec(k).fit_range)
            if b is not None:
                lo[a], hi[a] = b
            if is_log(k):
                lo[a] = max(lo[a], 0.0)
        self.lo, self.hi = lo, hi
        self.set_scale(scale if scale is not None else np.broadcast_to([core.get(k) for k in self.names], (N, self.p)))
        self.w_Y = wp.array(np.ascontiguousarray(Y).view(np.float64).reshape(N, m, 8), dtype=wp.float64, device=dev)
        # error-measure denominator per problem, summed on the device (on the host it took
        # longer than the upload); a NaN or infinity makes its problem's sum so
        w_y2 = wp.empty(N, dtype=wp.float64, device=dev)
        wp.launch(klm.squared_norms, dim=N, device=dev, inputs=[self.w_Y, w_y2])
        self.y2 = w_y2.numpy()
        if not np.all(np.isfinite(self.y2)) and not np.all(np.isfinite(Y)):
            raise ValueError("Y: NaN or infinite values")
        self.w_W = wp.array(W, dtype=wp.float64, device=dev)
        self.w_zc = wp.array(zc, dtype=wp.float64, device=dev)
        self.w_fixed = wp.array(np.ascontiguousarray(fixed_table), dtype=wp.float64, device=dev)
        self.w_row_src = wp.array(np.array(row_src, dtype=np.int32), dtype=wp.int32, device=dev)
        self.w_kind = wp.array(self.kind, dtype=wp.int32, device=dev)
        #: how the Jacobians are made: "tangent", "difference" or "broyden" (:meth:`_jacobian_kind`)
        self.jacobian = self._jacobian_kind(jacobian)
        self.tangents = self.jacobian == "tangent"
        #: :func:`levenberg_marquardt` runs the secant iteration (:class:`~tawarp.fit.lm.SecantProblems`)
        self.secant = self.jacobian == "broyden"
        #: degrees of freedom of a problem's residuals (8 m real values, p parameters)
        self.dof = max(8 * m - self.p, 1)
        self.normal = klm.normal_kernel(self.p, self.tangents)
        self.fixed_table = fixed_table
        self._no_tangent = wp.zeros((1, 1, 1, 1), dtype=wp.float64, device=dev)
        self._no_out, self._no_step = (
            wp.zeros((1, 1, 1), dtype=wp.float64, device=dev),
            wp.zeros((1, 1), dtype=wp.float64, device=dev),
        )
        self._rows = _ints(np.zeros(0), dev)
        self.evaluations = 0
        self.launches = 0

    def _jacobian_kind(self, jacobian: str) -> str:
        """How the Jacobians are made: ``jacobian`` "tangent" (the tangent cascade, which
        needs fixed cells), "difference" (forward differences at every trial), "broyden"
        (forward differences at the start, where a secant step fails and at the solution,
        rank-one updates between: one cascade per trial), or "auto": "broyden" where the
        problems cascade (the fewest cascades per fit, on every device); at Q = 0 (the
        closed form, :func:`cold_batch`), where an evaluation costs little and the secant's
        extra iterations would cost more, the tangent cascade on the CPU and forward
        differences on a GPU (measured: bench/README.md, section "tawarp/fit/estimate.py")."""
        if jacobian not in ("auto", "tangent", "difference", "broyden"):
            raise ValueError(f"jacobian: {jacobian!r}; expected 'auto', 'tangent', 'difference' or 'broyden'")
        if jacobian == "tangent" and self.engine.estimating:
            raise ValueError(
                "jacobian='tangent': the cell count adapts per set (pass fixed cells or let fit() pick them)"
            )
        if jacobian != "auto":
            return jacobian
        if not self.cold:
            return "broyden"
        return "tangent" if wp.get_device(self.device).is_cpu and not self.engine.estimating else "difference"

    def set_scale(self, ref):
        """Reference values ``ref`` (N, p) of z = 0 (the starts): log parameters scale by
        them (v = ref exp(z)), linear ones step from them by their field's ``scale``
        (v = ref + scale z)."""
        ref = np.broadcast_to(np.asarray(ref, dtype=float), (self.N, self.p))
        log = self.kind == 1
        if not np.all(np.isfinite(ref) & (~log | (ref > 0))):
            raise ValueError(
                f"start values of {self.names} must be finite, and > 0 for the log-scaled ones "
                f"({[k for k in self.names if is_log(k)]}); they set the scale of each parameter"
            )
        #: the problems' model (:class:`ProblemModel`): scaling and fit range, no priors
        self.model = ProblemModel(self.names, log, ref, self.step, self.lo, self.hi)
        self.scale, self.offset = self.model.scale, self.model.offset
        self.w_scale = wp.array(self.scale, dtype=wp.float64, device=self.engine.device)
        self.w_offset = wp.array(self.offset, dtype=wp.float64, device=self.engine.device)
        self.zlo, self.zhi = self.model.bounds_x()
        self.w_zhi = wp.array(self.zhi, dtype=wp.float64, device=self.engine.device)

    # -- transforms (:class:`ProblemModel`; ``pid`` the problem of each row) --------------
    def to_z(self, v, pid):
        return self.model.x_of(v, pid)

    def to_v(self, z, pid):
        return self.model.values(z, pid)

    def dv_dz(self, z, pid):
        return self.model.dv_dx(z, pid)

    def project(self, z, pid):
        return np.clip(z, self.zlo[pid], self.zhi[pid])

    def change_rule(self):
        """How :func:`levenberg_marquardt` measures a step against ``xtol``: the relative
        change in natural units, ``|expm1(dz)|`` for log parameters, ``scale |dz| / |v|``
        for linear ones (:mod:`tawarp.kernels.lm_step`)."""
        return self.kind, self.scale, self.offset

    # -- launches ------------------------------------------------------------------------
    def _cascade(self, part: klm.Slots, first: int, sets: int, layout: int = 0):
        """The T-matrices (k sets, m, 8) of ``sets`` sets per slot of ``part`` (``first`` and
        the set layout: :func:`tawarp.kernels.lm.build_sets`) by plain cascades; counts the
        launch and its sets."""
        k = part.ids.shape[0]
        varying = wp.empty((self.w_row_src.shape[0], k * sets), dtype=wp.float64, device=self.device)
        wp.launch(
            klm.build_sets,
            dim=k * sets,
            device=self.device,
            inputs=[part, self._scaling(), self.w_fixed, self.w_row_src, layout, first, varying],
        )
        self.launches += 1
        self.evaluations += k * sets
        return self.engine.evaluate(varying)[0]

    def _arange(self, n: int) -> wp.array:
        """0, 1, ..., n - 1 on the device (kept: no upload per iteration)."""
        if self._rows.shape[0] < n:
            self._rows = _ints(np.arange(n), self.device)
        return self._rows[:n]

    def _scaling(self) -> klm.Scaling:
        return scaling(self.w_kind, self.w_scale, self.w_offset, self.device)

    def _data(self) -> klm.Measured:
        return measured(self.w_Y, self.w_W, self.w_zc, self.device)

    def _sums(self, kernel, inputs: list, dest: wp.array, sums: klm.NormalEquations):
        """Launch the row kernel ``kernel`` (:func:`tawarp.kernels.lm.normal_kernel`, the
        secant ``sums``) on ``inputs`` for the n = ``dest.shape[0]`` slots of a launch and
        add its row blocks' partial sums into the rows ``dest`` of ``sums``."""
        n, p, dev = dest.shape[0], self.p, self.device
        if not n:
            return
        blocks = klm.row_blocks(self.freqs.size)
        partial = wp.empty((2 + p + p * p, blocks, n), dtype=wp.float64, device=dev)
        wp.launch(kernel, dim=(blocks, n), device=dev, inputs=inputs + [partial])
        wp.launch(klm.normal_sums(p)[2], dim=n, device=dev, inputs=[partial, dest, sums])

    def _difference_steps(self, ids: wp.array, z: wp.array) -> wp.array:
        """The forward-difference steps (n, p) at ``z`` (n, p) of problems ``ids``, on the
        device: FD_STEP towards the interior at an upper bound."""
        step = wp.empty(z.shape, dtype=wp.float64, device=self.device)
        if z.shape[0]:
            wp.launch(
                klm.difference_steps,
                dim=z.shape,
                device=self.device,
                inputs=[slots(ids, z, step, self.device), self.w_zhi, FD_STEP, step],
            )
        return step

    def evaluate(self, pid: np.ndarray, z, max_sets: int = 1 << 20):
        """cost, raw, g, H of problems ``pid`` (data index per slot) at scaled ``z`` (NumPy, or
        a Warp array on the device: the LM's trial points stay there), as Warp arrays on the
        device: :func:`levenberg_marquardt` keeps them there (a non-finite cost, g or H counts
        as an invalid evaluation there). The Jacobian comes from the tangent cascade (each
        problem's point and its 2p neighbours z +- Engine.tangent_step give the point
        coefficients' derivatives, one cascade carries the T-matrix's) or from forward
        differences (1 + p cascades, step FD_STEP towards the interior at a bound)."""
        p, dev = self.p, self.device
        n = len(pid)
        ids = wp.array(np.asarray(pid, dtype=np.int32), dtype=wp.int32, device=dev)
        z = (
            z
            if isinstance(z, wp.array)
            else wp.array(np.ascontiguousarray(z, dtype=np.float64), dtype=wp.float64, device=dev)
        )
        if self.tangents:
            sets, step = 1 + 2 * p, wp.full(z.shape, self.engine.tangent_step, dtype=wp.float64, device=dev)
        else:
            sets, step = 1 + p, self._difference_steps(ids, z)
        w_cost, w_raw = wp.empty(n, dtype=wp.float64, device=dev), wp.empty(n, dtype=wp.float64, device=dev)
        w_g, w_H = wp.empty((n, p), dtype=wp.float64, device=dev), wp.empty((n, p, p), dtype=wp.float64, device=dev)
        per = max(1, max_sets // sets)
        rows = self.w_row_src.shape[0]
        data = self._data()
        for lo in range(0, n, per):
            hi = min(n, lo + per)
            k = hi - lo
            part = slots(ids[lo:hi], z[lo:hi], step[lo:hi], dev)
            if self.tangents:
                varying = wp.empty((rows, k * sets), dtype=wp.float64, device=dev)
                wp.launch(
                    klm.build_sets,
                    dim=k * sets,
                    device=dev,
                    inputs=[part, self._scaling(), self.w_fixed, self.w_row_src, 1, 0, varying],
                )
                out, tangent = self.engine.evaluate_tangents(varying, part.step, p)
                self.launches += 1
                self.evaluations += k * sets
            else:
                out, tangent = self._cascade(part, 0, sets), self._no_tangent
            sums = normal_equations((w_cost[lo:hi], w_raw[lo:hi], w_g[lo:hi], w_H[lo:hi]), dev)
            self._sums(self.normal, [part, data, out, tangent], self._arange(k), sums)
        return w_cost, w_raw, w_g, w_H

    # -- the secant iteration (:class:`tawarp.fit.lm.SecantProblems`) ---------------------
    def secant_store(self, Q: int) -> klm.Secant:
        """The device store of Q slots' T-matrices and Jacobians (:class:`tawarp.kernels.lm.Secant`)."""
        rows, dev = 8 * self.freqs.size, self.device
        rec = klm.Secant()
        rec.T = wp.empty((rows, Q), dtype=wp.float64, device=dev)
        rec.dT = wp.empty((rows * self.p, Q), dtype=wp.float64, device=dev)
        rec.fresh = wp.zeros(Q, dtype=wp.int32, device=dev)
        rec.trial = wp.empty((rows, Q), dtype=wp.float64, device=dev)
        rec.second = wp.full(Q, -1, dtype=wp.int32, device=dev)
        rec.d2T = wp.zeros((1, 1), dtype=wp.float64, device=dev)
        return rec

    def evaluate_start(self, pid: np.ndarray, z: np.ndarray, store: klm.Secant, max_sets: int = 1 << 20):
        """cost, raw, g, H (Warp arrays) of the Q slots (problems ``pid``) at their starts ``z``
        (Q, p), whose T-matrices and forward-difference Jacobians fill ``store``. Slots whose
        sets are the same (the same start, heat input and fixed values: a batch fitted from
        one start) share one evaluation: the model does not depend on the data."""
        p, dev = self.p, self.device
        Q = len(pid)
        step = np.where(z + FD_STEP > self.zhi[pid], -FD_STEP, FD_STEP)
        key = np.concatenate([self.to_v(z, pid), self.fixed_table[:, pid].T, step], axis=1)
        if Q and np.all(key == key[:1]):  # one start for the batch: no sort
            first, group = np.zeros(1, dtype=np.int64), np.zeros(Q, dtype=np.int64)
        else:
            _, first, group = np.unique(key, axis=0, return_index=True, return_inverse=True)
            group = group.reshape(-1)
        kernels = klm.secant_kernels(p)
        blocks = klm.row_blocks(self.freqs.size)
        sets = 1 + p
        per = max(1, max_sets // sets)
        rep = slots(pid[first], z[first], step[first], dev)
        for lo in range(0, first.size, per):
            hi = min(first.size, lo + per)
            out = self._cascade(slots(rep.ids[lo:hi], rep.z[lo:hi], rep.step[lo:hi], dev), 0, sets)
            mine = np.flatnonzero((group >= lo) & (group < hi)).astype(np.int32)
            wp.launch(
                kernels.differences,
                dim=(blocks, mine.size),
                device=dev,
                inputs=[
                    _ints(mine, dev),
                    _ints((group[mine] - lo) * sets, dev),
                    wp.array(step[mine], dtype=wp.float64, device=dev),
                    1,
                    out,
                    store,
                ],
            )
        self._second_derivatives(pid, z, first, group, store, max_sets)
        cost, raw = wp.empty(Q, dtype=wp.float64, device=dev), wp.empty(Q, dtype=wp.float64, device=dev)
        g, H = wp.empty((Q, p), dtype=wp.float64, device=dev), wp.empty((Q, p, p), dtype=wp.float64, device=dev)
        every = _ints(np.arange(Q), dev)
        self._sums(
            kernels.sums,
            [every, _ints(pid, dev), self._data(), store, self._no_out, self._no_step, every],
            every,
            normal_equations((cost, raw, g, H), dev),
        )
        return cost, raw, g, H

    def _second_derivatives(self, pid, z, first, group, store: klm.Secant, max_sets: int):
        """The second derivatives of the T-matrices at the starts shared by at least
        ``2 (p + p (p + 1) / 2)`` slots (``first`` the representative slot of each group of
        slots with the same sets, ``group`` each slot's), into ``store`` (``d2T``, ``second``):
        their p + p (p + 1) / 2 extra cascades at step :data:`SECOND_STEP` cost less than
        the trial that the first step's geodesic acceleration and the Jacobian's Taylor
        update at the first trial point save each slot (:func:`tawarp.fit.lm.levenberg_marquardt`)."""
        p, dev = self.p, self.device
        sets = p + p * (p + 1) // 2
        size = np.bincount(group, minlength=first.size)
        shared = np.flatnonzero(size >= 2 * sets)
        if not shared.size:
            return
        reps = first[shared]
        store.d2T = wp.empty((8 * self.freqs.size * (sets - p), shared.size), dtype=wp.float64, device=dev)
        column = np.full(first.size, -1, dtype=np.int32)
        column[shared] = np.arange(shared.size)
        store.second = _ints(column[group], dev)
        second_differences = klm.secant_kernels(p).second_differences
        step = np.full((reps.size, p), SECOND_STEP)
        rep = slots(pid[reps], z[reps], step, dev)
        per = max(1, max_sets // sets)
        for lo in range(0, reps.size, per):
            hi = min(reps.size, lo + per)
            out = self._cascade(slots(rep.ids[lo:hi], rep.z[lo:hi], rep.step[lo:hi], dev), 1, sets, layout=2)
            wp.launch(
                second_differences,
                dim=(klm.row_blocks(self.freqs.size), hi - lo),
                device=dev,
                inputs=[_ints(reps[lo:hi], dev), lo, SECOND_STEP, out, store],
            )

    def curvature(self, ids: wp.array, trial, store: klm.Secant) -> wp.array:
        """J^T r_vv (n, p) of the trials' slots along their steps v (``trial.dz``), from the
        second derivatives at their starts (0 for slots without): the geodesic acceleration's
        right-hand side (:func:`tawarp.kernels.lm.secant_kernels`)."""
        n, p, dev = ids.shape[0], self.p, self.device
        blocks = klm.row_blocks(self.freqs.size)
        partial = wp.empty((p, blocks, n), dtype=wp.float64, device=dev)
        wp.launch(
            klm.secant_kernels(p).curvature,
            dim=(blocks, n),
            device=dev,
            inputs=[trial.act, ids, self._data(), store, trial.dz, partial],
        )
        jv = wp.empty((n, p), dtype=wp.float64, device=dev)
        wp.launch(klm.reduce_rows, dim=(n, p), device=dev, inputs=[partial, jv])
        return jv

    def evaluate_trial(self, ids: wp.array, trial, store: klm.Secant, max_sets: int = 1 << 20):
        """The trials' normal equations into ``trial.at_zt`` (:class:`tawarp.kernels.lm_step.Trial`
        of problems ``ids``): one cascade per trial point, the Jacobian the slot's updated by
        the step (Broyden's rank-one update); the values kept in ``store.trial``."""
        n, dev = ids.shape[0], self.device
        trial_sums = klm.secant_kernels(self.p).trial_sums
        rows = self._arange(n)
        for lo in range(0, n, max(1, max_sets)):
            hi = min(n, lo + max(1, max_sets))
            # the point alone: build_sets reads no step (the trial's dz stands in)
            out = self._cascade(slots(ids[lo:hi], trial.zt[lo:hi], trial.dz[lo:hi], dev), 0, 1)
            self._sums(
                trial_sums,
                [trial.act[lo:hi], ids[lo:hi], self._data(), store, out, trial.dz[lo:hi], rows[lo:hi]],
                rows[lo:hi],
                trial.at_zt,
            )

    def refresh(self, slots_q: np.ndarray, pid: np.ndarray, state, store: klm.Secant, max_sets: int = 1 << 20):
        """Forward-difference Jacobians (p cascades each: the point's T-matrices are in
        ``store``) of the LM slots ``slots_q`` (problems ``pid[slots_q]``) at their z of
        ``state`` (:class:`tawarp.kernels.lm_step.Iterate`), into ``store`` and the
        state's normal equations."""
        p, dev = self.p, self.device
        n = slots_q.size
        act = _ints(slots_q, dev)
        ids = _ints(pid[slots_q], dev)
        z = wp.empty((n, p), dtype=wp.float64, device=dev)
        wp.launch(klm.gather_rows, dim=(n, p), device=dev, inputs=[state.z, act, z])
        step = self._difference_steps(ids, z)
        kernels = klm.secant_kernels(p)
        blocks = klm.row_blocks(self.freqs.size)
        per = max(1, max_sets // p)
        for lo in range(0, n, per):
            hi = min(n, lo + per)
            out = self._cascade(slots(ids[lo:hi], z[lo:hi], step[lo:hi], dev), 1, p)
            group = _ints(np.arange(hi - lo) * p, dev)
            wp.launch(
                kernels.differences,
                dim=(blocks, hi - lo),
                device=dev,
                inputs=[act[lo:hi], group, step[lo:hi], 0, out, store],
            )
        self._sums(kernels.sums, [act, ids, self._data(), store, self._no_out, self._no_step, act], act, state.at_z)


def _ints(a, device) -> wp.array:
    return wp.array(np.ascontiguousarray(a, dtype=np.int32), dtype=wp.int32, device=device)


# ----------------------------------------------------------------------------------------
def covariance(prob: Problems, pid, z, H, cost, absolute_sigma=False):
    """(cov_v, std, corr, cond, s2, V) at the solution, natural units: the covariance of
    :class:`tawarp.fit.problem_model.ProblemModel` (no priors: ``s^2 H^-1`` by the delta
    method, s^2 = 1 with ``absolute_sigma``, else the reduced chi^2) for many problems; V
    (n, p, p) the eigenvectors of J^T J in scaled variables, weakest first. The
    eigendecomposition (Jacobi, :mod:`tawarp.kernels.eigen`) and the rest
    (:mod:`tawarp.kernels.covariance`) run on ``prob.device``, one thread per problem."""
    n, p = z.shape
    dev = prob.device
    dof = max(8 * prob.freqs.size - p, 1)
    s2 = noise_variance(cost, dof, not absolute_sigma)
    D = prob.dv_dz(z, pid) if n else np.zeros((0, p))

    def put(a):
        return wp.array(np.ascontiguousarray(a, dtype=np.float64), dtype=wp.float64, device=dev)

    w, V = wp.empty((n, p), dtype=wp.float64, device=dev), wp.empty((n, p, p), dtype=wp.float64, device=dev)
    wp.launch(keigen.eigh_kernel(p), dim=n, device=dev, inputs=[put(H), w, V])
    cov, corr = wp.empty((n, p, p), dtype=wp.float64, device=dev), wp.empty((n, p, p), dtype=wp.float64, device=dev)
    std, cond = wp.empty((n, p), dtype=wp.float64, device=dev), wp.empty(n, dtype=wp.float64, device=dev)
    wp.launch(kcov.covariance_kernel(p), dim=n, device=dev, inputs=[w, V, put(D), put(s2), cov, std, corr, cond])
    return cov.numpy(), std.numpy(), corr.numpy(), cond.numpy(), s2, V.numpy()


def _problem_warnings(names, corr, cond, V, converged, reason, corr_limit, cond_limit) -> list[tuple]:
    """The groups (key, problem rows, message(i)) of :class:`~tawarp.fit.result.ProblemWarnings`:
    pairs of parameters correlated beyond ``corr_limit``, a condition number beyond
    ``cond_limit`` (naming the directions of the weakest eigenvector ``V[:, :, 0]``), no
    convergence (one group per reason). The tests are vectorised; a message is formatted
    only when read."""
    p = len(names)
    iu = np.triu_indices(p, 1)
    pair = corr[:, iu[0], iu[1]]
    with np.errstate(invalid="ignore"):
        hit = np.isfinite(pair) & (np.abs(pair) > corr_limit)
        ill = ~np.isfinite(cond) | (cond > cond_limit)
    groups = []
    for k, (a, b) in enumerate(zip(*iu)):

        def correlated(i, k=k, a=a, b=b):
            return (
                f"{names[a]} and {names[b]} are too correlated to separate "
                f"(correlation {pair[i, k]:+.4f}); fix one of them"
            )

        groups.append((("corr", int(a), int(b)), np.flatnonzero(hit[:, k]), correlated))

    def conditioned(i):
        v = np.abs(V[i, :, 0])
        dom = ", ".join(names[k] for k in np.argsort(-v) if v[k] > 0.3 * v.max())
        return (
            f"ill-conditioned (condition number {cond[i]:.3g} of J^T J in scaled variables > "
            f"{cond_limit:g}): the direction mostly along {dom} is not determined"
        )

    groups.append((("cond",), np.flatnonzero(ill), conditioned))
    bad = ~np.asarray(converged, dtype=bool)
    reason = np.asarray(reason, dtype=str)
    for why in dict.fromkeys(reason[bad].tolist()):
        groups.append(
            (("conv", why), np.flatnonzero(bad & (reason == why)), lambda i: f"did not converge ({reason[i]})")
        )
    return groups


def _sign_patterns(k: int, p: int, seed: int) -> np.ndarray:
    rng = generator(seed, "fit")
    pats = [np.ones(p), -np.ones(p)] + [rng.choice([-1.0, 1.0], size=p) for _ in range(max(0, k - 2))]
    return np.array(pats[:k])


def spread_starts(core: Core, names, n: int, seed: int = 0, ranges: dict | None = None) -> np.ndarray:
    """``n`` Sobol starts (n, p) inside each field's ``prior`` range (:mod:`tawarp.model.fields`) (log-uniform for log parameters)."""
    from scipy.stats import qmc

    ranges = dict(ranges or {})
    p = len(names)
    seed = checked_seed(seed, "spread_starts")
    u = qmc.Sobol(d=p, scramble=True, seed=seed).random(n) if n > 1 else np.full((1, p), 0.5)
    out = np.empty((n, p))
    for a, k in enumerate(names):
        rng = ranges.get(k, ranges.get(field_of(k), field_spec(k).prior))
        if rng is None:
            v = core.get(k)
            rng = (0.8 * v, 1.2 * v)
        lo, hi = rng
        out[:, a] = np.exp(np.log(lo) + u[:, a] * np.log(hi / lo)) if is_log(k) else lo + u[:, a] * (hi - lo)
    return out


def with_ties(values: dict, ties: dict | None) -> dict:
    """``values`` {name: value} with every tied name given its free parameter's value
    (``ties`` {free name: [tied names]})."""
    out = dict(values)
    for k, others in (ties or {}).items():
        for o in others:
            out[o] = out[k]
    return out


def _as_start(start, names, N) -> np.ndarray:
    if isinstance(start, dict):
        missing = set(names) - set(start)
        if missing:
            raise KeyError(f"start: no value for {sorted(missing)}")
        return np.stack([np.broadcast_to(np.asarray(start[k], dtype=float), (N,)) for k in names], axis=1)
    s = np.asarray(start, dtype=float)
    return np.broadcast_to(s, (N, len(names))).copy()


def fit(
    core: Core,
    freqs,
    Y,
    names,
    start=None,
    *,
    heat_input=0.0,
    fixed=None,
    weights=None,
    ties=None,
    bounds=None,
    settings: ForwardSettings | None = None,
    device: str | None = None,
    damping: str = "nielsen",
    xtol: float = 1e-3,
    gtol: float = 1e-8,
    max_iter: int = 100,
    restarts: int = 0,
    restart_spread: float = 0.2,
    n_starts: int = 8,
    seed: int = 0,
    absolute_sigma: bool = False,
    corr_limit: float = 0.95,
    cond_limit: float = 1e8,
    progress: bool = False,
    warn: bool = True,
    max_sets: int = 1 << 20,
    jacobian: str = "auto",
) -> FitResult:
    """Fit the free parameters ``names`` of N independent problems at once.

    Parameters
    ----------
    core : the core; its values are the defaults of every parameter not free or fixed.
    freqs : (m,) [Hz]; ``Y`` (N, m, 4) or (m, 4) complex measured dimensionless coefficients.
    names : p <= 8 free parameters ``SEGMENT.FIELD``.
    start : (N, p), (p,) or {name: scalar or (N,)} start values (natural units); None runs
        a spread of ``n_starts`` Sobol starts per problem (:func:`spread_starts`).
    heat_input : scalar or (N,) [W]; ``fixed`` {name: scalar or (N,)} per-problem values.
    weights : None, (N, m, 4) or (N, m, 4, 2) (re, im): 1/sigma of the dimensionless values.
    ties : {free name: [names given the same value]} (ceramic: stack and hot exchanger).
    bounds : {name: (lo, hi)} natural units, replacing each field's ``fit_range`` (:mod:`tawarp.model.fields`).
    settings, device : forward settings (cells, ...) and device; adaptive cells are
        replaced by fixed counts (:func:`smooth_settings`), sized at the starts with room
        for h to grow 1.56x (:data:`FIT_K_FACTOR`) and checked at the solutions: where the
        rule asks for more there, every problem runs again from its solution with them.
    damping : "nielsen" (default) or "paper" (halve on success, double on failure).
    xtol, gtol, max_iter : stopping rule (module doc).
    restarts : extra problems per problem from the solution ± ``restart_spread``.
    absolute_sigma : covariance H^-1 instead of s^2 H^-1 (the weights are 1/sigma of the
        noise, not relative ones).
    warn : also issue the batch warnings as :class:`FitWarning`.
    jacobian : "auto" (default: "broyden" where the problems cascade; at Q = 0 "tangent"
        on the CPU unless the cells adapt per set, "difference" on a GPU: measured),
        "broyden" (secant updates between forward differences; the covariance from forward
        differences at the solution), "tangent" (derivatives carried through the cascade,
        ~1e-10 relative) or "difference" (forward differences, step 1e-6 in z, ~1e-6
        relative). Module doc.

    Returns a :class:`FitResult`.
    """
    t0 = time.perf_counter()
    if restarts < 0:
        raise ValueError(f"restarts must be >= 0, got {restarts}")
    seed = checked_seed(seed, "fit")
    names = list(names)
    Yarr = np.asarray(Y)
    N = 1 if Yarr.ndim == 2 else Yarr.shape[0]
    # the starts, and z's scale from them (Problems.set_scale): a spread's geometric mean
    if start is None:
        starts = spread_starts(core, names, n_starts, seed)  # (n_starts, p)
        sized = dict(zip(names, starts.T))
        scale = np.exp(np.mean(np.log(starts), axis=0))[None].repeat(N, 0)
    else:
        start_v = _as_start(start, names, N)
        sized = dict(zip(names, start_v.T))
        scale = start_v
    sized = with_ties(sized, ties)
    chosen = settings
    settings = smooth_settings(core, freqs, settings, {**sized, **(fixed or {})}, heat_input, FIT_K_FACTOR)
    problem_kw = dict(
        heat_input=heat_input, fixed=fixed, weights=weights, ties=ties, bounds=bounds, device=device, jacobian=jacobian
    )
    prob = Problems(core, freqs, Y, names, settings=settings, scale=scale, **problem_kw)
    p = prob.p
    lm_kw = dict(damping=damping, xtol=xtol, gtol=gtol, max_iter=max_iter, progress=progress, max_sets=max_sets)
    data = np.arange(N)
    alt_v, alt_cost, alt_conv, alt_spread = [], [], [], []  # other runs per problem, for distinct minima
    if start is None:
        pid = np.repeat(data, n_starts)
        v0 = np.tile(starts, (N, 1))
        st = levenberg_marquardt(prob, pid, prob.to_z(v0, pid), **lm_kw)
        cost_rank = np.where(st.converged, st.cost, np.inf)
        cost_rank = np.where(np.isfinite(cost_rank), cost_rank, np.where(np.isfinite(st.cost), st.cost * 1e30, np.inf))
        best = np.argmin(cost_rank.reshape(N, n_starts), axis=1) + data * n_starts
        start_v = v0[best]
        spread_v = prob.to_v(st.z, pid).reshape(N, n_starts, p)
        alt_v.append(spread_v)
        alt_cost.append(st.cost.reshape(N, n_starts))
        alt_conv.append(st.converged.reshape(N, n_starts))
        alt_spread.append(np.ones((N, n_starts), dtype=bool))
        sel = best
    else:
        pid = data
        st = levenberg_marquardt(prob, pid, prob.to_z(start_v, pid), **lm_kw)
        sel = data
    z = st.z[sel]
    cost, raw, H = st.cost[sel], st.raw[sel], st.H[sel]
    its, reason, conv = st.iterations[sel], st.reason[sel].astype(str), st.converged[sel]
    restart_values = restart_cost = restart_conv = None
    if restarts > 0:
        v_sol = prob.to_v(z, data)
        pats = _sign_patterns(restarts, p, seed)
        v0 = (v_sol[:, None, :] * (1.0 + restart_spread * pats[None])).reshape(-1, p)
        rpid = np.repeat(data, restarts)
        rz0 = prob.project(prob.to_z(v0, rpid), rpid)
        rs = levenberg_marquardt(prob, rpid, rz0, **lm_kw)
        restart_values = prob.to_v(rs.z, rpid).reshape(N, restarts, p)
        restart_cost = rs.cost.reshape(N, restarts)
        restart_conv = rs.converged.reshape(N, restarts)
        alt_v.append(restart_values)
        alt_cost.append(restart_cost)
        alt_conv.append(restart_conv)
        alt_spread.append(np.zeros((N, restarts), dtype=bool))
        # keep the best converged solution
        rc = np.where(restart_conv, restart_cost, np.inf)
        j = np.argmin(rc, axis=1)
        i = np.flatnonzero(rc[data, j] < cost * (1 - 1e-12))
        q = i * restarts + j[i]
        z[i], cost[i], raw[i], H[i] = rs.z[q], rs.cost[q], rs.raw[q], rs.H[q]
        its[i], reason[i], conv[i] = rs.iterations[q], rs.reason[q], True
    if chosen is None or chosen.cells is None:  # fit() sized the cells: check them where the fits ended
        rerun = _cells_at_solutions(prob, z, data, chosen, lm_kw, problem_kw)
        if rerun is not None:
            prob, st = rerun
            z, cost, raw, H, reason = st.z, st.cost, st.raw, st.H, st.reason.astype(str)
            its, conv = its + st.iterations, st.converged
    cov, std, corr, cond, s2, V = covariance(prob, data, z, H, cost, absolute_sigma)
    values = prob.to_v(z, data)
    distinct = local = None
    per = _problem_warnings(names, corr, cond, V, conv, reason, corr_limit, cond_limit)
    if alt_v:
        av = np.concatenate(alt_v, axis=1)
        ac = np.concatenate(alt_cost, axis=1)
        aok = np.concatenate(alt_conv, axis=1)
        asp = np.concatenate(alt_spread, axis=1)
        tol = np.maximum(np.where(np.isfinite(std), std, 0.0), 10 * xtol * np.abs(values))
        away = aok & np.any(np.abs(av - values[:, None, :]) > tol[:, None, :], axis=2)
        with np.errstate(divide="ignore", invalid="ignore"):
            close_cost = (ac - cost[:, None]) / np.maximum(s2, 1e-300)[:, None] < 25.0
        far_all = away & (~asp | close_cost)
        local = np.sum(away & asp & ~close_cost, axis=1)
        distinct = far_all.any(axis=1)

        def other_minimum(i):
            far = far_all[i]
            j = int(np.flatnonzero(far)[np.argmin(ac[i][far])])
            return (
                f"restarts landed in different minima: best cost {cost[i]:.4g} at {_fmt(names, values[i])}, "
                f"another at cost {ac[i, j]:.4g}, {_fmt(names, av[i, j])}"
            )

        per.append((("minima",), np.flatnonzero(distinct & far_all.any(axis=1)), other_minimum))
    problem_warnings = ProblemWarnings(N, per)
    warn_list = problem_warnings.summary()
    if warn:
        for msg in warn_list:
            _warnings.warn(msg, FitWarning, stacklevel=2)
    rms = np.sqrt(raw / np.maximum(prob.y2, 1e-300))
    return FitResult(
        names=names,
        values=values,
        std=std,
        covariance=cov,
        correlation=corr,
        condition=cond,
        iterations=its,
        converged=conv,
        reason=np.asarray(reason, dtype=str),
        cost=cost,
        rms_error=rms,
        s2=s2,
        dof=max(8 * prob.freqs.size - p, 1),
        start=start_v,
        warnings=warn_list,
        problem_warnings=problem_warnings,
        distinct_minima=distinct,
        restart_values=restart_values,
        restart_cost=restart_cost,
        restart_converged=restart_conv,
        local_minima=local,
        evaluations=prob.evaluations,
        launches=prob.launches,
        seconds=time.perf_counter() - t0,
        weighted=weights is not None,
        lower=prob.lo,
        upper=prob.hi,
    )


def _cells_at_solutions(prob: Problems, z, pid, settings: ForwardSettings | None, lm_kw: dict, problem_kw: dict):
    """The fixed cells sized at the starts (:data:`FIT_K_FACTOR`) against those the
    adaptive rule asks for at the solutions z (their largest values, the tied and fixed
    parameters with them): None where none exceeds its count, else (problems, state) of
    every problem re-run from its solution with the cells sized there (the same scaled
    variables, so the solutions are the new starts; ``problem_kw`` the arguments
    :class:`Problems` had)."""
    v = prob.to_v(z, pid)
    values = {**with_ties({k: v[:, a] for a, k in enumerate(prob.names)}, prob.ties), **prob.fixed}
    core, freqs, q = prob.core, prob.freqs, prob.heat_input
    need = smooth_settings(core, freqs, settings, values, q, 1.0).cells
    if all(need[s] <= prob.settings.cells.get(s, 0) for s in need):
        return None
    resized = smooth_settings(core, freqs, settings, values, q, FIT_K_FACTOR)
    again = Problems(
        core,
        freqs,
        prob.Y,
        prob.names,
        settings=resized,
        scale=np.where(prob.kind == 1, prob.scale, prob.offset),
        **problem_kw,
    )
    again.evaluations, again.launches = prob.evaluations, prob.launches
    return again, levenberg_marquardt(again, pid, z, **lm_kw)


def _fmt(names, v) -> str:
    return ", ".join(f"{k} = {x:.4g}" for k, x in zip(names, v))


def predict(
    core: Core,
    freqs,
    values: dict | None = None,
    heat_input=0.0,
    ties=None,
    settings: ForwardSettings | None = None,
    **kw,
) -> np.ndarray:
    """Dimensionless coefficients (n, m, 4) of ``core`` with ``values`` {name: scalar or (n,)}
    (tied names follow their free parameter), normalised with the core's duct impedance."""
    from ..model.forward import transfer_matrices

    values = with_ties(values or {}, ties)
    res = transfer_matrices(core, freqs, heat_input=heat_input, params=values, settings=settings, **kw)
    return res.dimensionless()
