"""Warp kernel of the design objectives, evaluated on the heat grid after the heat solve.

Per parameter set i (one thread), from the nodal temperatures of
:meth:`tawarp.model.forward.Engine.heat` (exact at the nodes: exponentially fitted scheme):

- ``out[i, GRADIENT]`` gradient across the stack ``(T(x3) - T(x2)) / l_s`` [K/m];
- ``out[i, T_MAX]`` maximum temperature over the thermal domain [K]: the nodes, and inside
  each cell with a source (the heater) the zero of dtheta/dx, in closed form on the
  exact cell profile (theta' has at most one zero in a constant-coefficient cell);
- ``out[i, HEAT_LEAK]`` heat leaked to the wall in the stack ``∫ (2 h_s/R) theta S dx`` [W],
  exact per cell: ``∫ theta = d [mean tanh(v)/v + sigma (1 - tanh(v)/v) / k^2]``,
  ``v = k d / 2``, mean of the two nodal values, ``2 h/R = lam k^2`` of the cell;
- ``out[i, T_HOT]`` temperature at the hot end of the stack T(x3) [K].
"""

from typing import Any

import warp as wp

from .heat import cell_coeffs_at, cell_profile, segment_nonlinear, tanhx_x
from .layout import LENGTH, RADIUS, T_COLD, seg_value

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code


@wp.func
def cell_coeffs(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    theta: wp.array2d(dtype=wp.float64),
    i: int,
    s: int,
    node: int,
):
    """Heat coefficients (lam, k, sigma) of the cell starting at ``node``: the segment's
    own, or, with a temperature-dependent model, those at the converged profile."""
    return cell_coeffs_at(params, flags, gas, theta, i, s, node, segment_nonlinear(params, i, s))


#: Output columns (named in the objectives table, tawarp.design.objectives).
GRADIENT = wp.constant(0)
T_MAX = wp.constant(1)
HEAT_LEAK = wp.constant(2)
T_HOT = wp.constant(3)
N_METRICS = 4
PI = wp.constant(wp.float64(3.141592653589793))


@wp.func
def atanhx_x(z: wp.float64):
    """artanh(z) / z for |z| < 1 (-> 1 at 0)."""
    if wp.abs(z) < wp.float64(1.0e-3):
        z2 = z * z
        return wp.float64(1.0) + z2 / wp.float64(3.0) * (wp.float64(1.0) + wp.float64(0.6) * z2)
    return wp.float64(0.5) * wp.log((wp.float64(1.0) + z) / (wp.float64(1.0) - z)) / z


@wp.func
def cell_max(theta_l: wp.float64, theta_r: wp.float64, k: wp.float64, sigma: wp.float64, d: wp.float64):
    """Largest theta in a cell (ends or interior stationary point).

    About the cell centre (m = xi - d/2, u = k m, v = k d/2) the profile of
    :func:`cell_profile` is (mean - sigma/k^2) cosh(u)/cosh(v) + half sinh(u)/sinh(v) +
    sigma/k^2, so theta' = 0 where tanh(k m) = z = 2 half k / (d tanh(v)/v (sigma - mean k^2)):
    m = artanh(z)/k, written with artanh(z)/z and tanh(v)/v so that k -> 0 (the parabola,
    m = 2 half / (d sigma)) is the same expression. One stationary point at most, inside
    when theta' > 0 at the left end and < 0 at the right; the value there is the profile's
    own (flat at a stationary point: the rounding of m costs nothing to first order)."""
    best = wp.max(theta_l, theta_r)
    t0, g0 = cell_profile(theta_l, theta_r, k, sigma, d, wp.float64(0.0))
    t1, g1 = cell_profile(theta_l, theta_r, k, sigma, d, d)
    if g0 > wp.float64(0.0) and g1 < wp.float64(0.0):
        mean = wp.float64(0.5) * (theta_l + theta_r)
        half = wp.float64(0.5) * (theta_r - theta_l)
        slope = wp.float64(2.0) * half / (d * tanhx_x(wp.float64(0.5) * k * d) * (sigma - mean * k * k))
        z = k * slope
        m = wp.float64(0.5) * d
        if z < wp.float64(0.0):
            m = -m
        if wp.abs(z) < wp.float64(1.0):
            m = wp.clamp(atanhx_x(z) * slope, wp.float64(-0.5) * d, wp.float64(0.5) * d)
        tm, gm = cell_profile(theta_l, theta_r, k, sigma, d, m + wp.float64(0.5) * d)
        best = wp.max(best, tm)
    return best


@wp.kernel
def design_metrics(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    theta: wp.array2d(dtype=wp.float64),
    first: int,
    count: int,
    cells: int,
    stack: int,
    out: wp.array2d(dtype=wp.float64),
):
    i = wp.tid()
    Tc = params[T_COLD, i]
    R = params[RADIUS, i]
    n0 = (stack - first) * cells
    n1 = n0 + cells
    L = seg_value(params, i, stack, LENGTH)
    out[i, GRADIENT] = (theta[i, n1] - theta[i, n0]) / L
    out[i, T_HOT] = Tc + theta[i, n1]
    # heat leak in the stack: per cell (2 h/R) S ∫theta = lam k^2 S ∫theta (h from k, lam of the cell)
    d = L / wp.float64(cells)
    integral = wp.float64(0.0)
    for c in range(cells):
        lam, k, sigma = cell_coeffs(params, flags, gas, theta, i, stack, n0 + c)
        v = wp.float64(0.5) * k * d
        tx = tanhx_x(v)
        part = wp.float64(0.0)
        if sigma != wp.float64(0.0):
            if v < wp.float64(1.0e-3):
                part = sigma * d * d / wp.float64(12.0)
            else:
                part = sigma * (wp.float64(1.0) - tx) / (k * k)
        mean = wp.float64(0.5) * (theta[i, n0 + c] + theta[i, n0 + c + 1])
        integral = integral + lam * k * k * d * (mean * tx + part)
    out[i, HEAT_LEAK] = PI * R * R * integral
    # maximum temperature
    best = theta[i, 0]
    for s in range(first, first + count):
        d_s = seg_value(params, i, s, LENGTH) / wp.float64(cells)
        for c in range(cells):
            node = (s - first) * cells + c
            lam_s, k_s, sigma_s = cell_coeffs(params, flags, gas, theta, i, s, node)
            if sigma_s != wp.float64(0.0):
                best = wp.max(best, cell_max(theta[i, node], theta[i, node + 1], k_s, sigma_s, d_s))
            else:
                best = wp.max(best, wp.max(theta[i, node], theta[i, node + 1]))
    out[i, T_MAX] = Tc + best


@wp.kernel
def metric_columns(
    metrics: wp.array2d(dtype=wp.float64), columns: wp.array(dtype=wp.int32), out: wp.array2d(dtype=Any)
):
    """out[c, i] = metrics[i, columns[c]] in out's precision (float32: to nearest, as
    NumPy's cast): chosen columns, each contiguous. A sweep file stores float32 (half the
    copy to the host); a table's objectives come back as float64 columns, which Dask
    passes between workers without the copy a strided column costs."""
    c, i = wp.tid()
    out[c, i] = out.dtype(metrics[i, columns[c]])


for _dtype in (wp.float32, wp.float64):  # instantiated here: the module holds both (and AOT builds them)
    wp.overload(metric_columns, {"out": wp.array2d(dtype=_dtype)})


#: Kinds of a design variable in :func:`design_table`.
LINEAR = wp.constant(0)
LOG = wp.constant(1)
MATERIAL = wp.constant(2)


@wp.struct
class DesignVariables:
    """A design space's variables on the device (:class:`tawarp.design.space.DeviceTable`),
    variable v of ``kind[v]`` (LINEAR, LOG or MATERIAL): on the grid, ``size[v]`` values
    ``grid[start[v]:]`` (a material's choices: their indices) at C-order ``stride[v]``; from
    a unit coordinate u, ``low[v] + u span[v]`` (in logs for LOG). ``row[v]``: its row of
    the varying table; ``materials`` (choices, parameters) the material parameters written
    into the rows ``material_rows``."""

    grid: wp.array(dtype=wp.float64)
    kind: wp.array(dtype=wp.int32)
    stride: wp.array(dtype=wp.int64)
    size: wp.array(dtype=wp.int32)
    start: wp.array(dtype=wp.int32)
    low: wp.array(dtype=wp.float64)
    span: wp.array(dtype=wp.float64)
    row: wp.array(dtype=wp.int32)
    materials: wp.array2d(dtype=wp.float64)
    material_rows: wp.array(dtype=wp.int32)


@wp.func
def design_coordinate(
    lo: wp.int64,
    i: int,
    v: int,
    unit: wp.array2d(dtype=wp.float64),
    dv: DesignVariables,
):
    """(value, material index) of variable v at point lo + i: on the grid when ``unit`` is
    empty (C-order index ((lo + i) // stride) % size into the variable's grid values at
    ``start``), else from the unit-cube coordinate unit[i, v] as DesignSpace.from_unit
    scales it (clipped to [0, 1]; low + u span, for LOG the exp of the log-scale values)
    and, for the material, min(floor(u size), size - 1) as the sweep's Sobol points."""
    if unit.shape[0] == 0:
        k = int(((lo + wp.int64(i)) // dv.stride[v]) % wp.int64(dv.size[v]))
        if dv.kind[v] == MATERIAL:
            return wp.float64(k), k
        return dv.grid[dv.start[v] + k], k
    u = unit[i, v]
    if dv.kind[v] == MATERIAL:
        k = wp.min(int(u * wp.float64(dv.size[v])), dv.size[v] - 1)
        return wp.float64(k), k
    x = dv.low[v] + wp.clamp(u, wp.float64(0.0), wp.float64(1.0)) * dv.span[v]
    if dv.kind[v] == LOG:
        x = wp.exp(x)
    return x, 0


@wp.kernel
def sobol_points(
    first: wp.int64,
    directions: wp.array2d(dtype=wp.int64),
    shift: wp.array(dtype=wp.int64),
    scale: wp.float64,
    unit: wp.array2d(dtype=wp.float64),
):
    """unit[k, d] = coordinate d of point first + k of a scrambled Sobol sequence (one thread
    per coordinate): the digital ``shift`` XOR the direction numbers ``directions[d, j]`` of
    the set bits j of the point's Gray code i ^ (i >> 1), times ``scale`` = 2^-bits. This is
    the construction of scipy.stats.qmc.Sobol, whose points it gives bit for bit from that
    engine's numbers (:func:`tawarp.design.samplers.sobol_directions`): any point is made
    where it is used, without the sequence's recurrence. The sequence's 2^30 points and
    30-bit numbers fit int32 (half the integer instructions of int64); the loop ends at
    the Gray code's highest set bit."""
    k, d = wp.tid()
    i = wp.int32(first + wp.int64(k))
    gray = i ^ (i >> 1)
    q = wp.int32(shift[d])
    j = int(0)
    while gray != 0:
        if (gray & 1) != 0:
            q = q ^ wp.int32(directions[d, j])
        gray = gray >> 1
        j = j + 1
    unit[k, d] = wp.float64(q) * scale


@wp.kernel
def design_table(
    lo: wp.int64,
    unit: wp.array2d(dtype=wp.float64),
    dv: DesignVariables,
    heat_input: wp.float64,
    table: wp.array2d(dtype=wp.float64),
    values: wp.array2d(dtype=wp.float64),
):
    """Column i of DesignSpace.varying_table for design point lo + i (one thread), on the
    device: row 0 the heat input, a material's rows (``material_rows``) the row of
    ``materials`` (one per choice) it picks, then each continuous variable's value in its
    ``row`` (after the material: an explicit stack variable overrides the material's
    value, as on the host). With a non-empty ``values``, values[v, i] keeps each
    variable's value (the material as its index)."""
    i = wp.tid()
    table[0, i] = heat_input
    for v in range(dv.kind.shape[0]):
        if dv.kind[v] == MATERIAL:
            x, k = design_coordinate(lo, i, v, unit, dv)
            for p in range(dv.material_rows.shape[0]):
                table[dv.material_rows[p], i] = dv.materials[k, p]
            if values.shape[0] > 0:
                values[v, i] = x
    for v in range(dv.kind.shape[0]):
        if dv.kind[v] != MATERIAL:
            x, k = design_coordinate(lo, i, v, unit, dv)
            table[dv.row[v], i] = x
            if values.shape[0] > 0:
                values[v, i] = x


@wp.kernel
def sampler_coordinates(
    values: wp.array2d(dtype=wp.float64),
    dv: DesignVariables,
    X: wp.array2d(dtype=wp.float64),
):
    """The sampler coordinates X[i, v] of design values ``values[v, i]`` (one thread per
    point and variable): a continuous variable's unit coordinate (v - low) / span (of
    log v for LOG; 0 when the range is one value), a material its index. The inverse of
    :func:`design_coordinate`'s scaling, written once so that a generation told from the
    device's values and one told again from stored values are told alike."""
    i, v = wp.tid()
    x = values[v, i]
    if dv.kind[v] == MATERIAL:
        X[i, v] = x
    elif dv.span[v] == wp.float64(0.0):
        X[i, v] = wp.float64(0.0)
    elif dv.kind[v] == LOG:
        X[i, v] = (wp.log(x) - dv.low[v]) / dv.span[v]
    else:
        X[i, v] = (x - dv.low[v]) / dv.span[v]
