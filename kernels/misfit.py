"""The misfits and normal equations of many least-squares fits, where their model values are.

A fit evaluated at a point z with forward-difference neighbours ``z + step_a e_a``
(:class:`tawarp.fit.problems.KindProblems`) needs, of its parameter sets' model values Y,
only a few numbers: the cost r^T r of the weighted residuals ``r = w (Y - y)`` (re parts,
then im parts) on its rows, their unweighted sum |Y - y|^2, the gradient g = J^T r and the
Gauss-Newton matrix H = J^T J of ``J_a = (r_a - r) / step_a``. :func:`normal_equations`
forms them from the T-matrices where a launch left them (one thread per fit and pair of
columns of J, each summing over the fit's rows in order: the same sums every run), so
that the model values themselves never travel to the host.

Model values are read through a table: row k of set s is ``scale[k]`` times the complex
entry ``e[k]`` of column ``columns[s, q[k]]`` of ``values`` (columns, entries x 2: re, im),
times the set's complex ``gain[s]``. For the T-matrix kind the columns are the distinct
sets of a launch, q the heat input and e the entry of a row's (frequency, coefficient) in
the (m, 2, 2) T-matrices, and ``scale`` makes the coefficient dimensionless (1, 1/Zc, Zc,
1: the operations of :func:`tawarp.model.coefficients.normalize_entries`, whose complex
division by a real Zc multiplies by 1/Zc); model values already formed on the host are the
table ``columns[s, 0] = s``, e = k, scale = 1. A model value is thus the host's bit for bit;
the sums over rows are in another order than NumPy's (rounding apart).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code


@wp.func
def model_value(
    values: wp.array2d(dtype=wp.float64),
    columns: wp.array2d(dtype=wp.int32),
    gain: wp.array2d(dtype=wp.float64),
    row_q: wp.array(dtype=wp.int32),
    row_e: wp.array(dtype=wp.int32),
    scale: wp.array(dtype=wp.float64),
    s: int,
    k: int,
):
    """Model value (re, im) of row k of set s (the module's table; an empty ``gain``: 1 for
    every set); NaN where the set's column of that row was not computed (column -1)."""
    col = columns[s, row_q[k]]
    if col < 0:
        return wp.vec2d(wp.float64(wp.nan), wp.float64(wp.nan))
    e = 2 * row_e[k]
    re = values[col, e] * scale[k]
    im = values[col, e + 1] * scale[k]
    if gain.shape[0] == 0:
        return wp.vec2d(re, im)
    g_re = gain[s, 0]
    g_im = gain[s, 1]
    return wp.vec2d(re * g_re - im * g_im, re * g_im + im * g_re)


@wp.kernel
def normal_equations(
    values: wp.array2d(dtype=wp.float64),
    columns: wp.array2d(dtype=wp.int32),
    gain: wp.array2d(dtype=wp.float64),
    row_q: wp.array(dtype=wp.int32),
    row_e: wp.array(dtype=wp.int32),
    scale: wp.array(dtype=wp.float64),
    fits: wp.array2d(dtype=wp.int32),
    step: wp.array2d(dtype=wp.float64),
    data_y: wp.array3d(dtype=wp.float64),
    data_w: wp.array3d(dtype=wp.float64),
    rows: wp.array(dtype=wp.int32),
    out: wp.array2d(dtype=wp.float64),
):
    """Thread (f, a, b), a <= b <= p: of fit f, described by ``fits[f]`` = (first, p,
    data, row start, row count, slot), whose sets are first (the point) and first + a (its
    neighbour along parameter a - 1, step[f, a - 1]), over its rows rows[row start : +
    row count] (repeats count again: a bootstrap's weights), with its data's y and w
    (data_y, data_w [data, k, re / im]):

    - (0, 0): the cost r^T r into out[slot, 0] and the sum |Y - y|^2 into out[slot, 1];
    - (0, b): g[b - 1] = J_b^T r into out[.., 1 + b];
    - (a, b): H[a - 1, b - 1] = J_a^T J_b into out[.., 1 + P + (a - 1) P + b] and its mirror
      (P = step.shape[1]: out has 2 + P + P^2 columns)."""
    f, a, b = wp.tid()
    p = fits[f, 1]
    if a > b or b > p:
        return
    s0 = fits[f, 0]
    d = fits[f, 2]
    start = fits[f, 3]
    acc = wp.float64(0.0)
    raw = wp.float64(0.0)
    step_a = wp.float64(0.0)
    step_b = wp.float64(0.0)
    if a > 0:
        step_a = step[f, a - 1]
    if b > 0:
        step_b = step[f, b - 1]
    for t in range(fits[f, 4]):
        k = rows[start + t]
        y0 = model_value(values, columns, gain, row_q, row_e, scale, s0, k)
        w_re = data_w[d, k, 0]
        w_im = data_w[d, k, 1]
        d_re = y0[0] - data_y[d, k, 0]
        d_im = y0[1] - data_y[d, k, 1]
        r_re = w_re * d_re
        r_im = w_im * d_im
        if b == 0:
            acc += r_re * r_re + r_im * r_im
            raw += d_re * d_re + d_im * d_im
        else:
            yb = model_value(values, columns, gain, row_q, row_e, scale, s0 + b, k)
            jb_re = (w_re * (yb[0] - data_y[d, k, 0]) - r_re) / step_b
            jb_im = (w_im * (yb[1] - data_y[d, k, 1]) - r_im) / step_b
            if a == 0:
                acc += jb_re * r_re + jb_im * r_im
            else:
                ya = model_value(values, columns, gain, row_q, row_e, scale, s0 + a, k)
                ja_re = (w_re * (ya[0] - data_y[d, k, 0]) - r_re) / step_a
                ja_im = (w_im * (ya[1] - data_y[d, k, 1]) - r_im) / step_a
                acc += ja_re * jb_re + ja_im * jb_im
    P = step.shape[1]
    o = fits[f, 5]
    if b == 0:
        out[o, 0] = acc
        out[o, 1] = raw
    elif a == 0:
        out[o, 1 + b] = acc
    else:
        out[o, 1 + P + (a - 1) * P + b] = acc
        out[o, 1 + P + (b - 1) * P + a] = acc
