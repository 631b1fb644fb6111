"""Warp kernel of the design objectives, evaluated on the heat grid after the heat solve.

Per parameter set i (one thread), from the nodal temperatures of
:meth:`tawarp.forward.Engine.heat` (exact at the nodes: exponentially fitted scheme):

- ``out[i, GRADIENT]`` gradient across the stack ``(T(x3) - T(x2)) / l_s`` [K/m];
- ``out[i, T_MAX]`` maximum temperature over the thermal domain [K]: the nodes, and inside
  each cell with a source (the heater) the zero of dtheta/dx, found by bisection on the
  exact cell profile (theta' has at most one zero in a constant-coefficient cell);
- ``out[i, HEAT_LEAK]`` heat leaked to the wall in the stack ``∫ (2 h_s/R) theta S dx`` [W],
  exact per cell: ``∫ theta = d [mean tanh(v)/v + sigma (1 - tanh(v)/v) / k^2]``,
  ``v = k d / 2``, mean of the two nodal values, ``2 h/R = lam k^2`` of the cell;
- ``out[i, T_HOT]`` temperature at the hot end of the stack T(x3) [K].
"""

import warp as wp

from .heat import cell_coeffs_at, cell_profile, segment_nonlinear, tanhx_x
from .layout import LENGTH, RADIUS, T_COLD, seg_value

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code


@wp.func
def cell_coeffs(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32),
                gas: wp.array(dtype=wp.float64), theta: wp.array2d(dtype=wp.float64), i: int, s: int, node: int):
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
def cell_max(theta_l: wp.float64, theta_r: wp.float64, k: wp.float64, sigma: wp.float64, d: wp.float64):
    """Largest theta in a cell (ends or interior stationary point)."""
    best = wp.max(theta_l, theta_r)
    t0, g0 = cell_profile(theta_l, theta_r, k, sigma, d, wp.float64(0.0))
    t1, g1 = cell_profile(theta_l, theta_r, k, sigma, d, d)
    if g0 > wp.float64(0.0) and g1 < wp.float64(0.0):
        a = wp.float64(0.0)
        b = d
        for _it in range(60):
            m = wp.float64(0.5) * (a + b)
            tm, gm = cell_profile(theta_l, theta_r, k, sigma, d, m)
            if gm > wp.float64(0.0):
                a = m
            else:
                b = m
        tm, gm = cell_profile(theta_l, theta_r, k, sigma, d, wp.float64(0.5) * (a + b))
        best = wp.max(best, tm)
    return best


@wp.kernel
def design_metrics(params: wp.array2d(dtype=wp.float64), flags: wp.array2d(dtype=wp.int32),
                   gas: wp.array(dtype=wp.float64), theta: wp.array2d(dtype=wp.float64),
                   first: int, count: int, cells: int, stack: int, out: wp.array2d(dtype=wp.float64)):
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
