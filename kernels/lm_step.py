"""Kernels of one batched Levenberg-Marquardt iteration (:func:`tawarp.fit.lm.levenberg_marquardt`).

The LM bookkeeping of every problem runs on the problems' device, one thread per
problem, so the host only launches, evaluates and compacts the active set. Three records
hold the arrays, indexed by the problem's slot ``q`` of the batch (Q slots):
:class:`Setup` what stays fixed (``pid[q]`` the slot's data index, which selects the rows
of the bounds and of the change rule; the options), :class:`Iterate` the state (``z``
(Q, p) scaled variables, its :class:`~tawarp.kernels.lm.NormalEquations` ``F = r^T r``,
``g = J^T r``, ``H = J^T J``, the damping ``mu``, ``nu``, ``iterations``, ``reason``,
``converged``) and :class:`Trial` the step of each active slot.

Five kernels per ``p`` (:func:`step_kernels`, closures with compile-time loop bounds, the
p x p matrices in registers):

1. ``init`` (one thread per slot): invalid evaluations (a non-finite cost, g or H) become
   ``cost = inf`` / ``"invalid"``; ``mu = tau max diag H`` (1e-3 if that is not > 0);
   the initial gradient test (``"gtol"``); ``done`` marks slots that do not iterate.
2. ``propose`` (one thread per active slot ``act[s]``): the damped step
   ``(H + mu I) d = -g`` on the free components (a component held at its bound by a gradient
   pushing outward takes no part), by Cholesky; the trial ``zt = clip(z + d, zlo, zhi)``,
   ``dz = zt - z`` and the predicted decrease ``pred = -(2 g.dz + dz.H.dz)``.
3. ``update`` (one thread per active slot, after the problems evaluated the trials):
   acceptance (``accepted``), damping (Nielsen's or the paper's), the stopping tests and
   reasons in the order ``xtol``, ``gtol``, ``bound``, ``stalled``, ``max_iterations``.
4. ``confirm`` (a secant run, :mod:`tawarp.fit.lm`): whether a stop on ``xtol`` stands on
   the fresh Jacobian at the solution.
5. ``accelerate`` (a secant run's first trials): the geodesic acceleration of the step.

and, in a secant run, :func:`secant_accept_kernels` after ``update``.

The relative change of a step compared with ``xtol`` is the problem's own notion, given as
data per parameter (``Setup.change``: ``kind`` (p,), ``scale`` ``offset`` (N, p)):
:data:`CHANGE_LINEAR` ``s |dz| / |o + s zt|`` (v = o + s z), :data:`CHANGE_LOG`
``|expm1(dz)|`` (v = s exp(z)), :data:`CHANGE_ABSOLUTE` ``|dz|`` (z already measures
relative change). Everything is float64.
"""

import warp as wp

from .lm import KIND_LINEAR, KIND_LOG, ROW_BLOCK, NormalEquations, Scaling, Secant, secant_kernels

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

#: relative-change rules (the first two are the parameter transforms of :mod:`.lm`)
CHANGE_LINEAR = KIND_LINEAR
CHANGE_LOG = KIND_LOG
CHANGE_ABSOLUTE = wp.constant(2)

#: reason codes; 0 while iterating (:data:`tawarp.fit.lm.REASONS` names them)
R_XTOL = wp.constant(1)
R_GTOL = wp.constant(2)
R_BOUND = wp.constant(3)
R_STALLED = wp.constant(4)
R_MAX_ITERATIONS = wp.constant(5)
R_INVALID = wp.constant(6)

#: damping rules
DAMP_NIELSEN = wp.constant(0)
DAMP_PAPER = wp.constant(1)


@wp.struct
class Setup:
    """What stays fixed through a run: per slot q the problem's data index ``pid[q]``, which
    selects the rows of the bounds ``zlo``, ``zhi`` (N, p) and of the ``change`` rule (its
    ``kind`` a CHANGE_* code per parameter); the damping rule (DAMP_*), the initial damping
    factor ``tau``, the stopping tests' ``xtol``, ``gtol`` and ``max_iter``, and a secant
    run's ``confirm`` (``confirm`` kernel)."""

    pid: wp.array(dtype=wp.int32)
    zlo: wp.array2d(dtype=wp.float64)
    zhi: wp.array2d(dtype=wp.float64)
    change: Scaling
    damping: int
    tau: wp.float64
    xtol: wp.float64
    gtol: wp.float64
    max_iter: int
    confirm: wp.float64


@wp.struct
class Iterate:
    """The state of every slot q (Q,): ``z`` (Q, p) and its normal equations ``at_z``, the
    damping ``mu``, ``nu``, the ``iterations`` made, the stopping ``reason`` (R_*; 0 while
    iterating) and ``converged``."""

    z: wp.array2d(dtype=wp.float64)
    at_z: NormalEquations
    mu: wp.array(dtype=wp.float64)
    nu: wp.array(dtype=wp.float64)
    iterations: wp.array(dtype=wp.int32)
    reason: wp.array(dtype=wp.int32)
    converged: wp.array(dtype=wp.int32)


@wp.struct
class Trial:
    """The trial step of every active slot s: ``act[s]`` its slot q, the trial point ``zt``
    (n, p), the step ``dz`` = zt - z, the predicted decrease ``pred``, ``chol_ok`` (0: the
    damped matrix was not positive definite, no step), the normal equations ``at_zt``
    of the evaluated trial and ``accepted`` (1: the slot moved to it)."""

    act: wp.array(dtype=wp.int32)
    zt: wp.array2d(dtype=wp.float64)
    dz: wp.array2d(dtype=wp.float64)
    pred: wp.array(dtype=wp.float64)
    chol_ok: wp.array(dtype=wp.int32)
    at_zt: NormalEquations
    accepted: wp.array(dtype=wp.int32)


@wp.func
def is_free(z: wp.float64, g: wp.float64, lo: wp.float64, hi: wp.float64):
    """1 unless the component sits at a bound with the gradient pushing outward."""
    if z <= lo and g > wp.float64(0.0):
        return 0
    if z >= hi and g < wp.float64(0.0):
        return 0
    return 1


@wp.func
def nan_max(m: wp.float64, x: wp.float64):
    """max(m, x) that keeps a NaN once met, as NumPy's max reduction."""
    if wp.isnan(m) or x <= m:
        return m
    return x


@wp.func
def expm1(x: wp.float64):
    """exp(x) - 1 without cancellation for small |x| (Kahan's correction; Warp has none)."""
    u = wp.exp(x)
    if u == wp.float64(1.0):
        return x
    um1 = u - wp.float64(1.0)
    if um1 == wp.float64(-1.0):
        return um1
    return um1 * x / wp.log(u)


_STEP_KERNELS = {}


def step_kernels(p: int):
    """(init, propose, update, confirm, accelerate) kernels for ``p`` parameters per problem
    (cached per p)."""
    if p in _STEP_KERNELS:
        return _STEP_KERNELS[p]
    P = wp.constant(p)
    vecp = wp.types.vector(length=p, dtype=wp.float64)
    matp = wp.types.matrix(shape=(p, p), dtype=wp.float64)
    veci = wp.types.vector(length=p, dtype=wp.int32)

    @wp.func
    def grad_cosine(setup: Setup, state: Iterate, q: int, cost: wp.float64):
        """max over free a of |g_a| / sqrt(H_aa F) of slot q at cost F, and the number of
        free components."""
        b = setup.pid[q]
        z = state.z
        g = state.at_z.g
        H = state.at_z.H
        tiny = wp.float64(1e-300)
        c = wp.float64(0.0)
        nfree = int(0)
        for a in range(P):
            if is_free(z[q, a], g[q, a], setup.zlo[b, a], setup.zhi[b, a]) == 1:
                nfree += 1
                ca = wp.abs(g[q, a]) / wp.sqrt(wp.max(H[q, a, a], tiny) * wp.max(cost, tiny))
                c = nan_max(c, ca)
        return c, nfree

    @wp.func
    def valid(sums: NormalEquations, q: int):
        """cost of row q, or inf where the evaluation is not finite (cost, g or H)."""
        c = sums.cost[q]
        ok = wp.isfinite(c)
        for a in range(P):
            ok = ok and wp.isfinite(sums.g[q, a])
            for b in range(P):
                ok = ok and wp.isfinite(sums.H[q, a, b])
        if ok:
            return c
        return wp.float64(wp.inf)

    @wp.func
    def relative_change(setup: Setup, b: int, trial: Trial, s: int):
        """The largest relative change of the parameters of trial s (problem b) over its
        step, by the change rule (module doc)."""
        scale = setup.change.scale
        offset = setup.change.offset
        dz = trial.dz
        rel = wp.float64(0.0)
        for a in range(P):
            k = setup.change.kind[a]
            r = wp.abs(dz[s, a])
            if k == CHANGE_LOG:
                r = wp.abs(expm1(dz[s, a]))
            elif k == CHANGE_LINEAR:
                r = scale[b, a] * r / wp.max(wp.abs(offset[b, a] + scale[b, a] * trial.zt[s, a]), wp.float64(1e-300))
            rel = nan_max(rel, r)
        return rel

    @wp.kernel(enable_backward=False, module="unique")
    def init(setup: Setup, state: Iterate, done: wp.array(dtype=wp.int32)):
        q = wp.tid()
        H = state.at_z.H
        c = valid(state.at_z, q)
        state.at_z.cost[q] = c
        m = H[q, 0, 0]
        for a in range(1, P):
            m = nan_max(m, H[q, a, a])
        m = setup.tau * m
        if not (wp.isfinite(m) and m > wp.float64(0.0)):
            m = wp.float64(1e-3)
        state.mu[q] = m
        state.nu[q] = wp.float64(2.0)
        state.reason[q] = 0
        state.converged[q] = 0
        done[q] = 0
        gcos, nfree = grad_cosine(setup, state, q, c)
        if not wp.isfinite(c):
            state.reason[q] = R_INVALID
            done[q] = 1
        elif gcos <= setup.gtol or c == wp.float64(0.0):
            state.reason[q] = R_GTOL
            state.converged[q] = 1
            done[q] = 1

    @wp.func
    def damped_solve(setup: Setup, state: Iterate, q: int, rhs_in: vecp):
        """x solving (H + mu I) x = rhs_in on the free components of slot q (x = 0 on the
        others; identity rows and columns there), by Cholesky with sums in index order (the
        host's reductions); ok = 0 where a pivot is <= 0 (or NaN): not positive definite."""
        b = int(setup.pid[q])
        z = state.z
        g = state.at_z.g
        H = state.at_z.H
        fr = veci()
        for a in range(P):
            fr[a] = is_free(z[q, a], g[q, a], setup.zlo[b, a], setup.zhi[b, a])
        A = matp()
        rhs = vecp()
        for i in range(P):
            if fr[i] == 1:
                rhs[i] = rhs_in[i]
            for j in range(P):
                if fr[i] == 1 and fr[j] == 1:
                    A[i, j] = H[q, i, j]
                    if i == j:
                        A[i, j] = H[q, i, j] + state.mu[q]
                elif i == j:
                    A[i, j] = wp.float64(1.0)
        L = matp()
        ok = int(1)
        for j in range(P):
            acc = wp.float64(0.0)
            for k in range(j):
                acc += L[j, k] * L[j, k]
            d = A[j, j] - acc
            if not (d > wp.float64(0.0)):
                ok = 0
                d = wp.float64(1.0)
            L[j, j] = wp.sqrt(d)
            for i in range(j + 1, P):
                acc2 = wp.float64(0.0)
                for k in range(j):
                    acc2 += L[i, k] * L[j, k]
                L[i, j] = (A[i, j] - acc2) / L[j, j]
        y = vecp()
        for i in range(P):
            acc = wp.float64(0.0)
            for k in range(i):
                acc += L[i, k] * y[k]
            y[i] = (rhs[i] - acc) / L[i, i]
        x = vecp()
        for ii in range(P):
            i = P - 1 - ii
            acc = wp.float64(0.0)
            for k in range(i + 1, P):
                acc += L[k, i] * x[k]
            x[i] = (y[i] - acc) / L[i, i]
        return x, ok

    @wp.func
    def take_step(setup: Setup, state: Iterate, trial: Trial, s: int, q: int, step: vecp):
        """Trial s of slot q at z + step projected onto the bounds: its zt, dz and the
        predicted decrease -(2 g.dz + dz.H.dz)."""
        b = int(setup.pid[q])
        z = state.z
        g = state.at_z.g
        H = state.at_z.H
        zt = trial.zt
        dz = trial.dz
        for a in range(P):
            t = wp.min(wp.max(z[q, a] + step[a], setup.zlo[b, a]), setup.zhi[b, a])
            zt[s, a] = t
            dz[s, a] = t - z[q, a]
        # g.dz in two interleaved partial sums, even and odd components (NumPy einsum's
        # order: the device takes the same decisions as the host LM it replaced, to the bit
        # on the CPU for p < 8)
        gd = wp.float64(0.0)
        gd_odd = wp.float64(0.0)
        for a in range(P):
            if a % 2 == 0:
                gd += g[q, a] * dz[s, a]
            else:
                gd_odd += g[q, a] * dz[s, a]
        gd = gd + gd_odd
        dHd = wp.float64(0.0)
        for a in range(P):
            for c in range(P):
                dHd += dz[s, a] * H[q, a, c] * dz[s, c]
        trial.pred[s] = -(wp.float64(2.0) * gd + dHd)

    @wp.kernel(enable_backward=False, module="unique")
    def propose(setup: Setup, state: Iterate, trial: Trial):
        s = wp.tid()
        q = int(trial.act[s])
        g = state.at_z.g
        minus_g = vecp()
        for a in range(P):
            minus_g[a] = -g[q, a]
        x, ok = damped_solve(setup, state, q, minus_g)
        if ok == 0:
            x = vecp()
        take_step(setup, state, trial, s, q, x)
        trial.chol_ok[s] = ok

    @wp.kernel(enable_backward=False, module="unique")
    def accelerate(setup: Setup, state: Iterate, trial: Trial, curvature: wp.array2d(dtype=wp.float64)):
        """Geodesic acceleration of ``propose``'s step v (Transtrum & Sethna 2012): with
        ``curvature[s]`` = J^T r_vv (r_vv the residuals' second derivative along v), the
        trial moves to z + v + a / 2, a = -(H + mu I)^-1 J^T r_vv; slots with no curvature
        (all 0) or no step keep theirs."""
        s = wp.tid()
        q = int(trial.act[s])
        c = vecp()
        some = int(0)
        for a in range(P):
            c[a] = -curvature[s, a]
            if curvature[s, a] != wp.float64(0.0):
                some = 1
        if some == 0 or trial.chol_ok[s] == 0:
            return
        x, ok = damped_solve(setup, state, q, c)
        if ok == 0:
            return
        step = vecp()
        for a in range(P):
            step[a] = trial.dz[s, a] + wp.float64(0.5) * x[a]
        take_step(setup, state, trial, s, q, step)

    @wp.kernel(enable_backward=False, module="unique")
    def update(setup: Setup, state: Iterate, trial: Trial, done: wp.array(dtype=wp.int32)):
        s = wp.tid()
        q = int(trial.act[s])
        b = int(setup.pid[q])
        now = state.at_z
        new = trial.at_zt
        nu = state.nu
        zt = trial.zt
        pred = trial.pred
        c_new = valid(new, s)
        c_old = now.cost[q]
        rho = wp.float64(-1.0)
        if pred[s] > wp.float64(0.0):
            rho = (c_old - c_new) / pred[s]
        acc = trial.chol_ok[s] == 1 and wp.isfinite(c_new) and rho > wp.float64(0.0) and c_new < c_old
        it = state.iterations[q] + 1
        state.iterations[q] = it
        trial.accepted[s] = int(acc)
        # accepted: move, take the trial's Jacobian
        if acc:
            for a in range(P):
                state.z[q, a] = zt[s, a]
                now.g[q, a] = new.g[s, a]
                for e in range(P):
                    now.H[q, a, e] = new.H[s, a, e]
            now.cost[q] = c_new
            now.raw[q] = new.raw[s]
        m = state.mu[q]
        if setup.damping == DAMP_NIELSEN:
            if acc:
                t = wp.float64(2.0) * rho - wp.float64(1.0)
                m = m * wp.max(wp.float64(1.0) / wp.float64(3.0), wp.float64(1.0) - wp.pow(t, wp.float64(3.0)))
                nu[q] = wp.float64(2.0)
            else:
                m = m * nu[q]
                nu[q] = nu[q] * wp.float64(2.0)
        else:
            if acc:
                m = m * wp.float64(0.5)
            else:
                m = m * wp.float64(2.0)
        state.mu[q] = m
        # convergence tests
        rel = relative_change(setup, b, trial, s)
        cq = now.cost[q]
        gcos, nfree = grad_cosine(setup, state, q, cq)
        why = int(0)
        good = int(0)
        if acc and rel < setup.xtol:
            why = R_XTOL
            good = 1
        elif gcos <= setup.gtol or cq == wp.float64(0.0):
            why = R_GTOL
            good = 1
        elif nfree == 0:
            why = R_BOUND
            good = 1
        elif (not acc) and m > wp.float64(1e16):
            why = R_STALLED
            if gcos <= wp.float64(1e-4):
                good = 1
        elif it >= setup.max_iter:
            why = R_MAX_ITERATIONS
        done[s] = 0
        if why != 0:
            state.reason[q] = why
            state.converged[q] = good
            done[s] = 1

    @wp.kernel(enable_backward=False, module="unique")
    def confirm(setup: Setup, state: Iterate, trial: Trial, again: wp.array(dtype=wp.int32)):
        """Slots that stopped on ``xtol`` with a secant Jacobian, after the fresh one at z
        replaced it (``trial``: ``propose``'s step with it): the stop stands where that step
        is below ``xtol`` too and its predicted decrease of the cost below ``confirm`` F,
        else the slot iterates again (``again[s]`` = 1)."""
        s = wp.tid()
        q = int(trial.act[s])
        again[s] = 0
        small = relative_change(setup, int(setup.pid[q]), trial, s) < setup.xtol
        if not (small and trial.pred[s] <= setup.confirm * state.at_z.cost[q]):
            state.reason[q] = 0
            state.converged[q] = 0
            again[s] = 1

    _STEP_KERNELS[p] = (init, propose, update, confirm, accelerate)
    return _STEP_KERNELS[p]


_SECANT_STEP_KERNELS = {}


def secant_accept_kernels(p: int):
    """The kernels (rows, flags) (cached per p) that follow ``update`` in a secant LM run.
    ``rows`` (one thread per row block b and active slot s, ``dim = (row_blocks(m), n)``,
    :func:`tawarp.kernels.lm.row_blocks`): an accepted trial's values and its rank-one
    updated Jacobian (:func:`tawarp.kernels.lm.secant_kernels`' ``broyden_row``, the
    update the trial's sums were made with) become the slot's in the
    :class:`~tawarp.kernels.lm.Secant` store. ``flags`` (one thread per active slot, after
    ``rows``): an accepted slot's Jacobian is no longer fresh; a rejected trial from a
    secant Jacobian sets ``done[s]`` = 2: the slot's Jacobian is to be refreshed by
    differences before its next step (the rejection may be the secant's fault); the
    second derivatives serve the first trial alone."""
    if p in _SECANT_STEP_KERNELS:
        return _SECANT_STEP_KERNELS[p]
    P = wp.constant(p)
    vecp = wp.types.vector(length=p, dtype=wp.float64)
    kernels = secant_kernels(p)
    broyden_row, taylor_row = kernels.broyden_row, kernels.taylor_row

    @wp.kernel(enable_backward=False, module="unique")
    def accept_rows(store: Secant, trial: Trial):
        b, s = wp.tid()
        if trial.accepted[s] != 1:
            return
        q = int(trial.act[s])
        dz = vecp()
        for a in range(P):
            dz[a] = trial.dz[s, a]
        d2 = wp.dot(dz, dz)
        inv_dz2 = wp.float64(0.0)
        if d2 > wp.float64(0.0):
            inv_dz2 = wp.float64(1.0) / d2
        taylor = store.second[q] >= 0
        for row in range(b * ROW_BLOCK * 8, wp.min(store.T.shape[0], (b + 1) * ROW_BLOCK * 8)):
            jr = vecp()
            for a in range(P):
                jr[a] = store.dT[row * P + a, q]
            t_new = store.trial[row, s]
            if taylor:
                jr = taylor_row(store, row, q, jr, dz)
            else:
                jr = broyden_row(jr, t_new - store.T[row, q], dz, inv_dz2)
            for a in range(P):
                store.dT[row * P + a, q] = jr[a]
            store.T[row, q] = t_new

    @wp.kernel(enable_backward=False, module="unique")
    def accept_flags(store: Secant, trial: Trial, done: wp.array(dtype=wp.int32)):
        s = wp.tid()
        q = int(trial.act[s])
        if trial.accepted[s] == 1:
            store.fresh[q] = 0
        elif done[s] == 0 and store.fresh[q] == 0:
            done[s] = 2
        store.second[q] = -1

    _SECANT_STEP_KERNELS[p] = (accept_rows, accept_flags)
    return _SECANT_STEP_KERNELS[p]
