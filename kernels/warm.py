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


#: Parts a search's kept sets (and the rows' spread its sets) are split into, a thread
#: each: a thread that walked every kept set alone took about a millisecond a launch on a
#: GPU, most of it idle; each part keeps its own best, and the parts are taken in order.
PARTS = wp.constant(64)


@wp.func
def part_range(total: int, part: int):
    """The [start, end) of ``part``'s share of ``total`` items (PARTS parts, in order)."""
    size = (total + PARTS - 1) // PARTS
    start = wp.min(part * size, total)
    return start, wp.min(start + size, total)


@wp.kernel
def row_spread_parts(
    kept: wp.array2d(dtype=wp.float64),
    count: int,
    table: wp.array2d(dtype=wp.float64),
    heated: wp.array(dtype=wp.int32),
    lo: wp.array2d(dtype=wp.float64),
    hi: wp.array2d(dtype=wp.float64),
    big: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
):
    """Thread (r, p): over part p of the kept and new sets together, row r's smallest and
    largest value, largest |v| and flags (1: a NaN, 2: a value not > 0)."""
    r, p = wp.tid()
    a0, a1 = part_range(count + heated.shape[0], p)
    low = wp.float64(wp.inf)
    high = wp.float64(-wp.inf)
    most = wp.float64(0.0)
    f = int(0)
    for a in range(a0, a1):
        v = wp.float64(0.0)
        if a < count:
            v = kept[a, r]
        else:
            v = table[r, heated[a - count]]
        if wp.isnan(v):
            f = f | 1
        low = wp.min(low, v)
        high = wp.max(high, v)
        most = wp.max(most, wp.abs(v))
        if not (v > wp.float64(0.0)):
            f = f | 2
    lo[r, p] = low
    hi[r, p] = high
    big[r, p] = most
    flags[r, p] = f


@wp.kernel
def row_spread(
    lo: wp.array2d(dtype=wp.float64),
    hi: wp.array2d(dtype=wp.float64),
    big: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    differ: wp.array(dtype=wp.int32),
    positive: wp.array(dtype=wp.int32),
    scale: wp.array(dtype=wp.float64),
):
    """Per row r of the kept and new sets together, from its parts (:func:`row_spread_parts`):
    whether its values differ (none NaN), are all positive, and their largest |v| (1 where
    it is 0). Minima, maxima and flags are exact in any order: the values of one walk over
    every set (where a row holds a NaN its scale is not read)."""
    r = wp.tid()
    low = wp.float64(wp.inf)
    high = wp.float64(-wp.inf)
    most = wp.float64(0.0)
    f = int(0)
    for p in range(PARTS):
        low = wp.min(low, lo[r, p])
        high = wp.max(high, hi[r, p])
        most = wp.max(most, big[r, p])
        f = f | flags[r, p]
    differ[r] = int((f & 1) == 0 and low < high)
    positive[r] = int((f & 2) == 0)
    if most > wp.float64(0.0):
        scale[r] = most
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
def nearest_parts(
    u: wp.array2d(dtype=wp.float64),
    n_rows: wp.array(dtype=wp.int32),
    count: int,
    oldest: int,
    best: wp.array2d(dtype=wp.float64),
    at: wp.array2d(dtype=wp.int32),
):
    """Thread (j, p): among part p of the kept sets by age (oldest first), the nearest to
    new set j in the largest |difference| of u and its age (the oldest of equally near
    ones; -1 in an empty part)."""
    j, p = wp.tid()
    me = count + j
    a0, a1 = part_range(count, p)
    near = wp.float64(wp.inf)
    age = int(-1)
    for a in range(a0, a1):
        i = (oldest + a) % count
        d = wp.float64(0.0)
        for q in range(n_rows[0]):
            d = wp.max(d, wp.abs(u[me, q] - u[i, q]))
            if d >= near:
                break
        if d < near:
            near = d
            age = a
    best[j, p] = near
    at[j, p] = age


@wp.kernel
def nearest_start(
    best: wp.array2d(dtype=wp.float64),
    at: wp.array2d(dtype=wp.int32),
    count: int,
    oldest: int,
    radius: wp.float64,
    heated: wp.array(dtype=wp.int32),
    kept_theta: wp.array2d(dtype=wp.float64),
    start: wp.array2d(dtype=wp.float64),
):
    """Row heated[j] of ``start`` (zeros before): the excess of the kept set nearest new set
    j (its parts' nearest, :func:`nearest_parts`, taken in age order: the oldest of equally
    near ones), where it is within ``radius``."""
    j = wp.tid()
    near = wp.float64(wp.inf)
    age = int(-1)
    for p in range(PARTS):
        if best[j, p] < near:
            near = best[j, p]
            age = at[j, p]
    if age >= 0 and near <= radius:
        slot = (oldest + age) % count
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
