"""Warp kernels of the heat solve's warm starts on a GPU
(:class:`tawarp.model.warm_starts.DeviceWarmStarts`): the kept sets' values and converged
excesses stay on the device, and a new set's start is the excess of the nearest kept set
by the rule of :class:`tawarp.model.warm_starts.WarmStarts` (per row that differs between
the sets: ln v where every value of the row is positive, else v over the row's largest
|v|; the largest |difference| over those rows; the nearest kept set within a radius, the
oldest of equals). A launch's start then needs no copy of the excesses to the host and
back, and no search on the host.

The sets of a search: the kept ones, ``kept`` (capacity, rows) and ``kept_theta``
(capacity, columns), ``count`` of them in a ring whose oldest is slot ``oldest``; the new
ones, columns ``heated`` of ``table`` (rows, n), the launch's varying table.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code


@wp.kernel
def row_spread(
    kept: wp.array2d(dtype=wp.float64),
    count: int,
    table: wp.array2d(dtype=wp.float64),
    heated: wp.array(dtype=wp.int32),
    differ: wp.array(dtype=wp.int32),
    positive: wp.array(dtype=wp.int32),
    scale: wp.array(dtype=wp.float64),
):
    """Per row r of the kept and new sets together: whether its values differ (none NaN),
    are all positive, and their largest |v| (1 where it is 0)."""
    r = wp.tid()
    lo = wp.float64(wp.inf)
    hi = wp.float64(-wp.inf)
    big = wp.float64(0.0)
    pos = int(1)
    nan = int(0)
    for a in range(count + heated.shape[0]):
        v = wp.float64(0.0)
        if a < count:
            v = kept[a, r]
        else:
            v = table[r, heated[a - count]]
        if wp.isnan(v):
            nan = 1
        lo = wp.min(lo, v)
        hi = wp.max(hi, v)
        big = wp.max(big, wp.abs(v))
        if not (v > wp.float64(0.0)):
            pos = 0
    differ[r] = int(nan == 0 and lo < hi)
    positive[r] = pos
    if big > wp.float64(0.0):
        scale[r] = big
    else:
        scale[r] = wp.float64(1.0)


@wp.kernel
def differing_rows(differ: wp.array(dtype=wp.int32), rows: wp.array(dtype=wp.int32), n_rows: wp.array(dtype=wp.int32)):
    """The rows that differ, in order (one thread: a table has a hundred rows or so)."""
    k = int(0)
    for r in range(differ.shape[0]):
        if differ[r] != 0:
            rows[k] = r
            k += 1
    n_rows[0] = k


@wp.func
def scaled(v: wp.float64, positive: int, scale: wp.float64):
    """A value in the distance's units: ln v on a positive row, else v over the row's scale."""
    if positive != 0:
        return wp.log(v)
    return v / scale


@wp.kernel
def scaled_values(
    kept: wp.array2d(dtype=wp.float64),
    count: int,
    table: wp.array2d(dtype=wp.float64),
    heated: wp.array(dtype=wp.int32),
    rows: wp.array(dtype=wp.int32),
    n_rows: wp.array(dtype=wp.int32),
    positive: wp.array(dtype=wp.int32),
    scale: wp.array(dtype=wp.float64),
    u: wp.array2d(dtype=wp.float64),
):
    """u[a, q]: set a's value on the q-th differing row in the distance's units (the kept
    sets first, by slot, then the new ones)."""
    a, q = wp.tid()
    if q >= n_rows[0]:
        return
    r = rows[q]
    v = wp.float64(0.0)
    if a < count:
        v = kept[a, r]
    else:
        v = table[r, heated[a - count]]
    u[a, q] = scaled(v, positive[r], scale[r])


@wp.kernel
def nearest_start(
    u: wp.array2d(dtype=wp.float64),
    n_rows: wp.array(dtype=wp.int32),
    count: int,
    oldest: int,
    radius: wp.float64,
    heated: wp.array(dtype=wp.int32),
    kept_theta: wp.array2d(dtype=wp.float64),
    start: wp.array2d(dtype=wp.float64),
):
    """Row heated[j] of ``start`` (zeros before): the excess of the kept set nearest new set
    j in the largest |difference| of u, where it is within ``radius`` (the oldest of
    equally near ones)."""
    j = wp.tid()
    me = count + j
    best = wp.float64(wp.inf)
    slot = int(-1)
    for a in range(count):
        i = (oldest + a) % count
        d = wp.float64(0.0)
        for q in range(n_rows[0]):
            d = wp.max(d, wp.abs(u[me, q] - u[i, q]))
            if d >= best:
                break
        if d < best:
            best = d
            slot = i
    if slot >= 0 and best <= radius:
        for c in range(start.shape[1]):
            start[heated[j], c] = kept_theta[slot, c]


@wp.kernel
def keep_sets(
    table: wp.array2d(dtype=wp.float64),
    theta: wp.array2d(dtype=wp.float64),
    heated: wp.array(dtype=wp.int32),
    slots: wp.array(dtype=wp.int32),
    kept: wp.array2d(dtype=wp.float64),
    kept_theta: wp.array2d(dtype=wp.float64),
):
    """Set heated[k] of the launch (its values and converged excess) into ring slot slots[k]."""
    k = wp.tid()
    i = slots[k]
    for r in range(kept.shape[1]):
        kept[i, r] = table[r, heated[k]]
    for c in range(kept_theta.shape[1]):
        kept_theta[i, c] = theta[heated[k], c]
