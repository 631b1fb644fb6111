"""The misfits and normal equations of many least-squares fits, where their model values are.

A fit evaluated at a point z with forward-difference neighbours ``z + step_a e_a``
(:class:`tawarp.fit.problems.KindProblems`) needs, of its parameter sets' model values Y,
only a few numbers: the cost r^T r of the weighted residuals ``r = w (Y - y)`` (re parts,
then im parts) on its rows, their unweighted sum |Y - y|^2, the gradient g = J^T r and the
Gauss-Newton matrix H = J^T J of ``J_a = (r_a - r) / step_a``. Three kernels form them
from the T-matrices where a launch left them, so that the model values themselves never
travel to the host: :func:`weighted_misfits` (a thread per set and row), then
:func:`partial_products` (a thread per fit, pair of columns of J and chunk of rows) and
:func:`normal_equations` (the chunks' sums in order: the same sums every run).

Model values are read through a table (:class:`ModelTable`): row k of set s is
``scale[k]`` times the complex entry ``e[k]`` of column ``columns[s, q[k]]`` of ``values``
(columns, entries x 2: re, im), times the set's complex ``gain[s]``. For the T-matrix kind
the columns are the distinct sets of a launch, q the heat input and e the entry of a row's
(frequency, coefficient) in the (m, 2, 2) T-matrices, and ``scale`` makes the
coefficient dimensionless (1, 1/Zc, Zc, 1: the operations of
:func:`tawarp.model.coefficients.normalize_entries`, whose complex division by a real Zc
multiplies by 1/Zc); model values already formed on the host are the
table ``columns[s, 0] = s``, e = k, scale = 1. A model value is thus the host's operations
on the same numbers (a complex product may round differently in its last bit, which the
forward difference's step raises in J); the sums over rows run in another order than
NumPy's. tests/test_misfit_device.py bounds both.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code


@wp.struct
class ModelTable:
    """The model values of a launch's sets, as the module doc reads them."""

    values: wp.array2d(dtype=wp.float64)
    columns: wp.array2d(dtype=wp.int32)
    gain: wp.array2d(dtype=wp.float64)
    row_q: wp.array(dtype=wp.int32)
    row_e: wp.array(dtype=wp.int32)
    scale: wp.array(dtype=wp.float64)


@wp.func
def model_value(table: ModelTable, s: int, k: int):
    """Model value (re, im) of row k of set s (the module's table; an empty ``gain``: 1 for
    every set); NaN where the set's column of that row was not computed (column -1)."""
    col = table.columns[s, table.row_q[k]]
    if col < 0:
        return wp.vec2d(wp.float64(wp.nan), wp.float64(wp.nan))
    e = 2 * table.row_e[k]
    re = table.values[col, e] * table.scale[k]
    im = table.values[col, e + 1] * table.scale[k]
    if table.gain.shape[0] == 0:
        return wp.vec2d(re, im)
    g_re = table.gain[s, 0]
    g_im = table.gain[s, 1]
    return wp.vec2d(re * g_re - im * g_im, re * g_im + im * g_re)


#: Row chunks of a fit's sums (:func:`partial_products`): a thread sums one chunk's rows,
#: and :func:`normal_equations` the chunks in order (a thread per sum over a fit's hundreds
#: of rows waits on each row's loads one after the other).
CHUNKS = wp.constant(8)


@wp.kernel
def weighted_misfits(
    table: ModelTable,
    fits: wp.array2d(dtype=wp.int32),
    data_y: wp.array3d(dtype=wp.float64),
    data_w: wp.array3d(dtype=wp.float64),
    rows: wp.array(dtype=wp.int32),
    r: wp.array3d(dtype=wp.float64),
    raw: wp.array2d(dtype=wp.float64),
):
    """Thread (f, j, t): of fit f, its sets' model values in ``table``, described by
    ``fits[f]`` = (first, p, data, row start, row count, slot), the weighted misfit of its
    set first + j (j = 0 the point, j = a its neighbour along parameter a - 1) at its t-th
    row k = rows[row start + t] (repeats count again: a bootstrap's weights):
    r[slot, j, 2 t : 2 t + 2] = w (Y - y) (re, im) with its data's y and w (data_y,
    data_w [data, k, re / im]); and for the point raw[slot, t] = |Y - y|^2 (the fits of an
    evaluation's launches share these arrays, each in its slot)."""
    f, j, t = wp.tid()
    if j > fits[f, 1] or t >= fits[f, 4]:
        return
    d = fits[f, 2]
    o = fits[f, 5]
    k = rows[fits[f, 3] + t]
    y = model_value(table, fits[f, 0] + j, k)
    d_re = y[0] - data_y[d, k, 0]
    d_im = y[1] - data_y[d, k, 1]
    r[o, j, 2 * t] = data_w[d, k, 0] * d_re
    r[o, j, 2 * t + 1] = data_w[d, k, 1] * d_im
    if j == 0:
        raw[o, t] = d_re * d_re + d_im * d_im


@wp.kernel
def partial_products(
    fits: wp.array2d(dtype=wp.int32),
    step: wp.array2d(dtype=wp.float64),
    r: wp.array3d(dtype=wp.float64),
    raw: wp.array2d(dtype=wp.float64),
    partial: wp.array4d(dtype=wp.float64),
    partial_raw: wp.array2d(dtype=wp.float64),
):
    """Thread (f, a, b, c), a <= b <= p: the sum over chunk c of fit f's rows (rows c n / C
    to (c + 1) n / C, C = :data:`CHUNKS`) of r^T r (a = b = 0), J_b^T r (a = 0) or
    J_a^T J_b, with ``J_a = (r_a - r) / step[slot, a - 1]``, into partial[slot, a, b, c];
    thread (f, 0, 0, c) also that of |Y - y|^2 into partial_raw[slot, c]."""
    f, a, b, c = wp.tid()
    if a > b or b > fits[f, 1]:
        return
    o = fits[f, 5]
    n = fits[f, 4]
    lo = c * n // CHUNKS
    hi = (c + 1) * n // CHUNKS
    step_a = wp.float64(1.0)
    step_b = wp.float64(1.0)
    if a > 0:
        step_a = step[o, a - 1]
    if b > 0:
        step_b = step[o, b - 1]
    acc = wp.float64(0.0)
    acc_raw = wp.float64(0.0)
    for e in range(2 * lo, 2 * hi):
        r0 = r[o, 0, e]
        if b == 0:
            acc += r0 * r0
        elif a == 0:
            acc += (r[o, b, e] - r0) / step_b * r0
        else:
            acc += (r[o, a, e] - r0) / step_a * ((r[o, b, e] - r0) / step_b)
    partial[o, a, b, c] = acc
    if b == 0:
        for t in range(lo, hi):
            acc_raw += raw[o, t]
        partial_raw[o, c] = acc_raw


@wp.kernel
def normal_equations(
    fits: wp.array2d(dtype=wp.int32),
    partial: wp.array4d(dtype=wp.float64),
    partial_raw: wp.array2d(dtype=wp.float64),
    out: wp.array2d(dtype=wp.float64),
):
    """Thread (f, a, b), a <= b <= p: the chunks' sums of :func:`partial_products` in order:

    - (0, 0): the cost r^T r into out[slot, 0] and the sum |Y - y|^2 into out[slot, 1];
    - (0, b): g[b - 1] = J_b^T r into out[slot, 1 + b];
    - (a, b): H[a - 1, b - 1] = J_a^T J_b into out[slot, 1 + P + (a - 1) P + b] and its
      mirror (out has 2 + P + P^2 columns)."""
    f, a, b = wp.tid()
    if a > b or b > fits[f, 1]:
        return
    o = fits[f, 5]
    acc = wp.float64(0.0)
    for c in range(CHUNKS):
        acc += partial[o, a, b, c]
    P = partial.shape[1] - 1
    if b == 0:
        acc_raw = wp.float64(0.0)
        for c in range(CHUNKS):
            acc_raw += partial_raw[o, c]
        out[o, 0] = acc
        out[o, 1] = acc_raw
    elif a == 0:
        out[o, 1 + b] = acc
    else:
        out[o, 1 + P + (a - 1) * P + b] = acc
        out[o, 1 + P + (b - 1) * P + a] = acc
