"""Warp kernels of a sweep's reductions (:mod:`tawarp.design.sweep`): what a sweep keeps of
its outputs instead of (or beside) the raw values, computed on the device chunk by chunk.

Every reduction orders float32 outputs (what a sweep file stores) by an integer key,
:func:`ordered_key`: the value's IEEE-754 bit pattern read as a signed magnitude, so that
integers compare as the floats do (-0 and +0 equal), and reductions over chunks are
exact and independent of the order of the threads:

- histograms (:func:`histogram`): bins of equal relative width, the key's top 20 bits
  (sign, exponent and 11 mantissa bits: a bin spans 2^-11 of its values), counted with
  integer atomics, their occupied bins compacted in order for the host
  (:func:`occupied_bins`, :func:`compact_bins`);
- best, per variable level (:func:`marginal_best`): the smallest *rank key* (the key of
  the sign-adjusted objective times 2^32 plus the point index: better first, ties by
  index) by integer ``atomic_min``;
- top-k and the Pareto front of two objectives: candidates better than a threshold
  (:func:`top_candidates`; the first chunk: its K first after a radix sort,
  :func:`first_candidates`), or not dominated within the chunk (:func:`pareto_bins`, a
  prefix minimum by :func:`prefix_min_step`, :func:`pareto_candidates`), compacted by an
  atomic counter; the host sorts and merges them exactly.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

#: key bits dropped for a histogram bin: 32 - 12 = 20 bits kept
HIST_SHIFT_BITS = 12
HIST_SHIFT = wp.constant(HIST_SHIFT_BITS)
#: bins of a histogram: every key >> HIST_SHIFT, offset to be non-negative
HIST_BINS = 1 << 20
HIST_OFFSET_BINS = 1 << 19
HIST_OFFSET = wp.constant(HIST_OFFSET_BINS)
#: histogram bins per block of the compaction (:func:`occupied_bins`, :func:`compact_bins`)
HIST_BLOCK_BINS = 256
HIST_BLOCK = wp.constant(HIST_BLOCK_BINS)
#: key bits dropped for a Pareto filter bin (2^16 bins of the first objective)
PARETO_SHIFT = wp.constant(16)
PARETO_BINS = 1 << 16
PARETO_OFFSET = wp.constant(1 << 15)
#: the rank key of a point that is not a candidate (NaN, or empty)
NONE_KEY = 2**63 - 1
NONE = wp.constant(wp.int64(NONE_KEY))
TWO32 = wp.constant(wp.int64(4294967296))


@wp.func
def pow2(e: int):
    """2^e as a float64, exactly, for |e| <= 186 (three shifts: cheaper than pow)."""
    a = wp.abs(e)
    p = wp.float64(wp.int64(1) << wp.int64(wp.min(a, 62)))
    p *= wp.float64(wp.int64(1) << wp.int64(wp.clamp(a - 62, 0, 62)))
    p *= wp.float64(wp.int64(1) << wp.int64(wp.clamp(a - 124, 0, 62)))
    if e < 0:
        return wp.float64(1.0) / p
    return p


@wp.func
def ordered_key(v: wp.float32):
    """The float32 ``v``'s bit pattern as a signed magnitude (int64): +-(exponent field
    2^23 + mantissa field), computed exactly from the value (Warp has no bit cast):
    monotone in v, equal for equal values; +-inf get +-(255 2^23). Not for NaN."""
    x = wp.abs(wp.float64(v))
    mag = wp.int64(0)
    if x == wp.float64(wp.inf):
        mag = wp.int64(255) * wp.int64(8388608)
    elif x < wp.float64(1.1754943508222875e-38):  # subnormal (or 0): the mantissa field is x 2^149
        mag = wp.int64(x * wp.float64(7.1362384635297994e44))
    else:
        e = int(wp.floor(wp.log2(x)))
        # log2 may round across a power of two: correct e so that 2^e <= x < 2^(e + 1)
        if pow2(e) > x:
            e -= 1
        if pow2(e + 1) <= x:
            e += 1
        m = (x / pow2(e) - wp.float64(1.0)) * wp.float64(8388608.0)
        mag = wp.int64(e + 127) * wp.int64(8388608) + wp.int64(m)
    if v < wp.float32(0.0):
        return -mag
    return mag


@wp.func
def rank_key(v: wp.float32, sign: wp.float32, index: wp.int64):
    """Key ordering points better first (``sign`` = 1 minimize, -1 maximize), ties by
    index: ordered_key(sign v) 2^32 + index; NONE for NaN."""
    if wp.isnan(v):
        return NONE
    return ordered_key(sign * v) * TWO32 + index


@wp.kernel
def histogram(values: wp.array2d(dtype=wp.float32), counts: wp.array2d(dtype=wp.int64), nan: wp.array(dtype=wp.int64)):
    """counts[o, bin] += 1 for each output o of each point (NaN counted apart)."""
    o, i = wp.tid()
    v = values[o, i]
    if wp.isnan(v):
        wp.atomic_add(nan, o, wp.int64(1))
    else:
        b = int((ordered_key(v) >> wp.int64(HIST_SHIFT)) + wp.int64(HIST_OFFSET))
        wp.atomic_add(counts, o, b, wp.int64(1))


@wp.kernel
def occupied_bins(counts: wp.array2d(dtype=wp.int64), occupied: wp.array2d(dtype=wp.int32)):
    """occupied[o, b // HIST_BLOCK] += 1 for each bin b of output o that holds a count
    (``occupied`` zeroed first; once per sweep, not per chunk: the histogram's own atomics
    stay ones whose value is not read back)."""
    o, b = wp.tid()
    if counts[o, b] != wp.int64(0):
        wp.atomic_add(occupied, o, b // HIST_BLOCK, 1)


@wp.kernel
def compact_bins(
    counts: wp.array2d(dtype=wp.int64),
    occupied: wp.array2d(dtype=wp.int32),
    start: wp.array2d(dtype=wp.int32),
    bins: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int64),
):
    """The histogram's occupied bins in order, those of output o's block j of HIST_BLOCK
    bins (``occupied[o, j]`` of them, :func:`occupied_bins`) from place start[o, j]: ``bins``
    the bin, ``count`` its count, so that the host reads the few occupied bins instead of
    every one."""
    o, j = wp.tid()
    if occupied[o, j] == 0:
        return
    k = start[o, j]
    for b in range(j * HIST_BLOCK, (j + 1) * HIST_BLOCK):
        c = counts[o, b]
        if c != wp.int64(0):
            bins[k] = b
            count[k] = c
            k += 1


@wp.kernel
def marginal_best(
    lo: wp.int64,
    objective: wp.array(dtype=wp.float32),
    sign: wp.float32,
    grid_stride: wp.array(dtype=wp.int64),
    grid_size: wp.array(dtype=wp.int32),
    values: wp.array2d(dtype=wp.float64),
    low: wp.array(dtype=wp.float64),
    span: wp.array(dtype=wp.float64),
    log: wp.array(dtype=wp.int32),
    levels: wp.array(dtype=wp.int32),
    first_level: wp.array(dtype=wp.int32),
    best: wp.array(dtype=wp.int64),
):
    """For each variable v, the best rank key of the points at each of its levels
    (``best[first_level[v] + level]``): a grid's index along v (``values`` empty: from
    the C-order index with ``grid_stride``, ``grid_size``), else the value's bin among
    ``levels[v]`` equal bins of [low, low + span) (of its logarithm where ``log[v]``;
    ``span`` 0: the value is the level, a material index)."""
    i = wp.tid()
    key = rank_key(objective[i], sign, lo + wp.int64(i))
    if key == NONE:
        return
    for v in range(levels.shape[0]):
        level = int(0)
        if values.shape[0] == 0:
            level = int(((lo + wp.int64(i)) // grid_stride[v]) % wp.int64(grid_size[v]))
        elif span[v] == wp.float64(0.0):
            level = int(values[v, i])
        else:
            x = values[v, i]
            if log[v] != 0:
                x = wp.log(x)
            t = (x - low[v]) / span[v]
            level = wp.clamp(int(wp.floor(t * wp.float64(levels[v]))), 0, levels[v] - 1)
        if key < best[first_level[v] + level]:  # a plain read first: few atomics once the best are found
            wp.atomic_min(best, first_level[v] + level, key)


@wp.struct
class Candidates:
    """A chunk's candidates, compacted from slot 0: ``count[0]`` of them, their rank keys
    (or point indices), outputs (chunk, outputs) and values (chunk, variables): a row per
    slot, so that the filled slots are one contiguous block to copy to the host."""

    count: wp.array(dtype=wp.int32)
    key: wp.array(dtype=wp.int64)
    out: wp.array2d(dtype=wp.float32)
    val: wp.array2d(dtype=wp.float64)


@wp.func
def keep_candidate(
    i: int, key: wp.int64, outputs: wp.array2d(dtype=wp.float32), values: wp.array2d(dtype=wp.float64), cand: Candidates
):
    """Append point i of the chunk (its rank key or index ``key``, outputs, values)."""
    slot = wp.atomic_add(cand.count, 0, 1)
    cand.key[slot] = key
    for o in range(outputs.shape[0]):
        cand.out[slot, o] = outputs[o, i]
    for v in range(values.shape[0]):
        cand.val[slot, v] = values[v, i]


@wp.func
def pareto_keys(outputs: wp.array2d(dtype=wp.float32), rows: wp.vec2i, signs: wp.vec2f, i: int):
    """Point i's bin of the first objective (output ``rows[0]``) for the Pareto filter and
    the ordered key of the second (both sign-adjusted: smaller is better); bin -1 where an
    objective is NaN (the point is left out)."""
    a = outputs[rows[0], i]
    b = outputs[rows[1], i]
    if wp.isnan(a) or wp.isnan(b):
        return -1, NONE
    bin = int((ordered_key(signs[0] * a) >> wp.int64(PARETO_SHIFT)) + wp.int64(PARETO_OFFSET))
    return bin, ordered_key(signs[1] * b)


@wp.kernel
def top_candidates(
    lo: wp.int64,
    outputs: wp.array2d(dtype=wp.float32),
    row: int,
    sign: wp.float32,
    threshold: wp.int64,
    values: wp.array2d(dtype=wp.float64),
    cand: Candidates,
):
    """Points whose rank key (output ``row``) is below ``threshold`` (the k-th best so
    far), with their outputs and values, compacted (in any order) from slot 0."""
    i = wp.tid()
    key = rank_key(outputs[row, i], sign, lo + wp.int64(i))
    if key < threshold:
        keep_candidate(i, key, outputs, values, cand)


@wp.kernel
def chunk_rank_keys(
    lo: wp.int64,
    outputs: wp.array2d(dtype=wp.float32),
    row: int,
    sign: wp.float32,
    keys: wp.array(dtype=wp.int64),
    point: wp.array(dtype=wp.int32),
):
    """Rank keys of output ``row`` of a chunk's points, to be sorted with their places."""
    i = wp.tid()
    keys[i] = rank_key(outputs[row, i], sign, lo + wp.int64(i))
    point[i] = i


@wp.kernel
def first_candidates(
    keys: wp.array(dtype=wp.int64),
    point: wp.array(dtype=wp.int32),
    outputs: wp.array2d(dtype=wp.float32),
    values: wp.array2d(dtype=wp.float64),
    cand: Candidates,
):
    """The first places of sorted rank keys (``keys``, ``point``: the chunk's top) as
    candidates, those with a key (not NaN)."""
    j = wp.tid()
    if keys[j] != NONE:
        i = point[j]
        keep_candidate(i, keys[j], outputs, values, cand)


@wp.kernel
def pareto_bins(
    outputs: wp.array2d(dtype=wp.float32),
    rows: wp.vec2i,
    signs: wp.vec2f,
    best1: wp.array(dtype=wp.int64),
):
    """best1[bin of the first objective's key] = the smallest key of the second objective
    among the chunk's points in that bin (points with a NaN objective left out)."""
    i = wp.tid()
    bin, k1 = pareto_keys(outputs, rows, signs, i)
    if bin < 0:
        return
    if k1 < best1[bin]:  # a plain read first: few atomics once the bin's best is found
        wp.atomic_min(best1, bin, k1)


@wp.kernel
def prefix_min_step(src: wp.array(dtype=wp.int64), step: int, dst: wp.array(dtype=wp.int64)):
    """One step of Hillis and Steele's scan: dst[j] = min(src[j], src[j - step])."""
    j = wp.tid()
    v = src[j]
    if j >= step:
        v = wp.min(v, src[j - step])
    dst[j] = v


@wp.kernel
def pareto_candidates(
    lo: wp.int64,
    outputs: wp.array2d(dtype=wp.float32),
    rows: wp.vec2i,
    signs: wp.vec2f,
    before: wp.array(dtype=wp.int64),
    values: wp.array2d(dtype=wp.float64),
    cand: Candidates,
):
    """Points not dominated by a point of an earlier first-objective bin (``before[b]``:
    the smallest second-objective key over the bins before b; an earlier bin's first
    objective is strictly smaller, so a second objective <= this point's dominates it),
    compacted with their outputs and values. The exact front is the host's, from these."""
    i = wp.tid()
    bin, k1 = pareto_keys(outputs, rows, signs, i)
    if bin < 0:
        return
    if bin == 0 or before[bin - 1] > k1:
        keep_candidate(i, lo + wp.int64(i), outputs, values, cand)
