"""The package's one least-squares engine: batched Levenberg-Marquardt.

:func:`levenberg_marquardt` runs Q independent problems in lockstep on any
:class:`LMProblems` (scaled variables z, bounds, one ``evaluate`` per iteration that
returns the cost, ``g = J^T r`` and ``H = J^T J`` of every active problem). Problems that
converge leave the active set, so later evaluations (forward launches) only contain the
problems still iterating. Damping, stopping rule and reasons: :mod:`tawarp.fit.estimate`'s
module doc. Two implementations of :class:`LMProblems` exist: the T-matrix problems of
:class:`tawarp.fit.estimate.Problems` reduce residuals to (cost, g, H) on the device
(:mod:`tawarp.kernels.lm`); :class:`tawarp.fit.problems.KindProblems` does it on the host
for any measurement kind (:mod:`tawarp.measure`).

The iteration's arithmetic (damped Cholesky step, projection onto the bounds, acceptance,
damping, stopping tests) runs on the problems' device in the kernels of
:mod:`tawarp.kernels.lm_step`, one thread per problem, on the records this module builds
(:func:`normal_equations`, :func:`scaling`, :func:`slots`, :func:`measured` and the LM's
state): with 1e5 problems the NumPy bookkeeping of (n, p, p) arrays cost the host more than
the device's evaluations. The host launches, calls ``evaluate`` and compacts the active set
from the done flags, its one read of an iteration (the trial points stay on the device).

*The secant iteration* (:class:`SecantProblems` with ``secant`` set: the T-matrix problems'
``jacobian="broyden"``): the problems keep each slot's model values and Jacobian on the
device; a trial costs the evaluation of its point alone, and its Jacobian is the slot's
moved by Broyden's rank-one update along the step (the ``update`` kernel's acceptance
then makes it the slot's, :func:`tawarp.kernels.lm_step.secant_accept_kernels`). A rejected
step from a secant Jacobian has the slot's Jacobian refreshed (forward differences) before
the next. A slot whose start's second derivatives the problems made (a start shared by
many) takes a geodesically accelerated first step (the ``accelerate`` kernel on the
problems' ``curvature``) and a Taylor-updated Jacobian at its first trial. When every
slot has stopped, those that stopped on a secant Jacobian get the
fresh one at their solution, whose ``J^T J`` the returned ``H`` is (the covariance's);
those that stopped on ``xtol`` stop only if the step from it is below ``xtol`` and
:data:`SECANT_CONFIRM` standard deviations (the ``confirm`` kernel), else they iterate on.

*Starts that meet* (``starts_of`` and ``merge``): where several slots are starts of one
problem, a start stops once its Gauss-Newton model and that of a lower start predict one
minimum (:func:`stop_tests`, which also gives the Newton decrements from the same Cholesky
factors): a multistart fit pays for each of its minima once, not once a start.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import warp as wp

from ..kernels import lm as klm
from ..kernels import lm_step
from ..progress import progress_bar

#: A secant run's solution stands where the Gauss-Newton step from the fresh Jacobian at
#: it is below xtol and moves the parameters by less than this many standard deviations
#: (its predicted decrease of the cost below SECANT_CONFIRM^2 F / dof, the Mahalanobis
#: length of the step in the covariance s^2 (J^T J)^-1, s^2 = F / dof): the rank-one updates
#: converge superlinearly, not quadratically, and xtol alone left geometry fits 0.4 std
#: from the minimum (bench/README.md, section "tawarp/fit/estimate.py").
SECANT_CONFIRM = 0.1

#: names of the reason codes of :mod:`tawarp.kernels.lm_step` (code 0: still iterating)
REASONS = ("", "xtol", "gtol", "bound", "stalled", "max_iterations", "invalid")
#: reason of a problem that :func:`levenberg_marquardt`'s ``drop`` stopped
DROPPED = "dropped"
#: reason of a problem that :func:`levenberg_marquardt`'s ``decrement`` test stopped
DECREMENT = "decrement"
#: reason of a start that :func:`levenberg_marquardt`'s ``merge`` test stopped: it met a
#: better start of its problem
MERGED = "merged"
#: Two starts meet (:func:`stop_tests`) only where their Gauss-Newton models predict
#: minima whose costs differ by less than this (half a unit of log-likelihood), and the
#: lead's model predicts the other start's cost to this or MEET_QUADRATIC of its quadratic
#: term (the cost is quadratic between them). Far from a minimum two models can agree in
#: place and still lead into two optima: on an outside effect's misfit (chi^2 five times
#: the residuals) two starts whose predicted minima lay within 10 sd ended 1000 apart in
#: chi^2, and the test of place alone lost the model's better ln Z.
MEET_COST = 1.0
MEET_QUADRATIC = 0.1


@dataclass
class LMState:
    """Per problem: final z, cost, raw (unweighted misfit), g, H, iterations, reason, converged."""

    z: np.ndarray
    cost: np.ndarray
    raw: np.ndarray
    g: np.ndarray
    H: np.ndarray
    iterations: np.ndarray
    reason: np.ndarray
    converged: np.ndarray


class LMProblems(Protocol):
    """What :func:`levenberg_marquardt` needs of a batch of least-squares problems in scaled
    variables z (:class:`tawarp.fit.estimate.Problems`, :class:`tawarp.fit.problems.KindProblems`).

    ``zlo``, ``zhi`` (N, p): bounds of z per problem (+-inf for none); every z the LM tries
    is clipped onto them. ``device`` (optional, default the CPU): where the iteration runs.
    ``evaluate(pid, z, max_sets)``: ``(cost, raw, g, H)`` of problems ``pid`` (n,) at z
    (n, p) (NumPy on the CPU; on another device the trial points come as a Warp array
    there), cost (n,) the weighted sum of squared residuals ``r^T r`` (inf where the
    model fails; a non-finite cost, g or H makes it so), raw (n,) its unweighted
    counterpart (passed through), ``g = J^T r`` (n, p), ``H = J^T J`` (n, p, p), J the
    Jacobian in z; NumPy arrays or Warp arrays on ``device``.
    ``jacobian_if_below`` (optional, default False): ``evaluate`` of the trials then takes
    ``below`` (n,), the cost each problem's trial must beat to be accepted, and may leave g
    and H non-finite where it does not beat it (such a trial is rejected whatever its
    Jacobian: its forward differences need not be evaluated).
    ``change_rule()``: ``(kind (p,), scale (N, p), offset (N, p))``, how the size of a step
    dz that ended at z is measured against ``xtol`` (:mod:`tawarp.kernels.lm_step`:
    ``CHANGE_LINEAR`` ``s |dz| / |o + s z|``, ``CHANGE_LOG`` ``|expm1(dz)|``,
    ``CHANGE_ABSOLUTE`` ``|dz|``).
    """

    zlo: np.ndarray
    zhi: np.ndarray

    def evaluate(self, pid: np.ndarray, z: np.ndarray, max_sets: int = ...) -> tuple: ...

    def change_rule(self) -> tuple: ...


class SecantProblems(LMProblems, Protocol):
    """:class:`LMProblems` that run the secant iteration (module doc) where ``secant`` is
    True (:class:`tawarp.fit.estimate.Problems`). ``dof``: the residuals' degrees of
    freedom (s^2 = F / dof). ``secant_store(Q)``: the device store of Q slots' model values
    and Jacobians (:class:`tawarp.kernels.lm.Secant`). ``evaluate_start(pid, z, store,
    max_sets)``: ``(cost, raw, g, H)`` at the starts with forward-difference Jacobians, into
    the store. ``evaluate_trial(ids, trial, store, max_sets)``: the trials'
    (:class:`tawarp.kernels.lm_step.Trial`, ``ids`` their data indices on the device) normal
    equations into ``trial.at_zt``, with the Jacobians updated by the steps.
    ``refresh(slots, pid, state, store, max_sets)``: forward-difference Jacobians of the
    slots at their z of ``state`` (:class:`tawarp.kernels.lm_step.Iterate`), into the store
    and the state's normal equations. ``curvature(ids, trial, store)``: J^T r_vv (n, p) of
    the first trials' steps v (0 where the store has no second derivatives)."""

    secant: bool
    dof: int

    def secant_store(self, Q: int): ...

    def evaluate_start(self, pid: np.ndarray, z: np.ndarray, store, max_sets: int = ...) -> tuple: ...

    def evaluate_trial(self, ids: wp.array, trial: lm_step.Trial, store, max_sets: int = ...) -> None: ...

    def refresh(
        self, slots: np.ndarray, pid: np.ndarray, state: lm_step.Iterate, store, max_sets: int = ...
    ) -> None: ...

    def curvature(self, ids: wp.array, trial: lm_step.Trial, store) -> wp.array: ...


def _device_array(a, device, dtype=wp.float64, own=False) -> wp.array:
    """``a`` as a Warp array of ``dtype`` on ``device``: a NumPy array copied there, a Warp
    one as it is (``own``: cloned, for the state the kernels overwrite)."""
    if isinstance(a, wp.array):
        return wp.clone(a) if own else a
    return wp.array(np.ascontiguousarray(a, dtype=wp.dtype_to_numpy(dtype)), dtype=dtype, device=device)


def normal_equations(sums, device, own=False) -> klm.NormalEquations:
    """The kernels' :class:`tawarp.kernels.lm.NormalEquations` of an evaluation's
    ``(cost, raw, g, H)`` (NumPy or Warp arrays) on ``device``."""
    rec = klm.NormalEquations()
    rec.cost, rec.raw, rec.g, rec.H = (_device_array(a, device, own=own) for a in sums)
    return rec


def scaling(kind, scale, offset, device) -> klm.Scaling:
    """The kernels' :class:`tawarp.kernels.lm.Scaling` of ``kind`` (p,), ``scale`` and
    ``offset`` (N, p) (NumPy or Warp arrays) on ``device``."""
    rec = klm.Scaling()
    rec.kind = _device_array(kind, device, wp.int32)
    rec.scale = _device_array(scale, device)
    rec.offset = _device_array(offset, device)
    return rec


def slots(ids, z, step, device) -> klm.Slots:
    """The kernels' :class:`tawarp.kernels.lm.Slots` of a launch: data index ``ids``, scaled
    variables ``z`` and Jacobian steps ``step`` per slot (NumPy or Warp arrays) on ``device``."""
    rec = klm.Slots()
    rec.ids = _device_array(ids, device, wp.int32)
    rec.z = _device_array(z, device)
    rec.step = _device_array(step, device)
    return rec


def measured(Y, W, zc, device) -> klm.Measured:
    """The kernels' :class:`tawarp.kernels.lm.Measured` data ``Y``, weights ``W`` (N or 1,
    m, 8) and duct impedances ``zc`` (N,) (NumPy or Warp arrays) on ``device``."""
    rec = klm.Measured()
    rec.Y = _device_array(Y, device)
    rec.W = _device_array(W, device)
    rec.zc = _device_array(zc, device)
    return rec


def _setup(prob: LMProblems, pid: np.ndarray, device, damping, tau, xtol, gtol, max_iter) -> lm_step.Setup:
    """The kernels' :class:`tawarp.kernels.lm_step.Setup` of problems ``pid`` of ``prob``."""
    rec = lm_step.Setup()
    rec.pid = _device_array(pid, device, wp.int32)
    rec.zlo = _device_array(prob.zlo, device)
    rec.zhi = _device_array(prob.zhi, device)
    rec.change = scaling(*prob.change_rule(), device)
    rec.damping = lm_step.DAMP_NIELSEN if damping == "nielsen" else lm_step.DAMP_PAPER
    rec.tau, rec.xtol, rec.gtol, rec.max_iter = float(tau), float(xtol), float(gtol), int(max_iter)
    if getattr(prob, "secant", False):
        rec.confirm = SECANT_CONFIRM**2 / prob.dof
    return rec


def _iterate(z: np.ndarray, sums, device) -> lm_step.Iterate:
    """The kernels' :class:`tawarp.kernels.lm_step.Iterate` at the starts ``z`` (Q, p) with
    their evaluation ``sums``; the damping and flags are the ``init`` kernel's to set."""
    Q = z.shape[0]
    rec = lm_step.Iterate()
    rec.z = _device_array(z, device)
    rec.at_z = normal_equations(sums, device, own=True)
    rec.mu, rec.nu = (wp.empty(Q, dtype=wp.float64, device=device) for _ in range(2))
    rec.iterations = wp.zeros(Q, dtype=wp.int32, device=device)
    rec.reason, rec.converged = (wp.empty(Q, dtype=wp.int32, device=device) for _ in range(2))
    return rec


def _trial(active: np.ndarray, p: int, device, sums: bool = False) -> lm_step.Trial:
    """The kernels' :class:`tawarp.kernels.lm_step.Trial` of the slots ``active``, for
    ``propose`` to fill; with ``sums`` its ``at_zt`` too, for a secant evaluation to fill
    (else the evaluation's arrays become it)."""
    n = active.size
    rec = lm_step.Trial()
    rec.act = _device_array(active, device, wp.int32)
    rec.zt, rec.dz = (wp.empty((n, p), dtype=wp.float64, device=device) for _ in range(2))
    rec.pred = wp.empty(n, dtype=wp.float64, device=device)
    rec.chol_ok, rec.accepted = (wp.empty(n, dtype=wp.int32, device=device) for _ in range(2))
    if sums:
        rec.at_zt = normal_equations(
            (
                wp.empty(n, dtype=wp.float64, device=device),
                wp.empty(n, dtype=wp.float64, device=device),
                wp.empty((n, p), dtype=wp.float64, device=device),
                wp.empty((n, p, p), dtype=wp.float64, device=device),
            ),
            device,
        )
    return rec


@dataclass
class NewtonSteps:
    """The Gauss-Newton steps of stacked slots (:func:`newton_steps`): ``ok`` (n,) where H,
    held on the components free of their bounds, is positive definite; of those slots,
    ``step`` (m, p) = ``H^-1 g`` (the iteration goes to ``z - step``), ``y`` (m, p) with
    ``y.y = g^T H^-1 g``, and ``inside`` (m,) where ``z - step`` stays inside the bounds;
    ``H`` (n, p, p) the held normal equations' matrix."""

    ok: np.ndarray
    step: np.ndarray
    y: np.ndarray
    inside: np.ndarray
    H: np.ndarray

    def decrement(self) -> np.ndarray:
        """The Newton decrements ``g^T H^-1 g`` (n,): the decrease of the cost ``F`` that the
        Gauss-Newton step predicts (F(z + d) = F + 2 g.d + d.H.d), on the components free of
        their bounds; inf where that H is not positive definite or the step would reach a
        bound (the iteration would put that component on it, where a caller may treat it
        apart: the loop's evidence integrates it one-sided)."""
        out = np.full(self.ok.size, np.inf)
        out[np.flatnonzero(self.ok)[self.inside]] = np.sum(self.y[self.inside] ** 2, axis=1)
        return out


def newton_steps(z: np.ndarray, g: np.ndarray, H: np.ndarray, zlo: np.ndarray, zhi: np.ndarray) -> NewtonSteps:
    """:class:`NewtonSteps` of slots at ``z`` (n, p) with ``g``, ``H`` and bounds ``zlo``,
    ``zhi`` (n, p) each, on the components free of their bounds (the kernels' ``is_free``: a
    component pinned by ``zlo = zhi``, or on a bound with the gradient pushing out, takes no
    part)."""
    free = (zhi > zlo) & ~((z <= zlo) & (g > 0)) & ~((z >= zhi) & (g < 0))
    Hf, gf = held_fixed(H, g, free)  # every slot at once
    ok = np.ones(len(z), dtype=bool)
    try:
        c = np.linalg.cholesky(Hf)
    except np.linalg.LinAlgError:  # some H not positive definite: no step there
        ok = np.array([_positive_definite(h) for h in Hf], dtype=bool)
        c = np.linalg.cholesky(Hf[ok]) if ok.any() else np.zeros((0,) + Hf.shape[1:])
    y = np.linalg.solve(c, gf[ok][:, :, None])
    step = np.linalg.solve(np.swapaxes(c, 1, 2), y)[:, :, 0]
    to = z[ok] - step
    inside = np.all(~free[ok] | ((to > zlo[ok]) & (to < zhi[ok])), axis=1)
    return NewtonSteps(ok, step, y[:, :, 0], inside, Hf)


def stop_tests(
    z: np.ndarray,
    g: np.ndarray,
    H: np.ndarray,
    zlo: np.ndarray,
    zhi: np.ndarray,
    cost: np.ndarray,
    slots: np.ndarray,
    starts_of: np.ndarray,
    merge: np.ndarray,
    open_: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The iteration's two stop tests of the iterating ``slots`` (n,), from one Cholesky
    factor a slot (:func:`newton_steps`), every slot's arrays (Q, ...) given: ``z``, ``g``,
    ``H``, bounds ``zlo``, ``zhi``, ``cost``, ``starts_of`` (its problem; < 0: none),
    ``merge`` and ``open_``. Returns their Newton decrements (:meth:`NewtonSteps.decrement`) and
    which of them have met a better start of their problem.

    Each problem's lowest-cost start among the ``open_`` slots is its lead. Another start
    meets it where the two Gauss-Newton models, ``F(z + d) = F + 2 g.d + d.H.d``, predict
    one minimum: their minima (each projected onto the bounds) lie within ``merge``
    standard deviations of each other in the lead's posterior (``sqrt(d^T H d)``, H the
    lead's ``J^T J``) at costs within :data:`MEET_COST` of each other, and the lead's
    model predicts the start's own cost to :data:`MEET_COST` or :data:`MEET_QUADRATIC` of
    its quadratic term, whichever is larger (the cost is quadratic between them). Both then
    descend into one minimum, and the lead, already lower, finds it. Where either H is not
    positive definite nothing meets."""
    lead = np.full(slots.size, -1)
    mine = np.flatnonzero(open_ & (starts_of >= 0))
    if mine.size:
        order = mine[np.lexsort((mine, cost[mine], starts_of[mine]))]
        leads = order[np.r_[True, starts_of[order][1:] != starts_of[order][:-1]]]
        lead_of = np.full(int(starts_of.max()) + 1, -1)
        lead_of[starts_of[leads]] = leads
        ask = (starts_of[slots] >= 0) & (merge[slots] > 0)
        lead[ask] = lead_of[starts_of[slots[ask]]]
        lead[(lead == slots) | (cost[slots] < cost[np.maximum(lead, 0)])] = -1
    both, at = np.unique(np.concatenate([slots, lead[lead >= 0]]), return_inverse=True)
    z, g, cost, zlo, zhi = z[both], g[both], cost[both], zlo[both], zhi[both]
    st = newton_steps(z, g, H[both], zlo, zhi)
    met = np.zeros(slots.size, dtype=bool)
    i = np.flatnonzero(lead >= 0)
    if i.size:
        aim = np.full(z.shape, np.nan)  # NaN where H has no Cholesky factor: never meets
        aim[st.ok] = np.clip(z[st.ok] - st.step, zlo[st.ok], zhi[st.ok])
        floor = _quadratic(cost, g, st.H, aim - z)
        s, l = at[i], at[slots.size :]
        d, e = aim[s] - aim[l], z[s] - z[l]
        eHe = np.einsum("ni,nij,nj->n", e, st.H[l], e)
        met[i] = (
            (np.einsum("ni,nij,nj->n", d, st.H[l], d) < merge[slots[i]] ** 2)
            & (np.abs(floor[s] - floor[l]) < MEET_COST)
            & (np.abs(cost[s] - _quadratic(cost[l], g[l], st.H[l], e)) <= np.maximum(MEET_COST, MEET_QUADRATIC * eHe))
        )
    return st.decrement()[at[: slots.size]], met


def _quadratic(cost: np.ndarray, g: np.ndarray, H: np.ndarray, d: np.ndarray) -> np.ndarray:
    """The Gauss-Newton model's cost ``F + 2 g.d + d.H.d`` at steps ``d`` (n, p)."""
    return cost + 2.0 * np.einsum("ni,ni->n", g, d) + np.einsum("ni,nij,nj->n", d, H, d)


def held_fixed(H: np.ndarray, g: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stacked normal equations ``H d = -g`` (H (n, p, p), g (n, p)) with the components
    outside the mask ``free`` (n, p) held: their rows and columns of H the identity's and
    their gradient 0, so each system solves as its free components' own, their step 0 and
    nothing added to ``g^T H^-1 g``."""
    both = free[:, :, None] & free[:, None, :]
    return np.where(both, H, np.eye(H.shape[-1])), np.where(free, g, 0.0)


def _positive_definite(A: np.ndarray) -> bool:
    """Whether the symmetric ``A`` has a Cholesky factor (positive definite, no NaN)."""
    try:
        np.linalg.cholesky(A)
    except np.linalg.LinAlgError:
        return False
    return True


def levenberg_marquardt(
    prob: LMProblems,
    pid: np.ndarray,
    z0: np.ndarray,
    *,
    damping: str = "nielsen",
    xtol: float = 1e-3,
    gtol: float = 1e-8,
    max_iter: int = 100,
    tau: float = 1e-3,
    progress: bool = False,
    max_sets: int = 1 << 20,
    drop=None,
    decrement: float | np.ndarray = 0.0,
    starts_of: np.ndarray | None = None,
    merge: float | np.ndarray = 0.0,
) -> LMState:
    """Run batched LM on problems with data index ``pid`` (Q,) from scaled starts ``z0``
    (Q, p). Converged problems drop out of later launches (active-set compaction).
    ``prob``: any :class:`LMProblems`; a :class:`SecantProblems` with ``secant`` set runs
    the secant iteration (module doc). ``drop``: None, or ``drop(slots, cost) -> bool``
    called after every iteration with the slots still iterating (in increasing order) and
    every slot's cost (Q,) at its current z: the slots it marks stop there (reason ``"dropped"``, not
    converged), a race between starts of one problem (:func:`tawarp.loop.run.fit_models`).
    ``decrement`` > 0 (a scalar, or one per slot (Q,)): a problem also stops, converged (reason ``"decrement"``), where the
    Gauss-Newton step from its z would lower the cost by less than this (the Newton
    decrement ``g^T H^-1 g`` on the components free of their bounds, :meth:`NewtonSteps.decrement`):
    a caller that needs the minimum's cost to that much (the loop's evidence) need not iterate
    on to ``gtol``, whose cosine test can take many more steps each worth far less.
    ``starts_of`` (Q,) and ``merge`` > 0 (a scalar or one per slot): slots of one
    ``starts_of`` label (>= 0) are starts of one problem, and a start stops (reason
    ``"merged"``, not converged) where its Gauss-Newton model and that of a start of its
    problem at a lower cost predict one minimum, within ``merge`` posterior standard
    deviations and in cost (:func:`stop_tests`): starts that meet descend into one
    minimum, which one of them finds."""
    if damping not in ("nielsen", "paper"):
        raise ValueError(f"damping = {damping!r}; expected 'nielsen' or 'paper'")
    Q, p = z0.shape
    if p == 0:
        raise ValueError("levenberg_marquardt: no free parameters")
    decrement = np.broadcast_to(np.asarray(decrement, dtype=float), (Q,))
    merge = np.broadcast_to(np.asarray(merge, dtype=float), (Q,))
    starts_of = np.full(Q, -1) if starts_of is None else np.asarray(starts_of)
    tested = (decrement > 0) | ((starts_of >= 0) & (merge > 0))  # the slots stop_tests asks about
    dev = wp.get_device(getattr(prob, "device", "cpu"))
    init, propose, update, confirm, accelerate = lm_step.step_kernels(p)
    secant = bool(getattr(prob, "secant", False))
    pid = np.asarray(pid)
    setup = _setup(prob, pid, dev, damping, tau, xtol, gtol, max_iter)
    zlo, zhi = prob.zlo[pid], prob.zhi[pid]
    z = np.clip(np.array(z0, dtype=float), zlo, zhi)
    if secant:
        store = prob.secant_store(Q)
        state = _iterate(z, prob.evaluate_start(pid, z, store, max_sets), dev)
    else:
        state = _iterate(z, prob.evaluate(pid, z, max_sets), dev)
    done = wp.empty(Q, dtype=wp.int32, device=dev)
    wp.launch(init, dim=Q, device=dev, inputs=[setup, state, done])
    active = np.flatnonzero(done.numpy() == 0)
    dropped = np.zeros(Q, dtype=bool)
    met = np.zeros(Q, dtype=bool)
    small = np.zeros(Q, dtype=bool)
    bar = progress_bar(Q, "fits", progress, unit="fit")
    bar.update(Q - active.size)
    first = True
    while True:
        trial = None
        while active.size:
            n = active.size
            if trial is None or trial.act.shape[0] != n:  # the slots changed: their records
                trial = _trial(active, p, dev, secant)
                ids = _device_array(pid[active], dev, wp.int32)
                done = wp.empty(n, dtype=wp.int32, device=dev)
            wp.launch(propose, dim=n, device=dev, inputs=[setup, state, trial])
            if secant:
                if first:  # the starts' second derivatives, where the problems have them
                    curvature = prob.curvature(ids, trial, store)
                    wp.launch(accelerate, dim=n, device=dev, inputs=[setup, state, trial, curvature])
                    first = False
                prob.evaluate_trial(ids, trial, store, max_sets)
            else:
                # the trial points stay on a GPU (a NumPy view of them on the CPU)
                zt = trial.zt.numpy() if dev.is_cpu else trial.zt
                beat = {"below": state.at_z.cost.numpy()[active]} if getattr(prob, "jacobian_if_below", False) else {}
                trial.at_zt = normal_equations(prob.evaluate(pid[active], zt, max_sets, **beat), dev)
            wp.launch(update, dim=n, device=dev, inputs=[setup, state, trial, done])
            if secant:
                accept_rows, accept_flags = lm_step.secant_accept_kernels(p)
                blocks = klm.row_blocks(store.T.shape[0] // 8)
                wp.launch(accept_rows, dim=(blocks, n), device=dev, inputs=[store, trial])
                wp.launch(accept_flags, dim=n, device=dev, inputs=[store, trial, done])
            flags = done.numpy()  # the one host round trip of an iteration
            if secant and np.any(flags == 2):
                prob.refresh(active[flags == 2], pid, state, store, max_sets)
            finished = flags == 1
            if drop is not None and (~finished).any():
                cut = np.zeros_like(finished)
                cut[~finished] = drop(active[~finished], state.at_z.cost.numpy())
                dropped[active[cut]] = True
                finished |= cut
            rest = np.flatnonzero(~finished)
            rest = rest[tested[active[rest]]]
            if rest.size:
                slots = active[rest]
                dec, meets = stop_tests(
                    *(a.numpy() for a in (state.z, state.at_z.g, state.at_z.H)),
                    zlo,
                    zhi,
                    state.at_z.cost.numpy(),
                    slots,
                    starts_of,
                    merge,
                    ~(dropped | met),
                )
                near = ~meets & (dec < decrement[slots])
                met[slots[meets]] = True
                small[slots[near]] = True
                finished[rest[meets | near]] = True
            if finished.any():
                active = active[~finished]
                bar.update(int(finished.sum()))
                trial = None
        if not secant:
            break
        # Each solution's Jacobian (whose J^T J gives the covariance) is a fresh
        # forward-difference one at the solution, never a secant one: the slots that ended
        # on a rank-one updated Jacobian get theirs, and those that stopped on xtol stop
        # only if the step from it is below xtol and SECANT_CONFIRM std too (else they
        # iterate on from it, on the fresh Jacobian).
        stale = np.flatnonzero(store.fresh.numpy() == 0)
        if not stale.size:
            break
        prob.refresh(stale, pid, state, store, max_sets)
        ended = stale[(state.reason.numpy()[stale] == lm_step.R_XTOL) & ~dropped[stale]]
        if not ended.size:
            break
        check = _trial(ended, p, dev)
        again = wp.empty(ended.size, dtype=wp.int32, device=dev)
        wp.launch(propose, dim=ended.size, device=dev, inputs=[setup, state, check])
        wp.launch(confirm, dim=ended.size, device=dev, inputs=[setup, state, check, again])
        active = ended[again.numpy() == 1]
        bar.update(-active.size)
    bar.close()
    reason = np.array(REASONS, dtype=object)[state.reason.numpy()]
    reason[dropped] = DROPPED
    reason[met] = MERGED
    reason[small] = DECREMENT
    return LMState(
        state.z.numpy(),
        state.at_z.cost.numpy(),
        state.at_z.raw.numpy(),
        state.at_z.g.numpy(),
        state.at_z.H.numpy(),
        state.iterations.numpy().astype(int),
        reason,
        ((state.converged.numpy() != 0) | small) & ~(dropped | met),
    )
