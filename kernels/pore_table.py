"""Circular-pore functions f, g at real s = r / delta from a Chebyshev table.

f and g of a circular pore depend on the one real variable s (:mod:`.pore`), so the
cascade kernel reads them from a table built once per process instead of running the
Bessel-ratio recurrence (up to sqrt(2) s + 16 complex steps) at every Gauss point.

Table: the pieces split u = ln s over [ln S_MIN, ln S_MAX] into equal widths of a quarter
octave; on each piece the stored function is a Chebyshev series of TERMS terms in
t = 2 (u - u_k) / width - 1. In u the poles of f and g (the zeros of J0((1 + i) s)) lie
at distance pi/4 from the real axis at every s, so the same piece width and term count
hold over the whole range: a quarter octave gives a Bernstein ellipse of rho ~ 18 and
12 terms reach ~1e-15. Each piece stores the smaller of the pair (g for small s, where
f -> 1; f for large s, where g -> 1) and the other is 1 minus it, so neither loses
digits to cancellation. Outside [S_MIN, S_MAX] the functions of :mod:`.pore` are used.

The node values come from :func:`.pore.pore_circular` (below 1e-15 relative, checked
against mpmath in tests/test_pore.py); the table is exact to ~2e-15 relative to |f| and
to |g| (tests/test_pore.py asserts 1e-13; studies/pore_table_accuracy.py measures it).
The complex-frequency path (:func:`.pore.pore_functions_complex`) is not tabulated.
"""

import math

import numpy as np
import warp as wp

from .pore import PORE_PLATES, pore_circular, pore_plates

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

S_MIN = 1.0e-3
S_MAX = 1.0e4
PIECES_PER_OCTAVE = 4
TERMS = 12

_PIECE_WIDTH = math.log(2.0) / PIECES_PER_OCTAVE
PIECES = math.ceil(math.log(S_MAX / S_MIN) / _PIECE_WIDTH - 1e-9)

TABLE_S_MIN = wp.constant(wp.float64(S_MIN))
TABLE_S_MAX = wp.constant(wp.float64(S_MAX))
TABLE_LOG_S_MIN = wp.constant(wp.float64(math.log(S_MIN)))
TABLE_PIECES_PER_UNIT = wp.constant(wp.float64(1.0 / _PIECE_WIDTH))
TABLE_PIECES = wp.constant(PIECES)
TABLE_TERMS = wp.constant(TERMS)


@wp.func
def pore_circular_tabulated(table: wp.array(dtype=wp.float64), s: wp.float64):
    """f, g of a circular pore, s = r / delta > 0, from ``table`` (:func:`circular_table`).
    Layout: per piece a flag (1: the series is g, 0: it is f), then TERMS (re, im)
    Chebyshev coefficients."""
    if not (s >= TABLE_S_MIN and s < TABLE_S_MAX):   # also NaN: never an index from it
        return pore_circular(s)
    u = (wp.log(s) - TABLE_LOG_S_MIN) * TABLE_PIECES_PER_UNIT
    k = wp.min(int(u), TABLE_PIECES - 1)
    t = wp.float64(2.0) * (u - wp.float64(k)) - wp.float64(1.0)
    base = k * (2 * TABLE_TERMS + 1)
    # Clenshaw's recurrence for sum c_j T_j(t), real and imaginary parts together
    two_t = t + t
    b1r = wp.float64(0.0)
    b1i = wp.float64(0.0)
    b2r = wp.float64(0.0)
    b2i = wp.float64(0.0)
    for jj in range(TABLE_TERMS - 1):
        j = base + 1 + 2 * (TABLE_TERMS - 1 - jj)
        br = table[j] + two_t * b1r - b2r
        bi = table[j + 1] + two_t * b1i - b2i
        b2r = b1r
        b2i = b1i
        b1r = br
        b1i = bi
    p = wp.vec2d(table[base + 1] + t * b1r - b2r, table[base + 2] + t * b1i - b2i)
    q = wp.vec2d(wp.float64(1.0) - p[0], -p[1])
    if table[base] != wp.float64(0.0):
        return q, p
    return p, q


@wp.func
def pore_functions(model: int, s: wp.float64, table: wp.array(dtype=wp.float64)):
    """f, g of the pore ``model`` (PORE_CIRCULAR or PORE_PLATES) at s = r / delta > 0;
    ``table`` is :func:`circular_table` on the kernel's device."""
    if model == PORE_PLATES:
        return pore_plates(s)
    return pore_circular_tabulated(table, s)


@wp.kernel
def _circular_nodes(s: wp.array(dtype=wp.float64), f: wp.array(dtype=wp.vec2d), g: wp.array(dtype=wp.vec2d)):
    i = wp.tid()
    fi, gi = pore_circular(s[i])
    f[i] = fi
    g[i] = gi


def circular_coefficients() -> np.ndarray:
    """The table as float64 numbers: PIECES records of 1 + 2 TERMS (see
    :func:`pore_circular_tabulated`), from f, g at the TERMS Chebyshev points of the
    first kind of each piece (a discrete cosine transform gives the coefficients)."""
    k = np.arange(TERMS)
    angles = np.pi * (k + 0.5) / TERMS
    t = np.cos(angles)
    u = math.log(S_MIN) + _PIECE_WIDTH * (np.arange(PIECES)[:, None] + (t[None, :] + 1.0) / 2.0)
    s = wp.array(np.exp(u).ravel(), dtype=wp.float64, device="cpu")
    f = wp.empty(s.shape[0], dtype=wp.vec2d, device="cpu")
    g = wp.empty(s.shape[0], dtype=wp.vec2d, device="cpu")
    wp.launch(_circular_nodes, dim=s.shape[0], inputs=[s, f, g], device="cpu")
    f = f.numpy().view(np.complex128).reshape(PIECES, TERMS)
    g = g.numpy().view(np.complex128).reshape(PIECES, TERMS)
    # per piece the smaller of the two (compared at the piece's nodes)
    use_g = np.abs(g).max(axis=1) < np.abs(f).max(axis=1)
    values = np.where(use_g[:, None], g, f)
    # c_j = (2 / n) sum_k v_k cos(j angle_k), c_0 halved
    coeffs = (2.0 / TERMS) * values @ np.cos(np.outer(angles, k))
    coeffs[:, 0] /= 2.0
    table = np.empty((PIECES, 1 + 2 * TERMS))
    table[:, 0] = use_g
    table[:, 1::2] = coeffs.real
    table[:, 2::2] = coeffs.imag
    return table.ravel()


_TABLES: dict = {}


def circular_table(device) -> wp.array:
    """The table of :func:`circular_coefficients` on ``device``, built once per process."""
    key = str(wp.get_device(device))
    if key not in _TABLES:
        if "host" not in _TABLES:
            _TABLES["host"] = circular_coefficients()
        _TABLES[key] = wp.array(_TABLES["host"], dtype=wp.float64, device=device)
    return _TABLES[key]
