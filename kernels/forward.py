"""The forward kernels: parameter expansion, heat solve, T-matrix cascade, profiles.

Launch order for a batch of n parameter sets and m frequencies:

1. :func:`expand_parameters` (n threads) fills the (rows, n) table from the core's base
   values and the rows that vary.
2. :func:`heat_kernel` (n threads) solves the tridiagonal heat model once per set: the
   profile is shared by all m frequencies (measured faster than solving it in every
   (set, frequency) thread, see bench/forward.py). On a GPU the iterations of a
   temperature-dependent set run as launches of their own instead, :func:`heat_rows_kernel`
   (a thread per heat cell) and :func:`picard_kernel` (a thread per set) in turn.
3. :func:`cell_counts` (n threads) sizes each set's Magnus cells and grades their grids to
   the heat model's excess (:func:`cell_grid`), and :func:`make_point_kernel` (n C threads,
   C a set's cells) computes the frequency-independent factors of A
   (:class:`tawarp.kernels.acoustics.PointCoefficients`: temperature profile, gas
   properties, pore scales) at every Gauss point of the set once, for all its frequencies.
4. :func:`cascade_keys` and a radix sort order the sets by their cells, and
   :func:`make_transfer_kernel` (n m threads, and n s more for the error estimate): one
   thread per (set, frequency) cascades the segment matrices from x1 to x6 from those
   points, adding only what depends on the frequency (pore functions, Magnus steps).
5. :func:`refined_error` (n threads) compares the s sampled frequencies on the set's cells
   and on the refined grid (:func:`refined_cells`); only the sets above the target are
   raised (:func:`raise_density`), gathered (``kernels/batch.py``) and run again, and
   :func:`count_above` tells the host whether another rerun is needed.
"""

from typing import Any

import warp as wp

from .acoustics import (
    CMat2,
    PartGeometry,
    PointCoefficients,
    axpy2,
    cmat2,
    cosh_sinhc,
    cosh_sinhc_scaled,
    cscale2,
    expm2_scaled,
    expm2_tangent,
    expm2_traceless,
    geometry_difference,
    identity2,
    magnus6_accumulate,
    magnus6_exponent,
    magnus6_omega,
    magnus6_tangent,
    matmul2,
    parallel2,
    parallel2_tangent,
    part_geometry,
    point_coefficients,
    point_difference,
    pore_point,
    propagation_at,
    propagation_circular,
    plain_part,
    propagation_tangent,
    propagation_value,
    scale2,
    sinhc_derivative,
    slit_geometry,
    slit_point,
    traceless_exp,
    traceless_parts,
    with_bypass,
    without_bypass,
    zero2,
)
from .cmath import cabs, cexp
from .gas import G_GAMMA, G_R, sound_speed_squared
from .heat import (
    ROW_VALUES,
    cell_rows,
    cell_shape,
    contact_at,
    gap_share,
    picard_step,
    profile_at,
    segment_heat_coeffs,
    segment_nonlinear,
    segment_profile,
    solve_heat,
    store_wall_rows,
    temperature_at,
    wall_cell_rows,
    wall_field_on,
    wall_step,
)
from .layout import (
    BYPASS_GAP,
    F_POROUS,
    F_PORE_MODEL,
    F_HEATER,
    F_IMPOSED,
    F_THERMAL,
    HEAT_INPUT,
    LENGTH,
    P_MEAN,
    PORE_RADIUS,
    POROSITY,
    RADIUS,
    T_COLD,
    T_END,
    T_START,
    FRAME_MOBILITY,
    THERMAL_RADIUS_RATIO,
    TORTUOSITY,
    VISCOUS_SHAPE_FACTOR,
    seg_value,
)
from .pore import PORE_CIRCULAR, PORE_PLATES, PORE_SCREENS, PoreTable

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

TWO_PI = wp.constant(wp.float64(6.283185307179586))
PI = wp.constant(wp.float64(3.141592653589793))
# Gauss-Legendre points of [0, 1] for the three-point rule: 1/2 - sqrt(15)/10, 1/2, 1/2 + sqrt(15)/10
GAUSS = wp.constant(wp.vec3d(0.1127016653792583, 0.5, 0.8872983346207417))
#: Most Magnus cells of one segment (the host refuses a set above it: the cascade would not
#: end, and a larger count overflows the int32 point indices).
MAX_CELLS = 100_000
CELL_CAP = wp.constant(wp.float64(MAX_CELLS + 1))
#: The error estimate's refinement: a segment of n Magnus cells has n + ceil(n/2) on the
#: refined grid (:func:`refined_cells`), at least 1.5 times as many, so the sixth-order
#: scheme's error on the n cells is at most 1/(1 - 1.5^-6) times the difference of the two
#: grids' results (Richardson). A ratio of 2 (step doubling) estimated the error as well on
#: random cores and cost a third more points and refined cascades (bench/README.md).
REFINEMENT = 1.5
REFINED_ERROR_FACTOR = wp.constant(wp.float64(1.0 / (1.0 - REFINEMENT**-6)))
#: Register cap of the point kernel (``__maxnreg__``): two blocks of 256 threads per SM, no
#: spill in its Gauss points' loop (bench/README.md).
POINT_MAX_REGISTERS = 128


@wp.struct
class SetTable:
    """A batch of parameter sets as the forward kernels read them: ``params`` (rows, n) the
    parameter table, ``flags`` (segments, N_FLAGS) the core's structure
    (:mod:`tawarp.kernels.layout`) and ``gas`` the gas constants (:mod:`tawarp.kernels.gas`)."""

    params: wp.array2d(dtype=wp.float64)
    flags: wp.array2d(dtype=wp.int32)
    gas: wp.array(dtype=wp.float64)


@wp.kernel
def expand_parameters(
    base: wp.array(dtype=wp.float64),
    varying: wp.array2d(dtype=wp.float64),
    rows: wp.array(dtype=wp.int32),
    params: wp.array2d(dtype=wp.float64),
):
    """params[:, i] = base, then params[rows[v], i] = varying[v, i]."""
    i = wp.tid()
    for r in range(base.shape[0]):
        params[r, i] = base[r]
    for v in range(rows.shape[0]):
        params[rows[v], i] = varying[v, i]


@wp.kernel
def heat_kernel(
    sets: SetTable,
    first: int,
    count: int,
    heat_cells: int,
    fitted: int,
    max_iter: int,
    tol: wp.float64,
    theta: wp.array2d(dtype=wp.float64),
    scratch: wp.array2d(dtype=wp.float64),
    rows: wp.array2d(dtype=wp.float64),
    pending: wp.array(dtype=wp.int32),
):
    """The heat model of set i (:func:`tawarp.kernels.heat.solve_heat`). With ``pending``
    of n entries, the sets that iterate are left to :func:`heat_rows_kernel` and
    :func:`picard_kernel`, pending[i] = 1 for those of the single-field iterations, 2 for
    those of the two-field iterations and 0 for the others (an empty ``pending``: every set
    solved here)."""
    i = wp.tid()
    params = sets.params
    flags = sets.flags
    gas = sets.gas
    defer = int(0)
    if pending.shape[0] > 0:
        defer = 1
    left = solve_heat(
        params, flags, gas, i, first, count, heat_cells, fitted, max_iter, tol, theta, scratch, rows, defer
    )
    if defer != 0:
        pending[i] = left


@wp.kernel
def heat_rows_kernel(
    sets: SetTable,
    first: int,
    heat_cells: int,
    fitted: int,
    pending: wp.array(dtype=wp.int32),
    theta: wp.array2d(dtype=wp.float64),
    rows: wp.array2d(dtype=wp.float64),
):
    """Thread (i, r): the rows of heat cell r of pending set i at its current iterate
    theta[i, :], into rows[i, :] (:func:`tawarp.kernels.heat.cell_rows` at ROW_VALUES r, or
    for the two fields :func:`tawarp.kernels.heat.wall_cell_rows` at WALL_ROW_VALUES r): the
    cells of one iteration side by side, where one thread per set computes them one after
    the other (a Kirchhoff cell's inversions of U(theta) dominate an iteration)."""
    i, r = wp.tid()
    p = pending[i]
    if p == 0:
        return
    params = sets.params
    flags = sets.flags
    gas = sets.gas
    if p == 2:
        A, B, C, D, E, F, tied = wall_cell_rows(
            params, flags, gas, i, first, heat_cells, fitted, r, theta[i, r], theta[i, r + 1]
        )
        store_wall_rows(rows, i, r, A, B, C, D, E, F, tied)
        return
    a, b, c, d, e, f = cell_rows(params, flags, gas, i, first, heat_cells, fitted, 1, r, theta[i, r], theta[i, r + 1])
    k = ROW_VALUES * r
    rows[i, k] = a
    rows[i, k + 1] = b
    rows[i, k + 2] = c
    rows[i, k + 3] = d
    rows[i, k + 4] = e
    rows[i, k + 5] = f


@wp.kernel
def picard_kernel(
    sets: SetTable,
    first: int,
    count: int,
    heat_cells: int,
    fitted: int,
    tol: wp.float64,
    theta: wp.array2d(dtype=wp.float64),
    scratch: wp.array2d(dtype=wp.float64),
    rows: wp.array2d(dtype=wp.float64),
    pending: wp.array(dtype=wp.int32),
    left: wp.array(dtype=wp.int32),
):
    """One iteration of pending set i from the rows :func:`heat_rows_kernel` stored
    (:func:`tawarp.kernels.heat.picard_step`, for the two fields
    :func:`tawarp.kernels.heat.wall_step`): the set stops pending when it converged, else
    it counts itself in left[0] (the host launches at most ``picard_iterations`` of them)."""
    i = wp.tid()
    p = pending[i]
    if p == 0:
        return
    params = sets.params
    flags = sets.flags
    gas = sets.gas
    converged = int(0)
    if p == 2:
        converged = wall_step(params, flags, gas, i, first, count, heat_cells, fitted, 1, tol, theta, scratch, rows, 1)
    else:
        converged = picard_step(params, flags, gas, i, first, count, heat_cells, fitted, tol, theta, scratch, rows, 1)
    if converged != 0:
        pending[i] = 0
    else:
        wp.atomic_add(left, 0, 1)


@wp.func
def pore_geometry(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32), i: int, s: int):
    """(porosity, pore radius [m], tortuosity) of segment s; a duct is one circular pore
    of the tube's radius. Beside a ``bypass_gap`` g > 0 the pores fill phi (1 - x) of the
    section, x = g (2R - g)/R^2 the gap's share (:func:`tawarp.kernels.heat.gap_share`):
    the stack of radius R - g."""
    if flags[s, F_POROUS] == 0:
        return wp.float64(1.0), params[RADIUS, i], wp.float64(1.0)
    phi = seg_value(params, i, s, POROSITY)
    gap = seg_value(params, i, s, BYPASS_GAP)
    if gap > wp.float64(0.0):
        phi = phi * (wp.float64(1.0) - gap_share(gap, params[RADIUS, i]))
    return phi, seg_value(params, i, s, PORE_RADIUS), seg_value(params, i, s, TORTUOSITY)


@wp.func
def thermal_radius(
    params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32), i: int, s: int, r: wp.float64
):
    """Radius [m] of the thermal function f_k: r times ``thermal_radius_ratio`` in a porous
    segment (a ratio <= 0 counts as 1), r in a duct and in wire screens (their Prandtl
    number is read from the two radii, :func:`tawarp.kernels.acoustics.screen_entries`)."""
    if flags[s, F_POROUS] == 0 or flags[s, F_PORE_MODEL] == PORE_SCREENS:
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
def segment_geometry(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32), i: int, s: int):
    """:class:`tawarp.kernels.acoustics.PartGeometry` of segment s of set i; a porous segment
    with a ``bypass_gap`` g > 0 [m] has the gap's section share g (2R - g)/R^2 and its
    half-spacing g/2 over the pores' radii: the slit beside its pores
    (:func:`tawarp.kernels.acoustics.slit_point`, the cascade's ``gap_segment``)."""
    phi, r, q = pore_geometry(params, flags, i, s)
    radius = params[RADIUS, i]
    geo = part_geometry(
        phi, q, PI * radius * radius, frame_mobility(params, flags, i, s), shape_factor(params, flags, i, s)
    )
    if flags[s, F_POROUS] != 0:
        gap = seg_value(params, i, s, BYPASS_GAP)
        if gap > wp.float64(0.0):
            half = wp.float64(0.5) * gap
            geo = with_bypass(
                geo,
                gap_share(gap, radius),
                wp.log(half / r),
                wp.log(half / thermal_radius(params, flags, i, s, r)),
            )
    return geo


# the 2-ports of a segment with a bypass gap (make_transfer_kernel's gap_segment,
# tawarp.kernels.onset.gap_matrix_complex): the segment as it stands (no gap), its pores
# beside the gap, the gap's slit
CHANNEL_PART = wp.constant(0)
CHANNEL_PORES = wp.constant(1)
CHANNEL_SLIT = wp.constant(2)


@wp.func
def channel_geometry(geo: PartGeometry, channel: int):
    """The :class:`tawarp.kernels.acoustics.PartGeometry` of ``channel`` of a segment of
    geometry ``geo``: the slit's (:func:`tawarp.kernels.acoustics.slit_geometry`), the pores'
    without the gap, or ``geo`` itself."""
    if channel == CHANNEL_SLIT:
        return slit_geometry(geo)
    if channel == CHANNEL_PORES:
        return without_bypass(geo)
    return geo


@wp.func
def channel_point(pc: PointCoefficients, geo: PartGeometry, channel: int):
    """The point coefficients of ``channel`` at a point whose pores' are ``pc``
    (:func:`tawarp.kernels.acoustics.slit_point` for the slit, else ``pc``)."""
    if channel == CHANNEL_SLIT:
        return slit_point(pc, geo)
    return pc


@wp.func
def channel_model(model: int, channel: int):
    """The pore model of ``channel`` of a segment of pore model ``model``: plates for the slit."""
    if channel == CHANNEL_SLIT:
        return PORE_PLATES
    return model


@wp.func
def imposed_temperature(params: wp.array2d(dtype=wp.float64), i: int, s: int, xi: wp.float64):
    """(T [K], dT/dx [K/m]) at local position xi [m] of segment s with imposed
    temperatures: linear from T_start at its start to T_end at its end."""
    t0 = seg_value(params, i, s, T_START)
    slope = (seg_value(params, i, s, T_END) - t0) / seg_value(params, i, s, LENGTH)
    return t0 + slope * xi, slope


@wp.func
def temperature_varies(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32), i: int, s: int):
    """True when the temperature may vary along segment s of set i: a segment of the heat
    model, or imposed temperatures that differ at its ends (it then takes Magnus cells)."""
    if flags[s, F_THERMAL] != 0:
        return True
    return flags[s, F_IMPOSED] != 0 and seg_value(params, i, s, T_START) != seg_value(params, i, s, T_END)


@wp.func
def temperature_scale(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
):
    """(k [1/m], c [m/s]) of :func:`magnus_cell_count` for segment s of set i: the rate k at
    which its temperature profile varies (the heat model's decay rate; |ln(T_end/T_start)|/L
    for imposed temperatures) and its slowest sound speed (at T_cold; at the colder end)."""
    if flags[s, F_IMPOSED] != 0:
        t0 = seg_value(params, i, s, T_START)
        t1 = seg_value(params, i, s, T_END)
        k = wp.abs(wp.log(t1 / t0)) / seg_value(params, i, s, LENGTH)
        return k, wp.sqrt(sound_speed_squared(gas, wp.min(t0, t1)))
    lam, k, sigma = segment_heat_coeffs(params, flags, gas, i, s)
    return k, wp.sqrt(sound_speed_squared(gas, params[T_COLD, i]))


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
def tangent_row(rows: Any, a: int):
    """Row a of a (P, 8) matrix of tangents as a :class:`CMat2`."""
    return cmat2(
        wp.vec2d(rows[a, 0], rows[a, 1]),
        wp.vec2d(rows[a, 2], rows[a, 3]),
        wp.vec2d(rows[a, 4], rows[a, 5]),
        wp.vec2d(rows[a, 6], rows[a, 7]),
    )


@wp.func
def with_tangent_row(rows: Any, a: int, m: CMat2):
    """``rows`` with row a set to m (:func:`tangent_row`'s inverse)."""
    rows[a, 0] = m.a[0]
    rows[a, 1] = m.a[1]
    rows[a, 2] = m.b[0]
    rows[a, 3] = m.b[1]
    rows[a, 4] = m.c[0]
    rows[a, 5] = m.c[1]
    rows[a, 6] = m.d[0]
    rows[a, 7] = m.d[1]
    return rows


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


@wp.func
def refined_cells(n: int):
    """Magnus cells on the error estimate's refined grid of a segment of n cells: n + ceil(n/2)
    (:data:`REFINEMENT`)."""
    return n + (n + 1) // 2


@wp.kernel
def refined_error(
    sets: SetTable,
    out: wp.array3d(dtype=wp.float64),
    refined: wp.array3d(dtype=wp.float64),
    sample: wp.array(dtype=wp.int32),
    err: wp.array(dtype=wp.float64),
):
    """err[i] = :data:`REFINED_ERROR_FACTOR` times the max over k of
    max_c |Y_c - Y2_c| / max_c |Y2_c| (dimensionless), Y the coefficients (Tpp, Tpu/Zc,
    Tup Zc, Tuu) of out[i, sample[k]] (the set's cells) and Y2 those of refined[i, k] (the
    refined grid, :func:`refined_cells`), Zc = p_mean / (c_cold S) [Pa s/m^3] the cold duct's
    impedance of set i. NaN where a coefficient is not finite (as NumPy's max): such a set
    is not refined, the validity checks name it."""
    i = wp.tid()
    params = sets.params
    gas = sets.gas
    radius = params[RADIUS, i]
    zc = params[P_MEAN, i] / wp.sqrt(gas[G_R] * params[T_COLD, i] / gas[G_GAMMA]) / (PI * radius * radius)
    worst = wp.float64(0.0)
    finite = int(1)
    for k in range(sample.shape[0]):
        gap = wp.float64(0.0)
        size = wp.float64(0.0)
        for c in range(4):
            y2 = dimensionless(refined, i, k, c, zc)
            dy = cabs(dimensionless(out, i, sample[k], c, zc) - y2)
            a2 = cabs(y2)
            if wp.isnan(dy) or wp.isnan(a2):
                finite = 0
            gap = wp.max(gap, dy)
            size = wp.max(size, a2)
        worst = wp.max(worst, gap / size)
    if finite == 0:
        worst = wp.float64(wp.nan)
    err[i] = REFINED_ERROR_FACTOR * worst


#: A rerun's raise of a set's density: (estimate / target)^(1/6) (the scheme's order) times
#: RAISE_MARGIN, clipped to [RAISE_LEAST, RAISE_MOST] (:func:`raise_density`).
RAISE_MARGIN = wp.constant(wp.float64(1.1))
RAISE_LEAST = wp.constant(wp.float64(1.25))
RAISE_MOST = wp.constant(wp.float64(4.0))


@wp.kernel
def raise_density(
    err: wp.array(dtype=wp.float64),
    density: wp.array(dtype=wp.float64),
    target: wp.float64,
    most_density: wp.float64,
    count: wp.array(dtype=wp.int32),
    index: wp.array(dtype=wp.int32),
    part_density: wp.array(dtype=wp.float64),
):
    """For each set i whose error estimate err[i] exceeds ``target`` (not NaN): count[0] + 1,
    and while there is a slot k < index.shape[0] left (the slots taken in no set order), its
    density[i] raised by RAISE_MARGIN (err / target)^(1/6) clipped to [RAISE_LEAST, RAISE_MOST]
    (at most ``most_density``), index[k] = i and part_density[k] the raised density: the
    rerun's sets (Engine._adapted). A set beyond the slots keeps its density and
    estimate for a later rerun."""
    i = wp.tid()
    if err[i] > target:
        k = wp.atomic_add(count, 0, 1)
        if k < index.shape[0]:
            factor = wp.min(wp.max(RAISE_MARGIN * wp.pow(err[i] / target, SIXTH_ROOT), RAISE_LEAST), RAISE_MOST)
            d = wp.min(density[i] * factor, most_density)
            density[i] = d
            index[k] = i
            part_density[k] = d


@wp.kernel
def count_above(err: wp.array(dtype=wp.float64), target: wp.float64, count: wp.array(dtype=wp.int32)):
    """count[0] += the sets whose error estimate err[i] exceeds ``target``."""
    i = wp.tid()
    if err[i] > target:
        wp.atomic_add(count, 0, 1)


#: The most cell steps a cascade order's key tells apart (:func:`cascade_keys`); a set with
#: more (only ever refused: :data:`MAX_CELLS`) sorts with those at the cap.
ORDER_KEY_CAP = wp.constant(2**30)


@wp.kernel
def cascade_keys(
    cells: wp.array2d(dtype=wp.int32),
    set0: int,
    stride: int,
    keys: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32),
):
    """keys[g] and order[g] = g for group g (sets set0 + g stride ... of ``stride`` sets) of
    a cascade launch: a radix sort of the pairs on ``keys`` orders the groups by decreasing
    cell steps over ``cells``' columns (a part at uniform temperature one step), the
    launch's ``order`` (:func:`make_transfer_kernel`). A warp's threads are a few
    neighbouring groups (three sampled frequencies of each of ~11 sets on the refined grid, a
    set's frequencies on the main one), and it runs each segment's cell loop for as long as its
    longest thread: sets drawn at random lost a fifth of the refined grid's warp time to
    shorter neighbours (bench/README.md)."""
    g = wp.tid()
    i = set0 + g * stride
    steps = int(0)
    for c in range(cells.shape[1]):
        steps = steps + wp.max(cells[i, c], 1)
    keys[g] = ORDER_KEY_CAP - wp.min(steps, ORDER_KEY_CAP)
    order[g] = g


@wp.func
def magnus_cell_count(density: wp.float64, k: wp.float64, length: wp.float64, omega: wp.float64, c_cold: wp.float64):
    """Magnus cells of a thermal segment of length ``length`` [m] at cell density ``density``:
    ceil(density (1 + k L + omega L / c_cold)), k [1/m] the heat model's decay rate, omega
    [rad/s], c_cold [m/s]: the profile varies on the scale 1/k and the wave on c/omega, and a
    sixth-order cell's error scales with the sixth power of its length over those scales.
    The one rule of the cascade, the onset's walk (:mod:`tawarp.kernels.onset`) and the
    fits' fixed counts (:func:`tawarp.kernels.lm.magnus_cells`). Capped at :data:`MAX_CELLS` + 1
    (a NaN or infinite count too): an int32 conversion of a larger value is undefined, and
    the host refuses any count above :data:`MAX_CELLS` (``cell_counts``' ``most[2]``)."""
    n = wp.ceil(density * (wp.float64(1.0) + k * length + omega * length / c_cold))
    if not (n <= CELL_CAP):
        n = CELL_CAP
    return int(n)


#: A Magnus cell's local error grows as its length to this power (a sixth-order scheme).
LOCAL_ORDER = wp.constant(wp.float64(7.0))
#: Gradings below this (:func:`excess_grading`) are taken as none: the uniform grid, on which
#: the cells' share of :func:`graded_share` is within 1e-3 of 1.
MIN_GRADING = wp.constant(wp.float64(1.0e-3))
#: The steepest grading (:func:`excess_grading`): cells e^100 times longer at the cold end
#: than at the hot one, beyond which the excess is far below rounding; e^-kappa stays normal.
MAX_GRADING = wp.constant(wp.float64(100.0))


@wp.func
def excess_grading(
    theta: wp.array2d(dtype=wp.float64), i: int, node0: int, heat_cells: int, k: wp.float64, length: wp.float64
):
    """kappa of :func:`cell_grid` for a thermal segment of decay rate k [1/m] and ``length``
    [m] whose heat-model nodes node0 ... node0 + heat_cells hold set i's temperature
    excess: the excess decays from the segment's hotter end as e^(-lam y) (y [m] from that
    end, lam = min(k, ln(theta_hot/theta_cold)/L): two hot ends decay less), and a Magnus
    cell's error with h^7 e^(-lam y), so cells of length h e^(lam y / 7) spread the error
    evenly: kappa = lam L / 7, positive where the hotter end is the segment's start,
    negative where it is its end. 0 (uniform) for gradings below :data:`MIN_GRADING` (or
    NaN); at most :data:`MAX_GRADING`."""
    start = wp.abs(theta[i, node0])
    end = wp.abs(theta[i, node0 + heat_cells])
    hot = wp.max(start, end)
    cold = wp.min(start, end)
    decay = k * length
    if cold > wp.float64(0.0):
        decay = wp.min(decay, wp.log(hot / cold))
    kappa = wp.min(decay / LOCAL_ORDER, MAX_GRADING)
    if not (kappa >= MIN_GRADING):
        return wp.float64(0.0)
    if end > start:
        return -kappa
    return kappa


#: 1/6 (a float64 constant: a quotient of literals in a kernel is taken in float32)
SIXTH_ROOT = wp.constant(wp.float64(1.0 / 6.0))


@wp.func
def graded_share(kappa: wp.float64):
    """Cells on :func:`cell_grid`'s graded grid over those on a uniform one of the same
    error, for an excess that decays as e^(-lam y) along the segment (|kappa| = lam L/7,
    :func:`excess_grading`): with g = 7 (1 - e^(-|kappa|)) over lam L = 7 |kappa|, the graded
    cells' length at the hot end is the uniform one's times (g / (1 - e^(-lam L)))^(-1/6),
    for the same sum of h^6 e^(-lam y) (the error), so the share is
    g (g / (1 - e^(-lam L)))^(1/6) / (lam L): 0.64 at lam L = 12, 1 at kappa = 0 (measured:
    bench/README.md, "Cells graded to the excess")."""
    a = wp.abs(kappa)
    if a == wp.float64(0.0):
        return wp.float64(1.0)
    g = LOCAL_ORDER * (wp.float64(1.0) - wp.exp(-a))
    decay = LOCAL_ORDER * a
    return g * wp.pow(g / (wp.float64(1.0) - wp.exp(-decay)), SIXTH_ROOT) / decay


@wp.func
def cell_grid(kappa: wp.float64, length: wp.float64, n: int):
    """The grid of a segment of ``length`` L [m] in n Magnus cells graded by ``kappa``
    (:func:`excess_grading`), as :func:`cell_edge` reads it: (L/n, 0, 0, 0) uniform
    (kappa = 0); else the boundaries y_m = (L/K) ln(1/w_m) from the hot end,
    w_m = e^-K + (n - m) (1 - e^-K)/n (K = |kappa|, m counted from the hot end), so that
    the cells' lengths grow as e^(K y / L): (-L/K, (1 - e^-K)/n, e^-K, 0) where the hot end
    is the segment's start (x = y), (L/K, ..., L) where it is its end (x = L - y). A grid of
    more cells on the same kappa (the error estimate's refined grid) is the same map cut
    more finely."""
    if kappa == wp.float64(0.0):
        return wp.vec4d(length / wp.float64(n), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    big = wp.abs(kappa)
    floor = wp.exp(-big)
    scale = length / big
    offset = wp.float64(0.0)
    if kappa > wp.float64(0.0):
        scale = -scale
    else:
        offset = length
    return wp.vec4d(scale, (wp.float64(1.0) - floor) / wp.float64(n), floor, offset)


@wp.func
def graded(grid: wp.vec4d):
    """True for :func:`cell_grid`'s graded grids (False: uniform)."""
    return grid[1] != wp.float64(0.0)


@wp.func
def cell_edge(grid: wp.vec4d, n: int, c: int):
    """x [m] of the start of cell c (c = n: the end) of :func:`cell_grid`'s grid of n cells."""
    if not graded(grid):
        return wp.float64(c) * grid[0]
    beyond = c  # cells between the edge and the cold end: here the segment's start
    if grid[0] < wp.float64(0.0):  # the hot end is the segment's start
        beyond = n - c
    return grid[3] + grid[0] * wp.log(grid[2] + wp.float64(beyond) * grid[1])


@wp.func
def cell_span(grid: wp.vec4d, n: int, c: int):
    """Length [m] of cell c of :func:`cell_grid`'s grid of n cells: the difference of its
    :func:`cell_edge`'s, a uniform grid's h itself (a cascade's h, bit for bit)."""
    if graded(grid):
        return cell_edge(grid, n, c + 1) - cell_edge(grid, n, c)
    return grid[0]


@wp.func
def gauss_points(grid: wp.vec4d, n: int, c: int):
    """Local positions [m] of the three Gauss points (:data:`GAUSS`) of cell c of
    :func:`cell_grid`'s grid of n cells: x_c + GAUSS h_c (:func:`cell_edge`,
    :func:`cell_span`, whose logs are taken once for the three); on a uniform grid
    (c + GAUSS) h."""
    if not graded(grid):
        return (wp.vec3d(wp.float64(c)) + GAUSS) * grid[0]
    x = cell_edge(grid, n, c)
    return wp.vec3d(x) + GAUSS * (cell_edge(grid, n, c + 1) - x)


@wp.func
def segment_cells(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    theta: wp.array2d(dtype=wp.float64),
    first: int,
    heat_cells: int,
    seg_cells: wp.array(dtype=wp.int32),
    density: wp.float64,
    omega_max: wp.float64,
    i: int,
    s: int,
):
    """(n, kappa): Magnus cells of segment s of set i, whose temperature varies
    (:func:`temperature_varies`), and the grading of their grid (:func:`cell_grid`):
    ``seg_cells[s]`` on a uniform grid (fixed cells: a fit's tangent cascade differences
    neighbours' points at the same places), or where that is 0 :func:`magnus_cell_count`
    (:func:`temperature_scale`) at ``density`` and the batch's highest angular frequency
    ``omega_max`` [rad/s], on a grid graded to the heat model's excess in ``theta``
    (:func:`excess_grading`; nodes of the thermal segments from ``first``, ``heat_cells``
    each) with :func:`graded_share` of the uniform grid's cells. Uniform where the excess
    is not one decaying piece: a heater's segment (its source makes the profile concave),
    imposed temperatures (linear), a heat grid of several cells (the temperature-dependent
    effects' profile, in pieces whose joins the cells straddle: graded, its error fell
    irregularly as the cells were refined, tests/test_nonlinear_heat.py). One count for all
    of a set's frequencies, so that they share its points (:func:`make_point_kernel`); the
    count's omega term is small beside its k term in a stack (3 % more cells than
    per-frequency counts on bench/forward.py's sets)."""
    n_cells = seg_cells[s]
    kappa = wp.float64(0.0)
    if n_cells == 0:
        k, c = temperature_scale(params, flags, gas, i, s)
        length = seg_value(params, i, s, LENGTH)
        if flags[s, F_IMPOSED] == 0 and flags[s, F_HEATER] == 0 and heat_cells == 1:
            kappa = excess_grading(theta, i, (s - first) * heat_cells, heat_cells, k, length)
        n_cells = magnus_cell_count(density * graded_share(kappa), k, length, omega_max, c)
    return n_cells, kappa


@wp.func
def segment_uniform(flags: wp.array2d(dtype=wp.int32), cells: wp.array2d(dtype=wp.int32), i: int, column: int, s: int):
    """True when segment s of set i is at uniform temperature on the grid of ``column``: it
    has no Magnus cells (:func:`cell_counts`); its matrix is exp(A L)."""
    return cells[i, column] == 0


@wp.func
def segment_points(flags: wp.array2d(dtype=wp.int32), cells: wp.array2d(dtype=wp.int32), i: int, column: int, s: int):
    """Points of segment s in set i's point list: 3 Gauss points per Magnus cell of a
    thermal segment (``cells[i, column]``), one for a part at uniform temperature."""
    if segment_uniform(flags, cells, i, column, s):
        return 1
    return 3 * cells[i, column]


@wp.func
def segment_slots(flags: wp.array2d(dtype=wp.int32), cells: wp.array2d(dtype=wp.int32), i: int, column: int, s: int):
    """Threads of the point kernel for segment s of set i: one per Magnus cell (its three
    Gauss points), one for a part at uniform temperature (its one point)."""
    if segment_uniform(flags, cells, i, column, s):
        return 1
    return cells[i, column]


@wp.kernel
def cell_counts(
    sets: SetTable,
    theta: wp.array2d(dtype=wp.float64),
    first: int,
    heat_cells: int,
    seg_cells: wp.array(dtype=wp.int32),
    cell_density: wp.array(dtype=wp.float64),
    omega_max: wp.float64,
    cells: wp.array2d(dtype=wp.int32),
    grids: wp.array2d(dtype=wp.vec4d),
    most: wp.array(dtype=wp.int32),
):
    """cells[i, g n_seg + s]: Magnus cells of segment s of set i on grid g, and
    grids[i, g n_seg + s] where they lie (:func:`cell_grid`): at density cell_density[i]
    (g = 0, :func:`segment_cells`) and on the error estimate's refined grid (g = 1, where
    ``cells`` has its columns: :func:`refined_cells` of grid 0's on the same grading);
    most[0] = the largest point count
    of a set over the grids, most[1] its largest count of point-kernel slots
    (:func:`segment_slots`), most[2] the largest cell count of a segment (above
    :data:`MAX_CELLS`: refused on the host). ``theta``, ``first``, ``heat_cells``: the
    heat solve's excess (:func:`excess_grading`).
    0 for a segment at uniform temperature (its grid one step of its length): one that is
    neither thermal nor imposed with different end temperatures, and every thermal segment
    of a set without heat input (its heat model has no source, so theta = 0 exactly and
    exp(A L) is the segment's exact matrix: a two-step characterization's first fits, at
    Q = 0, need no Magnus cell), and every segment of a set at density 0 (an empty slot of a
    rerun, :func:`raise_density`: cheap, its results unread)."""
    i = wp.tid()
    params = sets.params
    flags = sets.flags
    gas = sets.gas
    n_seg = flags.shape[0]
    heated = params[HEAT_INPUT, i] != wp.float64(0.0)
    counted = cell_density[i] > wp.float64(0.0)
    points = int(0)
    slots = int(0)
    for s in range(n_seg):
        length = seg_value(params, i, s, LENGTH)
        n = int(0)
        kappa = wp.float64(0.0)
        if counted and temperature_varies(params, flags, i, s) and (heated or flags[s, F_THERMAL] == 0):
            n, kappa = segment_cells(
                params, flags, gas, theta, first, heat_cells, seg_cells, cell_density[i], omega_max, i, s
            )
        for g in range(cells.shape[1] // n_seg):
            column = g * n_seg + s
            cells[i, column] = n
            grids[i, column] = cell_grid(kappa, length, wp.max(n, 1))
            wp.atomic_max(most, 2, n)
            points = points + segment_points(flags, cells, i, column, s)
            slots = slots + segment_slots(flags, cells, i, column, s)
            n = refined_cells(n)
    wp.atomic_max(most, 0, points)
    wp.atomic_max(most, 1, slots)


@wp.func(inline=False)  # the rare profiles: kept out of the point kernel's inlined code
def rare_profile(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    theta: wp.array2d(dtype=wp.float64),
    i: int,
    s: int,
    node0: int,
    cells: int,
    k: wp.float64,
    sigma: wp.float64,
    d: wp.float64,
    nonlin: int,
    xi: wp.float64,
):
    """:func:`tawarp.kernels.heat.segment_profile`, out of line (:func:`gauss_profile`)."""
    return segment_profile(params, flags, gas, theta, i, s, node0, cells, k, sigma, d, nonlin, xi)


@wp.func
def gauss_profile(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    theta: wp.array2d(dtype=wp.float64),
    i: int,
    s: int,
    node0: int,
    cells: int,
    k: wp.float64,
    sigma: wp.float64,
    d: wp.float64,
    shape: wp.vec4d,
    nonlin: int,
    xi: wp.float64,
):
    """:func:`tawarp.kernels.heat.segment_profile` (the same values, bit for bit:
    tests/test_forward.py) with its usual case inline, the exact profile of the heat cell
    at xi (:func:`tawarp.kernels.heat.profile_at`, given ``shape`` =
    :func:`tawarp.kernels.heat.cell_shape` of (k, d), which the segment's cells share: the
    caller takes it once for its points), and its rare ones out of line
    (:func:`rare_profile`): a wall that is a field of its own, a contact resistance at the
    segment's start, the Kirchhoff cells of ``nonlin``: inlined, their code crowded the
    point kernel's registers (bench/README.md, "The error estimate's points")."""
    c = wp.min(int(xi / d), cells - 1)
    if nonlin != 0 or wall_field_on(params, i, s) != 0 or contact_at(params, i, s, node0, c) != wp.float64(0.0):
        return rare_profile(params, flags, gas, theta, i, s, node0, cells, k, sigma, d, nonlin, xi)
    return profile_at(shape, theta[i, node0 + c], theta[i, node0 + c + 1], k, sigma, d, xi - wp.float64(c) * d)


def make_point_kernel(nonlinear: bool, max_registers: int | None = POINT_MAX_REGISTERS):
    """The point kernel (below), compiled for a linear heat model only (``nonlinear``
    False: the Kirchhoff profile of the temperature-dependent effects is left out, which
    frees registers on the GPU) or for both; ``max_registers`` caps the registers of a CUDA
    thread (``__maxnreg__``; None: uncapped)."""

    def point_kernel(
        sets: SetTable,
        theta: wp.array2d(dtype=wp.float64),
        cells: wp.array2d(dtype=wp.int32),
        grids: wp.array2d(dtype=wp.vec4d),
        first: int,
        heat_cells: int,
        set0: int,
        points: wp.array2d(dtype=PointCoefficients),
        spans: wp.array2d(dtype=wp.float64),
    ):
        """points[i, p]: :class:`PointCoefficients` of point p of set set0 + i, and spans[i, p]
        the length [m] of the cell whose first point p is (a part at uniform temperature: its
        length), the cascade's h (:func:`cell_span`: a graded cell's length is a log's
        difference, computed here once per set, not per frequency); launched on
        (sets, the most slots of a set, :func:`segment_slots`). A set's points run over its
        grids (``cells``' column blocks, ``grids`` their :func:`cell_grid`), and in each over
        the segments in order: one point (the cold or the imposed temperature) for a part at
        uniform temperature, the three Gauss points x + (1/2 - sqrt(15)/10, 1/2,
        1/2 + sqrt(15)/10) h of each of its Magnus cells [x, x + h] for a thermal segment, a
        thread per cell (they share its heat cell's coefficients)."""
        li, slot = wp.tid()
        params = sets.params
        flags = sets.flags
        gas = sets.gas
        i = set0 + li
        n_seg = flags.shape[0]
        p_mean = params[P_MEAN, i]
        radius = params[RADIUS, i]
        area = PI * radius * radius
        T_cold = params[T_COLD, i]
        # find the thread's segment first and do its work once, after the search: work
        # inside the search loop ran once per segment a warp's threads span (Nsight
        # Compute: 9 of 32 threads active per instruction)
        rest = slot
        p = int(0)
        column = int(-1)
        for c in range(cells.shape[1]):
            slots = segment_slots(flags, cells, i, c, c % n_seg)
            if rest < slots:
                column = c
                break
            rest = rest - slots
            p = p + segment_points(flags, cells, i, c, c % n_seg)
        if column < 0:  # beyond this set's slots
            return
        s = column % n_seg
        phi, r, q = pore_geometry(params, flags, i, s)
        r_k = thermal_radius(params, flags, i, s, r)
        grid = grids[i, column]
        if segment_uniform(flags, cells, i, column, s):
            T = T_cold
            if flags[s, F_IMPOSED] != 0:
                T = seg_value(params, i, s, T_START)
            points[li, p] = point_coefficients(gas, p_mean, T, wp.float64(0.0), phi, r, q, area, r_k)
            spans[li, p] = grid[0]
            return
        n_cells = cells[i, column]
        xs = gauss_points(grid, n_cells, rest)
        spans[li, p + 3 * rest] = cell_span(grid, n_cells, rest)
        if flags[s, F_IMPOSED] != 0:
            for g in range(3):
                T, dT = imposed_temperature(params, i, s, xs[g])
                points[li, p + 3 * rest + g] = point_coefficients(gas, p_mean, T, dT, phi, r, q, area, r_k)
        else:
            lam, k, sigma = segment_heat_coeffs(params, flags, gas, i, s)
            d = seg_value(params, i, s, LENGTH) / wp.float64(heat_cells)
            node0 = (s - first) * heat_cells
            shape = cell_shape(k, d)
            nonlin = 0
            if wp.static(nonlinear):  # compiled out of the linear kernel: fewer registers on the GPU
                nonlin = segment_nonlinear(params, i, s)
            for g in range(3):
                th, dth = gauss_profile(
                    params, flags, gas, theta, i, s, node0, heat_cells, k, sigma, d, shape, nonlin, xs[g]
                )
                points[li, p + 3 * rest + g] = point_coefficients(gas, p_mean, T_cold + th, dth, phi, r, q, area, r_k)

    # a unique module does not inherit this file's module options; the Gauss points' loops
    # stay loops (max_unroll 1): unrolled, their profile and coefficients' code came three times
    kw = {} if max_registers is None else {"cuda_max_registers": int(max_registers)}
    return wp.kernel(point_kernel, module="unique", enable_backward=False, module_options={"max_unroll": 1}, **kw)


def make_transfer_kernel(max_registers: int | None = None, tangents: int = 0, plain: bool = False):
    """The cascade kernel (below); ``max_registers`` caps the registers of a CUDA thread
    (``__maxnreg__``). ``tangents`` = P > 0 compiles the tangent cascade: the derivatives
    of each T-matrix along P parameters, carried through the cascade with the value.
    ``plain`` compiles a cascade for cores whose parts are all plain
    (:func:`tawarp.kernels.acoustics.plain_part`: circular pores, rigid frame, no shape
    factor, no bypass gap): A is :func:`tawarp.kernels.acoustics.propagation_circular` alone
    (the tangents': the pore model and the effects as constants), with no call to the other
    parts' out-of-line code, whose presence in a loop makes the GPU compiler keep the loop's
    values clear of the callee's registers (bench/README.md: 250 registers instead of 128);
    a part that is not plain gives NaN. The other cascade takes a segment with a bypass gap
    as two 2-ports side by side, out of line (``gap_segment`` below)."""
    P = wp.constant(tangents)

    @wp.func
    def point_propagation(
        pc: PointCoefficients,
        geo: PartGeometry,
        omega: wp.float64,
        half_log_omega: wp.float64,
        gamma: wp.float64,
        model: int,
        pore_table: PoreTable,
    ):
        # A at one point of a part (make_transfer_kernel's ``plain``)
        if wp.static(plain):
            return propagation_circular(pc, geo, omega, half_log_omega, gamma, pore_table)
        return propagation_at(pc, geo, omega, half_log_omega, gamma, model, pore_table)

    @wp.func
    def part_model(model: int):
        # a plain cascade's parts are circular pores (make_transfer_kernel's ``plain``): a
        # constant, whose branches the compiler folds
        if wp.static(plain):
            return PORE_CIRCULAR
        return model

    @wp.func
    def part_effects(geo: PartGeometry):
        # a plain cascade's parts have a rigid frame and no shape factor: constants, whose
        # branches the compiler folds (and their derivatives are 0)
        if wp.static(plain):
            return part_geometry(geo.porosity, geo.tortuosity, geo.area, wp.float64(0.0), wp.float64(1.0))
        return geo

    Q = max(tangents, 1)  # local sizes must be > 0; the P = 0 kernel never touches them
    stride = wp.constant(1 + 2 * tangents)
    tangent_rows = wp.types.matrix(shape=(Q, 8), dtype=wp.float64)
    scale_rows = wp.types.matrix(shape=(Q, 2), dtype=wp.float64)

    def make_cells(channel: bool):
        """The cells of one segment (``segment_cells`` below), compiled for a part as it
        stands (``channel`` False) or for a channel of a segment with a bypass gap (True):
        its points the channel's (:func:`channel_point`), each cell's exponential scaled
        (:func:`tawarp.kernels.acoustics.expm2_scaled`: a slit far narrower than the viscous
        depth grows as e^(|k| L), beyond float64 over a stack)."""

        @wp.func
        def cell_point(points: wp.array2d(dtype=PointCoefficients), li: int, p: int, segment: PartGeometry, kind: int):
            # point p of set li: the channel ``kind``'s of a segment of geometry ``segment``
            if wp.static(channel):
                return channel_point(points[li, p], segment, kind)
            return points[li, p]

        @wp.func
        def point_tangent(
            points: wp.array2d(dtype=PointCoefficients),
            plus: int,
            p: int,
            segment_plus: PartGeometry,
            segment_minus: PartGeometry,
            kind: int,
            inv_two_step: wp.float64,
        ):
            # the central difference of point p between the neighbour sets plus and plus + 1
            if wp.static(channel):
                return point_difference(
                    channel_point(points[plus, p], segment_plus, kind),
                    channel_point(points[plus + 1, p], segment_minus, kind),
                    inv_two_step,
                )
            return point_difference(points[plus, p], points[plus + 1, p], inv_two_step)

        @wp.func
        def cell_exponent(
            points: wp.array2d(dtype=PointCoefficients),
            li: int,
            p: int,
            uniform: bool,
            h: wp.float64,
            geo: PartGeometry,
            segment: PartGeometry,
            kind: int,
            omega: wp.float64,
            half_log_omega: wp.float64,
            gamma: wp.float64,
            model: int,
            pore_table: PoreTable,
        ):
            """Magnus exponent of one cell of length h [m] whose points start at points[li, p]:
            the three Gauss points' A added into :func:`magnus6_omega`'s b's as each is evaluated
            (only the b's are live between the points, not three A's besides them), or h A of the
            one point of a part at uniform temperature (``uniform``; its matrix is exp(A h))."""
            a = point_propagation(
                cell_point(points, li, p, segment, kind), geo, omega, half_log_omega, gamma, model, pore_table
            )
            if uniform:
                return scale2(a, h)
            zero = zero2()
            b1, b2, b3 = magnus6_accumulate(zero, zero, zero, a, 0, h)
            a = point_propagation(
                cell_point(points, li, p + 1, segment, kind), geo, omega, half_log_omega, gamma, model, pore_table
            )
            b1, b2, b3 = magnus6_accumulate(b1, b2, b3, a, 1, h)
            a = point_propagation(
                cell_point(points, li, p + 2, segment, kind), geo, omega, half_log_omega, gamma, model, pore_table
            )
            b1, b2, b3 = magnus6_accumulate(b1, b2, b3, a, 2, h)
            return magnus6_omega(b1, b2, b3)

        @wp.func
        def segment_cells(
            sets: SetTable,
            points: wp.array2d(dtype=PointCoefficients),
            spans: wp.array2d(dtype=wp.float64),
            step: wp.array2d(dtype=wp.float64),
            pore_table: PoreTable,
            li: int,
            i: int,
            group: int,
            s: int,
            p: int,
            uniform: bool,
            n_cells: int,
            length: wp.float64,
            segment: PartGeometry,
            segment_model: int,
            kind: int,
            omega: wp.float64,
            half_log_omega: wp.float64,
            gamma: wp.float64,
            m: CMat2,
            log_scale: wp.vec2d,
            sigma: wp.float64,
            dm: tangent_rows,
            dlog: scale_rows,
        ):
            """(m, log_scale, sigma, dm, dlog, p) after the ``n_cells`` cells of segment s
            (length [m], geometry ``segment``, pore model ``segment_model``) of set i
            (the launch's set li), whose points start at points[li, p], each cell of
            length spans[li, q] at its first point q (:func:`make_point_kernel`; the
            tangents' d h = d length / n_cells: fixed cells, a uniform grid): each cell's
            exp(Omega) = e^(tau + sigma_c) E multiplies m by E, log_scale sums the tau and
            sigma the sigma_c (0 unless ``channel``), dm (P, 8) and dlog (P, 2) the
            derivatives of m and log_scale along the tangents' P parameters
            (``transfer_kernel``'s docstring).
            ``kind``: the channel (read by a ``channel`` cascade only)."""
            params = sets.params
            flags = sets.flags
            geo = segment
            model = segment_model
            if wp.static(channel):
                geo = channel_geometry(segment, kind)
                model = channel_model(segment_model, kind)
            for c in range(n_cells):
                h = spans[li, p]
                if wp.static(tangents == 0):
                    om = cell_exponent(
                        points, li, p, uniform, h, geo, segment, kind, omega, half_log_omega, gamma, model, pore_table
                    )
                    if wp.static(channel):
                        e, tau, cell_sigma = expm2_scaled(om)
                        sigma = sigma + cell_sigma
                    else:
                        e, tau = expm2_traceless(om)
                else:
                    cmodel = part_model(model)
                    cgeo = part_effects(geo)
                    pc1 = cell_point(points, li, p, segment, kind)
                    s1 = pore_point(pc1, half_log_omega, cmodel, pore_table, 1)
                    a1 = propagation_value(s1, pc1, cgeo, omega, gamma, cmodel)
                    pc2 = pc1
                    pc3 = pc1
                    s2 = s1
                    s3 = s1
                    a2 = a1
                    a3 = a1
                    om = scale2(a1, length)
                    if not uniform:
                        pc2 = cell_point(points, li, p + 1, segment, kind)
                        pc3 = cell_point(points, li, p + 2, segment, kind)
                        s2 = pore_point(pc2, half_log_omega, cmodel, pore_table, 1)
                        s3 = pore_point(pc3, half_log_omega, cmodel, pore_table, 1)
                        a2 = propagation_value(s2, pc2, cgeo, omega, gamma, cmodel)
                        a3 = propagation_value(s3, pc3, cgeo, omega, gamma, cmodel)
                        om = magnus6_exponent(a1, a2, a3, h)
                    tau, na, delta = traceless_parts(om)
                    if wp.static(channel):
                        ch, sh, cell_sigma = cosh_sinhc_scaled(delta)
                        sigma = sigma + cell_sigma
                    else:
                        ch, sh = cosh_sinhc(delta)
                    dsh = sinhc_derivative(delta, ch, sh)
                    e = traceless_exp(om, na, ch, sh)
                    for a in range(P):
                        plus = li + 1 + 2 * a
                        inv_two_step = wp.float64(0.5) / step[group, a]
                        dlength = (
                            seg_value(params, i + 1 + 2 * a, s, LENGTH) - seg_value(params, i + 2 + 2 * a, s, LENGTH)
                        ) * inv_two_step
                        segment_plus = segment_geometry(params, flags, i + 1 + 2 * a, s)
                        segment_minus = segment_geometry(params, flags, i + 2 + 2 * a, s)
                        if wp.static(channel):
                            dgeo = geometry_difference(
                                channel_geometry(segment_plus, kind),
                                channel_geometry(segment_minus, kind),
                                inv_two_step,
                            )
                        else:
                            dgeo = geometry_difference(segment_plus, segment_minus, inv_two_step)
                        d1 = propagation_tangent(
                            s1,
                            pc1,
                            point_tangent(points, plus, p, segment_plus, segment_minus, kind, inv_two_step),
                            cgeo,
                            dgeo,
                            omega,
                            gamma,
                            cmodel,
                        )
                        dom = axpy2(dlength, a1, scale2(d1, length))
                        if not uniform:
                            d2 = propagation_tangent(
                                s2,
                                pc2,
                                point_tangent(points, plus, p + 1, segment_plus, segment_minus, kind, inv_two_step),
                                cgeo,
                                dgeo,
                                omega,
                                gamma,
                                cmodel,
                            )
                            d3 = propagation_tangent(
                                s3,
                                pc3,
                                point_tangent(points, plus, p + 2, segment_plus, segment_minus, kind, inv_two_step),
                                cgeo,
                                dgeo,
                                omega,
                                gamma,
                                cmodel,
                            )
                            dom = magnus6_tangent(a1, a2, a3, h, d1, d2, d3, dlength / wp.float64(n_cells))
                        de, dtau = expm2_tangent(om, na, ch, sh, dsh, dom)
                        # d(E M) = dE M + E dM; the cells' tau are summed like the value's. Row a
                        # in place (not with_tangent_row: no copy of the P rows in the loop)
                        dma = axpy2(wp.float64(1.0), matmul2(de, m), matmul2(e, tangent_row(dm, a)))
                        dm[a, 0] = dma.a[0]
                        dm[a, 1] = dma.a[1]
                        dm[a, 2] = dma.b[0]
                        dm[a, 3] = dma.b[1]
                        dm[a, 4] = dma.c[0]
                        dm[a, 5] = dma.c[1]
                        dm[a, 6] = dma.d[0]
                        dm[a, 7] = dma.d[1]
                        dlog[a, 0] = dlog[a, 0] + dtau[0]
                        dlog[a, 1] = dlog[a, 1] + dtau[1]
                m = matmul2(e, m)
                log_scale = log_scale + tau
                if uniform:
                    p = p + 1
                else:
                    p = p + 3
            return m, log_scale, sigma, dm, dlog, p

        return segment_cells

    part_cells = make_cells(False)
    channel_cells = make_cells(True)

    @wp.func(inline=False)  # a bypass gap's segment: kept out of the cascade's inlined code
    def gap_segment(
        sets: SetTable,
        points: wp.array2d(dtype=PointCoefficients),
        spans: wp.array2d(dtype=wp.float64),
        step: wp.array2d(dtype=wp.float64),
        pore_table: PoreTable,
        li: int,
        i: int,
        group: int,
        s: int,
        p: int,
        uniform: bool,
        n_cells: int,
        length: wp.float64,
        segment: PartGeometry,
        model: int,
        omega: wp.float64,
        half_log_omega: wp.float64,
        gamma: wp.float64,
        m: CMat2,
        dm: tangent_rows,
    ):
        """(T m, d(T m)): the cascade's m and its derivatives dm along the P parameters
        carried through segment s, T its T-matrix with a bypass gap (which carries its own
        scale: the cascade's log_scale and its derivatives stay). The whole step is out of
        line, so that the cascade's loop holds one call for it. T: two 2-ports side by side
        between the segment's end planes:
        its pores (the segment without its gap, porosity phi (1 - x): :func:`pore_geometry`)
        and the gap's slit (:func:`tawarp.kernels.acoustics.slit_point`), each cascaded over
        the segment's cells from the same points (the same temperature profile), joined
        at the ends only, where their admittance matrices add
        (:func:`tawarp.kernels.acoustics.parallel2`)."""
        zero = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
        mp, sp, sigma_p, dmp, dsp, q = channel_cells(
            sets,
            points,
            spans,
            step,
            pore_table,
            li,
            i,
            group,
            s,
            p,
            uniform,
            n_cells,
            length,
            segment,
            model,
            CHANNEL_PORES,
            omega,
            half_log_omega,
            gamma,
            identity2(),
            zero,
            wp.float64(0.0),
            tangent_rows(),
            scale_rows(),
        )
        mg, sg, sigma_g, dmg, dsg, q = channel_cells(
            sets,
            points,
            spans,
            step,
            pore_table,
            li,
            i,
            group,
            s,
            p,
            uniform,
            n_cells,
            length,
            segment,
            model,
            CHANNEL_SLIT,
            omega,
            half_log_omega,
            gamma,
            identity2(),
            zero,
            wp.float64(0.0),
            tangent_rows(),
            scale_rows(),
        )
        # each channel is e^(S + sigma) M with det e^(2 S)
        lp = sp + wp.vec2d(sigma_p, wp.float64(0.0))
        lg = sg + wp.vec2d(sigma_g, wp.float64(0.0))
        gp = sp * wp.float64(2.0)
        gg = sg * wp.float64(2.0)
        t = parallel2(mp, lp, gp, mg, lg, gg)
        for a in range(P):
            dt = parallel2_tangent(
                mp,
                tangent_row(dmp, a),
                lp,
                gp,
                wp.vec2d(dsp[a, 0], dsp[a, 1]),
                mg,
                tangent_row(dmg, a),
                lg,
                gg,
                wp.vec2d(dsg[a, 0], dsg[a, 1]),
            )
            # d(T m) = dT m + T dm
            dm = with_tangent_row(dm, a, axpy2(wp.float64(1.0), matmul2(dt, m), matmul2(t, tangent_row(dm, a))))
        return matmul2(t, m), dm

    def transfer_kernel(
        sets: SetTable,
        freqs: wp.array(dtype=wp.float64),
        cells: wp.array2d(dtype=wp.int32),
        points: wp.array2d(dtype=PointCoefficients),
        spans: wp.array2d(dtype=wp.float64),
        set0: int,
        order: wp.array(dtype=wp.int32),
        pore_table: PoreTable,
        out: wp.array3d(dtype=wp.float64),
        refined: wp.array3d(dtype=wp.float64),
        step: wp.array2d(dtype=wp.float64),
        tangent: wp.array4d(dtype=wp.float64),
    ):
        """out[i, j] = (Tpp, Tpu, Tup, Tuu) as (re, im) pairs: the core T-matrix of set i at
        frequency freqs[j] [Hz], j < m = out.shape[1]; refined[i, k] the same at frequency
        freqs[m + k] on the refined grid (the error estimate's, :func:`refined_cells`;
        k < refined.shape[1]); for the sets i = set0 ... set0 + points.shape[0] - 1, whose
        :func:`make_point_kernel` points ``points`` (and cell lengths ``spans``) holds and
        :func:`cell_counts` cells ``cells``.
        Launched on points.shape[0] (m + refined.shape[1]) threads, the refined ones first:
        they run longest, and in warps of their own they hold up no short thread. Each grid's
        threads take the sets in ``order`` (local indices, :func:`cascade_keys`: warps of
        sets with alike cells), or in their own order where ``order`` is empty.
        ``pore_table``: :func:`tawarp.kernels.pore_table.circular_table` on the kernel's
        device.

        Tangent kernel (P > 0): the sets come in groups of 1 + 2P, a point z and z +- step[g, a] e_a
        of its P scaled parameters (group g = set i / (1 + 2P), local to the launch: ``out`` and
        ``tangent`` are indexed by it, ``params`` by set0 + i). Launched on
        points.shape[0] / (1 + 2P) m threads (no refined grid: fixed cells), it writes the
        value at z to out[g, j] and dT/dz_a to tangent[g, a, j]. Only the cascade is
        differentiated (:func:`tawarp.kernels.acoustics.magnus6_tangent`,
        :func:`tawarp.kernels.acoustics.expm2_tangent`, and A by
        :func:`tawarp.kernels.acoustics.propagation_tangent`: the same physics as the
        value's, on dual numbers); the frequency-independent point coefficients' and part
        geometries' derivatives are the central differences of the neighbours' (the heat
        solve and the point kernel, a few per cent of a set's cost)."""
        t = wp.tid()
        params = sets.params
        flags = sets.flags
        gas = sets.gas
        n_freqs = out.shape[1]
        n_refined = points.shape[0] * refined.shape[1]
        li = (t - n_refined) // n_freqs
        j = (t - n_refined) % n_freqs
        grid = 0
        if t < n_refined:
            li = t // refined.shape[1]
            j = n_freqs + t % refined.shape[1]
            grid = 1
        if order.shape[0] > 0:
            li = order[li]
        group = li
        li = li * stride
        i = set0 + li
        omega = TWO_PI * freqs[j]
        half_log_omega = wp.float64(0.5) * wp.log(omega)
        gamma = gas[G_GAMMA]
        n_seg = flags.shape[0]
        p = int(0)
        for column in range(grid * n_seg):  # the refined grid's points follow the main grid's
            p = p + segment_points(flags, cells, i, column, column % n_seg)
        m = identity2()
        log_scale = wp.vec2d(wp.float64(0.0), wp.float64(0.0))  # sum of the cells' tau (expm2_traceless)
        dm = tangent_rows()
        dlog = scale_rows()
        sigma = wp.float64(0.0)  # part_cells' scaled exponentials' (none: no channel)
        for s in range(n_seg):
            length = seg_value(params, i, s, LENGTH)
            geo = segment_geometry(params, flags, i, s)
            model = flags[s, F_PORE_MODEL]
            if wp.static(plain):
                if not plain_part(geo, model):  # a part this kernel does not compute: NaN, never a wrong A
                    log_scale = wp.vec2d(wp.float64(wp.nan), wp.float64(wp.nan))
            uniform = segment_uniform(flags, cells, i, grid * n_seg + s, s)
            n_cells = 1
            if not uniform:
                n_cells = cells[i, grid * n_seg + s]
            # the plain kernel is compiled without the gap: its flag is a constant False there
            gap = False
            if wp.static(not plain):
                gap = geo.gap_share > wp.float64(0.0)
            if gap:
                m, dm = gap_segment(
                    sets,
                    points,
                    spans,
                    step,
                    pore_table,
                    li,
                    i,
                    group,
                    s,
                    p,
                    uniform,
                    n_cells,
                    length,
                    geo,
                    model,
                    omega,
                    half_log_omega,
                    gamma,
                    m,
                    dm,
                )
                p = p + segment_points(flags, cells, i, grid * n_seg + s, s)
            else:
                m, log_scale, sigma, dm, dlog, p = part_cells(
                    sets,
                    points,
                    spans,
                    step,
                    pore_table,
                    li,
                    i,
                    group,
                    s,
                    p,
                    uniform,
                    n_cells,
                    length,
                    geo,
                    model,
                    CHANNEL_PART,
                    omega,
                    half_log_omega,
                    gamma,
                    m,
                    log_scale,
                    sigma,
                    dm,
                    dlog,
                )
        scale = cexp(log_scale)
        if j < n_freqs:
            store_matrix(out, group, j, cscale2(m, scale))
        else:
            store_matrix(refined, group, j - n_freqs, cscale2(m, scale))
        for a in range(P):
            # T = e^S M: dT = e^S (dS M + dM)
            da = axpy2(wp.float64(1.0), cscale2(m, wp.vec2d(dlog[a, 0], dlog[a, 1])), tangent_row(dm, a))
            da = cscale2(da, scale)
            tangent[group, a, j, 0] = da.a[0]
            tangent[group, a, j, 1] = da.a[1]
            tangent[group, a, j, 2] = da.b[0]
            tangent[group, a, j, 3] = da.b[1]
            tangent[group, a, j, 4] = da.c[0]
            tangent[group, a, j, 5] = da.c[1]
            tangent[group, a, j, 6] = da.d[0]
            tangent[group, a, j, 7] = da.d[1]

    kw = {} if max_registers is None else {"cuda_max_registers": int(max_registers)}
    # a unique module does not inherit this file's module options
    return wp.kernel(transfer_kernel, module="unique", enable_backward=False, **kw)


@wp.kernel
def profile_kernel(
    sets: SetTable,
    theta: wp.array2d(dtype=wp.float64),
    first: int,
    heat_cells: int,
    x: wp.array(dtype=wp.float64),
    T: wp.array2d(dtype=wp.float64),
    dTdx: wp.array2d(dtype=wp.float64),
):
    """T(x) [K] and dT/dx [K/m] of set i at positions x[j] [m] from plane x1 (the
    cold temperature outside the thermal segments and those with imposed temperatures)."""
    i, j = wp.tid()
    params = sets.params
    flags = sets.flags
    gas = sets.gas
    start = wp.float64(0.0)
    T[i, j] = params[T_COLD, i]
    dTdx[i, j] = wp.float64(0.0)
    for s in range(flags.shape[0]):
        length = seg_value(params, i, s, LENGTH)
        xi = x[j] - start
        if xi >= wp.float64(0.0) and xi <= length:
            if flags[s, F_THERMAL] != 0:
                t, dt = temperature_at(params, flags, gas, theta, i, s, first, heat_cells, xi)
                T[i, j] = t
                dTdx[i, j] = dt
            elif flags[s, F_IMPOSED] != 0:
                t, dt = imposed_temperature(params, i, s, xi)
                T[i, j] = t
                dTdx[i, j] = dt
        start = start + length
