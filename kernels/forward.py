"""The forward kernels: parameter expansion, heat solve, T-matrix cascade, profiles.

Launch order for a batch of n parameter sets and m frequencies:

1. :func:`expand_parameters` (n threads) fills the (rows, n) table from the core's base
   values and the rows that vary.
2. :func:`heat_kernel` (n threads) solves the tridiagonal heat model once per set: the
   profile is shared by all m frequencies (measured faster than solving it in every
   (set, frequency) thread, see bench/forward.py).
3. :func:`make_transfer_kernel` (n m threads, and n s more for the error estimate): one
   thread per (set, frequency) cascades the segment matrices from x1 to x6.
4. :func:`step_doubling_error` (n threads) compares the s sampled frequencies at the
   chosen and at twice the cell density; only the sets above the target are gathered
   (``kernels/batch.py``) and run again, at a raised density.
"""

import warp as wp

from .acoustics import CMat2, expm2, identity2, magnus6_step, matmul2, propagation_matrix, scale2
from .cmath import cabs
from .gas import G_GAMMA, G_R, sound_speed_squared
from .heat import segment_heat_coeffs, segment_nonlinear, segment_profile, solve_heat, temperature_at
from .layout import (F_POROUS, F_PORE_MODEL, F_THERMAL, LENGTH, P_MEAN, PORE_RADIUS, POROSITY, RADIUS, T_COLD,
                     FRAME_MOBILITY, THERMAL_RADIUS_RATIO, TORTUOSITY, VISCOUS_SHAPE_FACTOR, seg_value)

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

TWO_PI = wp.constant(wp.float64(6.283185307179586))
PI = wp.constant(wp.float64(3.141592653589793))
# Gauss-Legendre points of [0, 1] for the three-point rule: 1/2 - sqrt(15)/10, 1/2, 1/2 + sqrt(15)/10
GAUSS_1 = wp.constant(wp.float64(0.1127016653792583))
GAUSS_2 = wp.constant(wp.float64(0.5))
GAUSS_3 = wp.constant(wp.float64(0.8872983346207417))


@wp.kernel
def expand_parameters(base: wp.array(dtype=wp.float64), varying: wp.array2d(dtype=wp.float64),
                      rows: wp.array(dtype=wp.int32), params: wp.array2d(dtype=wp.float64)):
    """params[:, i] = base, then params[rows[v], i] = varying[v, i]."""
    i = wp.tid()
    for r in range(base.shape[0]):
        params[r, i] = base[r]
    for v in range(rows.shape[0]):
        params[rows[v], i] = varying[v, i]


@wp.kernel
def heat_kernel(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32),
                gas: wp.array(dtype=wp.float64), first: int, count: int, heat_cells: int, fitted: int,
                max_iter: int, tol: wp.float64,
                theta: wp.array2d(dtype=wp.float64), scratch: wp.array2d(dtype=wp.float64)):
    i = wp.tid()
    solve_heat(params, flags, gas, i, first, count, heat_cells, fitted, max_iter, tol, theta, scratch)


@wp.func
def pore_geometry(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32), i: int, s: int):
    """(porosity, pore radius [m], tortuosity) of segment s; a duct is one circular pore
    of the tube's radius."""
    if flags[s, F_POROUS] == 0:
        return wp.float64(1.0), params[RADIUS, i], wp.float64(1.0)
    return seg_value(params, i, s, POROSITY), seg_value(params, i, s, PORE_RADIUS), seg_value(params, i, s, TORTUOSITY)


@wp.func
def thermal_radius(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32), i: int, s: int,
                   r: wp.float64):
    """Radius [m] of the thermal function f_k: r times ``thermal_radius_ratio`` in a porous
    segment (a ratio <= 0 counts as 1), r in a duct."""
    if flags[s, F_POROUS] == 0:
        return r
    ratio = seg_value(params, i, s, THERMAL_RADIUS_RATIO)
    if ratio <= wp.float64(0.0):
        return r
    return r * ratio


@wp.func
def shape_factor(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32), i: int, s: int):
    """Viscous shape factor r/Lambda of a porous segment (1 = circular pore; a duct: 1)."""
    if flags[s, F_POROUS] == 0:
        return wp.float64(1.0)
    return seg_value(params, i, s, VISCOUS_SHAPE_FACTOR)


@wp.func
def frame_mobility(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32), i: int, s: int):
    """1/rho_frame [m^3/kg] of a limp-frame porous segment; 0 (rigid) for a duct."""
    if flags[s, F_POROUS] == 0:
        return wp.float64(0.0)
    return seg_value(params, i, s, FRAME_MOBILITY)


@wp.func
def gradient_matrix(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32),
                    gas: wp.array(dtype=wp.float64), theta: wp.array2d(dtype=wp.float64), i: int, s: int, node0: int,
                    heat_cells: int, k: wp.float64, sigma: wp.float64, dh: wp.float64, xi: wp.float64,
                    p_mean: wp.float64, omega: wp.float64, T_cold: wp.float64, phi: wp.float64, r: wp.float64,
                    q: wp.float64, model: int, area: wp.float64, r_k: wp.float64, mob: wp.float64, sf: wp.float64,
                    nonlin: int, pore_table: wp.array(dtype=wp.float64)):
    """A(x) at local position xi [m] of thermal segment s whose heat cells start at node0;
    (k, sigma) are the segment's (unused when ``nonlin``: the Kirchhoff cell's profile,
    :func:`tawarp.kernels.heat.nonlinear_profile`)."""
    th, dth = segment_profile(params, flags, gas, theta, i, s, node0, heat_cells, k, sigma, dh, nonlin, xi)
    return propagation_matrix(gas, p_mean, omega, T_cold + th, dth, phi, r, q, model, area, r_k, mob, sf, pore_table)


@wp.func
def store_matrix(out: wp.array3d(dtype=wp.float64), i: int, j: int, m: CMat2):
    """out[i, j] = (Tpp, Tpu, Tup, Tuu) of m as (re, im) pairs."""
    out[i, j, 0] = m.a[0]
    out[i, j, 1] = m.a[1]
    out[i, j, 2] = m.b[0]
    out[i, j, 3] = m.b[1]
    out[i, j, 4] = m.c[0]
    out[i, j, 5] = m.c[1]
    out[i, j, 6] = m.d[0]
    out[i, j, 7] = m.d[1]


@wp.func
def dimensionless(out: wp.array3d(dtype=wp.float64), i: int, j: int, c: int, zc: wp.float64):
    """Coefficient c of (Tpp, Tpu / Zc, Tup Zc, Tuu) of out[i, j], as
    :func:`tawarp.model.coefficients.normalize` rounds it (a division for Tpu)."""
    y = wp.vec2d(out[i, j, 2 * c], out[i, j, 2 * c + 1])
    if c == 1:
        y = wp.vec2d(y[0] / zc, y[1] / zc)
    elif c == 2:
        y = wp.vec2d(y[0] * zc, y[1] * zc)
    return y


@wp.kernel
def step_doubling_error(params: wp.array2d(dtype=wp.float64), gas: wp.array(dtype=wp.float64),
                        out: wp.array3d(dtype=wp.float64), doubled: wp.array3d(dtype=wp.float64),
                        sample: wp.array(dtype=wp.int32), err: wp.array(dtype=wp.float64)):
    """err[i] = max over k of max_c |Y_c - Y2_c| / max_c |Y2_c| (dimensionless), Y the
    coefficients (Tpp, Tpu/Zc, Tup Zc, Tuu) of out[i, sample[k]] (cell density d) and Y2
    those of doubled[i, k] (2d), Zc = p_mean / (c_cold S) [Pa s/m^3] the cold duct's
    impedance of set i. NaN where a coefficient is not finite (as NumPy's max): such a set
    is not refined, the validity checks name it."""
    i = wp.tid()
    radius = params[RADIUS, i]
    zc = params[P_MEAN, i] / wp.sqrt(gas[G_R] * params[T_COLD, i] / gas[G_GAMMA]) / (PI * radius * radius)
    worst = wp.float64(0.0)
    finite = int(1)
    for k in range(sample.shape[0]):
        gap = wp.float64(0.0)
        size = wp.float64(0.0)
        for c in range(4):
            y2 = dimensionless(doubled, i, k, c, zc)
            dy = cabs(dimensionless(out, i, sample[k], c, zc) - y2)
            a2 = cabs(y2)
            if wp.isnan(dy) or wp.isnan(a2):
                finite = 0
            gap = wp.max(gap, dy)
            size = wp.max(size, a2)
        worst = wp.max(worst, gap / size)
    if finite == 0:
        worst = wp.float64(wp.nan)
    err[i] = worst


@wp.func
def magnus_cell_count(density: wp.float64, k: wp.float64, length: wp.float64, omega: wp.float64,
                      c_cold: wp.float64):
    """Magnus cells of a thermal segment of length ``length`` [m] at cell density ``density``:
    ceil(density (1 + k L + omega L / c_cold)), k [1/m] the heat model's decay rate, omega
    [rad/s], c_cold [m/s]: the profile varies on the scale 1/k and the wave on c/omega, and a
    sixth-order cell's error scales with the sixth power of its length over those scales.
    The one rule of the cascade, the onset's walk (:mod:`tawarp.kernels.onset`) and the
    fits' fixed counts (:func:`tawarp.kernels.lm.magnus_cells`)."""
    return int(wp.ceil(density * (wp.float64(1.0) + k * length + omega * length / c_cold)))


def make_transfer_kernel(nonlinear: bool, max_registers: int | None = None):
    """The cascade kernel (below), compiled for a linear heat model only (``nonlinear``
    False: the Kirchhoff profile of the temperature-dependent effects is left out, which
    frees registers on the GPU) or for both; ``max_registers`` caps the registers of a
    CUDA thread (``__maxnreg__``)."""

    def transfer_kernel(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32),
                        gas: wp.array(dtype=wp.float64), theta: wp.array2d(dtype=wp.float64),
                        freqs: wp.array(dtype=wp.float64), seg_cells: wp.array(dtype=wp.int32),
                        cell_density: wp.array(dtype=wp.float64), first: int, heat_cells: int,
                        pore_table: wp.array(dtype=wp.float64),
                        out: wp.array3d(dtype=wp.float64), doubled: wp.array3d(dtype=wp.float64)):
        """out[i, j] = (Tpp, Tpu, Tup, Tuu) as (re, im) pairs: the core T-matrix of set i at
        frequency freqs[j] [Hz], j < m = out.shape[1]; doubled[i, k] the same at frequency
        freqs[m + k] and twice the cell density (the step-doubling error estimate,
        k < doubled.shape[1]). Launched on n (m + doubled.shape[1]) threads, the doubled ones
        first: they run longest, and in warps of their own they hold up no short thread.
        A thermal segment gets seg_cells[s] Magnus cells, or, where that is 0,
        ceil(cell_density[i] (1 + k L + w L / c_cold)) cells (twice that density for
        ``doubled``): the profile varies on the scale 1/k of the heat model and the wave on
        c/w, and the sixth-order error of a cell scales with the sixth power of its length
        over those scales. ``pore_table``:
        :func:`tawarp.kernels.pore_table.circular_table` on the kernel's device."""
        t = wp.tid()
        n_freqs = out.shape[1]
        n_doubled = out.shape[0] * doubled.shape[1]
        i = (t - n_doubled) // n_freqs
        j = (t - n_doubled) % n_freqs
        density_factor = wp.float64(1.0)
        if t < n_doubled:
            i = t // doubled.shape[1]
            j = n_freqs + t % doubled.shape[1]
            density_factor = wp.float64(2.0)
        omega = TWO_PI * freqs[j]
        p_mean = params[P_MEAN, i]
        radius = params[RADIUS, i]
        area = PI * radius * radius
        T_cold = params[T_COLD, i]
        m = identity2()
        for s in range(flags.shape[0]):
            length = seg_value(params, i, s, LENGTH)
            phi, r, q = pore_geometry(params, flags, i, s)
            r_k = thermal_radius(params, flags, i, s, r)
            mob = frame_mobility(params, flags, i, s)
            sf = shape_factor(params, flags, i, s)
            model = flags[s, F_PORE_MODEL]
            if flags[s, F_THERMAL] == 0:
                a = propagation_matrix(gas, p_mean, omega, T_cold, wp.float64(0.0), phi, r, q, model, area, r_k, mob, sf,
                                       pore_table)
                m = matmul2(expm2(scale2(a, length)), m)
            else:
                lam, k, sigma = segment_heat_coeffs(params, flags, gas, i, s)
                dh = length / wp.float64(heat_cells)
                node0 = (s - first) * heat_cells
                nonlin = 0
                if wp.static(nonlinear):   # compiled out of the linear kernel: fewer registers on the GPU
                    nonlin = segment_nonlinear(params, i, s)
                n_cells = seg_cells[s]
                if n_cells == 0:
                    c_cold = wp.sqrt(sound_speed_squared(gas, T_cold))
                    n_cells = magnus_cell_count(density_factor * cell_density[i], k, length, omega, c_cold)
                h = length / wp.float64(n_cells)
                for c in range(n_cells):
                    x0 = wp.float64(c) * h
                    a1 = gradient_matrix(params, flags, gas, theta, i, s, node0, heat_cells, k, sigma, dh, x0 + GAUSS_1 * h,
                                         p_mean, omega, T_cold, phi, r, q, model, area, r_k, mob, sf, nonlin, pore_table)
                    a2 = gradient_matrix(params, flags, gas, theta, i, s, node0, heat_cells, k, sigma, dh, x0 + GAUSS_2 * h,
                                         p_mean, omega, T_cold, phi, r, q, model, area, r_k, mob, sf, nonlin, pore_table)
                    a3 = gradient_matrix(params, flags, gas, theta, i, s, node0, heat_cells, k, sigma, dh, x0 + GAUSS_3 * h,
                                         p_mean, omega, T_cold, phi, r, q, model, area, r_k, mob, sf, nonlin, pore_table)
                    m = matmul2(magnus6_step(a1, a2, a3, h), m)
        if j < n_freqs:
            store_matrix(out, i, j, m)
        else:
            store_matrix(doubled, i, j - n_freqs, m)

    kw = {} if max_registers is None else {"cuda_max_registers": int(max_registers)}
    # a unique module does not inherit this file's module options
    return wp.kernel(transfer_kernel, module="unique", enable_backward=False, **kw)


@wp.kernel
def profile_kernel(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32),
                   gas: wp.array(dtype=wp.float64), theta: wp.array2d(dtype=wp.float64),
                   first: int, heat_cells: int, x: wp.array(dtype=wp.float64),
                   T: wp.array2d(dtype=wp.float64), dTdx: wp.array2d(dtype=wp.float64)):
    """T(x) [K] and dT/dx [K/m] of set i at positions x[j] [m] from plane x1 (the
    cold temperature outside the thermal segments)."""
    i, j = wp.tid()
    start = wp.float64(0.0)
    T[i, j] = params[T_COLD, i]
    dTdx[i, j] = wp.float64(0.0)
    for s in range(flags.shape[0]):
        length = seg_value(params, i, s, LENGTH)
        xi = x[j] - start
        if flags[s, F_THERMAL] != 0 and xi >= wp.float64(0.0) and xi <= length:
            t, dt = temperature_at(params, flags, gas, theta, i, s, first, heat_cells, xi)
            T[i, j] = t
            dTdx[i, j] = dt
        start = start + length
