"""Kernels of the batched Levenberg-Marquardt estimator (:mod:`tawarp.fit.estimate`).

One LM iteration of a batch of independent least-squares problems is one forward
launch (:class:`tawarp.model.forward.Engine`) framed by two kernels of this module:

1. :func:`build_sets` (one thread per parameter set) writes the Engine's varying table
   from the scaled variables ``z`` of the active problems: per problem its point and
   either its ``p`` forward-difference neighbours ``z + step[a] e_a`` (``1 + p`` sets,
   each cascaded) or its ``2p`` neighbours ``z +- step[a] e_a`` of the tangent pass
   (``1 + 2p`` sets, of which only the point is cascaded: the neighbours give the
   central differences of its Gauss points' coefficients,
   :meth:`tawarp.model.forward.Engine.evaluate_tangents`).
2. the normal-equations kernel of :func:`normal_kernel` (one thread per active problem
   and block of :data:`ROW_BLOCK` frequencies, whose partial sums :func:`normal_sums`'
   ``reduce_sums`` adds in order per problem) reads its problem's T-matrices and
   Jacobian at those frequencies, normalizes them with the problem's ``Zc``, and
   accumulates over their real residuals (``8 m`` in all)
   ``r = w (Y_model - Y_meas)`` (re and im of Tpp, Tpu/Zc, Tup*Zc, Tuu):
   ``cost = r.r``, ``g = J^T r``, ``H = J^T J`` (p x p) and the unweighted
   ``sum |Y_model - Y_meas|^2`` of the error measure; the Jacobian column ``a`` is
   ``w dY/dz_a`` from the tangent cascade or the forward difference
   ``w (Y(z + step_a e_a) - Y(z)) / step_a``.

The kernels of step 2 are specialised per ``p`` (a closure with compile-time loop
bounds), so the Jacobian row and ``H`` live in registers. Everything is float64.

The secant iteration (``jacobian="broyden"``) keeps each problem's T-matrices and their
Jacobian in a :class:`Secant` store on the device: :func:`build_sets` lays out the point
alone (a trial), the neighbours alone (a refresh at a point whose values are stored) or
both (the start), and the kernels of :func:`secant_kernels` make the forward differences
into the store and the normal equations from it, at a trial point with the Jacobian
moved by Broyden's rank-one update.

Two small kernels give the host side of the fits what the forward kernels compute,
from the same Warp functions (no host copy of the physics to drift):
:func:`magnus_cells` (the cascade's adaptive cell count of each thermal segment) and
:func:`gas_transport` (viscosity and conductivity of the gas laws).
"""

from typing import Any, NamedTuple

import warp as wp

from .forward import SetTable, magnus_cell_count, temperature_scale, temperature_varies
from .gas import conductivity, viscosity
from .layout import LENGTH, seg_value

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code


@wp.kernel(enable_backward=False)
def magnus_cells(
    sets: SetTable,
    omega: wp.float64,
    cell_density: wp.array(dtype=wp.float64),
    k_factor: wp.float64,
    cells: wp.array2d(dtype=wp.int32),
):
    """cells[i, s]: the Magnus cells the cascade kernel (:func:`tawarp.kernels.forward.make_transfer_kernel`'s)
    gives thermal segment s of parameter set i at angular frequency ``omega`` [rad/s],
    ``ceil(cell_density[i] (1 + k_factor k L + omega L / c_cold))`` with the heat model's decay
    rate k of :func:`segment_heat_coeffs` (wall conductance and every other term included;
    an imposed profile's rate for imposed temperatures, :func:`temperature_scale`);
    ``k_factor = 1`` is the kernel's own count, > 1 leaves room for k to grow. 0 for
    segments at uniform temperature."""
    i, s = wp.tid()
    params = sets.params
    flags = sets.flags
    cells[i, s] = 0
    if temperature_varies(params, flags, i, s):
        k, c = temperature_scale(params, flags, sets.gas, i, s)
        cells[i, s] = magnus_cell_count(cell_density[i], k_factor * k, seg_value(params, i, s, LENGTH), omega, c)


@wp.kernel(enable_backward=False)
def gas_transport(
    gas: wp.array(dtype=wp.float64),
    T: wp.array(dtype=wp.float64),
    mu: wp.array(dtype=wp.float64),
    k: wp.array(dtype=wp.float64),
):
    """Dynamic viscosity mu [Pa s] and conductivity k [W/(m K)] at temperatures T [K]."""
    i = wp.tid()
    mu[i] = viscosity(gas, T[i])
    k[i] = conductivity(gas, T[i])


#: kinds of parameter transform: natural value v from the scaled variable z and the scale s
KIND_LINEAR = wp.constant(0)  # v = o + s z
KIND_LOG = wp.constant(1)  # v = s exp(z)


@wp.struct
class Scaling:
    """The transform of each parameter a of problem (data index) pid between its natural
    value v and its scaled variable z: ``kind[a]`` :data:`KIND_LOG` v = scale[pid, a] exp(z),
    :data:`KIND_LINEAR` v = offset[pid, a] + scale[pid, a] z; ``kind`` (p,), ``scale`` and
    ``offset`` (N, p)."""

    kind: wp.array(dtype=wp.int32)
    scale: wp.array2d(dtype=wp.float64)
    offset: wp.array2d(dtype=wp.float64)


@wp.struct
class Slots:
    """The problems of one launch, one per slot: ``ids`` (slots,) each one's data index,
    ``z`` (slots, p) its scaled variables and ``step`` (slots, p) the step in z of its
    Jacobian's neighbours."""

    ids: wp.array(dtype=wp.int32)
    z: wp.array2d(dtype=wp.float64)
    step: wp.array2d(dtype=wp.float64)


@wp.struct
class Measured:
    """What the problems fit, per data index: ``Y`` (N, m, 8) the measured dimensionless
    values and ``W`` (N or 1, m, 8) their weights (re, im of Tpp, Tpu/Zc, Tup Zc, Tuu; one
    row of W serves every problem), ``zc`` (N,) the duct impedance Zc that normalizes them."""

    Y: wp.array3d(dtype=wp.float64)
    W: wp.array3d(dtype=wp.float64)
    zc: wp.array(dtype=wp.float64)


@wp.struct
class NormalEquations:
    """The least-squares sums of evaluations, one row per slot: ``cost`` the weighted
    ``r.r``, ``raw`` the unweighted ``sum |Y_model - Y_meas|^2``, ``g`` (slots, p) ``J^T r``
    and ``H`` (slots, p, p) ``J^T J``."""

    cost: wp.array(dtype=wp.float64)
    raw: wp.array(dtype=wp.float64)
    g: wp.array2d(dtype=wp.float64)
    H: wp.array3d(dtype=wp.float64)


@wp.func
def coefficient_scale(k: int, zc: wp.float64):
    """The factor that makes raw value k (re, im of Tpp, Tpu, Tup, Tuu) dimensionless:
    1/Zc for Tpu, Zc for Tup, 1 for the others."""
    if k == 2 or k == 3:
        return wp.float64(1.0) / zc
    if k == 4 or k == 5:
        return zc
    return wp.float64(1.0)


#: frequencies per thread of the kernels that run over a problem's 8 m rows (the
#: normal equations, the secant store's updates): a problem's rows are spread over
#: ceil(m / ROW_BLOCK) threads, whose partial sums :func:`normal_sums`' ``reduce_sums``
#: adds in order (one thread per problem over all its rows left the device at 1e5
#: problems with a few threads per SM, each a serial chain of 8 m dependent loads)
ROW_BLOCK = wp.constant(4)


def row_blocks(m: int) -> int:
    """Threads per problem of the row kernels for m frequencies (:data:`ROW_BLOCK`)."""
    return -(-m // int(ROW_BLOCK))


_SUM_FUNCS = {}


def normal_sums(p: int):
    """(add_row, store_partial, reduce_sums) of the normal equations for ``p`` parameters
    (cached per p), shared by the difference, tangent and secant kernels: ``add_row(g, H,
    jr, r)`` adds the residual r with Jacobian row jr to g = J^T r and H = J^T J;
    ``store_partial(partial, b, s, cost, raw, g, H)`` writes the sums of row block b of
    slot s into ``partial`` (2 + p + p^2, blocks, slots); the kernel ``reduce_sums``
    (one thread per slot s) adds a slot's blocks in order into row ``dest[s]`` of a
    :class:`NormalEquations`."""
    if p in _SUM_FUNCS:
        return _SUM_FUNCS[p]
    P = wp.constant(p)
    vecp = wp.types.vector(length=p, dtype=wp.float64)
    matp = wp.types.matrix(shape=(p, p), dtype=wp.float64)

    @wp.func
    def add_row(gv: vecp, Hm: matp, jr: vecp, r: wp.float64):
        return gv + r * jr, Hm + wp.outer(jr, jr)

    @wp.func
    def store_partial(
        partial: wp.array3d(dtype=wp.float64), b: int, s: int, c2: wp.float64, u2: wp.float64, gv: vecp, Hm: matp
    ):
        partial[0, b, s] = c2
        partial[1, b, s] = u2
        for a in range(P):
            partial[2 + a, b, s] = gv[a]
            for c in range(P):
                partial[2 + P + a * P + c, b, s] = Hm[a, c]

    @wp.kernel(enable_backward=False, module="unique")
    def reduce_sums(partial: wp.array3d(dtype=wp.float64), dest: wp.array(dtype=wp.int32), sums: NormalEquations):
        s = wp.tid()
        c2 = wp.float64(0.0)
        u2 = wp.float64(0.0)
        gv = vecp()
        Hm = matp()
        for b in range(partial.shape[1]):
            c2 += partial[0, b, s]
            u2 += partial[1, b, s]
            pg = vecp()
            pH = matp()
            for a in range(P):
                pg[a] = partial[2 + a, b, s]
                for c in range(P):
                    pH[a, c] = partial[2 + P + a * P + c, b, s]
            gv = gv + pg
            Hm = Hm + pH
        e = dest[s]
        sums.cost[e] = c2
        sums.raw[e] = u2
        for a in range(P):
            sums.g[e, a] = gv[a]
            for c in range(P):
                sums.H[e, a, c] = Hm[a, c]

    _SUM_FUNCS[p] = (add_row, store_partial, reduce_sums)
    return _SUM_FUNCS[p]


@wp.func
def second_pair(k: int, p: int):
    """The parameters (a, b) that the set k of a second-difference group moves: k < p is
    z + h e_k (a = k, b = -1), then z + h (e_a + e_b) for a <= b in row order (p (p + 1) / 2
    sets; a = b is z + 2 h e_a)."""
    if k < p:
        return k, -1
    r = k - p
    for a in range(p):
        if r < p - a:
            return a, a + r
        r -= p - a
    return -1, -1


@wp.kernel(enable_backward=False)
def build_sets(
    slots: Slots,
    scaling: Scaling,
    fixed: wp.array2d(dtype=wp.float64),
    row_src: wp.array(dtype=wp.int32),
    central: int,
    first: int,
    varying: wp.array2d(dtype=wp.float64),
):
    """varying[r, col]: each slot has ``sets`` = columns / slots consecutive sets, slot =
    col // sets and set j = first + col % sets of its group: forward differences (set j =
    1 + a is z + step e_a; the point and its p neighbours with ``first`` = 0 and 1 + p sets,
    the point alone with 1 set, the neighbours alone with ``first`` = 1 and p sets), or with
    ``central`` = 1 set j = 1 + 2a, 2 + 2a is z +- step e_a (1 + 2p sets: the tangent
    pass's neighbours, :meth:`tawarp.model.forward.Engine.evaluate_tangents`), or with
    ``central`` = 2 set j >= 1 is the point of second differences k = j - 1
    (:func:`second_pair`: z + step e_a, then z + step (e_a + e_b), a <= b). row_src[r]
    >= 0 names the free parameter a = row_src[r] (value from z, perturbed in its sets),
    row_src[r] < 0 the per-problem fixed row -1 - row_src[r]; ``scaling`` gives v from z."""
    col = wp.tid()
    z = slots.z
    step = slots.step
    scale = scaling.scale
    offset = scaling.offset
    p = z.shape[1]
    sets = varying.shape[1] // slots.ids.shape[0]
    slot = col // sets
    j = col - slot * sets + first
    pid = slots.ids[slot]
    for r in range(row_src.shape[0]):
        a = row_src[r]
        if a < 0:
            varying[r, col] = fixed[-1 - a, pid]
        else:
            zz = z[slot, a]
            if central == 0 and j == a + 1:
                zz = zz + step[slot, a]
            if central == 1 and j == 1 + 2 * a:
                zz = zz + step[slot, a]
            if central == 1 and j == 2 + 2 * a:
                zz = zz - step[slot, a]
            if central == 2 and j >= 1:
                pa, pb = second_pair(j - 1, p)
                if pa == a:
                    zz = zz + step[slot, a]
                if pb == a:
                    zz = zz + step[slot, a]
            if scaling.kind[a] == KIND_LOG:
                varying[r, col] = scale[pid, a] * wp.exp(zz)
            else:
                varying[r, col] = offset[pid, a] + scale[pid, a] * zz


_NORMAL_KERNELS = {}


def normal_kernel(p: int, tangents: bool = False):
    """The normal-equations kernel for ``p`` free parameters (cached per p and Jacobian),
    one thread per row block b (:data:`ROW_BLOCK` frequencies) and slot s (``dim =
    (row_blocks(m), slots)``); :func:`normal_sums`' ``reduce_sums`` adds the blocks.

    Inputs: the launch's :class:`Slots` (``z`` is not read), the :class:`Measured` data,
    ``out`` the Engine's raw T-matrices and ``tangent``. Forward differences (``tangents`` False):
    ``out`` (slots (1 + p), m, 8) holds a slot's point and its p neighbours, the Jacobian
    column a is ``w (Y(z + step_a e_a) - Y(z)) / step_a``, ``tangent`` is not read. Tangents:
    ``out`` (slots, m, 8) the points and ``tangent`` (slots, p, m, 8) their derivatives
    (:meth:`tawarp.model.forward.Engine.evaluate_tangents`), the column is ``w dY/dz_a``.
    Output: ``partial`` (2 + p + p^2, blocks, slots) (``store_partial``).
    """
    key = (p, bool(tangents))
    if key in _NORMAL_KERNELS:
        return _NORMAL_KERNELS[key]
    P = wp.constant(p)
    TANGENTS = wp.constant(bool(tangents))
    vecp = wp.types.vector(length=p, dtype=wp.float64)
    matp = wp.types.matrix(shape=(p, p), dtype=wp.float64)
    add_row, store_partial = normal_sums(p)[:2]

    @wp.kernel(enable_backward=False, module="unique")
    def normal_equations(
        slots: Slots,
        data: Measured,
        out: wp.array3d(dtype=wp.float64),
        tangent: wp.array4d(dtype=wp.float64),
        partial: wp.array3d(dtype=wp.float64),
    ):
        b, s = wp.tid()
        Y = data.Y
        W = data.W
        step = slots.step
        pid = slots.ids[s]
        zc = data.zc[pid]
        base = s
        if wp.static(not TANGENTS):
            base = s * (P + 1)
        inv_step = vecp()
        for a in range(P):
            inv_step[a] = wp.float64(1.0) / step[s, a]
        gv = vecp()
        Hm = matp()
        c2 = wp.float64(0.0)
        u2 = wp.float64(0.0)
        wrow = pid
        if W.shape[0] == 1:  # one weight row shared by every problem
            wrow = 0
        for f in range(b * ROW_BLOCK, wp.min(out.shape[1], (b + 1) * ROW_BLOCK)):
            for k in range(8):
                fac = coefficient_scale(k, zc)
                w = W[wrow, f, k]
                y0 = out[base, f, k] * fac
                d = y0 - Y[pid, f, k]
                r = w * d
                c2 += r * r
                u2 += d * d
                jr = vecp()
                for a in range(P):
                    if wp.static(TANGENTS):
                        jr[a] = w * tangent[s, a, f, k] * fac
                    else:
                        jr[a] = w * (out[base + 1 + a, f, k] * fac - y0) * inv_step[a]
                gv, Hm = add_row(gv, Hm, jr, r)
        store_partial(partial, b, s, c2, u2, gv, Hm)

    _NORMAL_KERNELS[key] = normal_equations
    return normal_equations


# -- secant (Broyden) Jacobians ------------------------------------------------------------
@wp.struct
class Secant:
    """The model of every slot q (Q slots) of a secant LM run, kept on the device between
    its iterations: ``T`` (8m, Q) the raw T-matrix values at the slot's z (row 8 f + k: re,
    im of the four entries at frequency f) and ``dT`` (8m p, Q) their Jacobian in z (row
    (8 f + k) p + a), rows first so that neighbouring slots' threads read neighbouring
    words; ``fresh`` (Q,) 1 while ``dT`` is the forward-difference Jacobian at z, 0 once a
    rank-one update made it; ``trial`` (8m, Q) the values at the trial of the launch's
    slot s (column s); ``second`` (Q,) the column of ``d2T`` (8m p (p + 1) / 2, G) that
    holds the second derivatives of the T-matrices at the slot's start (row (8 f + k) p
    (p + 1) / 2 + c, c the pair a <= b in row order), -1 for none or once its first trial
    used them."""

    T: wp.array2d(dtype=wp.float64)
    dT: wp.array2d(dtype=wp.float64)
    fresh: wp.array(dtype=wp.int32)
    trial: wp.array2d(dtype=wp.float64)
    second: wp.array(dtype=wp.int32)
    d2T: wp.array2d(dtype=wp.float64)


@wp.kernel(enable_backward=False)
def difference_steps(
    slots: Slots,
    zhi: wp.array2d(dtype=wp.float64),
    h: wp.float64,
    step: wp.array2d(dtype=wp.float64),
):
    """step[s, a] = h, or -h where z + h would pass the upper bound ``zhi`` of the slot's
    problem (forward differences towards the interior)."""
    s, a = wp.tid()
    step[s, a] = h
    if slots.z[s, a] + h > zhi[slots.ids[s], a]:
        step[s, a] = -h


@wp.kernel(enable_backward=False)
def squared_norms(Y: wp.array3d(dtype=wp.float64), y2: wp.array(dtype=wp.float64)):
    """y2[i] = the sum of Y[i]'s squares (the measured values' sum |Y|^2 of the error measure)."""
    i = wp.tid()
    acc = wp.float64(0.0)
    for f in range(Y.shape[1]):
        for k in range(Y.shape[2]):
            acc += Y[i, f, k] * Y[i, f, k]
    y2[i] = acc


@wp.kernel(enable_backward=False)
def gather_rows(src: wp.array2d(dtype=wp.float64), index: wp.array(dtype=wp.int32), dst: wp.array2d(dtype=wp.float64)):
    """dst[s] = src[index[s]]."""
    s, a = wp.tid()
    dst[s, a] = src[index[s], a]


@wp.kernel(enable_backward=False)
def reduce_rows(partial: wp.array3d(dtype=wp.float64), out: wp.array2d(dtype=wp.float64)):
    """out[s, a] = the sum over row blocks b, in order, of partial[a, b, s]."""
    s, a = wp.tid()
    acc = wp.float64(0.0)
    for b in range(partial.shape[1]):
        acc += partial[a, b, s]
    out[s, a] = acc


class SecantKernels(NamedTuple):
    """The secant iteration's kernels and functions for p parameters (:func:`secant_kernels`)."""

    differences: Any
    sums: Any
    trial_sums: Any
    broyden_row: Any
    taylor_row: Any
    second_differences: Any
    curvature: Any


_SECANT_KERNELS = {}


def secant_kernels(p: int) -> SecantKernels:
    """The :class:`SecantKernels` for ``p`` free parameters (cached per p). Every kernel
    runs one thread per row block b (:data:`ROW_BLOCK` frequencies) and slot s of its
    launch (``dim = (row_blocks(m), slots)``, the slot q = ``act[s]`` of the store).

    ``differences``: the forward-difference Jacobian of slot q into the :class:`Secant`
    store from the launch's T-matrices ``out``: slot s's group starts at set ``group[s]``
    (slots with the same sets share a group), with ``point`` = 1 the group is the point and
    its p neighbours (``T`` is written too), with 0 the neighbours alone (``T`` is read).
    ``sums`` / ``trial_sums``: the partial sums (:func:`normal_sums`' ``store_partial``,
    added by its ``reduce_sums``) of the slot at its z from the store, or at its trial
    point from the launch's T-matrices ``out`` (s, m, 8) with the Jacobian updated by the
    step ``dz`` (s, p) (Broyden's rank-one update, ``broyden_row``; the trial's values are
    kept in column ``dest[s]`` of ``Secant.trial``). The residuals are those of
    :func:`normal_kernel`. ``second_differences`` and ``curvature``: their own docs.
    """
    if p in _SECANT_KERNELS:
        return _SECANT_KERNELS[p]
    P = wp.constant(p)
    vecp = wp.types.vector(length=p, dtype=wp.float64)
    matp = wp.types.matrix(shape=(p, p), dtype=wp.float64)
    add_row, store_partial = normal_sums(p)[:2]

    NPAIR = wp.constant(p * (p + 1) // 2)

    @wp.func
    def pair_index(a: int, b: int):
        """The column c of the pair (a, b) (either order) among the p (p + 1) / 2 second
        derivatives (a <= b in row order)."""
        lo = wp.min(a, b)
        return lo * P - lo * (lo - 1) // 2 + wp.max(a, b) - lo

    @wp.func
    def taylor_row(store: Secant, row: int, q: int, jr: vecp, dz: vecp):
        """One row of the Jacobian at z + dz from the slot's second derivatives at z:
        J + d2T dz."""
        g = store.second[q]
        out = jr
        for a in range(P):
            for b in range(P):
                out[a] += store.d2T[row * NPAIR + pair_index(a, b), g] * dz[b]
        return out

    @wp.func
    def broyden_row(jr: vecp, dt: wp.float64, dz: vecp, inv_dz2: wp.float64):
        """One row of Broyden's update J + (dT - J dz) dz^T / (dz.dz): ``jr`` the row of J,
        ``dt`` the change of the row's value over the step ``dz`` (inv_dz2 = 1 / dz.dz, 0
        for no step)."""
        return jr + (dt - wp.dot(jr, dz)) * inv_dz2 * dz

    @wp.kernel(enable_backward=False, module="unique")
    def differences(
        act: wp.array(dtype=wp.int32),
        group: wp.array(dtype=wp.int32),
        step: wp.array2d(dtype=wp.float64),
        point: int,
        out: wp.array3d(dtype=wp.float64),
        store: Secant,
    ):
        b, s = wp.tid()
        q = act[s]
        g0 = group[s]
        inv_step = vecp()
        for a in range(P):
            inv_step[a] = wp.float64(1.0) / step[s, a]
        for f in range(b * ROW_BLOCK, wp.min(out.shape[1], (b + 1) * ROW_BLOCK)):
            for k in range(8):
                row = f * 8 + k
                t0 = wp.float64(0.0)
                if point == 1:
                    t0 = out[g0, f, k]
                    store.T[row, q] = t0
                else:
                    t0 = store.T[row, q]
                for a in range(P):
                    store.dT[row * P + a, q] = (out[g0 + point + a, f, k] - t0) * inv_step[a]
        if b == 0:
            store.fresh[q] = 1

    def make_sums(trial: bool):
        TRIAL = wp.constant(trial)

        @wp.kernel(enable_backward=False, module="unique")
        def sums_kernel(
            act: wp.array(dtype=wp.int32),
            ids: wp.array(dtype=wp.int32),
            data: Measured,
            store: Secant,
            out: wp.array3d(dtype=wp.float64),
            step: wp.array2d(dtype=wp.float64),
            dest: wp.array(dtype=wp.int32),
            partial: wp.array3d(dtype=wp.float64),
        ):
            b, s = wp.tid()
            q = act[s]
            pid = ids[s]
            e = dest[s]
            Y = data.Y
            W = data.W
            zc = data.zc[pid]
            dz = vecp()
            inv_dz2 = wp.float64(0.0)
            taylor = int(0)
            if wp.static(TRIAL):
                for a in range(P):
                    dz[a] = step[s, a]
                d2 = wp.dot(dz, dz)
                if d2 > wp.float64(0.0):
                    inv_dz2 = wp.float64(1.0) / d2
                if store.second[q] >= 0:
                    taylor = 1
            gv = vecp()
            Hm = matp()
            c2 = wp.float64(0.0)
            u2 = wp.float64(0.0)
            wrow = pid
            if W.shape[0] == 1:  # one weight row shared by every problem
                wrow = 0
            for f in range(b * ROW_BLOCK, wp.min(Y.shape[1], (b + 1) * ROW_BLOCK)):
                for k in range(8):
                    row = f * 8 + k
                    fac = coefficient_scale(k, zc)
                    jr = vecp()
                    for a in range(P):
                        jr[a] = store.dT[row * P + a, q]
                    t = store.T[row, q]
                    if wp.static(TRIAL):
                        t_new = out[s, f, k]
                        store.trial[row, e] = t_new
                        if taylor == 1:
                            jr = taylor_row(store, row, q, jr, dz)
                        else:
                            jr = broyden_row(jr, t_new - t, dz, inv_dz2)
                        t = t_new
                    w = W[wrow, f, k]
                    d = t * fac - Y[pid, f, k]
                    r = w * d
                    c2 += r * r
                    u2 += d * d
                    gv, Hm = add_row(gv, Hm, (w * fac) * jr, r)
            store_partial(partial, b, s, c2, u2, gv, Hm)

        return sums_kernel

    @wp.kernel(enable_backward=False, module="unique")
    def second_differences(
        rep: wp.array(dtype=wp.int32),
        col0: int,
        h: wp.float64,
        out: wp.array3d(dtype=wp.float64),
        store: Secant,
    ):
        """Column col0 + g of ``store.d2T``: the second derivatives of the T-matrices at the
        point of slot ``rep[g]`` (its values in ``store.T``) from the launch's group g of
        ``second_pair``'s p + p (p + 1) / 2 sets at step h (forward second differences,
        (T(z + h e_a + h e_b) - T(z + h e_a) - T(z + h e_b) + T(z)) / h^2)."""
        bl, i = wp.tid()
        q = rep[i]
        g = col0 + i
        g0 = i * (P + NPAIR)
        inv_h2 = wp.float64(1.0) / (h * h)
        for f in range(bl * ROW_BLOCK, wp.min(out.shape[1], (bl + 1) * ROW_BLOCK)):
            for k in range(8):
                row = f * 8 + k
                t0 = store.T[row, q]
                for a in range(P):
                    for b in range(a, P):
                        c = pair_index(a, b)
                        d = out[g0 + P + c, f, k] - out[g0 + a, f, k] - out[g0 + b, f, k] + t0
                        store.d2T[row * NPAIR + c, g] = d * inv_h2

    @wp.kernel(enable_backward=False, module="unique")
    def curvature(
        act: wp.array(dtype=wp.int32),
        ids: wp.array(dtype=wp.int32),
        data: Measured,
        store: Secant,
        v: wp.array2d(dtype=wp.float64),
        partial: wp.array3d(dtype=wp.float64),
    ):
        """partial[:, b, s]: row block b's part of J^T r_vv of slot act[s] along its step
        v[s], r_vv = sum_ab v_a v_b d2r/dz_a dz_b from the slot's second derivatives (0
        where it has none; :func:`reduce_rows` adds the blocks): the right-hand side of the
        geodesic acceleration (:mod:`tawarp.kernels.lm_step`)."""
        b, s = wp.tid()
        q = act[s]
        acc = vecp()
        g = store.second[q]
        if g >= 0:
            pid = ids[s]
            W = data.W
            zc = data.zc[pid]
            wrow = pid
            if W.shape[0] == 1:
                wrow = 0
            vs = vecp()
            for a in range(P):
                vs[a] = v[s, a]
            for f in range(b * ROW_BLOCK, wp.min(data.Y.shape[1], (b + 1) * ROW_BLOCK)):
                for k in range(8):
                    row = f * 8 + k
                    fac = coefficient_scale(k, zc)
                    rvv = wp.float64(0.0)
                    for a in range(P):
                        for c in range(P):
                            rvv += vs[a] * vs[c] * store.d2T[row * NPAIR + pair_index(a, c), g]
                    wf = W[wrow, f, k] * fac
                    for a in range(P):
                        acc[a] += (wf * store.dT[row * P + a, q]) * (wf * rvv)
        for a in range(P):
            partial[a, b, s] = acc[a]

    _SECANT_KERNELS[p] = SecantKernels(
        differences,
        make_sums(False),
        make_sums(True),
        broyden_row,
        taylor_row,
        second_differences,
        curvature,
    )
    return _SECANT_KERNELS[p]
