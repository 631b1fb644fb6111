"""Thermoviscous pore functions f and g = 1 - f, as float64 Warp funcs.

Convention: time dependence exp(-i w t), so the penetration depth delta enters
through (1 + i) / delta, and f tends to (1 + i) delta / (2 r_h) for wide pores
(r_h the hydraulic radius).  Swift's exp(+i w t) functions are the complex
conjugates of these.  Complex numbers are ``wp.vec2d`` (re, im), see
:mod:`.cmath`.  Every func returns the pair ``f, g``.

Circular pore, radius r, s = r / delta, z = (1 + i) s::

    f = 2 J1(z) / (z J0(z)),    g = 1 - f = -J2(z) / J0(z)

Parallel plates, half-spacing y0, s = y0 / delta, w = (1 - i) s::

    f = tanh(w) / w,            g = 1 - f

Methods by region (thresholds and term counts chosen by comparison with
mpmath at 40 digits, see tests/test_pore.py):

* circular, s < 20: ratios r_k = J_k / J_{k-1} = 1 / (2k/z - r_{k+1}), taken from
  Miller's unnormalised backward recurrence (no division per term) from J_{N+1} = 0
  with N = floor(|z|) + 16 (the
  truncation error drops below 1e-17 by N = |z| + 13.2 at worst).  Then
  f = 2 r_1 / z and g = -r_1 r_2, which has no cancellation as f -> 1.
* circular, s >= 20: J_n = (H1_n + H2_n) / 2 with |H1_n / H2_n| ~ exp(-2s)
  < 5e-18, so J1/J0 = H2_1/H2_0 = i S_1 / S_0 with the Hankel series
  S_nu = sum_k (-i)^k a_k(nu) / z^k (DLMF 10.17.4) summed to k = 18 (that
  term is below 4e-18 at s = 20); f = 2 (J1/J0) / z -> 2i / z and g = 1 - f,
  |f| small.
* plates, s < 1: Lambert's continued fraction
  tanh(w) / w = 1 / (1 + w^2 / T_1), T_k = (2k+1) + w^2 / T_{k+1}, evaluated
  backward from T_N = 2N + 1 with N = floor(|w|) + 16; then
  f = T_1 / (T_1 + w^2) and g = w^2 / (T_1 + w^2), again without cancellation.
* plates, s >= 1: tanh(w) = (1 - q) / (1 + q) with q = exp(-2w), |q| = exp(-2s)
  <= exp(-2), so nothing overflows or cancels, and g = 1 - f with |f| <= 0.8.

Rectangular channels (:func:`pore_rectangular`) are summed from their series and, at large
s, their boundary-layer form with the corners; pin arrays (:func:`pore_pins`) from modified
Bessel functions of complex argument (:func:`bessel_ik_scaled`). Their shape number (aspect
ratio, outer radius ratio) travels in the pore-model code (:func:`pore_model_code`).

The kernels take circular f, g at real s from a Chebyshev table in ln s instead
(:func:`pore_circular_tabulated`, built by :mod:`.pore_table` from :func:`pore_circular`):
one short series instead of the recurrence, accurate to ~6e-15.

Accuracy, relative to |f| and to |g| separately, for s in [1e-4, 1e4] on the
CPU: below 1e-15 (largest of 20000 random log-spaced s: 8.0e-16 for f and
7.4e-16 for g of the tube, 4.1e-16 and 4.6e-16 for the plates); the tests
assert 1e-13.
"""

import math

import warp as wp
from scipy.special import zeta as hurwitz_zeta

from .cmath import cabs, cdiv, cexp, cinv, cmul, cplx, creal, cscale, csqrt

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

PORE_CIRCULAR = wp.constant(0)
PORE_PLATES = wp.constant(1)
#: Stacked wire screens: Swift & Ward's correlations replace the pore functions in A(x)
#: (:func:`tawarp.kernels.acoustics.screen_entries`); the functions here give the circular
#: pore's for them, which A does not read.
PORE_SCREENS = wp.constant(2)
#: Pore geometries by their name in a core file (``pore_model``) -> the kernels' constant;
#: a rectangular channel's constant carries its aspect ratio (:func:`pore_model_code`).
PORE_MODELS = {
    "circular": PORE_CIRCULAR,
    "plates": PORE_PLATES,
    "rectangular": None,
    "pins": None,
    "screens": PORE_SCREENS,
}
# Rectangular channels: model = RECTANGULAR_BASE + round(SHAPE_UNITS * aspect ratio), pin
# arrays: PINS_BASE + round(SHAPE_UNITS * outer radius ratio), so the one int the kernels
# carry per segment also gives the pores' shape (to 1/SHAPE_UNITS).
RECTANGULAR_BASE = wp.constant(1000)
PINS_BASE = wp.constant(1100000000)
SHAPE_UNITS = wp.constant(1000)
#: Largest aspect ratio of a rectangular channel, largest outer radius ratio of a pin array
#: (the int32 model code's range).
ASPECT_MAX = 1.0e6
PIN_RATIO_MAX = 1.0e6

# Above this s the Hankel expansion replaces the Bessel-ratio recurrence.
CIRCULAR_ASYMPTOTIC_S = wp.constant(wp.float64(20.0))
# Terms of the Hankel series beyond the leading 1.
HANKEL_TERMS = wp.constant(18)
# From this s on the exponential form of tanh replaces the continued fraction.
PLATES_EXPONENTIAL_S = wp.constant(wp.float64(1.0))
# Depth of the backward recurrences beyond |z|, |w|.
RECURRENCE_MARGIN = wp.constant(16)


@wp.func
def _circular_recurrence(s: wp.float64):
    # Miller's algorithm: unnormalised J_{k-1} = (2k/z) J_k - J_{k+1} from J_{n+1} = 0,
    # J_n = 1. Its ratios are exactly those of the continued fraction
    # J_k/J_{k-1} = 1/(2k/z - J_{k+1}/J_k), without a complex division per term (a
    # division costs several multiplications on the GPU). 2k/z = k (1 - i)/s.
    n = int(wp.sqrt(wp.float64(2.0)) * s) + RECURRENCE_MARGIN
    inv_s = wp.float64(1.0) / s
    j_next = cplx(wp.float64(0.0), wp.float64(0.0))
    j = cplx(wp.float64(1.0), wp.float64(0.0))
    j2 = j
    for k in range(n, 0, -1):
        a = wp.float64(k) * inv_s
        j_prev = cplx(a * (j[0] + j[1]), a * (j[1] - j[0])) - j_next
        if wp.abs(j_prev[0]) + wp.abs(j_prev[1]) > wp.float64(1.0e200):
            # rescaling keeps the ratios: only reached for s far below 1e-6
            j_prev = cscale(j_prev, wp.float64(1.0e-200))
            j = cscale(j, wp.float64(1.0e-200))
            j2 = cscale(j2, wp.float64(1.0e-200))
        if k == 2:
            j2 = j
        j_next = j
        j = j_prev
    j1 = j_next
    r1 = cdiv(j1, j)
    r2 = cdiv(j2, j1)
    f = cscale(cplx(r1[0] + r1[1], r1[1] - r1[0]), inv_s)  # 2 r1 / z = r1 (1 - i) / s
    g = -cmul(r1, r2)
    return f, g


@wp.func
def _circular_hankel(s: wp.float64):
    # Successive terms of S_nu differ by the factor
    # (-i) (4 nu^2 - (2k-1)^2) / (8 k z), and -i / (8 z) = -(1 + i) / (16 s).
    v = cplx(wp.float64(-1.0), wp.float64(-1.0)) / (wp.float64(16.0) * s)
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    t0 = one
    t1 = one
    s0 = one
    s1 = one
    for k in range(1, HANKEL_TERMS + 1):
        m = wp.float64(2 * k - 1)
        kf = wp.float64(k)
        t0 = cscale(cmul(t0, v), -m * m / kf)
        t1 = cscale(cmul(t1, v), (wp.float64(4.0) - m * m) / kf)
        s0 = s0 + t0
        s1 = s1 + t1
    # f = 2 (J1/J0) / z = 2 i S_1 / (z S_0), and 2 i / z = (1 + i) / s.
    f = cscale(cmul(cplx(wp.float64(1.0), wp.float64(1.0)), cdiv(s1, s0)), wp.float64(1.0) / s)
    g = one - f
    return f, g


@wp.func
def pore_circular(s: wp.float64):
    """f, g of a circular pore, s = r / delta > 0."""
    if s < CIRCULAR_ASYMPTOTIC_S:
        return _circular_recurrence(s)
    return _circular_hankel(s)


@wp.func
def _plates_continued_fraction(s: wp.float64):
    # w^2 = (1 - i)^2 s^2 = -2 i s^2
    w2 = cplx(wp.float64(0.0), wp.float64(-2.0) * s * s)
    n = int(wp.sqrt(wp.float64(2.0)) * s) + RECURRENCE_MARGIN
    t = cplx(wp.float64(2 * n + 1), wp.float64(0.0))
    for k in range(n - 1, 0, -1):
        t = cplx(wp.float64(2 * k + 1), wp.float64(0.0)) + cdiv(w2, t)
    d = t + w2
    return cdiv(t, d), cdiv(w2, d)


@wp.func
def _plates_exponential(s: wp.float64):
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    q = cexp(cplx(wp.float64(-2.0) * s, wp.float64(2.0) * s))  # exp(-2w)
    w = cplx(s, -s)
    f = cdiv(one - q, cmul(one + q, w))
    return f, one - f


@wp.func
def pore_plates(s: wp.float64):
    """f, g of parallel plates, s = y0 / delta > 0 (y0 the half-spacing)."""
    if s < PLATES_EXPONENTIAL_S:
        return _plates_continued_fraction(s)
    return _plates_exponential(s)


# -- circular pores from a table (the kernels' path at real s) -----------------------------------
# Pieces of a sixteenth of an octave in u = ln s over [S_MIN, S_MAX], TERMS Chebyshev terms each;
# the host builds the table (tawarp.kernels.pore_table, which says why these sizes).

S_MIN = 1.0e-3
S_MAX = 1.0e4
PIECES_PER_OCTAVE = 16
TERMS = 8

TABLE_PIECE_WIDTH = math.log(2.0) / PIECES_PER_OCTAVE
PIECES = math.ceil(math.log(S_MAX / S_MIN) / TABLE_PIECE_WIDTH - 1e-9)

TABLE_LOG_S_MIN = wp.constant(wp.float64(math.log(S_MIN)))
TABLE_LOG_S_MAX = wp.constant(wp.float64(math.log(S_MAX)))
TABLE_PIECES_PER_UNIT = wp.constant(wp.float64(1.0 / TABLE_PIECE_WIDTH))
TABLE_PIECES = wp.constant(PIECES)
TABLE_TERMS = wp.constant(TERMS)
#: Rows of the table: per piece a flag (1: the series is g, 0: it is f), then TERMS (re, im)
#: coefficients of the series in powers of t.
TABLE_RECORD = 1 + 2 * TERMS
#: The table the kernels take (:func:`tawarp.kernels.pore_table.circular_table`): column k is
#: one piece, row r its field r. Columns: the circular pieces, then a header column whose
#: first SHAPE_SLOTS rows are pore-model codes (-1: empty), then the pieces of each shaped
#: pore (rectangular channels, pins) in the header's order, then the circular pore's pieces
#: of 1/g (:func:`circular_inverse_g`, flag 0). A field's row keeps neighbouring
#: pieces at neighbouring addresses: a warp's threads (neighbouring frequencies, a few pieces
#: apart) read each coefficient from one or two cache lines, where records of a piece's
#: fields spread them over as many lines as pieces. The kernels read it as contiguous rows of
#: TABLE_LENGTH columns (:func:`table_entry`): only circular_table's array is a PoreTable.
PoreTable = wp.array2d(dtype=wp.float64)
SHAPE_SLOTS = wp.constant(16)
SHAPE_HEADER = wp.constant(PIECES)
SHAPE_BLOCKS = wp.constant(PIECES + 1)
#: The first column of the circular pore's pieces of 1/g (:func:`circular_inverse_g`).
INVERSE_BLOCK = wp.constant(PIECES * (1 + 16) + 1)
#: Columns of the table: the circular pieces, the header, SHAPE_SLOTS shaped blocks, the
#: circular pore's 1/g.
TABLE_LENGTH = PIECES * (1 + 16 + 1) + 1
assert int(SHAPE_SLOTS) <= TABLE_RECORD  # the header's codes fit one column


@wp.func_native(f"return reinterpret_cast<const double*>(table.data)[row * {TABLE_LENGTH} + column];")
def table_entry(table: PoreTable, row: int, column: int) -> wp.float64:
    """table[row, column] of :func:`tawarp.kernels.pore_table.circular_table`'s contiguous
    (TABLE_RECORD, TABLE_LENGTH) array, its row length a compile-time constant: a literal
    row's offset is then an immediate of the GPU's load, where the array's own indexing
    reads the row stride at run time and took two 64-bit address instructions per load
    (bench/README.md, "Fewer instructions per cell and per point")."""
    ...


@wp.func
def _piece_series(table: PoreTable, offset: int, log_s: wp.float64):
    # (the series of the piece of log_s among the pieces from column ``offset``, its column),
    # for log_s inside the table's range
    u = (log_s - TABLE_LOG_S_MIN) * TABLE_PIECES_PER_UNIT
    k = wp.min(int(u), TABLE_PIECES - 1)
    t = wp.float64(2.0) * (u - wp.float64(k)) - wp.float64(1.0)
    col = offset + k
    # Horner's rule on the series' power-basis coefficients in t (one fused multiply-add
    # per term and part: half the instructions of Clenshaw's recurrence on the Chebyshev
    # coefficients they were converted from, :func:`tawarp.kernels.pore_table.pore_coefficients`)
    top = 1 + 2 * (TABLE_TERMS - 1)
    pr = table_entry(table, top, col)
    pi = table_entry(table, top + 1, col)
    for jj in range(TABLE_TERMS - 1):
        j = top - 2 - 2 * jj
        pr = table_entry(table, j, col) + t * pr
        pi = table_entry(table, j + 1, col) + t * pi
    return wp.vec2d(pr, pi), col


@wp.func
def _tabulated(table: PoreTable, offset: int, log_s: wp.float64):
    # f, g from the pieces starting at column ``offset``, for log_s inside the table's range
    p, col = _piece_series(table, offset, log_s)
    q = wp.vec2d(wp.float64(1.0) - p[0], -p[1])
    if table_entry(table, 0, col) != wp.float64(0.0):
        return q, p
    return p, q


@wp.func
def inside_table(log_s: wp.float64):
    """True when ``log_s`` = ln(r / delta) lies in the table's range (False for NaN: never
    an index from it)."""
    return log_s >= TABLE_LOG_S_MIN and log_s < TABLE_LOG_S_MAX


@wp.func
def circular_from_table(table: PoreTable, log_s: wp.float64):
    """f, g of a circular pore at ``log_s`` = ln(r / delta) inside the table's range
    (:func:`inside_table`), from ``table`` (:func:`tawarp.kernels.pore_table.circular_table`);
    the series is in ln s, so a caller that has the logarithm
    (:func:`tawarp.kernels.acoustics.propagation_at`) takes none."""
    return _tabulated(table, 0, log_s)


# the small-s series' coefficients -2/3, 11/24 (float64 constants: a quotient of literals in a
# kernel would be taken in float32)
TAIL_W1 = wp.constant(wp.float64(-2.0 / 3.0))
TAIL_W2 = wp.constant(wp.float64(11.0 / 24.0))


@wp.func(inline=False)  # outside the table: rare, kept out of the cascade's inlined code
def _circular_tails(log_s: wp.float64):
    # f, g of a circular pore outside the table's range from the leading terms of the series
    # pore_circular sums in full. Below S_MIN the power series of J0 and J2 in
    # w = -z^2/4 = -i s^2/2 give g = -J2/J0 = (w/2)(1 - 2w/3 + 11 w^2/24) (the omitted
    # term, of order w^3 < 1.3e-19, is below 1e-19 of g); from S_MAX the Hankel ratio
    # S_1/S_0 of _circular_hankel, as one series 1 + 4v - 8v^2 + 64v^3 in
    # v = -(1 + i)/(16 s) (the omitted term below 5e-18 of f). A few multiplications, no
    # division, in a function of few registers: (f, g) as one wp.vec4d (an out-of-line
    # function's second return value would pass through the stack).
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    if log_s < TABLE_LOG_S_MIN:
        s = wp.exp(log_s)
        w = cplx(wp.float64(0.0), wp.float64(-0.5) * s * s)
        series = one + cmul(w, cplx(TAIL_W1, wp.float64(0.0)) + cscale(w, TAIL_W2))
        g = cscale(cmul(w, series), wp.float64(0.5))
        return wp.vec4d(wp.float64(1.0) - g[0], -g[1], g[0], g[1])
    inv_s = wp.exp(-log_s)
    v = cplx(wp.float64(-0.0625) * inv_s, wp.float64(-0.0625) * inv_s)
    ratio = one + cmul(
        v,
        cplx(wp.float64(4.0), wp.float64(0.0))
        + cmul(v, cplx(wp.float64(-8.0), wp.float64(0.0)) + cscale(v, wp.float64(64.0))),
    )
    f = cscale(cmul(cplx(wp.float64(1.0), wp.float64(1.0)), ratio), inv_s)
    return wp.vec4d(f[0], f[1], wp.float64(1.0) - f[0], -f[1])


@wp.func
def pore_circular_tabulated(table: PoreTable, log_s: wp.float64):
    """f, g of a circular pore at ``log_s`` = ln(r / delta): :func:`circular_from_table`
    inside the table's range, the leading terms of :func:`pore_circular`'s series outside
    it (below 1e-17 relative there, tests/test_pore.py); NaN for a NaN ``log_s``."""
    if not inside_table(log_s):
        fg = _circular_tails(log_s)
        return wp.vec2d(fg[0], fg[1]), wp.vec2d(fg[2], fg[3])
    return circular_from_table(table, log_s)


@wp.func
def circular_inverse_g(table: PoreTable, log_s: wp.float64):
    """1/g = 1/(1 - f) of a circular pore at ``log_s`` = ln(r / delta): the table's pieces
    of 1/g inside its range (:func:`tawarp.kernels.pore_table.inverse_coefficients`; no
    division: the plain cascade's viscous function,
    :func:`tawarp.kernels.acoustics.propagation_circular`), the tails' g inverted outside it
    (:func:`pore_circular_tabulated`); NaN for a NaN ``log_s``."""
    if not inside_table(log_s):
        return _circular_inverse_tails(log_s)
    g_inverse, col = _piece_series(table, INVERSE_BLOCK, log_s)
    return g_inverse


@wp.func(inline=False)  # outside the table: rare, kept out of the cascade's inlined code
def _circular_inverse_tails(log_s: wp.float64):
    # 1/g of a circular pore outside the table's range, from _circular_tails' g
    fg = _circular_tails(log_s)
    return cinv(wp.vec2d(fg[2], fg[3]))


@wp.func
def _shape_slot(table: PoreTable, model: int):
    # the slot of the shaped pore ``model`` in the table's header, -1 if it has none
    for j in range(SHAPE_SLOTS):
        if table[j, SHAPE_HEADER] == wp.float64(model):
            return j
    return -1


@wp.func
def pore_functions_log(model: int, log_s: wp.float64, table: PoreTable):
    """f, g of the pore ``model`` (PORE_CIRCULAR, PORE_PLATES or a rectangular channel's or
    pin array's :func:`pore_model_code`) at ``log_s`` = ln(r / delta); ``table`` is
    :func:`tawarp.kernels.pore_table.circular_table` on the kernel's device, which holds the
    circular pieces and those of the shaped pores it was built for (others are computed).
    The circular pore inside the table is the cascade's usual case and is read here; every
    other case is :func:`_pore_functions_other`, kept apart so that the GPU compiler inlines
    this short path into the cascade and calls the long one (bench/README.md)."""
    if model == PORE_CIRCULAR:
        return pore_circular_tabulated(table, log_s)
    return _pore_functions_other(model, log_s, table)


@wp.func(inline=False)
def _pore_functions_other(model: int, log_s: wp.float64, table: PoreTable):
    # pore_functions_log's cases beyond a circular pore inside the table
    if model == PORE_PLATES:
        return pore_plates(wp.exp(log_s))
    if model >= RECTANGULAR_BASE:
        if inside_table(log_s):
            slot = _shape_slot(table, model)
            if slot >= 0:
                return _tabulated(table, SHAPE_BLOCKS + slot * TABLE_PIECES, log_s)
        return pore_functions_complex(model, cplx(wp.exp(log_s), wp.float64(0.0)))
    return pore_circular_tabulated(table, log_s)


@wp.func
def pore_log_derivative(model: int, log_s: wp.float64, f: wp.vec2d, g: wp.vec2d):
    """df/d ln s of the pore ``model`` at ``log_s`` = ln(r / delta) from f, g there (dg = -df).
    Circular: f = 2 J1(z)/(z J0(z)) with z = (1 + i) s and J1' = J0 - J1/z,
    J0' = -J1 give z df/dz = 2 (1 - f) + f^2 z^2/2, and z^2 = 2 i s^2::

        df/d ln s = 2 g + i s^2 f^2

    Plates: f = tanh(w)/w, w = (1 - i) s, w df/dw = 1 - f - f^2 w^2, w^2 = -2 i s^2::

        df/d ln s = g + 2 i s^2 f^2

    The two terms cancel to O(f) at large s (f ~ 1/s): about s ulps are lost, 1e-12 at
    s = 1e4 (tests/test_pore.py compares central differences). Rectangular channels:
    :func:`_rectangular_log_derivative` (f, g are not needed)."""
    if model >= PINS_BASE:
        return _pins_log_derivative(wp.exp(log_s), pin_ratio(model), f)
    if model >= RECTANGULAR_BASE:
        return _rectangular_log_derivative(wp.exp(log_s), rectangular_aspect(model))
    s2 = wp.exp(wp.float64(2.0) * log_s)
    f2 = cmul(f, f)
    if model == PORE_PLATES:
        return g + cplx(wp.float64(-2.0) * s2 * f2[1], wp.float64(2.0) * s2 * f2[0])
    return cscale(g, wp.float64(2.0)) + cplx(-s2 * f2[1], s2 * f2[0])


# -- complex argument (complex frequency, tawarp.model.onset) ---------------------------------
# At complex omega, s = r / delta = r sqrt(rho omega / (2 mu)) is complex too (principal
# root, so Re s > 0 for Re omega > 0). The same four methods hold with s complex; the
# thresholds move from s to the quantity that sets their error: the Hankel expansion's
# neglected H1/H2 ~ exp(-2 Im z), Im z = Re s + Im s, and the exponential tanh's
# |q| = exp(-2 Re w), Re w = Re s + Im s. At real s these are the real-s functions above
# up to rounding.


@wp.func
def _circular_recurrence_c(s: wp.vec2d):
    # as _circular_recurrence with 2k/z = k (1 - i)/s complex
    n = int(wp.sqrt(wp.float64(2.0)) * cabs(s)) + RECURRENCE_MARGIN
    two_over_z = cmul(cplx(wp.float64(1.0), wp.float64(-1.0)), cinv(s))
    j_next = cplx(wp.float64(0.0), wp.float64(0.0))
    j = cplx(wp.float64(1.0), wp.float64(0.0))
    j2 = j
    for k in range(n, 0, -1):
        j_prev = cscale(cmul(two_over_z, j), wp.float64(k)) - j_next
        if wp.abs(j_prev[0]) + wp.abs(j_prev[1]) > wp.float64(1.0e200):
            j_prev = cscale(j_prev, wp.float64(1.0e-200))
            j = cscale(j, wp.float64(1.0e-200))
            j2 = cscale(j2, wp.float64(1.0e-200))
        if k == 2:
            j2 = j
        j_next = j
        j = j_prev
    j1 = j_next
    r1 = cdiv(j1, j)
    r2 = cdiv(j2, j1)
    return cmul(r1, two_over_z), -cmul(r1, r2)


@wp.func
def _circular_hankel_c(s: wp.vec2d):
    # as _circular_hankel: v = -i/(8 z) = -(1 + i)/(16 s), f = (1 + i)/s S_1/S_0
    inv_s = cinv(s)
    v = cscale(cmul(cplx(wp.float64(-1.0), wp.float64(-1.0)), inv_s), wp.float64(0.0625))
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    t0 = one
    t1 = one
    s0 = one
    s1 = one
    for k in range(1, HANKEL_TERMS + 1):
        m = wp.float64(2 * k - 1)
        kf = wp.float64(k)
        t0 = cscale(cmul(t0, v), -m * m / kf)
        t1 = cscale(cmul(t1, v), (wp.float64(4.0) - m * m) / kf)
        s0 = s0 + t0
        s1 = s1 + t1
    f = cmul(cmul(cplx(wp.float64(1.0), wp.float64(1.0)), inv_s), cdiv(s1, s0))
    return f, one - f


@wp.func
def _plates_continued_fraction_c(s: wp.vec2d):
    # w^2 = -2 i s^2
    w2 = cscale(cmul(cplx(wp.float64(0.0), wp.float64(-1.0)), cmul(s, s)), wp.float64(2.0))
    n = int(wp.sqrt(wp.float64(2.0)) * cabs(s)) + RECURRENCE_MARGIN
    t = cplx(wp.float64(2 * n + 1), wp.float64(0.0))
    for k in range(n - 1, 0, -1):
        t = cplx(wp.float64(2 * k + 1), wp.float64(0.0)) + cdiv(w2, t)
    d = t + w2
    return cdiv(t, d), cdiv(w2, d)


@wp.func
def _plates_exponential_c(s: wp.vec2d):
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    w = cmul(cplx(wp.float64(1.0), wp.float64(-1.0)), s)
    q = cexp(cscale(w, wp.float64(-2.0)))
    f = cdiv(one - q, cmul(one + q, w))
    return f, one - f


@wp.func
def pore_functions_complex(model: int, s: wp.vec2d):
    """f, g of the pore ``model`` at complex s = r / delta (complex frequency)."""
    if model >= PINS_BASE:
        return pore_pins(s, pin_ratio(model))
    if model >= RECTANGULAR_BASE:
        return pore_rectangular(s, rectangular_aspect(model))
    reach = s[0] + s[1]  # Im z of the tube, Re w of the plates
    if model == PORE_PLATES:
        if reach < PLATES_EXPONENTIAL_S:
            return _plates_continued_fraction_c(s)
        return _plates_exponential_c(s)
    if reach < CIRCULAR_ASYMPTOTIC_S:
        return _circular_recurrence_c(s)
    return _circular_hankel_c(s)


# -- rectangular channels (Stinson, JASA 89:550, 1991) ------------------------------------------
# Half-widths a <= b, aspect ratio alpha = b/a >= 1, s = a/delta (``pore_radius`` is the
# half-width of the narrow side, so alpha -> infinity is the parallel plates of half-spacing a).
# Expanding the velocity in cos(m pi y / 2a) and solving across the wide side exactly
# (exp(-iwt), k^2 a^2 = 2 i s^2, q_m = (m pi/2)^2, m odd)::
#
#     g = g_plates(s) - R,   R = sum_m 8/(m pi)^2 T(z_m) E_m,
#     T(z) = tanh(z)/z,  z_m^2 = alpha^2 (q_m - 2 i s^2),  E_m = 2 s^2/(2 s^2 + i q_m)
#
# (at alpha -> infinity T -> 0 and g is the plates' g). The terms fall as m^-5: the first
# RECT_TERMS are summed, the rest (tanh = 1 there to exp(-100)) by its expansion in
# e = 8 i s^2/(m pi)^2 (|e| < 0.3 for |s| < 20),
#
#     sum_{m > 2 RECT_TERMS - 1} = 128 s^2/(i alpha pi^5) sum_j c_j (8 i s^2/pi^2)^j H_{5+2j},
#
# c_j the coefficients of (1 - e)^(-3/2), H_p = sum over those odd m of m^-p (RECT_TAIL_TERMS
# of them: the neglected one is below 1e-17 of g at |s| <= 20). For large s the velocity is the
# product of the two plates' boundary-layer profiles plus a correction at each of the four
# corners, whose integral is (4/pi - 1) delta^2 / (2 i) (from the corner's double sine
# transform); the rest is of order exp(-2 Re w), w = (1 - i) s::
#
#     g = g_plates(s) g_plates(alpha s) + i (4/pi - 1) / (2 alpha s^2)
#
# used from Re s + Im s >= RECT_ASYMPTOTIC_S (below 1e-15 there: tests/test_pore_geometries.py).

RECT_TERMS = wp.constant(16)
RECT_TAIL_TERMS = wp.constant(32)
RECT_ASYMPTOTIC_S = wp.constant(wp.float64(20.0))
PI = wp.constant(wp.float64(math.pi))
CORNER = wp.constant(wp.float64((4.0 / math.pi - 1.0) / 2.0))


def _rectangular_tail_coefficients() -> list[float]:
    """c_j H_{5+2j} (8/pi^2)^j 128/pi^5 for j < RECT_TAIL_TERMS (the i^j and 1/(i alpha)
    factors are applied in the kernel); H_p = 2^-p zeta(p, RECT_TERMS + 1/2) (Hurwitz)."""
    out = []
    c = 1.0
    for j in range(RECT_TAIL_TERMS):
        p = 5 + 2 * j
        h = 2.0**-p * float(hurwitz_zeta(p, RECT_TERMS + 0.5))
        out.append(c * h * (8.0 / math.pi**2) ** j * 128.0 / math.pi**5)
        c *= (1.5 + j) / (j + 1.0)
    return out


_TAIL = _rectangular_tail_coefficients()
RECT_TAIL = wp.constant(wp.types.vector(length=RECT_TAIL_TERMS, dtype=wp.float64)(*_TAIL))


def pore_model_code(name: str, shape: float = 1.0) -> int:
    """The kernels' int for pore model ``name``; ``shape`` is a rectangular channel's aspect
    ratio (>= 1) or a pin array's outer radius ratio (> 1), kept to 1/SHAPE_UNITS."""
    if name == "rectangular":
        return int(RECTANGULAR_BASE) + round(int(SHAPE_UNITS) * shape)
    if name == "pins":
        return int(PINS_BASE) + round(int(SHAPE_UNITS) * shape)
    return int(PORE_MODELS[name])


@wp.func
def rectangular_aspect(model: int):
    """Aspect ratio b/a of the rectangular channel whose :func:`pore_model_code` is ``model``."""
    return wp.float64(model - RECTANGULAR_BASE) / wp.float64(SHAPE_UNITS)


@wp.func
def pin_ratio(model: int):
    """Outer radius ratio r_o/r_i of the pin array whose :func:`pore_model_code` is ``model``."""
    return wp.float64(model - PINS_BASE) / wp.float64(SHAPE_UNITS)


@wp.func
def _plates_c(s: wp.vec2d):
    if s[0] + s[1] < PLATES_EXPONENTIAL_S:
        return _plates_continued_fraction_c(s)
    return _plates_exponential_c(s)


@wp.func
def _tanh_over(z: wp.vec2d):
    # tanh(z)/z and tanh(z) for Re z > 1 (every z_m here: Re z_m >= alpha pi / (2 sqrt 2))
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    q = cexp(cscale(z, wp.float64(-2.0)))
    t = cdiv(one - q, one + q)
    return cdiv(t, z), t


@wp.func
def _rectangular_sum(s: wp.vec2d, alpha: wp.float64, derivative: int):
    """R (and, when ``derivative`` != 0, dR/d ln s) of the series above."""
    s2 = cmul(s, s)
    two_s2 = cscale(s2, wp.float64(2.0))
    minus_2i_s2 = cplx(two_s2[1], -two_s2[0])
    alpha2 = alpha * alpha
    r = cplx(wp.float64(0.0), wp.float64(0.0))
    dr = r
    pi = PI
    for jj in range(RECT_TERMS):
        j = RECT_TERMS - 1 - jj  # small terms first
        m = wp.float64(2 * j + 1)
        q = wp.float64(0.25) * (m * pi) * (m * pi)
        w = wp.float64(8.0) / ((m * pi) * (m * pi))
        z2 = cscale(cplx(q, wp.float64(0.0)) + minus_2i_s2, alpha2)
        z = csqrt(z2)
        T, th = _tanh_over(z)
        E = cdiv(two_s2, two_s2 + cplx(wp.float64(0.0), q))
        r = r + cscale(cmul(T, E), w)
        if derivative != 0:
            one = cplx(wp.float64(1.0), wp.float64(0.0))
            # dT/d(z^2) = (1 - tanh^2 z - T)/(2 z^2), d(z^2)/d ln s = -4 i alpha^2 s^2
            dT_dz2 = cdiv(one - cmul(th, th) - T, cscale(z2, wp.float64(2.0)))
            dz2 = cscale(cplx(two_s2[1], -two_s2[0]), wp.float64(2.0) * alpha2)
            dE = cscale(cmul(E, one - E), wp.float64(2.0))
            dr = dr + cscale(cmul(cmul(dT_dz2, dz2), E) + cmul(T, dE), w)
    # tail: (1/(i alpha)) s^2 sum_j C_j (i s^2)^j
    i_s2 = cplx(-s2[1], s2[0])
    term = cscale(s2, wp.float64(1.0) / alpha)
    tail = cplx(wp.float64(0.0), wp.float64(0.0))
    dtail = tail
    for j in range(RECT_TAIL_TERMS):
        t = cscale(term, RECT_TAIL[j])
        tail = tail + t
        dtail = dtail + cscale(t, wp.float64(2 * j + 2))
        term = cmul(term, i_s2)
    # 1/i = -i
    r = r + cplx(tail[1], -tail[0])
    dr = dr + cplx(dtail[1], -dtail[0])
    return r, dr


@wp.func
def pore_rectangular(s: wp.vec2d, alpha: wp.float64):
    """f, g of a rectangular channel of aspect ratio ``alpha`` >= 1 at complex s = a/delta
    (a the narrow side's half-width)."""
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    if s[0] + s[1] < RECT_ASYMPTOTIC_S:
        fa, ga = _plates_c(s)
        r, dr = _rectangular_sum(s, alpha, 0)
        g = ga - r
        return one - g, g
    fa, ga = _plates_c(s)
    fb, gb = _plates_c(cscale(s, alpha))
    s2 = cmul(s, s)
    corner = cscale(cinv(s2), CORNER / alpha)
    corner = cplx(-corner[1], corner[0])  # times i
    # f = 1 - ga gb - corner = fa + fb - fa fb - corner: no cancellation when f is small
    f = fa + fb - cmul(fa, fb) - corner
    return f, one - f


@wp.func
def _rectangular_log_derivative(s: wp.float64, alpha: wp.float64):
    """df/d ln s of a rectangular channel at real s (:func:`pore_rectangular`)."""
    sc = cplx(s, wp.float64(0.0))
    s2 = s * s
    fa, ga = pore_plates(s)
    dfa = ga + cplx(wp.float64(-2.0) * s2 * cmul(fa, fa)[1], wp.float64(2.0) * s2 * cmul(fa, fa)[0])
    if s < RECT_ASYMPTOTIC_S:
        r, dr = _rectangular_sum(sc, alpha, 1)
        # f = 1 - g_plates + R
        return dfa + dr
    fb, gb = pore_plates(alpha * s)
    sb2 = alpha * s * alpha * s
    dfb = gb + cplx(wp.float64(-2.0) * sb2 * cmul(fb, fb)[1], wp.float64(2.0) * sb2 * cmul(fb, fb)[0])
    # corner = i c/s^2: d/d ln s = -2 corner
    c = CORNER / (alpha * s2)
    return dfa + dfb - cmul(dfa, fb) - cmul(fa, dfb) - cplx(wp.float64(0.0), wp.float64(-2.0) * c)


# -- pin arrays (Swift, *Thermoacoustics*, the pin-array stack; DeltaEC's STKPIN) -----------------
# Gas flows along pins of radius r_i, each in the cell of outer radius r_o that carries its share
# of the gas (r_o^2 = 2 sqrt(3)/pi y0^2 for a hexagonal array of half-pitch y0): no slip on the
# pin, no shear at r_o. With x = (1 - i) s, s = r_i/delta, R = r_o/r_i and the modified Bessel
# functions (exp(-iwt), (grad^2 - kappa^2) u = p'/mu, kappa r_i = x)::
#
#     f = 2/(x (R^2 - 1)) [I1(Rx) K1(x) - K1(Rx) I1(x)] / [I1(Rx) K0(x) + K1(Rx) I0(x)]
#
# evaluated with the scaled functions exp(-y) I_n(y), exp(y) K_n(y) and E = exp(-2 (R - 1) x),
# so nothing overflows: f = 2/(x (R^2 - 1)) [i1(Rx) k1(x) - E k1(Rx) i1(x)] / [i1(Rx) k0(x) + E k1(Rx) i0(x)].
# g = 1 - f is taken as such: it keeps eps/|g| relative, 1e-12 at s = 1e-2 (g ~ s^2).

BESSEL_SERIES_R = wp.constant(wp.float64(2.0))
BESSEL_ASYMPTOTIC_RE = wp.constant(wp.float64(20.0))
BESSEL_ASYMPTOTIC_ABS = wp.constant(wp.float64(28.0))
BESSEL_SERIES_TERMS = wp.constant(25)
BESSEL_ASYMPTOTIC_TERMS = wp.constant(20)
CF2_MAX_STEPS = wp.constant(500)
EULER_GAMMA = wp.constant(wp.float64(0.5772156649015329))


@wp.func
def _clog(z: wp.vec2d):
    return cplx(wp.log(cabs(z)), wp.atan2(z[1], z[0]))


@wp.func
def _bessel_ik_series(y: wp.vec2d):
    # |y| <= 2: A&S 9.6.10-11 (I0, I1) and 9.6.13 (K0), 9.6.11 (K1): with t = y^2/4,
    # K0 = -(ln(y/2) + gamma) I0 + sum H_k t^k/(k!)^2,
    # K1 = 1/y + ln(y/2) I1 - (y/4) sum (2 H_k + 1/(k+1) - 2 gamma) t^k/(k! (k+1)!)
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    zero = cplx(wp.float64(0.0), wp.float64(0.0))
    t = cscale(cmul(y, y), wp.float64(0.25))
    term0 = one
    term1 = one
    i0 = zero
    i1 = zero
    s0 = zero
    s1 = zero
    h = wp.float64(0.0)
    for k in range(BESSEL_SERIES_TERMS):
        if k > 0:
            kf = wp.float64(k)
            term0 = cscale(cmul(term0, t), wp.float64(1.0) / (kf * kf))
            term1 = cscale(cmul(term1, t), wp.float64(1.0) / (kf * (kf + wp.float64(1.0))))
            h = h + wp.float64(1.0) / kf
        i0 = i0 + term0
        i1 = i1 + term1
        s0 = s0 + cscale(term0, h)
        s1 = s1 + cscale(
            term1, wp.float64(2.0) * h + wp.float64(1.0) / wp.float64(k + 1) - wp.float64(2.0) * EULER_GAMMA
        )
    half_y = cscale(y, wp.float64(0.5))
    i1 = cmul(i1, half_y)
    lg = _clog(half_y)
    k0 = s0 - cmul(lg + creal(EULER_GAMMA), i0)
    k1 = cinv(y) + cmul(lg, i1) - cmul(cscale(y, wp.float64(0.25)), s1)
    up = cexp(-y)
    down = cexp(y)
    return cmul(i0, up), cmul(i1, up), cmul(k0, down), cmul(k1, down)


@wp.func
def _bessel_k_cf2(x: wp.vec2d):
    # Steed's continued fraction CF2 (Temme; Numerical Recipes' bessik, order 0), valid for
    # complex x (Thompson & Barnett 1987); returns exp(x) K0(x), exp(x) K1(x)
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    a1 = wp.float64(0.25)
    b = cscale(one + x, wp.float64(2.0))
    d = cinv(b)
    h = d
    delh = d
    q1 = cplx(wp.float64(0.0), wp.float64(0.0))
    q2 = one
    q = creal(a1)
    c = creal(a1)
    a = -a1
    s = one + cscale(delh, a1)
    for i in range(2, CF2_MAX_STEPS):
        a = a - wp.float64(2 * (i - 1))
        c = cscale(c, -a / wp.float64(i))
        qnew = cscale(q1 - cmul(b, q2), wp.float64(1.0) / a)
        q1 = q2
        q2 = qnew
        q = q + cmul(c, qnew)
        b = b + creal(wp.float64(2.0))
        d = cinv(b + cscale(d, a))
        delh = cmul(cmul(b, d) - one, delh)
        h = h + delh
        dels = cmul(q, delh)
        s = s + dels
        if cabs(dels) < wp.float64(1.0e-17) * cabs(s):
            break
    h = cscale(h, a1)
    k0 = cdiv(csqrt(cscale(cinv(x), PI * wp.float64(0.5))), s)
    k1 = cdiv(cmul(k0, x + creal(wp.float64(0.5)) - h), x)
    return k0, k1


@wp.func
def _bessel_i_ratio(x: wp.vec2d):
    # I1/I0 by Miller's backward recurrence I_{k-1} = (2k/x) I_k + I_{k+1} from I_{N+1} = 0
    n = int(cabs(x)) + 30
    two_over_x = cscale(cinv(x), wp.float64(2.0))
    nxt = cplx(wp.float64(0.0), wp.float64(0.0))
    cur = cplx(wp.float64(1.0), wp.float64(0.0))
    for k in range(n, 0, -1):
        prv = cscale(cmul(two_over_x, cur), wp.float64(k)) + nxt
        nxt = cur
        cur = prv
    return cdiv(nxt, cur)


@wp.func
def _bessel_asymptotic(y: wp.vec2d, nu: wp.float64, sign: wp.float64):
    # 1 + sum_k sign^k a_k(nu)/y^k (DLMF 10.40.1-2)
    one = cplx(wp.float64(1.0), wp.float64(0.0))
    inv8y = cscale(cinv(y), wp.float64(0.125))
    term = one
    out = one
    for k in range(1, BESSEL_ASYMPTOTIC_TERMS + 1):
        m = wp.float64(2 * k - 1)
        term = cscale(cmul(term, inv8y), sign * (wp.float64(4.0) * nu * nu - m * m) / wp.float64(k))
        out = out + term
    return out


@wp.func
def bessel_ik_scaled(y: wp.vec2d):
    """exp(-y) I0(y), exp(-y) I1(y), exp(y) K0(y), exp(y) K1(y) at complex y, Re y > 0: power
    series for |y| <= 2, Hankel's expansions where Re y >= 20 and |y| >= 28 (the neglected
    exp(-2y) of I below 1e-17), else Steed's CF2 for K and Miller's recurrence for I1/I0 with
    the Wronskian I0 K1 + I1 K0 = 1/y. 3e-15 relative against mpmath
    (tests/test_pore_geometries.py)."""
    if cabs(y) <= BESSEL_SERIES_R:
        return _bessel_ik_series(y)
    if y[0] >= BESSEL_ASYMPTOTIC_RE and cabs(y) >= BESSEL_ASYMPTOTIC_ABS:
        k_pref = csqrt(cscale(cinv(y), PI * wp.float64(0.5)))
        i_pref = csqrt(cinv(cscale(y, wp.float64(2.0) * PI)))
        zero = wp.float64(0.0)
        one = wp.float64(1.0)
        return (
            cmul(i_pref, _bessel_asymptotic(y, zero, -one)),
            cmul(i_pref, _bessel_asymptotic(y, one, -one)),
            cmul(k_pref, _bessel_asymptotic(y, zero, one)),
            cmul(k_pref, _bessel_asymptotic(y, one, one)),
        )
    k0, k1 = _bessel_k_cf2(y)
    r = _bessel_i_ratio(y)
    i0 = cinv(cmul(y, k1 + cmul(r, k0)))
    return i0, cmul(r, i0), k0, k1


@wp.struct
class PinTerms:
    """The scaled Bessel functions of a pin array at x (pin) and R x (cell edge), and E."""

    x: wp.vec2d
    i0: wp.vec2d
    i1: wp.vec2d
    k0: wp.vec2d
    k1: wp.vec2d
    i0o: wp.vec2d
    i1o: wp.vec2d
    k0o: wp.vec2d
    k1o: wp.vec2d
    e: wp.vec2d


@wp.func
def _pin_terms(s: wp.vec2d, ratio: wp.float64):
    pt = PinTerms()
    pt.x = cmul(cplx(wp.float64(1.0), wp.float64(-1.0)), s)
    i0, i1, k0, k1 = bessel_ik_scaled(pt.x)
    pt.i0 = i0
    pt.i1 = i1
    pt.k0 = k0
    pt.k1 = k1
    i0o, i1o, k0o, k1o = bessel_ik_scaled(cscale(pt.x, ratio))
    pt.i0o = i0o
    pt.i1o = i1o
    pt.k0o = k0o
    pt.k1o = k1o
    pt.e = cexp(cscale(pt.x, wp.float64(-2.0) * (ratio - wp.float64(1.0))))
    return pt


@wp.func
def pore_pins(s: wp.vec2d, ratio: wp.float64):
    """f, g of a pin array at complex s = r_i/delta (r_i the pin radius), outer radius ratio
    ``ratio`` = r_o/r_i > 1."""
    pt = _pin_terms(s, ratio)
    num = cmul(pt.i1o, pt.k1) - cmul(pt.e, cmul(pt.k1o, pt.i1))
    den = cmul(pt.i1o, pt.k0) + cmul(pt.e, cmul(pt.k1o, pt.i0))
    pref = cscale(cinv(pt.x), wp.float64(2.0) / (ratio * ratio - wp.float64(1.0)))
    f = cmul(pref, cdiv(num, den))
    return f, cplx(wp.float64(1.0), wp.float64(0.0)) - f


@wp.func
def _pins_log_derivative(s: wp.float64, ratio: wp.float64, f: wp.vec2d):
    """df/d ln s of a pin array at real s from f there: f = C N/D with C ~ 1/x, so
    df/d ln s = f (-1 + N'/N - D'/D), the primes d/d ln x by I0' = I1, I1' = I0 - I1/y,
    K0' = -K1, K1' = -K0 - K1/y (scaled: the exponentials cancel in N/D)."""
    pt = _pin_terms(cplx(s, wp.float64(0.0)), ratio)
    x = pt.x
    xo = cscale(x, ratio)
    # y times the derivative of each scaled function's unscaled partner, rescaled
    di1 = cmul(xo, pt.i0o) - pt.i1o  # (Rx) I1'(Rx) at the cell edge
    di1_in = cmul(x, pt.i0) - pt.i1  # x I1'(x)
    di0_in = cmul(x, pt.i1)  # x I0'(x)
    dk1 = -cmul(x, pt.k0) - pt.k1  # x K1'(x)
    dk0 = -cmul(x, pt.k1)  # x K0'(x)
    dk1o = -cmul(xo, pt.k0o) - pt.k1o  # (Rx) K1'(Rx)
    num = cmul(pt.i1o, pt.k1) - cmul(pt.e, cmul(pt.k1o, pt.i1))
    den = cmul(pt.i1o, pt.k0) + cmul(pt.e, cmul(pt.k1o, pt.i0))
    dnum = cmul(di1, pt.k1) + cmul(pt.i1o, dk1) - cmul(pt.e, cmul(dk1o, pt.i1) + cmul(pt.k1o, di1_in))
    dden = cmul(di1, pt.k0) + cmul(pt.i1o, dk0) + cmul(pt.e, cmul(dk1o, pt.i0) + cmul(pt.k1o, di0_in))
    return cmul(f, cdiv(dnum, num) - cdiv(dden, den) - creal(wp.float64(1.0)))
