"""Engine networks on Warp: the boundary determinant, complex eigenfrequencies and onsets of
many designs at once, one thread per design (:mod:`tawarp.model.network_batch`).

The equations are those of the NumPy reference (:mod:`tawarp.model.network_reference`),
convention exp(-i omega t); the segments' A(x) is :func:`tawarp.kernels.acoustics.propagation_complex`
(the one A of every path):

* a distributed segment at uniform temperature and section is ``exp(A L)``
  (:func:`~tawarp.kernels.acoustics.expm2`); with a linear temperature or a cone, ``cells``
  sixth-order Magnus steps on three Gauss points each;
* a compliance ``[[1, 0], [Y, 1]]``, ``Y = i omega V (1 + (gamma - 1) f_k) / (gamma p_m)``,
  ``f_k = (1 + i) delta_k A_surface / (2 V)``; an inertance ``[[1, a12 l], [0, 1]]``;
* the unknowns ``(p, Zs U)`` at every branch's start and the rows of the ends and junctions
  (:func:`network_det`), in a complex matrix of at most :data:`MAX_ROWS` rows, whose
  determinant comes from Gaussian elimination with partial pivoting;
* Muller's method for an eigenfrequency, Newton's method on (omega, T_hot) for an onset, and
  the onset with the mode followed from T_cold (:func:`followed_onset_kernel`).

Tables (:class:`NetworkTables`, built by :class:`tawarp.model.network_batch.NetworkBatch`):

* per design ``seg[i, s, F]`` with the fields below (a temperature is ``T = a + b T_hot``)
  and ``design[i, D]`` (p_mean, Zs);
* shared: ``seg_kind``, ``seg_model`` (pore model), ``seg_porous`` per segment,
  ``branch_first`` (B + 1),
  and per node ``node_first`` into the incidence lists ``inc_branch``, ``inc_side``
  (0 start, 1 end), ``node_kind`` (-1 junction, else an end kind), ``node_par`` (2 numbers
  per node: the radiation coefficients of an open end, Z of an impedance end, R and V of a
  load) and ``node_seg`` (the segment whose section and temperature the end sees).
"""

import warp as wp

from .acoustics import CMat2, cmat2, expm2, identity2, magnus6_step, matmul2, part_geometry, point_coefficients
from .acoustics import propagation_complex, scale2
from .cmath import cabs, cdiv, cmul, cmuli, cplx, cscale, csqrt
from .forward import GAUSS, PI
from .gas import G_CP, G_GAMMA, conductivity, density, sound_speed_squared

wp.set_module_options({"enable_backward": False})

# segment fields
(
    F_LENGTH,
    F_AREA0,
    F_AREA1,
    F_POROSITY,
    F_PORE_RADIUS,
    F_TORTUOSITY,
    F_T0A,
    F_T0B,
    F_T1A,
    F_T1B,
    F_VOLUME,
    F_SURFACE,
) = range(12)
N_FIELDS = 12
# design fields
D_P_MEAN, D_ZS = range(2)
N_DESIGN = 2
# segment kinds
KIND_DISTRIBUTED = wp.constant(0)
KIND_COMPLIANCE = wp.constant(1)
KIND_INERTANCE = wp.constant(2)
# node kinds (-1: junction)
NODE_JUNCTION = wp.constant(-1)
END_CLOSED = wp.constant(0)
END_OPEN = wp.constant(1)
END_IMPEDANCE = wp.constant(2)
END_LOAD = wp.constant(3)
END_KINDS = {"closed": 0, "open": 1, "impedance": 2, "load": 3}
#: Most rows of the boundary matrix: two per branch, so at most 4 branches.
MAX_ROWS = 8
CMatN = wp.types.matrix(shape=(MAX_ROWS, MAX_ROWS), dtype=wp.float64)
#: The branch matrices' four entries, one row per branch (real or imaginary parts).
CMatB = wp.types.matrix(shape=(MAX_ROWS // 2, 4), dtype=wp.float64)


@wp.struct
class NetworkTables:
    """The tables of a batch (module docstring) and the Magnus ``cells`` of a segment with a
    gradient or a taper."""

    gas: wp.array(dtype=wp.float64)
    seg: wp.array3d(dtype=wp.float64)
    design: wp.array2d(dtype=wp.float64)
    seg_kind: wp.array(dtype=wp.int32)
    seg_model: wp.array(dtype=wp.int32)
    seg_porous: wp.array(dtype=wp.int32)
    branch_first: wp.array(dtype=wp.int32)
    node_first: wp.array(dtype=wp.int32)
    inc_branch: wp.array(dtype=wp.int32)
    inc_side: wp.array(dtype=wp.int32)
    node_kind: wp.array(dtype=wp.int32)
    node_par: wp.array2d(dtype=wp.float64)
    node_seg: wp.array(dtype=wp.int32)
    cells: int


@wp.func
def seg_temperature(t: NetworkTables, i: int, s: int, end: int, T_hot: wp.float64):
    """T [K] at the start (end = 0) or end (1) of segment s at hot temperature T_hot."""
    if end == 0:
        return t.seg[i, s, F_T0A] + t.seg[i, s, F_T0B] * T_hot
    return t.seg[i, s, F_T1A] + t.seg[i, s, F_T1B] * T_hot


@wp.func
def point_matrix(
    t: NetworkTables, i: int, s: int, omega: wp.vec2d, T: wp.float64, dTdx: wp.float64, area: wp.float64, porous: int
):
    """A at one point of segment s: a duct (or inertance) is one circular pore of its radius."""
    one = wp.float64(1.0)
    phi = one
    q = one
    r = wp.sqrt(area / PI)
    if porous != 0:
        phi = t.seg[i, s, F_POROSITY]
        q = t.seg[i, s, F_TORTUOSITY]
        r = t.seg[i, s, F_PORE_RADIUS]
    pc = point_coefficients(t.gas, t.design[i, D_P_MEAN], T, dTdx, phi, r, q, area, r)
    geo = part_geometry(phi, q, area, wp.float64(0.0), one)
    return propagation_complex(pc, geo, omega, t.gas[G_GAMMA], t.seg_model[s])


@wp.func
def segment_matrix(t: NetworkTables, i: int, s: int, omega: wp.vec2d, T_hot: wp.float64):
    """Transfer matrix of segment s of design i at complex omega and hot temperature T_hot."""
    T0 = seg_temperature(t, i, s, 0, T_hot)
    T1 = seg_temperature(t, i, s, 1, T_hot)
    kind = t.seg_kind[s]
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    zero = cplx(wp.float64(0.0), wp.float64(0.0))
    if kind == KIND_COMPLIANCE:
        gamma = t.gas[G_GAMMA]
        p_mean = t.design[i, D_P_MEAN]
        V = t.seg[i, s, F_VOLUME]
        fk = zero
        if t.seg[i, s, F_SURFACE] > wp.float64(0.0):
            rho = density(t.gas, T0, p_mean)
            kappa = conductivity(t.gas, T0) / (rho * t.gas[G_CP])
            dk = csqrt(cdiv(cplx(wp.float64(2.0) * kappa, wp.float64(0.0)), omega))
            fk = cscale(
                cmul(cplx(wp.float64(1.0), wp.float64(1.0)), dk), t.seg[i, s, F_SURFACE] / (wp.float64(2.0) * V)
            )
        Y = cmuli(cscale(cmul(omega, one + cscale(fk, gamma - wp.float64(1.0))), V / (gamma * p_mean)))
        return cmat2(one, zero, Y, one)
    L = t.seg[i, s, F_LENGTH]
    A0 = t.seg[i, s, F_AREA0]
    A1 = t.seg[i, s, F_AREA1]
    porous = t.seg_porous[s]
    if kind == KIND_INERTANCE or (T0 == T1 and A0 == A1):
        # one call site of A for both (the kernels' code size): an inertance is a tube
        a = point_matrix(t, i, s, omega, T0, wp.float64(0.0), A0, porous * int(kind != KIND_INERTANCE))
        if kind == KIND_INERTANCE:
            return cmat2(one, cscale(a.b, L), zero, one)
        return expm2(scale2(a, L))
    # linear temperature and radius: sixth-order Magnus steps on ``cells`` equal cells
    h = L / wp.float64(t.cells)
    dTdx = (T1 - T0) / L
    r0 = wp.sqrt(A0 / PI)
    dr = (wp.sqrt(A1 / PI) - r0) / L
    m = identity2()
    a1 = m
    a2 = m
    for k in range(3 * t.cells):
        # cell k // 3, Gauss point k % 3: one call site of A (the kernels' code size)
        c = k // 3
        g = k - 3 * c
        x = (wp.float64(c) + GAUSS[g]) * h
        r = r0 + dr * x
        a = point_matrix(t, i, s, omega, T0 + dTdx * x, dTdx, PI * r * r, porous)
        if g == 0:
            a1 = a
        elif g == 1:
            a2 = a
        else:
            m = matmul2(magnus6_step(a1, a2, a, h), m)
    return m


@wp.func
def end_impedance(t: NetworkTables, node: int, i: int, side: int, omega: wp.vec2d, T_hot: wp.float64):
    """Z [Pa s/m^3] of an open, impedance or load end node (not a closed one) that sees its
    segment at ``side`` (0 start, 1 end)."""
    kind = t.node_kind[node]
    par0 = t.node_par[node, 0]
    par1 = t.node_par[node, 1]
    if kind == END_IMPEDANCE:
        return cplx(par0, par1)
    p_mean = t.design[i, D_P_MEAN]
    if kind == END_LOAD:
        # R + i gamma p_m / (omega V)
        return cplx(par0, wp.float64(0.0)) + cmuli(cdiv(cplx(t.gas[G_GAMMA] * p_mean / par1, wp.float64(0.0)), omega))
    s = t.node_seg[node]
    T = seg_temperature(t, i, s, side, T_hot)
    area = t.seg[i, s, F_AREA0]
    if side == 1:
        area = t.seg[i, s, F_AREA1]
    c = wp.sqrt(sound_speed_squared(t.gas, T))
    ka = cscale(omega, wp.sqrt(area / PI) / c)
    z0 = density(t.gas, T, p_mean) * c / area
    # (rho c / S) (res (ka)^2 - i corr ka)
    return cscale(cscale(cmul(ka, ka), par0) - cmuli(cscale(ka, par1)), z0)


@wp.func
def branch_matrix(t: NetworkTables, i: int, b: int, omega: wp.vec2d, T_hot: wp.float64):
    m = identity2()
    for s in range(t.branch_first[b], t.branch_first[b + 1]):
        m = matmul2(segment_matrix(t, i, s, omega, T_hot), m)
    return m


@wp.func
def side_rows(m: CMat2, side: int, zs: wp.float64):
    """(p row, Zs U row) coefficients on (p0, Zs U0) of a branch at its start or end."""
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    zero = cplx(wp.float64(0.0), wp.float64(0.0))
    if side == 0:
        return one, zero, zero, one
    return m.a, cscale(m.b, wp.float64(1.0) / zs), cscale(m.c, zs), m.d


@wp.func
def put(re: CMatN, im: CMatN, r: int, c: int, v: wp.vec2d):
    re[r, c] = re[r, c] + v[0]
    im[r, c] = im[r, c] + v[1]
    return re, im


@wp.func
def complex_det(re: CMatN, im: CMatN, n: int):
    """Determinant of the leading n x n block of the complex matrix (re, im) by Gaussian
    elimination with partial pivoting."""
    det = cplx(wp.float64(1.0), wp.float64(0.0))
    for k in range(n):
        piv = k
        best = wp.float64(-1.0)
        for r in range(k, n):
            a = re[r, k] * re[r, k] + im[r, k] * im[r, k]
            if a > best:
                best = a
                piv = r
        if piv != k:
            for c in range(n):
                x = re[k, c]
                re[k, c] = re[piv, c]
                re[piv, c] = x
                x = im[k, c]
                im[k, c] = im[piv, c]
                im[piv, c] = x
            det = -det
        d = cplx(re[k, k], im[k, k])
        det = cmul(det, d)
        if best == wp.float64(0.0):
            return det
        for r in range(k + 1, n):
            f = cdiv(cplx(re[r, k], im[r, k]), d)
            for c in range(k, n):
                v = cmul(f, cplx(re[k, c], im[k, c]))
                re[r, c] = re[r, c] - v[0]
                im[r, c] = im[r, c] - v[1]
    return det


@wp.func
def stored(bm: CMatB, bi: CMatB, b: int):
    """Branch b's matrix from the scratch rows (:func:`network_det`)."""
    return cmat2(cplx(bm[b, 0], bi[b, 0]), cplx(bm[b, 1], bi[b, 1]), cplx(bm[b, 2], bi[b, 2]), cplx(bm[b, 3], bi[b, 3]))


@wp.func
def network_det(t: NetworkTables, i: int, omega: wp.vec2d, T_hot: wp.float64):
    """det of the boundary matrix of design i (:mod:`tawarp.model.network_reference`)."""
    zs = t.design[i, D_ZS]
    n_branch = t.branch_first.shape[0] - 1
    re = CMatN()
    im = CMatN()
    # the branch matrices, four complex numbers each, in the rows of two scratch matrices
    bm = CMatB()
    bi = CMatB()
    for b in range(n_branch):
        m = branch_matrix(t, i, b, omega, T_hot)
        bm[b, 0] = m.a[0]
        bi[b, 0] = m.a[1]
        bm[b, 1] = m.b[0]
        bi[b, 1] = m.b[1]
        bm[b, 2] = m.c[0]
        bi[b, 2] = m.c[1]
        bm[b, 3] = m.d[0]
        bi[b, 3] = m.d[1]
    row = int(0)
    for node in range(t.node_first.shape[0] - 1):
        k0 = t.node_first[node]
        kind = t.node_kind[node]
        if kind != NODE_JUNCTION:
            b = t.inc_branch[k0]
            side = t.inc_side[k0]
            pp, pu, up, uu = side_rows(stored(bm, bi, b), side, zs)
            sign = wp.float64(1.0)  # flow out of the network into the end
            if side == 0:
                sign = wp.float64(-1.0)
            up = cscale(up, sign)
            uu = cscale(uu, sign)
            if kind == END_CLOSED:
                re, im = put(re, im, row, 2 * b, up)
                re, im = put(re, im, row, 2 * b + 1, uu)
            else:
                zr = cscale(end_impedance(t, node, i, side, omega, T_hot), wp.float64(1.0) / zs)
                re, im = put(re, im, row, 2 * b, pp - cmul(zr, up))
                re, im = put(re, im, row, 2 * b + 1, pu - cmul(zr, uu))
            row += 1
            continue
        b0 = t.inc_branch[k0]
        p0p, p0u, u0p, u0u = side_rows(stored(bm, bi, b0), t.inc_side[k0], zs)
        flow_row = row + t.node_first[node + 1] - k0 - 1
        for k in range(k0, t.node_first[node + 1]):
            b = t.inc_branch[k]
            pp, pu, up, uu = side_rows(stored(bm, bi, b), t.inc_side[k], zs)
            if k > k0:
                # p of the first branch end minus p of this one
                r = row + k - k0 - 1
                re, im = put(re, im, r, 2 * b0, p0p)
                re, im = put(re, im, r, 2 * b0 + 1, p0u)
                re, im = put(re, im, r, 2 * b, -pp)
                re, im = put(re, im, r, 2 * b + 1, -pu)
            sign = wp.float64(1.0)  # flow into the node
            if t.inc_side[k] == 0:
                sign = wp.float64(-1.0)
            re, im = put(re, im, flow_row, 2 * b, cscale(up, sign))
            re, im = put(re, im, flow_row, 2 * b + 1, cscale(uu, sign))
        row = flow_row + 1
    return complex_det(re, im, 2 * n_branch)


@wp.kernel
def det_kernel(
    t: NetworkTables, omega: wp.array(dtype=wp.vec2d), T_hot: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.vec2d)
):
    i = wp.tid()
    out[i] = network_det(t, i, omega[i], T_hot[i])


@wp.func
def muller_root(
    t: NetworkTables, i: int, guess: wp.vec2d, T_hot: wp.float64, spread: wp.float64, rtol: wp.float64, max_iter: int
):
    """Muller's method on det(omega) at T_hot from guess (1 -+ spread) and guess (the
    reference's :func:`tawarp.model.network_reference.muller`): (omega, steps; -1 if not
    converged)."""
    x0 = cscale(guess, wp.float64(1.0) - spread)
    x1 = cscale(guess, wp.float64(1.0) + spread)
    x2 = guess
    zero = cplx(wp.float64(0.0), wp.float64(0.0))
    y0 = zero
    y1 = zero
    y2 = zero
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    xn = x0
    step = zero
    # one call site of the determinant (the kernels' code size): evaluations 0-2 are the start
    # points, each later one the new iterate
    for k in range(max_iter + 3):
        yn = network_det(t, i, xn, T_hot)
        if k == 0:
            y0 = yn
            xn = x1
            continue
        if k == 1:
            y1 = yn
            xn = x2
            continue
        if k == 2:
            y2 = yn
        else:
            x0 = x1
            x1 = x2
            x2 = xn
            y0 = y1
            y1 = y2
            y2 = yn
            if cabs(step) < rtol * cabs(x2):
                return x2, k - 2
        q = cdiv(x2 - x1, x1 - x0)
        qq = cmul(q, q)
        A = cmul(q, y2) - cmul(cmul(q, one + q), y1) + cmul(qq, y0)
        B = cmul(cscale(q, wp.float64(2.0)) + one, y2) - cmul(cmul(one + q, one + q), y1) + cmul(qq, y0)
        C = cmul(one + q, y2)
        disc = csqrt(cmul(B, B) - cscale(cmul(A, C), wp.float64(4.0)))
        den = B + disc
        if cabs(B - disc) > cabs(B + disc):
            den = B - disc
        if cabs(den) == wp.float64(0.0):
            return x2, -1
        step = -cdiv(cscale(cmul(x2 - x1, C), wp.float64(2.0)), den)
        xn = x2 + step
    return x2, -1


@wp.kernel
def eigen_kernel(
    t: NetworkTables,
    guess: wp.array(dtype=wp.vec2d),
    T_hot: wp.array(dtype=wp.float64),
    spread: wp.float64,
    rtol: wp.float64,
    max_iter: int,
    omega: wp.array(dtype=wp.vec2d),
    iterations: wp.array(dtype=wp.int32),
):
    i = wp.tid()
    w, it = muller_root(t, i, guess[i], T_hot[i], spread, rtol, max_iter)
    omega[i] = w
    iterations[i] = it


@wp.func
def newton_onset(
    t: NetworkTables,
    i: int,
    w0: wp.float64,
    T0: wp.float64,
    w_ref: wp.float64,
    T_lo: wp.float64,
    T_hi: wp.float64,
    rtol: wp.float64,
    max_iter: int,
):
    """Newton's method on det(omega, T_hot) = 0 with omega real from (w0, T0)
    (:func:`tawarp.model.network_reference.onset_newton`: the same damped steps, the
    omega-derivative complex, the T-derivative a forward difference): (omega, T_hot, steps;
    -1 where an iterate leaves [T_lo, T_hi] or moves half of w_ref from w_ref, or no
    convergence)."""
    w = w0
    T = T0
    zero = wp.float64(0.0)
    F = cplx(zero, zero)
    Fw = F
    hw = wp.float64(1e-7) * w
    hT = wp.float64(1e-7) * T
    # one call site of the determinant (the kernels' code size): per step, det at (w, T),
    # (w + hw, T) and (w, T + hT)
    for k in range(3 * max_iter):
        j = k - 3 * (k // 3)
        wj = w
        Tj = T
        if j == 1:
            wj = w + hw
        if j == 2:
            Tj = T + hT
        d = network_det(t, i, cplx(wj, zero), Tj)
        if j == 0:
            F = d
            hw = wp.float64(1e-7) * w
            hT = wp.float64(1e-7) * T
            continue
        if j == 1:
            Fw = d
            continue
        dw = cscale(Fw - F, wp.float64(1.0) / hw)
        dT = cscale(d - F, wp.float64(1.0) / hT)
        jac = dw[0] * dT[1] - dT[0] * dw[1]
        sw = (-F[0] * dT[1] + dT[0] * F[1]) / jac
        sT = (-dw[0] * F[1] + F[0] * dw[1]) / jac
        scale = wp.float64(1.0)
        if wp.abs(sw) > wp.float64(0.1) * w:
            scale = wp.min(scale, wp.float64(0.1) * w / wp.abs(sw))
        if wp.abs(sT) > wp.float64(0.1) * T:
            scale = wp.min(scale, wp.float64(0.1) * T / wp.abs(sT))
        w = w + scale * sw
        T = T + scale * sT
        if T < T_lo or T > T_hi or wp.abs(w - w_ref) > wp.float64(0.5) * w_ref:
            return w, T, -1
        if wp.abs(sw) < rtol * w and wp.abs(sT) < rtol * T:
            return w, T, k // 3 + 1
    return w, T, -1


@wp.kernel
def onset_kernel(
    t: NetworkTables,
    omega0: wp.array(dtype=wp.float64),
    T0: wp.array(dtype=wp.float64),
    T_lo: wp.float64,
    T_hi: wp.float64,
    rtol: wp.float64,
    max_iter: int,
    omega: wp.array(dtype=wp.float64),
    T_hot: wp.array(dtype=wp.float64),
    iterations: wp.array(dtype=wp.int32),
):
    """Onset (real omega, T_hot) of design i by :func:`newton_onset` from a nearby onset
    (omega0, T0), started at the real part of the design's own eigenfrequency at T0 (Muller
    from omega0)."""
    i = wp.tid()
    wc, mit = muller_root(t, i, cplx(omega0[i], wp.float64(0.0)), T0[i], wp.float64(1e-3), rtol, max_iter)
    w = wc[0]
    if mit < 0:
        w = omega0[i]
    w, T, its = newton_onset(t, i, w, T0[i], omega0[i], T_lo, T_hi, rtol, max_iter)
    omega[i] = w
    T_hot[i] = T
    iterations[i] = its


@wp.kernel
def followed_onset_kernel(
    t: NetworkTables,
    guess: wp.array(dtype=wp.vec2d),
    T_grid: wp.array(dtype=wp.float64),
    jump_tol: wp.float64,
    halvings: int,
    rtol: wp.float64,
    max_iter: int,
    omega: wp.array(dtype=wp.vec2d),
    T_hot: wp.array(dtype=wp.float64),
    jumps: wp.array(dtype=wp.int32),
    status: wp.array(dtype=wp.int32),
):
    """Onset of design i with its mode followed as T_hot rises
    (:func:`tawarp.model.network_reference.onset`, on one thread): Muller's root at each
    point of ``T_grid`` from the linear prediction of the last two, a step halved (at most
    ``halvings`` times) where the root lands farther than ``jump_tol |omega|`` from the
    prediction, a jump counted where that persists; the first crossing of Im omega from below
    between two accepted points is refined by :func:`newton_onset` from their interpolation.
    ``status``: 1 onset found, 0 none on the grid, -1 a root or Newton's method failed."""
    i = wp.tid()
    n = T_grid.shape[0]
    status[i] = 0
    jumps[i] = 0
    T_hot[i] = wp.float64(0.0)
    min_step = (T_grid[1] - T_grid[0]) / wp.pow(wp.float64(2.0), wp.float64(halvings))
    T_a = T_grid[0]
    w_a = guess[i]
    w_b = w_a  # the point before w_a, for the predictor once have_two > 0
    T_b = T_a
    have_two = int(-1)  # -1: the first root (at T_grid[0]) is still to be found
    k = int(1)  # the grid point aimed at
    step = T_grid[1] - T_grid[0]
    # one call site of Muller's method (the kernels' code size): each pass tries one step
    for attempt in range(4 * n * (halvings + 2)):
        T = T_a + step
        pred = w_a
        if have_two < 0:
            T = T_a
        elif have_two > 0:
            pred = w_a + cscale(w_a - w_b, step / (T_a - T_b))
        w, it = muller_root(t, i, pred, T, wp.float64(1e-3), rtol, max_iter)
        if it < 0:
            status[i] = -1
            omega[i] = w_a
            return
        if have_two < 0:
            w_a = w
            have_two = 0
            continue
        if cabs(w - pred) > jump_tol * cabs(w_a):
            if step / wp.float64(2.0) >= min_step:
                step = step / wp.float64(2.0)
                continue
            jumps[i] = jumps[i] + 1
            have_two = -2  # the predictor restarts after the jump
        if w_a[1] < wp.float64(0.0) and w[1] >= wp.float64(0.0):
            f = -w_a[1] / (w[1] - w_a[1])
            w0 = w_a[0] + f * (w[0] - w_a[0])
            wn, Tn, its = newton_onset(t, i, w0, T_a + f * step, w0, T_a - step, T + step, rtol, max_iter)
            omega[i] = cplx(wn, wp.float64(0.0))
            T_hot[i] = Tn
            status[i] = 1
            if its < 0:
                status[i] = -1
            return
        w_b = w_a
        T_b = T_a
        w_a = w
        T_a = T
        have_two = have_two + 1
        if have_two < 0:
            have_two = 0
        if T_grid[k] - T_a <= wp.float64(1e-12) * T_grid[k]:  # the grid point reached (to rounding)
            k = k + 1
            if k == n:
                omega[i] = w_a
                return
        step = T_grid[k] - T_a
    status[i] = -1
    omega[i] = w_a
