"""Batch utilities on the device: a subset of parameter sets gathered, and its results
scattered back, without a host round trip (the cell-count estimate refines only the sets
still above its target)."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def gather_sets(
    params: wp.array2d(dtype=wp.float64),
    theta: wp.array2d(dtype=wp.float64),
    index: wp.array(dtype=wp.int32),
    params_out: wp.array2d(dtype=wp.float64),
    theta_out: wp.array2d(dtype=wp.float64),
):
    """Set ``index[k]`` of (``params`` (rows, n), ``theta`` (n, nodes)) as set k of
    (``params_out``, ``theta_out``)."""
    k = wp.tid()
    i = index[k]
    for r in range(params.shape[0]):
        params_out[r, k] = params[r, i]
    for c in range(theta.shape[1]):
        theta_out[k, c] = theta[i, c]


@wp.kernel
def scatter_sets(
    part: wp.array3d(dtype=wp.float64),
    index: wp.array(dtype=wp.int32),
    count: wp.array(dtype=wp.int32),
    out: wp.array3d(dtype=wp.float64),
):
    """Row k of ``part`` (k, m, c) as row ``index[k]`` of ``out`` (n, m, c) for k < count[0]
    (a part sized before its count was known: the slots beyond are empty); launched on (k, m)."""
    k, j = wp.tid()
    if k >= count[0]:
        return
    for c in range(part.shape[2]):
        out[index[k], j, c] = part[k, j, c]
