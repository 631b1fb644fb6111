"""Warp kernels of the design samplers (:mod:`tawarp.design.samplers`): CMA-ES and
NSGA-II generations made and updated on the device.

CMA-ES (Hansen, "The CMA Evolution Strategy: A Tutorial", arXiv:1604.00772, 2016; the
equation numbers below are the tutorial's): ``K`` independent instances (one per
material), their state in arrays with a leading instance axis, members of a generation
told with the instance (category) they belong to.

- :func:`cma_sample` (one thread per member): x = m + sigma B D z, z ~ N(0, I), resampled
  up to ``resample`` times while outside the unit box, then clipped (the bound handling
  of the ``cmaes`` package that Optuna wraps: repair, and the repaired point is the one
  told).
- ranking: :func:`rank_keys` then two stable radix sorts (``wp.utils.radix_sort_pairs``):
  members grouped by instance, feasible ones first by objective, then the infeasible by
  violation (Deb's rule), ties by member index.
- :func:`cma_moments` (one thread per instance and slice): weighted sums of y = (x - m) /
  sigma and y y^T over the best mu = lambda / 2 members, in fixed slices summed in a fixed
  order (no atomics: the same seed gives the same numbers).
- :func:`cma_update` (one thread per instance): mean, evolution paths, covariance (rank-one
  and rank-mu) and step size (eqs. 41-47), the stopping tests and the restart; then the
  covariance's eigendecomposition (:func:`tawarp.kernels.eigen.eigh_kernel`, one thread).

NSGA-II (Deb et al., IEEE Trans. Evol. Comput. 6 (2002) 182): :func:`fronts_2d` ranks two
objectives and computes the crowding distance in one sequential pass (run on the CPU:
``O(N log N)``, the points in lexicographic order), :func:`nsga_offspring` makes the
children (binary tournament, SBX, polynomial mutation) one thread each.

Random numbers: ``wp.rand_init(seed, thread)`` (PCG), the seed of a generation drawn on the
host from the sampler's seed; normal deviates are Warp's float32 ``randn`` widened to
float64 (the update uses the told x, so the deviates' resolution only shapes the sample).
CMA-ES's kernels read their seeds from a device array (:data:`SEEDS`), so that one captured
sequence of launches serves every generation.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

#: The int32 device array of CMA-ES's seeds: (the sample's, the update's restarts', whether
#: the told generation is the first).
SEEDS = 3
ZERO = wp.constant(wp.float64(0.0))
ONE = wp.constant(wp.float64(1.0))
HALF = wp.constant(wp.float64(0.5))
TWO = wp.constant(wp.float64(2.0))
#: step size of a (re)start: a sixth of the unit box, so that +-3 sigma spans it
SIGMA0 = wp.constant(wp.float64(1.0 / 6.0))
#: stopping tests of an instance (pycma's names): the step in x below TOLX (the unit box's
#: scale), the covariance's condition number above MAX_CONDITION, or the objective's range
#: over a generation and over the recent generations' best below TOLFUN (1 + |best|)
TOLX = wp.constant(wp.float64(1e-11))
MAX_CONDITION = wp.constant(wp.float64(1e14))
TOLFUN = wp.constant(wp.float64(1e-12))


@wp.struct
class CmaState:
    """The state of ``K`` CMA-ES instances, a leading instance axis (the tutorial's names):
    ``mean`` m (K, d) in the unit box, step size ``sigma`` (K,), covariance ``C`` (K, d, d)
    and its eigendecomposition ``B`` (K, d, d), ``eig`` (K, d) kept for sampling, evolution
    paths ``p_sigma`` and ``p_c`` (K, d), the last step's weighted mean ``yw`` (K, d),
    ``age`` (K,) generations since the (re)start, ``history`` (K, H) a ring of the best
    feasible objective of the last generations (tolfun), ``restarts`` (K,) so far."""

    mean: wp.array2d(dtype=wp.float64)
    sigma: wp.array(dtype=wp.float64)
    C: wp.array3d(dtype=wp.float64)
    B: wp.array3d(dtype=wp.float64)
    eig: wp.array2d(dtype=wp.float64)
    p_sigma: wp.array2d(dtype=wp.float64)
    p_c: wp.array2d(dtype=wp.float64)
    yw: wp.array2d(dtype=wp.float64)
    age: wp.array(dtype=wp.int32)
    history: wp.array2d(dtype=wp.float64)
    restarts: wp.array(dtype=wp.int32)


@wp.kernel
def cma_sample(
    seeds: wp.array(dtype=wp.int32),
    cma: CmaState,
    category: wp.array(dtype=wp.int32),
    resample: int,
    z: wp.array2d(dtype=wp.float64),
    X: wp.array2d(dtype=wp.float64),
):
    """Member i of instance ``category[i]``: X[i, :d] = m + sigma B diag(sqrt(eig)) z,
    resampled while outside [0, 1]^d (at most ``resample`` draws), then clipped; with a
    category column (X has d + 1 columns) X[i, d] = category[i]. The seed is
    ``seeds[0]`` (:data:`SEEDS`)."""
    i = wp.tid()
    k = category[i]
    d = cma.mean.shape[1]
    state = wp.rand_init(seeds[0], i)
    inside = bool(False)
    tries = int(0)
    while not inside and tries < resample:
        tries += 1
        for a in range(d):
            z[i, a] = wp.float64(wp.randn(state)) * wp.sqrt(wp.max(cma.eig[k, a], ZERO))
        inside = bool(True)
        for a in range(d):
            y = ZERO
            for b in range(d):
                y += cma.B[k, a, b] * z[i, b]
            x = cma.mean[k, a] + cma.sigma[k] * y
            X[i, a] = x
            if not (x >= ZERO and x <= ONE):
                inside = bool(False)
    for a in range(d):
        X[i, a] = wp.clamp(X[i, a], ZERO, ONE)
    if X.shape[1] > d:
        X[i, d] = wp.float64(category[i])


@wp.kernel
def told_rows(
    X: wp.array2d(dtype=wp.float64),
    asked: wp.array2d(dtype=wp.float64),
    n_cat: int,
    d: int,
    F: wp.array(dtype=wp.float64),
    violation: wp.array(dtype=wp.float64),
    U: wp.array2d(dtype=wp.float64),
    category: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
):
    """The members as the update reads them: a told row that is not finite (a store may
    hold such) is the row asked, failed (objective and violation inf); a NaN objective or
    violation is inf. ``counts[k]``: members of instance k (int atomics: exact)."""
    i = wp.tid()
    finite = bool(True)
    for a in range(X.shape[1]):
        if not wp.isfinite(X[i, a]):
            finite = bool(False)
    for a in range(d):
        U[i, a] = X[i, a] if finite else asked[i, a]
    c = int(0)
    if n_cat > 1:
        c = int(X[i, d]) if finite else int(asked[i, d])
        c = wp.clamp(c, 0, n_cat - 1)
    category[i] = c
    if not finite or wp.isnan(F[i]):
        F[i] = wp.float64(wp.inf)
    if not finite or wp.isnan(violation[i]):
        violation[i] = wp.float64(wp.inf)
    wp.atomic_add(counts, c, 1)


@wp.func
def feasible(f: wp.float64, violation: wp.float64):
    """Deb's feasibility: no violation and an objective (a failed member has none)."""
    return violation <= ZERO and f < wp.float64(wp.inf)


@wp.kernel
def rank_keys(
    F: wp.array(dtype=wp.float64),
    violation: wp.array(dtype=wp.float64),
    key: wp.array(dtype=wp.float64),
    member: wp.array(dtype=wp.int32),
):
    """First sort key: the objective of a feasible member (violation <= 0), the violation
    of an infeasible one (Deb's rule orders each group by these)."""
    i = wp.tid()
    key[i] = F[i] if feasible(F[i], violation[i]) else violation[i]
    member[i] = i


@wp.kernel
def class_keys(
    member: wp.array(dtype=wp.int32),
    F: wp.array(dtype=wp.float64),
    violation: wp.array(dtype=wp.float64),
    category: wp.array(dtype=wp.int32),
    key: wp.array(dtype=wp.int32),
):
    """Second (stable) sort key of the member at sorted place j: 2 k + infeasible, so that
    instance k's members are contiguous, the feasible first."""
    j = wp.tid()
    i = member[j]
    infeasible = int(1)
    if feasible(F[i], violation[i]):
        infeasible = 0
    key[j] = 2 * category[i] + infeasible


@wp.func
def first_member(counts: wp.array(dtype=wp.int32), k: int):
    """Place of instance k's first member in the sorted order."""
    off = int(0)
    for j in range(k):
        off += counts[j]
    return off


@wp.func
def raw_weight(lam: int, r: int):
    """Recombination weight of rank r (0-based) before normalization (eq. 49):
    ln((lambda + 1) / 2) - ln(r + 1) for r < mu = lambda / 2, else 0."""
    if r >= lam // 2:
        return ZERO
    return wp.log(HALF * wp.float64(lam + 1)) - wp.log(wp.float64(r + 1))


@wp.func
def start_state(k: int, cma: CmaState):
    """Instance k's state of a (re)start about its mean: sigma0, C = I, both evolution
    paths zero, age 0."""
    d = cma.p_c.shape[1]
    for a in range(d):
        cma.p_sigma[k, a] = ZERO
        cma.p_c[k, a] = ZERO
        for b in range(d):
            cma.C[k, a, b] = ONE if a == b else ZERO
    cma.sigma[k] = SIGMA0
    cma.age[k] = 0


@wp.kernel
def cma_moments(
    U: wp.array2d(dtype=wp.float64),
    member: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    cma: CmaState,
    part: wp.array3d(dtype=wp.float64),
):
    """Slice s of instance k: sum over ranks r = s, s + S, ... < mu of w_r y and w_r y y^T
    (raw weights), y = (x - m) / sigma; part[k, s] = (y_w (d), y y^T (d x d) row-major)."""
    k, s = wp.tid()
    S = part.shape[1]
    d = cma.mean.shape[1]
    for c in range(part.shape[2]):
        part[k, s, c] = ZERO
    lam = counts[k]
    off = first_member(counts, k)
    r = s
    while r < lam // 2:
        i = member[off + r]
        w = raw_weight(lam, r)
        for a in range(d):
            ya = (U[i, a] - cma.mean[k, a]) / cma.sigma[k]
            part[k, s, a] += w * ya
            for b in range(a + 1):
                yb = (U[i, b] - cma.mean[k, b]) / cma.sigma[k]
                part[k, s, d + a * d + b] += w * ya * yb
        r += S


@wp.kernel
def cma_update(
    seeds: wp.array(dtype=wp.int32),
    part: wp.array3d(dtype=wp.float64),
    member: wp.array(dtype=wp.int32),
    counts: wp.array(dtype=wp.int32),
    F: wp.array(dtype=wp.float64),
    violation: wp.array(dtype=wp.float64),
    cma: CmaState,
):
    """One CMA-ES update of instance k from its ranked members (eqs. 41-47 with c_m = 1,
    positive weights), then its stopping tests; a stopped (or not finite) instance restarts
    from a uniform point of the box with sigma0, C = I (a restart keeps the population,
    which is the batch's share). The restart seed is ``seeds[1]`` and ``first`` = ``seeds[2]``
    (:data:`SEEDS`); ``first`` (1): the told generation is the space-filling start: the
    mean is set to the weighted mean of its best half, sigma0, C = I.
    ``age[k]``: generations since the (re)start; ``history[k]``: ring of the best feasible
    objective of the last generations (tolfun)."""
    k = wp.tid()
    seed = seeds[1]
    first = seeds[2]
    d = cma.mean.shape[1]
    lam = counts[k]
    mu = lam // 2
    if mu < 1:
        return
    off = first_member(counts, k)
    # weights (eq. 49, 53): normalized to sum 1 over the best mu
    wsum = ZERO
    w2sum = ZERO
    for r in range(mu):
        w = raw_weight(lam, r)
        wsum += w
        w2sum += w * w
    mueff = wsum * wsum / w2sum
    n = wp.float64(d)
    cs = (mueff + TWO) / (n + mueff + wp.float64(5.0))
    ds = ONE + TWO * wp.max(ZERO, wp.sqrt((mueff - ONE) / (n + ONE)) - ONE) + cs
    cc = (wp.float64(4.0) + mueff / n) / (n + wp.float64(4.0) + TWO * mueff / n)
    c1 = TWO / ((n + wp.float64(1.3)) * (n + wp.float64(1.3)) + mueff)
    cmu = wp.min(ONE - c1, TWO * (mueff - TWO + ONE / mueff) / ((n + TWO) * (n + TWO) + mueff))
    chi = wp.sqrt(n) * (ONE - ONE / (wp.float64(4.0) * n) + ONE / (wp.float64(21.0) * n * n))
    # y_w (eq. 41) and sum w y y^T, the slices summed in a fixed order
    S = part.shape[1]
    for a in range(d):
        acc = ZERO
        for s in range(S):
            acc += part[k, s, a]
        cma.yw[k, a] = acc / wsum
    # the mean (eq. 41, c_m = 1) moves by sigma y_w; nothing below reads the mean
    for a in range(d):
        cma.mean[k, a] = cma.mean[k, a] + cma.sigma[k] * cma.yw[k, a]
    if first == 1:
        start_state(k, cma)
    else:
        g = cma.age[k] + 1
        cma.age[k] = g
        # p_sigma (eq. 43): C^-1/2 y_w = B diag(eig^-1/2) B^T y_w
        norm2 = ZERO
        for a in range(d):
            acc = ZERO
            for j in range(d):
                bt = ZERO
                for b in range(d):
                    bt += cma.B[k, b, j] * cma.yw[k, b]
                acc += cma.B[k, a, j] * bt / wp.sqrt(wp.max(cma.eig[k, j], wp.float64(1e-300)))
            ps = (ONE - cs) * cma.p_sigma[k, a] + wp.sqrt(cs * (TWO - cs) * mueff) * acc
            cma.p_sigma[k, a] = ps
            norm2 += ps * ps
        ps_norm = wp.sqrt(norm2)
        hsig = ZERO
        if ps_norm / wp.sqrt(ONE - wp.pow(ONE - cs, TWO * wp.float64(g))) < (wp.float64(1.4) + TWO / (n + ONE)) * chi:
            hsig = ONE
        delta = (ONE - hsig) * cc * (TWO - cc)
        for a in range(d):
            cma.p_c[k, a] = (ONE - cc) * cma.p_c[k, a] + hsig * wp.sqrt(cc * (TWO - cc) * mueff) * cma.yw[k, a]
        # covariance (eq. 47; sum of the normalized weights = 1)
        for a in range(d):
            for b in range(a + 1):
                ymu = ZERO
                for s in range(S):
                    ymu += part[k, s, d + a * d + b]
                c = (
                    (ONE + c1 * delta - c1 - cmu) * cma.C[k, a, b]
                    + c1 * cma.p_c[k, a] * cma.p_c[k, b]
                    + cmu * ymu / wsum
                )
                cma.C[k, a, b] = c
                cma.C[k, b, a] = c
        cma.sigma[k] = cma.sigma[k] * wp.exp((cs / ds) * (ps_norm / chi - ONE))
    # stopping tests
    best = F[member[off]]
    worst = F[member[off + lam - 1]]
    feasible_all = violation[member[off + lam - 1]] <= ZERO
    H = cma.history.shape[1]
    cma.history[k, cma.age[k] % H] = best
    stop = bool(False)
    finite = wp.isfinite(cma.sigma[k]) and cma.sigma[k] > ZERO
    emax = ZERO
    emin = wp.float64(wp.inf)
    cmax = ZERO
    for a in range(d):
        finite = finite and wp.isfinite(cma.mean[k, a]) and wp.isfinite(cma.p_c[k, a])
        emax = wp.max(emax, cma.eig[k, a])
        emin = wp.min(emin, cma.eig[k, a])
        cmax = wp.max(cmax, wp.sqrt(wp.abs(cma.C[k, a, a])))
        for b in range(d):
            finite = finite and wp.isfinite(cma.C[k, a, b])
    if not finite:
        stop = bool(True)
    elif first == 0:
        step = ZERO
        for a in range(d):
            step = wp.max(step, wp.abs(cma.p_c[k, a]))
        if cma.sigma[k] * wp.max(cmax, step) < TOLX:
            stop = bool(True)
        if emin > ZERO and emax / emin > MAX_CONDITION:
            stop = bool(True)
        if feasible_all and cma.age[k] >= H:
            lo = best
            hi = best
            for j in range(H):
                lo = wp.min(lo, cma.history[k, j])
                hi = wp.max(hi, cma.history[k, j])
            tol = TOLFUN * (ONE + wp.abs(best))
            if worst - best < tol and hi - lo < tol:
                stop = bool(True)
    if stop:
        cma.restarts[k] = cma.restarts[k] + 1
        state = wp.rand_init(seed, k)
        for a in range(d):
            cma.mean[k, a] = wp.float64(wp.randf(state))
        start_state(k, cma)
        for j in range(H):
            cma.history[k, j] = wp.float64(wp.inf)


@wp.kernel
def eig_factor(
    w: wp.array2d(dtype=wp.float64),
    V: wp.array3d(dtype=wp.float64),
    cma: CmaState,
):
    """The eigendecomposition C = B diag(eig) B^T kept for sampling (eigenvalues clipped at
    0: rounding may leave a tiny negative one)."""
    k, a = wp.tid()
    cma.eig[k, a] = wp.max(w[k, a], ZERO)
    for b in range(V.shape[2]):
        cma.B[k, a, b] = V[k, a, b]


@wp.kernel
def to_table_unit(
    X: wp.array2d(dtype=wp.float64),
    d: int,
    n_cat: int,
    U: wp.array2d(dtype=wp.float64),
    not_finite: wp.array(dtype=wp.int32),
):
    """Sampler coordinates (category as an index in column d) as the unit-cube points of
    :class:`tawarp.design.space.DeviceTable` (category k as (k + 1/2) / n_cat);
    ``not_finite[0]`` counts the coordinates that are not finite (the table would clip
    them into the box)."""
    i, a = wp.tid()
    if not wp.isfinite(X[i, a]):
        wp.atomic_add(not_finite, 0, 1)
    if a < d:
        U[i, a] = X[i, a]
    else:
        U[i, a] = (X[i, a] + HALF) / wp.float64(n_cat)


@wp.kernel
def fronts_2d(
    order: wp.array(dtype=wp.int32),
    F: wp.array2d(dtype=wp.float64),
    rank: wp.array(dtype=wp.int32),
    crowd: wp.array(dtype=wp.float64),
    last: wp.array(dtype=wp.float64),
    head: wp.array(dtype=wp.int32),
    tail: wp.array(dtype=wp.int32),
    prev: wp.array(dtype=wp.int32),
    succ: wp.array(dtype=wp.int32),
):
    """Non-dominated fronts of two minimized objectives and the crowding distance, one
    thread (launch with dim 1, on the CPU: a sequential O(N log N) pass).

    ``order``: the points in lexicographic order (F[:, 0], then F[:, 1]). A point is
    dominated by an earlier one with F[:, 1] <= its own (identical points share a front);
    front j keeps the smallest F[:, 1] of its members so far in ``last[j]``, an ascending
    list searched by bisection (Jensen, IEEE Trans. Evol. Comput. 7 (2003) 503). Along
    this order a front's members have F[:, 0] ascending and F[:, 1] descending, so the
    neighbours of a member in both objectives are its predecessor and successor in its
    front; fronts of at most two members, and each front's ends, get inf."""
    N = order.shape[0]
    nf = int(0)
    for t in range(N):
        i = order[t]
        j = int(0)
        if t > 0 and F[i, 0] == F[order[t - 1], 0] and F[i, 1] == F[order[t - 1], 1]:
            j = rank[order[t - 1]]
        else:
            lo = int(0)
            hi = nf
            while lo < hi:
                mid = (lo + hi) // 2
                if last[mid] > F[i, 1]:
                    hi = mid
                else:
                    lo = mid + 1
            j = lo
            if j == nf:
                nf += 1
                head[j] = i
                tail[j] = -1
            last[j] = F[i, 1]
        rank[i] = j
        prev[i] = tail[j]
        succ[i] = -1
        if tail[j] >= 0:
            succ[tail[j]] = i
        tail[j] = i
    for t in range(N):
        i = order[t]
        j = rank[i]
        p = prev[i]
        q = succ[i]
        if p < 0 or q < 0:
            crowd[i] = wp.float64(wp.inf)
        else:
            span0 = F[tail[j], 0] - F[head[j], 0]
            span1 = F[head[j], 1] - F[tail[j], 1]
            c = ZERO
            if span0 > ZERO:
                c += (F[q, 0] - F[p, 0]) / span0
            if span1 > ZERO:
                c += (F[p, 1] - F[q, 1]) / span1
            crowd[i] = c


@wp.func
def tournament(seed: int, stream: int, rank: wp.array(dtype=wp.int32), crowd: wp.array(dtype=wp.float64)):
    """Binary tournament on the random stream ``stream``: the better of two uniform parents
    (lower front, then larger crowding distance)."""
    P = rank.shape[0]
    state = wp.rand_init(seed, stream)
    a = wp.randi(state, 0, P)
    b = wp.randi(state, 0, P)
    if rank[a] < rank[b] or (rank[a] == rank[b] and crowd[a] > crowd[b]):
        return a
    return b


@wp.kernel
def nsga_offspring(
    seed: int,
    U: wp.array2d(dtype=wp.float64),
    category: wp.array(dtype=wp.int32),
    rank: wp.array(dtype=wp.int32),
    crowd: wp.array(dtype=wp.float64),
    eta_c: wp.float64,
    eta_m: wp.float64,
    n_cat: int,
    X: wp.array2d(dtype=wp.float64),
):
    """Child i: two tournament parents; SBX crossover (probability 0.9 per pair, each gene
    with probability 1/2, one of the two SBX children's genes at random); polynomial
    mutation (probability 1/d per gene); clipped to the box. Its category is a parent's,
    redrawn uniformly with probability 1/(d + 1)."""
    i = wp.tid()
    d = U.shape[1]
    state = wp.rand_init(seed, 3 * i)
    p1 = tournament(seed, 3 * i + 1, rank, crowd)
    p2 = tournament(seed, 3 * i + 2, rank, crowd)
    cross = wp.randf(state) < wp.float32(0.9)
    for a in range(d):
        x1 = U[p1, a]
        x2 = U[p2, a]
        c = x1
        if cross and wp.randf(state) < wp.float32(0.5):
            r = wp.float64(wp.randf(state))
            beta = wp.float64(0.0)
            if r <= HALF:
                beta = wp.pow(TWO * r, ONE / (eta_c + ONE))
            else:
                beta = wp.pow(ONE / (TWO * (ONE - r)), ONE / (eta_c + ONE))
            if wp.randf(state) < wp.float32(0.5):
                c = HALF * ((ONE + beta) * x1 + (ONE - beta) * x2)
            else:
                c = HALF * ((ONE - beta) * x1 + (ONE + beta) * x2)
        if wp.randf(state) * wp.float32(d) < wp.float32(1.0):
            r = wp.float64(wp.randf(state))
            if r < HALF:
                c += wp.pow(TWO * r, ONE / (eta_m + ONE)) - ONE
            else:
                c += ONE - wp.pow(TWO * (ONE - r), ONE / (eta_m + ONE))
        X[i, a] = wp.clamp(c, ZERO, ONE)
    if X.shape[1] > d:
        m = category[p1]
        if wp.randf(state) < wp.float32(0.5):
            m = category[p2]
        if n_cat > 1 and wp.randf(state) * wp.float32(d + 1) < wp.float32(1.0):
            m = wp.randi(state, 0, n_cat)
        X[i, d] = wp.float64(m)
