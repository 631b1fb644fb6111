"""The table of pore functions f, g at real s = r / delta, built on the host: circular
pores, and rectangular channels and pin arrays by their shape (:func:`circular_table`).

f and g of a circular pore depend on the one real variable s (:mod:`.pore`), so the
cascade kernel reads them from a table built once per process
(:func:`.pore.pore_circular_tabulated`) instead of running the Bessel-ratio recurrence
(sqrt(2) s + 16 complex steps) at every Gauss point.

Table: the pieces split u = ln s over [ln S_MIN, ln S_MAX] into equal widths of a
sixteenth of an octave; on each piece the stored function is a Chebyshev series of TERMS terms in
t = 2 (u - u_k) / width - 1, stored in powers of t (the kernels' Horner rule takes half the
instructions of Clenshaw's recurrence).
In u the poles of f and g (the zeros of J0((1 + i) s)) lie
at distance pi/4 from the real axis at every s, so the same piece width and term count
hold over the whole range: a sixteenth of an octave gives a Bernstein ellipse of rho ~ 73
and 8 terms reach ~6e-15 (a quarter octave needs 12; measured: bench/README.md, section
"kernels/pore_table.py"). Each piece stores the smaller of the pair (g for small
s, where f -> 1; f for large s, where g -> 1) and the other is 1 minus it, so neither loses
digits to cancellation. Outside [S_MIN, S_MAX] the leading terms of their series are used
(:func:`.pore.pore_circular_tabulated`). The circular pore's 1/g, all that A takes of the
viscous function, has pieces of its own (:func:`inverse_coefficients`): the plain cascade
reads it without a division (:func:`.pore.circular_inverse_g`).

The node values come from :func:`.pore.pore_circular` (below 1e-15 relative, checked
against mpmath in tests/test_pore.py); the table is exact to ~6e-15 relative to |f| and
to |g| (tests/test_pore.py asserts 1e-13; studies/pore_table_accuracy.py measures it).
The complex-frequency path (:func:`.pore.pore_functions_complex`) is not tabulated.

Rectangular channels and pin arrays have their poles in u at the same distance pi/4 from the
real axis (their modes decay with s^2 = -i lambda^2/2, as the tube's), so the same pieces and
terms serve them; their node values come from :func:`.pore.pore_functions_complex`, the
table's error against the converged series or mpmath is tested in
tests/test_pore_geometries.py. Tabulated, a cascade over such a stack runs at the circular
pore's speed (measured: bench/README.md, section "kernels/pore_table.py").
"""

import math

import numpy as np
import warp as wp
from numpy.polynomial import chebyshev

from .pore import (
    INVERSE_BLOCK,
    PIECES,
    PORE_CIRCULAR,
    RECTANGULAR_BASE,
    S_MIN,
    SHAPE_BLOCKS,
    SHAPE_HEADER,
    SHAPE_SLOTS,
    TABLE_LENGTH,
    TABLE_PIECE_WIDTH,
    TABLE_RECORD,
    TERMS,
    pore_circular,
    pore_functions_complex,
)

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code


@wp.kernel
def _nodes(model: int, s: wp.array(dtype=wp.float64), f: wp.array(dtype=wp.vec2d), g: wp.array(dtype=wp.vec2d)):
    i = wp.tid()
    if model == PORE_CIRCULAR:
        fi, gi = pore_circular(s[i])
    else:
        fi, gi = pore_functions_complex(model, wp.vec2d(s[i], wp.float64(0.0)))
    f[i] = fi
    g[i] = gi


def _node_values(model: int) -> tuple[np.ndarray, np.ndarray]:
    """f, g of pore ``model`` at the TERMS Chebyshev points of the first kind of each piece,
    (PIECES, TERMS) complex each."""
    angles = np.pi * (np.arange(TERMS) + 0.5) / TERMS
    u = math.log(S_MIN) + TABLE_PIECE_WIDTH * (np.arange(PIECES)[:, None] + (np.cos(angles)[None, :] + 1.0) / 2.0)
    s = wp.array(np.exp(u).ravel(), dtype=wp.float64, device="cpu")
    f = wp.empty(s.shape[0], dtype=wp.vec2d, device="cpu")
    g = wp.empty(s.shape[0], dtype=wp.vec2d, device="cpu")
    wp.launch(_nodes, dim=s.shape[0], inputs=[int(model), s, f, g], device="cpu")
    return (
        f.numpy().view(np.complex128).reshape(PIECES, TERMS),
        g.numpy().view(np.complex128).reshape(PIECES, TERMS),
    )


def _pieces(values: np.ndarray, flags: np.ndarray) -> np.ndarray:
    """The table's pieces (PIECES, 1 + 2 TERMS) of a function whose values at each piece's
    Chebyshev points are ``values`` (PIECES, TERMS), with a piece's flag (row 0) ``flags``:
    a discrete cosine transform gives the Chebyshev coefficients, stored in powers of the
    piece's variable t."""
    k = np.arange(TERMS)
    angles = np.pi * (k + 0.5) / TERMS
    # c_j = (2 / n) sum_k v_k cos(j angle_k), c_0 halved
    coeffs = (2.0 / TERMS) * values @ np.cos(np.outer(angles, k))
    coeffs[:, 0] /= 2.0
    # in powers of t for Horner's rule in the kernels: T_j's power coefficients (up to 64 for
    # T_7) multiply c_j, which falls as ~73^-j, so the conversion costs no digits
    to_powers = np.zeros((TERMS, TERMS))  # column j: T_j in powers of t
    for j in k:
        to_powers[: j + 1, j] = chebyshev.cheb2poly(np.eye(j + 1)[j])
    coeffs = coeffs @ to_powers.T
    table = np.empty((PIECES, 1 + 2 * TERMS))
    table[:, 0] = flags
    table[:, 1::2] = coeffs.real
    table[:, 2::2] = coeffs.imag
    return table


def pore_coefficients(model: int = int(PORE_CIRCULAR)) -> np.ndarray:
    """The pieces of pore ``model`` (circular, or a shaped pore's :func:`.pore.pore_model_code`)
    as a (PIECES, 1 + 2 TERMS) float64 array, a piece's fields in a row (the table's columns,
    :data:`.pore.PoreTable`), from f, g at the TERMS Chebyshev points of the
    first kind of each piece (:func:`_pieces`)."""
    f, g = _node_values(model)
    # per piece the smaller of the two (compared at the piece's nodes)
    use_g = np.abs(g).max(axis=1) < np.abs(f).max(axis=1)
    return _pieces(np.where(use_g[:, None], g, f), use_g)


def inverse_coefficients() -> np.ndarray:
    """The pieces of 1/g = 1/(1 - f) of a circular pore, as :func:`pore_coefficients`'
    (flag 0): :func:`.pore.circular_inverse_g`. Its poles in u = ln s, the zeros of
    J2((1 + i) s), lie at distance pi/4 from the real axis as f's do (the zeros of
    J0((1 + i) s)), so the same pieces and terms hold; no difference is taken, so no
    digit is lost where |1/g| is large (4/s^2 at small s)."""
    _, g = _node_values(int(PORE_CIRCULAR))
    return _pieces(1.0 / g, np.zeros(PIECES))


#: pore-model codes of the shaped pores tabulated so far, in slot order (at most SHAPE_SLOTS;
#: a later one is computed in the kernels instead)
_SHAPES: list[int] = []
_HOST: dict = {}
_TABLES: dict = {}


def circular_table(device, models=()) -> wp.array:
    """The pore table on ``device`` (:data:`.pore.PoreTable`, :data:`.pore.TABLE_LENGTH` columns): the circular pieces,
    built once per process, and those of every shaped pore (rectangular channel, pin array)
    among the pore-model codes ``models`` or asked for before, while SHAPE_SLOTS last. An
    array handed out earlier stays valid: a shape it lacks is computed instead."""
    for m in dict.fromkeys(int(m) for m in np.atleast_1d(models)):
        if m >= int(RECTANGULAR_BASE) and m not in _SHAPES and len(_SHAPES) < int(SHAPE_SLOTS):
            _SHAPES.append(m)
    if _HOST.get("shapes") != len(_SHAPES):
        table = _HOST.get("table")
        if table is None:
            table = np.zeros((TABLE_LENGTH, TABLE_RECORD))
            table[:PIECES] = pore_coefficients()
            table[INVERSE_BLOCK : INVERSE_BLOCK + PIECES] = inverse_coefficients()
            table[SHAPE_HEADER, : int(SHAPE_SLOTS)] = -1.0
        for j in range(_HOST.get("shapes", 0), len(_SHAPES)):
            table[SHAPE_HEADER, j] = _SHAPES[j]
            table[SHAPE_BLOCKS + j * PIECES : SHAPE_BLOCKS + (j + 1) * PIECES] = pore_coefficients(_SHAPES[j])
        _HOST.update(table=table, shapes=len(_SHAPES))
    key = str(wp.get_device(device))
    if _TABLES.get(key, (None, -1))[1] != len(_SHAPES):
        columns = np.ascontiguousarray(_HOST["table"].T)
        _TABLES[key] = (wp.array(columns, dtype=wp.float64, device=device), len(_SHAPES))
    return _TABLES[key][0]
