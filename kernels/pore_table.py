"""The table of circular-pore functions f, g at real s = r / delta, built on the host.

f and g of a circular pore depend on the one real variable s (:mod:`.pore`), so the
cascade kernel reads them from a table built once per process
(:func:`.pore.pore_circular_tabulated`) instead of running the Bessel-ratio recurrence
(sqrt(2) s + 16 complex steps) at every Gauss point.

Table: the pieces split u = ln s over [ln S_MIN, ln S_MAX] into equal widths of a
sixteenth of an octave; on each piece the stored function is a Chebyshev series of TERMS terms in
t = 2 (u - u_k) / width - 1. In u the poles of f and g (the zeros of J0((1 + i) s)) lie
at distance pi/4 from the real axis at every s, so the same piece width and term count
hold over the whole range: a sixteenth of an octave gives a Bernstein ellipse of rho ~ 73
and 8 terms reach ~6e-15. A quarter octave needed 12 terms for the same; the cascade
reads two series per Gauss point, and the shorter one made the CPU cascade 27 % faster
(bench/forward.py, one thread) for a table of 51 kB instead of 13 kB (both measured with
studies/pore_table_accuracy.py). Each piece stores the smaller of the pair (g for small
s, where f -> 1; f for large s, where g -> 1) and the other is 1 minus it, so neither loses
digits to cancellation. Outside [S_MIN, S_MAX] the functions of :mod:`.pore` are used.

The node values come from :func:`.pore.pore_circular` (below 1e-15 relative, checked
against mpmath in tests/test_pore.py); the table is exact to ~6e-15 relative to |f| and
to |g| (tests/test_pore.py asserts 1e-13; studies/pore_table_accuracy.py measures it).
The complex-frequency path (:func:`.pore.pore_functions_complex`) is not tabulated.
"""

import math

import numpy as np
import warp as wp

from .pore import PIECES, S_MIN, TABLE_PIECE_WIDTH, TERMS, pore_circular

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code


@wp.kernel
def _circular_nodes(s: wp.array(dtype=wp.float64), f: wp.array(dtype=wp.vec2d), g: wp.array(dtype=wp.vec2d)):
    i = wp.tid()
    fi, gi = pore_circular(s[i])
    f[i] = fi
    g[i] = gi


def circular_coefficients() -> np.ndarray:
    """The table as float64 numbers: PIECES records of 1 + 2 TERMS (see
    :func:`.pore.pore_circular_tabulated`), from f, g at the TERMS Chebyshev points of the
    first kind of each piece (a discrete cosine transform gives the coefficients)."""
    k = np.arange(TERMS)
    angles = np.pi * (k + 0.5) / TERMS
    t = np.cos(angles)
    u = math.log(S_MIN) + TABLE_PIECE_WIDTH * (np.arange(PIECES)[:, None] + (t[None, :] + 1.0) / 2.0)
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
