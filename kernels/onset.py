"""Complex-frequency eigenvalues of an engine: core between resonator ducts and end conditions.

With exp(-i omega t), a mode grows when Im omega > 0 (docs/physics.md, "Onset"). One thread per
parameter set finds omega where the end condition holds:

* each end is a row ``(a, b)`` with ``a p + b U = 0`` there (U positive towards +x):
  closed ``(0, 1)``, open ``(1, 0)``, an impedance Z of the termination (U into the
  termination): right end ``(1, -Z)``, left end ``(1, Z)``;
* the state starts at the left end as ``(p, U) = (b_L, -a_L)`` and is carried through the
  left duct, the core (:func:`core_vector`: each segment's 2x2 matrix at complex omega,
  :func:`segment_matrix_complex`, whose temperature is imposed or from the heat model) and
  the right duct; the residual is ``a_R p + b_R U`` at the right end
  (closed-closed: the Tup entry of the whole resonator's matrix);
* Muller's method from three points around the start value finds its zero
  (:func:`eigen_kernel`); :func:`residual_kernel` evaluates the residual at given points,
  for the onset's Newton refinement on (Re omega, Q) (:func:`tawarp.model.onset.onset`).

A thermal segment's Magnus cell count comes from a real reference frequency per set
(``omega_ref``), not from the iterate: the residual is then one analytic function of omega
during the search and across a batch of heat inputs (no jump of a whole cell).
"""

import warp as wp

from .acoustics import (
    CMat2,
    PartGeometry,
    expm2,
    expm2_scaled,
    identity2,
    magnus6_exponent,
    matmul2,
    parallel2,
    part_geometry,
    point_coefficients,
    propagation_complex,
    scale2,
)
from .cmath import cabs, cdiv, cmul, cplx, csqrt
from .forward import (
    CHANNEL_PART,
    CHANNEL_PORES,
    CHANNEL_SLIT,
    GAUSS,
    PI,
    TWO_PI,
    SetTable,
    channel_geometry,
    channel_model,
    channel_point,
    imposed_temperature,
    magnus_cell_count,
    pore_geometry,
    segment_geometry,
    temperature_scale,
    temperature_varies,
    thermal_radius,
)
from .gas import G_GAMMA
from .pore import PORE_CIRCULAR
from .heat import segment_heat_coeffs, segment_nonlinear, segment_profile, temperature_at
from .layout import F_IMPOSED, F_PORE_MODEL, F_THERMAL, LENGTH, P_MEAN, T_COLD, T_START, T_END, seg_value

# no adjoint code: nothing differentiates through the eigenvalue search (it has runtime-count
# loops), and generating it roughly doubles this large module's compile time
wp.set_module_options({"enable_backward": False})

END_CLOSED = wp.constant(0)
END_OPEN = wp.constant(1)
END_IMPEDANCE = wp.constant(2)
#: End kinds by their name in an engine file -> the kernels' constant.
END_KINDS = {"closed": END_CLOSED, "open": END_OPEN, "impedance": END_IMPEDANCE}

# resonator table columns: left duct (length [m], radius [m], temperature [K]), right duct
R_LEFT_LENGTH, R_LEFT_RADIUS, R_LEFT_T, R_RIGHT_LENGTH, R_RIGHT_RADIUS, R_RIGHT_T = range(6)
N_RESONATOR = 6


@wp.struct
class HeatedCore:
    """A batch of cores after their heat solve, as the complex-frequency kernels read it:
    ``sets`` the parameter table (:class:`tawarp.kernels.forward.SetTable`), ``theta``
    (n, nodes) the nodal excess temperatures [K] of :func:`tawarp.kernels.forward.heat_kernel`,
    whose heat cells start at segment ``first``, ``heat_cells`` per thermal segment;
    ``seg_cells`` (segments,) the Magnus cells of each segment whose temperature varies, 0
    where :func:`tawarp.kernels.forward.magnus_cell_count` sizes them at ``cell_density``."""

    sets: SetTable
    theta: wp.array2d(dtype=wp.float64)
    first: int
    heat_cells: int
    seg_cells: wp.array(dtype=wp.int32)
    cell_density: wp.float64


@wp.struct
class Resonator:
    """The resonator around a batch of cores: ``ducts`` (n, N_RESONATOR) the left and right
    ducts of each set (columns R_*), ``ends`` the kinds (END_*) of the left and right end,
    ``z_left``, ``z_right`` the impedance tables (freq [Hz], Z_re, Z_im) of impedance ends
    (:func:`table_impedance`)."""

    ducts: wp.array2d(dtype=wp.float64)
    ends: wp.array(dtype=wp.int32)
    z_left: wp.array2d(dtype=wp.float64)
    z_right: wp.array2d(dtype=wp.float64)


@wp.func
def mat_vec(m: CMat2, p: wp.vec2d, u: wp.vec2d):
    """m (p, U)."""
    return cmul(m.a, p) + cmul(m.b, u), cmul(m.c, p) + cmul(m.d, u)


@wp.func
def duct_step(
    gas: wp.array(dtype=wp.float64),
    p_mean: wp.float64,
    omega: wp.vec2d,
    T: wp.float64,
    radius: wp.float64,
    length: wp.float64,
    p: wp.vec2d,
    u: wp.vec2d,
):
    """(p, U) carried through an empty duct of ``length`` [m], ``radius`` [m] at uniform T [K]:
    exp(A L), the closed form of docs/physics.md."""
    area = PI * radius * radius
    one = wp.float64(1.0)
    pc = point_coefficients(gas, p_mean, T, wp.float64(0.0), one, radius, one, area, radius)
    a = propagation_complex(pc, part_geometry(one, one, area, wp.float64(0.0), one), omega, gas[G_GAMMA], PORE_CIRCULAR)
    return mat_vec(expm2(scale2(a, length)), p, u)


@wp.func
def segment_matrix_complex(core: HeatedCore, i: int, s: int, omega: wp.vec2d, omega_ref: wp.float64):
    """The 2x2 transfer matrix of segment s of parameter set i at complex angular frequency
    omega [rad/s] (re, im), exp(-i omega t): (p, U) at its end = M (p, U) at its start.

    Its temperature is its imposed profile (T_start to T_end), the heat model's (thermal
    segments, from the nodal excess ``core.theta``) or T_cold. At uniform temperature
    M = exp(A L) (the closed form of docs/physics.md); where it varies, the sixth-order
    Magnus cells of the forward cascade: ``core.seg_cells[s]``, or where 0
    :func:`tawarp.kernels.forward.magnus_cell_count` at ``core.cell_density`` and the real
    ``omega_ref`` [rad/s] (not omega: M is then one analytic function of omega). A segment
    with a bypass gap is its pores and its slit side by side (:func:`gap_matrix_complex`).
    Batched engines of any topology build on this matrix."""
    geo = segment_geometry(core.sets.params, core.sets.flags, i, s)
    if geo.gap_share > wp.float64(0.0):
        return gap_matrix_complex(core, i, s, omega, omega_ref, geo)
    m, tau, sigma = channel_matrix_complex(core, i, s, omega, omega_ref, geo, CHANNEL_PART)
    return m


@wp.func(inline=False)  # a bypass gap's segment: kept out of the walk's inlined code
def gap_matrix_complex(core: HeatedCore, i: int, s: int, omega: wp.vec2d, omega_ref: wp.float64, geo: PartGeometry):
    """:func:`segment_matrix_complex` of a segment with a bypass gap (geometry ``geo``): its
    pores and its slit (:func:`tawarp.kernels.forward.channel_geometry`), each over the
    segment's cells, their admittance matrices added at its ends
    (:func:`tawarp.kernels.acoustics.parallel2`), as the forward cascade's ``gap_segment``."""
    mp, tp, sp = channel_matrix_complex(core, i, s, omega, omega_ref, geo, CHANNEL_PORES)
    mg, tg, sg = channel_matrix_complex(core, i, s, omega, omega_ref, geo, CHANNEL_SLIT)
    return parallel2(
        mp,
        tp + wp.vec2d(sp, wp.float64(0.0)),
        tp * wp.float64(2.0),
        mg,
        tg + wp.vec2d(sg, wp.float64(0.0)),
        tg * wp.float64(2.0),
    )


@wp.func
def cell_matrix_complex(om: CMat2, channel: int):
    """(E, tau, sigma) of one cell's exponent ``om``, exp(om) = e^(tau + sigma) E: a part as
    it stands takes exp(om) itself (tau = sigma = 0), a channel beside a bypass gap its
    scaled form (:func:`tawarp.kernels.acoustics.expm2_scaled`: the slit's never overflows)."""
    if channel == CHANNEL_PART:
        return expm2(om), wp.vec2d(wp.float64(0.0), wp.float64(0.0)), wp.float64(0.0)
    return expm2_scaled(om)


@wp.func
def channel_matrix_complex(
    core: HeatedCore, i: int, s: int, omega: wp.vec2d, omega_ref: wp.float64, geo: PartGeometry, channel: int
):
    """(M, tau, sigma) of ``channel`` of segment s (geometry ``geo``; CHANNEL_PART: the
    segment as it stands) at complex omega, its matrix e^(tau + sigma) M with det e^(2 tau)
    (:func:`cell_matrix_complex`)."""
    params = core.sets.params
    flags = core.sets.flags
    gas = core.sets.gas
    p_mean = params[P_MEAN, i]
    T_cold = params[T_COLD, i]
    gamma = gas[G_GAMMA]
    length = seg_value(params, i, s, LENGTH)
    phi, r, q = pore_geometry(params, flags, i, s)
    r_k = thermal_radius(params, flags, i, s, r)
    cgeo = channel_geometry(geo, channel)
    model = channel_model(flags[s, F_PORE_MODEL], channel)
    if not temperature_varies(params, flags, i, s):
        T = T_cold
        if flags[s, F_IMPOSED] != 0:
            T = seg_value(params, i, s, T_START)
        pc = channel_point(point_coefficients(gas, p_mean, T, wp.float64(0.0), phi, r, q, geo.area, r_k), geo, channel)
        return cell_matrix_complex(scale2(propagation_complex(pc, cgeo, omega, gamma, model), length), channel)
    lam, k, sigma = segment_heat_coeffs(params, flags, gas, i, s)
    nonlin = segment_nonlinear(params, i, s)
    n_cells = core.seg_cells[s]
    if n_cells == 0:
        k_T, c = temperature_scale(params, flags, gas, i, s)
        n_cells = magnus_cell_count(core.cell_density, k_T, length, omega_ref, c)
    h = length / wp.float64(n_cells)
    m = identity2()
    tau = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    scale = wp.float64(0.0)
    for c in range(n_cells):
        x0 = wp.float64(c) * h
        a1 = gradient_matrix_complex(core, i, s, k, sigma, nonlin, x0 + GAUSS[0] * h, omega, r, r_k, geo, channel)
        a2 = gradient_matrix_complex(core, i, s, k, sigma, nonlin, x0 + GAUSS[1] * h, omega, r, r_k, geo, channel)
        a3 = gradient_matrix_complex(core, i, s, k, sigma, nonlin, x0 + GAUSS[2] * h, omega, r, r_k, geo, channel)
        e, cell_tau, cell_sigma = cell_matrix_complex(magnus6_exponent(a1, a2, a3, h), channel)
        m = matmul2(e, m)
        tau = tau + cell_tau
        scale = scale + cell_sigma
    return m, tau, scale


@wp.func
def gradient_matrix_complex(
    core: HeatedCore,
    i: int,
    s: int,
    k: wp.float64,
    sigma: wp.float64,
    nonlin: int,
    xi: wp.float64,
    omega: wp.vec2d,
    r: wp.float64,
    r_k: wp.float64,
    geo: PartGeometry,
    channel: int,
):
    """A(x) of ``channel`` (:func:`channel_matrix_complex`) at complex omega and local
    position xi [m] of segment s whose temperature varies: its imposed profile, or the heat
    model's with the segment's (k, sigma) and ``nonlin``
    (:func:`tawarp.kernels.heat.segment_profile`)."""
    params = core.sets.params
    flags = core.sets.flags
    gas = core.sets.gas
    heat_cells = core.heat_cells
    T = wp.float64(0.0)
    dT = wp.float64(0.0)
    if flags[s, F_IMPOSED] != 0:
        T, dT = imposed_temperature(params, i, s, xi)
    else:
        dh = seg_value(params, i, s, LENGTH) / wp.float64(heat_cells)
        node0 = (s - core.first) * heat_cells
        th, dth = segment_profile(params, flags, gas, core.theta, i, s, node0, heat_cells, k, sigma, dh, nonlin, xi)
        T = params[T_COLD, i] + th
        dT = dth
    pc = point_coefficients(gas, params[P_MEAN, i], T, dT, geo.porosity, r, geo.tortuosity, geo.area, r_k)
    return propagation_complex(
        channel_point(pc, geo, channel),
        channel_geometry(geo, channel),
        omega,
        gas[G_GAMMA],
        channel_model(flags[s, F_PORE_MODEL], channel),
    )


@wp.func
def core_vector(core: HeatedCore, i: int, omega: wp.vec2d, omega_ref: wp.float64, p_in: wp.vec2d, u_in: wp.vec2d):
    """(p, U) at x6 from (p, U) at x1 through the core of set i at complex omega: each
    segment's :func:`segment_matrix_complex` in turn (the cells of ``transfer_kernel``).
    Adaptive cell counts use the real ``omega_ref`` [rad/s]."""
    # loop-carried state as fresh locals (Warp carries reassigned variables through dynamic loops)
    p = wp.vec2d(p_in[0], p_in[1])
    u = wp.vec2d(u_in[0], u_in[1])
    for s in range(core.sets.flags.shape[0]):
        p, u = mat_vec(segment_matrix_complex(core, i, s, omega, omega_ref), p, u)
    return p, u


@wp.func
def table_impedance(table: wp.array2d(dtype=wp.float64), omega: wp.vec2d):
    """Z [Pa s/m^3] from rows (freq [Hz], Z_re, Z_im): linear in frequency on the interval
    holding Re omega / 2 pi (the end intervals extend beyond the table); a linear function is
    analytic, so it continues to complex omega as it stands. One row: a constant."""
    n = table.shape[0]
    z0 = cplx(table[0, 1], table[0, 2])
    if n == 1:
        return z0
    f_re = omega[0] / TWO_PI
    j = int(0)
    while j < n - 2 and table[j + 1, 0] <= f_re:
        j = j + 1
    za = cplx(table[j, 1], table[j, 2])
    zb = cplx(table[j + 1, 1], table[j + 1, 2])
    t = cplx(
        (omega[0] / TWO_PI - table[j, 0]) / (table[j + 1, 0] - table[j, 0]),
        omega[1] / TWO_PI / (table[j + 1, 0] - table[j, 0]),
    )
    return za + cmul(zb - za, t)


@wp.func
def end_row(kind: int, table: wp.array2d(dtype=wp.float64), omega: wp.vec2d, sign: wp.float64):
    """(a, b) of ``a p + b U = 0`` at an end; ``sign`` = +1 at the left end, -1 at the right
    (Z relates p to the volume velocity flowing out of the resonator)."""
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    zero = cplx(wp.float64(0.0), wp.float64(0.0))
    if kind == END_CLOSED:
        return zero, one
    if kind == END_OPEN:
        return one, zero
    z = table_impedance(table, omega)
    return one, cplx(sign * z[0], sign * z[1])


@wp.func
def engine_residual(core: HeatedCore, res: Resonator, i: int, omega: wp.vec2d, omega_ref: wp.float64):
    """a_R p + b_R U at the right end of set i for the state that meets the left end condition."""
    gas = core.sets.gas
    ducts = res.ducts
    p_mean = core.sets.params[P_MEAN, i]
    a_l, b_l = end_row(res.ends[0], res.z_left, omega, wp.float64(1.0))
    p = b_l
    u = -a_l
    p, u = duct_step(gas, p_mean, omega, ducts[i, R_LEFT_T], ducts[i, R_LEFT_RADIUS], ducts[i, R_LEFT_LENGTH], p, u)
    p, u = core_vector(core, i, omega, omega_ref, p, u)
    p, u = duct_step(gas, p_mean, omega, ducts[i, R_RIGHT_T], ducts[i, R_RIGHT_RADIUS], ducts[i, R_RIGHT_LENGTH], p, u)
    a_r, b_r = end_row(res.ends[1], res.z_right, omega, wp.float64(-1.0))
    return cmul(a_r, p) + cmul(b_r, u)


@wp.kernel
def eigen_kernel(
    core: HeatedCore,
    res: Resonator,
    guess: wp.array(dtype=wp.vec2d),
    omega_ref: wp.array(dtype=wp.float64),
    spread: wp.float64,
    tol: wp.float64,
    max_iter: int,
    omega_out: wp.array(dtype=wp.vec2d),
    iterations: wp.array(dtype=wp.int32),
    evaluations: wp.array(dtype=wp.int32),
):
    """omega_out[i]: the zero of :func:`engine_residual` nearest ``guess[i]`` [rad/s] by
    Muller's method from guess (1 -+ spread) and guess; stops when a step is below
    ``tol`` |omega|. iterations[i]: steps taken, or -1 when max_iter steps did not converge;
    evaluations[i]: residual (cascade) evaluations made."""
    i = wp.tid()
    w_ref = omega_ref[i]
    g = guess[i]
    zero = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    x0 = g - wp.vec2d(spread * g[0], spread * g[1])
    x1 = g + wp.vec2d(spread * g[0], spread * g[1] + spread * g[0])
    x2 = g
    f0 = zero
    f1 = zero
    f2 = zero
    # one call site of the residual (it is large: inlined once, the kernel compiles fast);
    # evaluations 0 and 1 only fill f0 and f1 at the start points, then each further one
    # is at Muller's new point x2
    done = int(-1)
    count = int(0)
    for it in range(max_iter + 2):
        if done < 0:
            count = count + 1
            x = x2
            if it == 0:
                x = x0
            elif it == 1:
                x = x1
            fx = engine_residual(core, res, i, x, w_ref)
            if it == 0:
                f0 = fx
            elif it == 1:
                f1 = fx
            else:
                f2 = fx
                h1 = x1 - x0
                h2 = x2 - x1
                d1 = cdiv(f1 - f0, h1)
                d2 = cdiv(f2 - f1, h2)
                a = cdiv(d2 - d1, h2 + h1)
                b = cmul(a, h2) + d2
                root = csqrt(cmul(b, b) - wp.float64(4.0) * cmul(f2, a))
                e = b + root
                if cabs(b - root) > cabs(e):
                    e = b - root
                step = zero
                if cabs(e) > wp.float64(0.0):
                    step = cdiv(wp.float64(-2.0) * f2, e)
                x0 = x1
                f0 = f1
                x1 = x2
                f1 = f2
                x2 = x2 + step
                if cabs(step) <= tol * cabs(x2):
                    done = it - 1
    omega_out[i] = x2
    iterations[i] = done
    evaluations[i] = count


@wp.kernel
def residual_kernel(
    core: HeatedCore,
    res: Resonator,
    column: wp.array(dtype=wp.int32),
    omega: wp.array(dtype=wp.vec2d),
    omega_ref: wp.array(dtype=wp.float64),
    out: wp.array(dtype=wp.vec2d),
):
    """out[j]: :func:`engine_residual` of parameter set ``column[j]`` (its params, theta,
    resonator row and ``omega_ref`` [rad/s]) at complex ``omega[j]`` [rad/s]: one evaluation
    per thread, for the onset's Newton refinement (finite differences in omega and Q)."""
    j = wp.tid()
    i = column[j]
    out[j] = engine_residual(core, res, i, omega[j], omega_ref[i])


@wp.kernel
def hot_kernel(core: HeatedCore, out: wp.array(dtype=wp.float64)):
    """out[i]: the largest steady temperature [K] of set i, imposed temperatures included. In
    each heat cell the profile
    has at most one interior maximum (a cosh plus a constant, or the Kirchhoff cell's
    smooth profile): the cell's ends, and where dT/dx goes from > 0 to < 0 across the cell,
    the zero of dT/dx by bisection (60 halvings: the cell length times 1e-18)."""
    i = wp.tid()
    params = core.sets.params
    flags = core.sets.flags
    gas = core.sets.gas
    theta = core.theta
    first = core.first
    heat_cells = core.heat_cells
    best = params[T_COLD, i]
    for s in range(flags.shape[0]):
        if flags[s, F_IMPOSED] != 0:
            best = wp.max(best, wp.max(seg_value(params, i, s, T_START), seg_value(params, i, s, T_END)))
        if flags[s, F_THERMAL] != 0:
            dh = seg_value(params, i, s, LENGTH) / wp.float64(heat_cells)
            for c in range(heat_cells):
                a = wp.float64(c) * dh
                b = a + dh
                ta, da = temperature_at(params, flags, gas, theta, i, s, first, heat_cells, a)
                tb, db = temperature_at(params, flags, gas, theta, i, s, first, heat_cells, b)
                best = wp.max(best, wp.max(ta, tb))
                if da > wp.float64(0.0) and db < wp.float64(0.0):
                    for it in range(60):
                        mid = wp.float64(0.5) * (a + b)
                        tm, dm = temperature_at(params, flags, gas, theta, i, s, first, heat_cells, mid)
                        if dm > wp.float64(0.0):
                            a = mid
                        else:
                            b = mid
                    mid = wp.float64(0.5) * (a + b)
                    tm, dm = temperature_at(params, flags, gas, theta, i, s, first, heat_cells, mid)
                    best = wp.max(best, tm)
    out[i] = best
