"""Acoustic two-port of one part (docs/physics.md, "Acoustics"), as Warp functions.

``d/dx (p, U) = A(x) (p, U)`` with ``A = [[0, a12], [a21, a22]]``::

    a12 = i q^2 rho w / (phi S (1 - f_nu))
    a21 = i phi S w / (rho c^2) (1 + (gamma - 1) f_k)
    a22 = (T'/T) (f_k - f_nu) / ((1 - f_nu)(1 - Pr))

(stacked wire screens: Swift & Ward's correlations in place of f_nu and f_k, and
``a22 = (T'/T) f_k``; :func:`screen_entries`.)

Parts at uniform temperature have constant A and their exact matrix is ``exp(A L)``;
parts with a gradient are integrated with the sixth-order Magnus scheme on three Gauss
points per cell. Both use :func:`expm2`, so one code path gives the closed form of
docs/physics.md (``exp(A L) = [[cos kL, i Zc sin kL], [i sin kL / Zc, cos kL]]``) and the
integrator.

A's physics is one function, :func:`propagation_entries`, over real, complex or dual
numbers (:mod:`.cmath`): A at real frequencies (:func:`propagation_at`, the forward
cascade), its derivative along a parameter (:func:`propagation_tangent`, the tangent
cascade) and A at complex frequencies (:func:`propagation_complex`, the onset) differ only in
where the pore functions come from, so every effect of A is in all three.
"""

from typing import Any

import warp as wp

from .cmath import (
    ccomplex,
    cre,
    cabs2,
    cconj,
    cdiv,
    cexp,
    cinv,
    cmul,
    cmuli,
    cone,
    creal,
    cscale,
    csqrt,
    dual,
    dual_real,
    dual_tangent,
    dual_value,
)
from .gas import G_CP, G_GAMMA, G_K0, G_KA, G_KS, G_MU0, G_MUA, G_MUS, G_R, transport_scale
from .pore import (
    PORE_CIRCULAR,
    PORE_SCREENS,
    PoreTable,
    circular_inverse_g,
    pore_circular_tabulated,
    pore_functions_complex,
    pore_functions_log,
    pore_log_derivative,
)

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code


@wp.struct
class CMat2:
    """2x2 complex matrix [[a, b], [c, d]]."""

    a: wp.vec2d
    b: wp.vec2d
    c: wp.vec2d
    d: wp.vec2d


@wp.func
def cmat2(a: wp.vec2d, b: wp.vec2d, c: wp.vec2d, d: wp.vec2d):
    m = CMat2()
    m.a = a
    m.b = b
    m.c = c
    m.d = d
    return m


@wp.func
def zero2():
    zero = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    return cmat2(zero, zero, zero, zero)


@wp.func
def identity2():
    one = wp.vec2d(wp.float64(1.0), wp.float64(0.0))
    zero = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    return cmat2(one, zero, zero, one)


@wp.func
def matmul2(x: CMat2, y: CMat2):
    return cmat2(
        cmul(x.a, y.a) + cmul(x.b, y.c),
        cmul(x.a, y.b) + cmul(x.b, y.d),
        cmul(x.c, y.a) + cmul(x.d, y.c),
        cmul(x.c, y.b) + cmul(x.d, y.d),
    )


@wp.func
def taylor_terms(size: wp.float64):
    """Terms of :func:`expm2`'s series at |delta|^2 = ``size`` < 1: the fewest j such that
    |delta|^(j+1)/(2j+2)! < 1e-17: 3 below |delta| = 7.9e-4, then 4, 5, 6, 7, 8 below
    8.1e-3, 4.1e-2, 0.136, 0.346, 0.736, and 9 up to 1 (1/20! ~ 4e-19)."""
    if size < wp.float64(6.3e-7):
        return 3
    if size < wp.float64(6.6e-5):
        return 4
    if size < wp.float64(1.68e-3):
        return 5
    if size < wp.float64(0.0185):
        return 6
    if size < wp.float64(0.120):
        return 7
    if size < wp.float64(0.54):
        return 8
    return 9


#: 1/3! (a float64 constant: a quotient of literals in a kernel is taken in float32)
SIXTH = wp.constant(wp.float64(1.0 / 6.0))


@wp.func
def cosh_sinhc(delta: wp.vec2d):
    """(cosh(sqrt delta), sinh(sqrt delta)/sqrt(delta)) of a complex delta: both entire in
    delta, a Taylor series for |delta| < 1 (no square root, no cancellation, the usual case
    of a Magnus cell, :func:`cosh_sinhc_series`), exponentials beyond."""
    size = cabs2(delta)
    if size < wp.float64(1.0):
        return cosh_sinhc_series(delta, size)
    both = cosh_sinhc_exponentials(delta)
    return wp.vec2d(both[0], both[1]), wp.vec2d(both[2], both[3])


@wp.func
def cosh_sinhc_series(delta: wp.vec2d, size: wp.float64):
    """:func:`cosh_sinhc` at |delta|^2 = ``size`` < 1 as sum delta^j/(2j)! and
    sum delta^j/(2j+1)! over j <= 5, 7 or 9 (:func:`taylor_terms` at the top of each tier's
    |delta|), on the powers of delta that both sums share (:func:`series_term`: a complex
    product per term and a real multiply-add per part and sum, where Horner's rule took a
    complex product per sum, bench/README.md). Terms 6-7 and 8-9 are added where |delta|
    needs them, after the first five: one code path, no copy per tier. The terms fall by
    |delta|/((2j)(2j+1)) < 1/12 from the second on, so summing from the largest loses no
    digit; the first omitted term is below 1e-17."""
    power = delta
    ch = creal(wp.float64(1.0)) + cscale(delta, wp.float64(0.5))
    sh = creal(wp.float64(1.0)) + cscale(delta, SIXTH)
    for j in range(2, 6):  # unrolled: j a literal
        power, ch, sh = series_term(delta, power, ch, sh, j)
    if size >= wp.float64(1.68e-3):
        for j in range(6, 8):
            power, ch, sh = series_term(delta, power, ch, sh, j)
        if size >= wp.float64(0.120):
            for j in range(8, 10):
                power, ch, sh = series_term(delta, power, ch, sh, j)
    return ch, sh


@wp.func
def series_term(delta: wp.vec2d, power: wp.vec2d, ch: wp.vec2d, sh: wp.vec2d, j: int):
    """(delta^j, ch + delta^j/(2j)!, sh + delta^j/(2j+1)!) from power = delta^(j-1), for a
    literal j (the coefficients fold to constants): a term of :func:`cosh_sinhc_series`."""
    power = cmul(power, delta)
    return power, ch + cscale(power, inverse_factorial(2 * j)), sh + cscale(power, inverse_factorial(2 * j + 1))


@wp.func
def inverse_factorial(n: int):
    """1/n! for a literal n < 20: an unrolled product of constants, which the compiler folds."""
    c = wp.float64(1.0)
    for k in range(2, 20):
        if k <= n:
            c = c / wp.float64(k)
    return c


@wp.func(inline=False)  # the rare |delta| >= 1 of a cell: kept out of the cascade's inlined code
def cosh_sinhc_exponentials(delta: wp.vec2d):
    """:func:`cosh_sinhc` from exponentials of sqrt(delta), for |delta| >= 1, as one
    (ch, sh) wp.vec4d: a function called out of line returns one value in registers, where
    two would pass through the stack. e^-r = 1/e^r: one exponential, sine and cosine."""
    r = csqrt(delta)
    ep = cexp(r)
    em = cinv(ep)
    ch = cscale(ep + em, wp.float64(0.5))
    sh = cdiv(cscale(ep - em, wp.float64(0.5)), r)
    return wp.vec4d(ch[0], ch[1], sh[0], sh[1])


@wp.func
def cosh_sinhc_scaled(delta: wp.vec2d):
    """(e^-sigma ch, e^-sigma sh, sigma) of :func:`cosh_sinhc`'s ch and sh: sigma = Re sqrt(delta)
    (principal root) for |delta| >= 1, where cosh and sinh grow as e^sigma and overflow
    beyond sigma ~ 710 (a slit far narrower than the viscous depth is a diffusion path of
    many decay lengths), and sigma = 0 below (:func:`cosh_sinhc` itself). The derivatives
    of :func:`sinhc_derivative` and :func:`expm2_tangent` are linear in (ch, sh): given
    the scaled pair they come scaled alike, sigma held fixed."""
    if cabs2(delta) < wp.float64(1.0):
        ch, sh = cosh_sinhc(delta)
        return ch, sh, wp.float64(0.0)
    return cosh_sinhc_scaled_exponentials(delta)


@wp.func(inline=False)  # the rare |delta| >= 1 of a bypass gap's cell: out of line
def cosh_sinhc_scaled_exponentials(delta: wp.vec2d):
    """:func:`cosh_sinhc_scaled` for |delta| >= 1, r = sqrt(delta): e^(r - sigma) = e^(i Im r)
    and e^(-r - sigma) = e^(-2 sigma) / e^(i Im r), neither above 1."""
    r = csqrt(delta)
    sigma = r[0]
    ep = cexp(wp.vec2d(wp.float64(0.0), r[1]))
    em = cscale(cinv(ep), wp.exp(wp.float64(-2.0) * sigma))
    return cscale(ep + em, wp.float64(0.5)), cdiv(cscale(ep - em, wp.float64(0.5)), r), sigma


@wp.func
def sinhc_derivative(delta: wp.vec2d, ch: wp.vec2d, sh: wp.vec2d):
    """d/d(delta) of sh = sinh(sqrt delta)/sqrt(delta), given ch and sh at delta
    (:func:`cosh_sinhc`): sum (k+1) delta^k/(2k+3)! for |delta| < 1 (the closed form
    (ch - sh)/(2 delta) cancels there), the closed form beyond. (d ch/d delta = sh/2.)"""
    size = cabs2(delta)
    if size < wp.float64(1.0):
        # terms k <= terms + 1 of sum c_k delta^k, c_k/c_{k-1} = 1/(2k (2k + 3)), c_0 = 1/6:
        # the omitted terms are below 1e-17 where :func:`taylor_terms` says so for sh
        terms = taylor_terms(size) + 1
        d = creal(wp.float64(1.0))
        for jj in range(10):
            if 10 - jj <= terms:
                k = wp.float64(10 - jj)
                d = creal(wp.float64(1.0)) + cscale(
                    cmul(delta, d), wp.float64(1.0) / ((wp.float64(2.0) * k) * (wp.float64(2.0) * k + wp.float64(3.0)))
                )
        return cscale(d, wp.float64(1.0) / wp.float64(6.0))
    return cdiv(cscale(ch - sh, wp.float64(0.5)), delta)


@wp.func
def traceless_parts(m: CMat2):
    """(tau, na, delta) of m: tau = tr/2, N = m - tau I = [[na, b], [c, -na]], N^2 = delta I."""
    tau = cscale(m.a + m.d, wp.float64(0.5))
    na = m.a - tau
    return tau, na, cmul(na, na) + cmul(m.b, m.c)


@wp.func
def expm2_traceless(m: CMat2):
    """exp(m) of a 2x2 complex matrix as (E, tau) with exp(m) = e^tau E: tau = tr/2,
    N = m - tau I, N^2 = delta I and E = exp(N) = cosh(sqrt delta) I + sinh(sqrt delta)/sqrt(delta) N
    (:func:`cosh_sinhc`). The scalar e^tau commutes with every matrix, so a cascade of
    cells can sum their tau and take one exponential
    (:func:`tawarp.kernels.forward.make_transfer_kernel`)."""
    tau, na, delta = traceless_parts(m)
    ch, sh = cosh_sinhc(delta)
    return traceless_exp(m, na, ch, sh), tau


@wp.func
def traceless_exp(m: CMat2, na: wp.vec2d, ch: wp.vec2d, sh: wp.vec2d):
    """E = exp(N) = ch I + sh N of :func:`expm2_traceless`, N = m - tau I = [[na, b], [c, -na]]."""
    return cmat2(ch + cmul(sh, na), cmul(sh, m.b), cmul(sh, m.c), ch - cmul(sh, na))


@wp.func
def expm2_tangent(m: CMat2, na: wp.vec2d, ch: wp.vec2d, sh: wp.vec2d, dsh: wp.vec2d, dm: CMat2):
    """(dE, dtau): the derivative of :func:`expm2_traceless`'s (E, tau) at m in the
    direction dm, given na of m (:func:`traceless_parts`), ch, sh (:func:`cosh_sinhc`) and
    dsh = d sh/d delta (:func:`sinhc_derivative`), which a cascade computes once for all
    its directions. From E = ch I + sh N: dE = dch I + dsh N + sh dN with
    d delta = 2 na dna + db c + b dc, dch = sh/2 d delta, dsh d delta."""
    dtau = cscale(dm.a + dm.d, wp.float64(0.5))
    dna = dm.a - dtau
    ddelta = cscale(cmul(na, dna), wp.float64(2.0)) + cmul(dm.b, m.c) + cmul(m.b, dm.c)
    dch = cmul(cscale(sh, wp.float64(0.5)), ddelta)
    dshd = cmul(dsh, ddelta)
    diag = cmul(dshd, na) + cmul(sh, dna)
    return cmat2(dch + diag, cmul(dshd, m.b) + cmul(sh, dm.b), cmul(dshd, m.c) + cmul(sh, dm.c), dch - diag), dtau


@wp.func
def cscale2(m: CMat2, z: wp.vec2d):
    """z m for a complex scalar z."""
    return cmat2(cmul(z, m.a), cmul(z, m.b), cmul(z, m.c), cmul(z, m.d))


@wp.func
def expm2(m: CMat2):
    """exp(m) of a 2x2 complex matrix (:func:`expm2_traceless`)."""
    e, tau = expm2_traceless(m)
    return cscale2(e, cexp(tau))


@wp.func
def expm2_scaled(m: CMat2):
    """exp(m) of a 2x2 complex matrix as (E, tau, sigma) with exp(m) = e^(tau + sigma) E and
    det E = e^(-2 sigma): :func:`expm2_traceless` with :func:`cosh_sinhc_scaled`'s pair,
    finite wherever exp(m) overflows."""
    tau, na, delta = traceless_parts(m)
    ch, sh, sigma = cosh_sinhc_scaled(delta)
    return traceless_exp(m, na, ch, sh), tau, sigma


@wp.func
def axpy2(s: wp.float64, x: CMat2, y: CMat2):
    """s x + y."""
    return cmat2(cscale(x.a, s) + y.a, cscale(x.b, s) + y.b, cscale(x.c, s) + y.c, cscale(x.d, s) + y.d)


@wp.func
def commutator2(x: CMat2, y: CMat2):
    """[x, y] = x y - y x, from its three free entries: a commutator is traceless and its
    diagonal products x11 y11, x22 y22 cancel, so 6 complex products instead of 16."""
    e = cmul(x.b, y.c) - cmul(y.b, x.c)
    dx = x.d - x.a
    dy = y.d - y.a
    return cmat2(e, cmul(x.b, dy) - cmul(y.b, dx), cmul(y.c, dx) - cmul(x.c, dy), -e)


@wp.func
def magnus6_b(a1: CMat2, a2: CMat2, a3: CMat2, h: wp.float64):
    """b1 = h A2, b2 = sqrt(15) h/3 (A3 - A1), b3 = 10 h/3 (A3 - 2 A2 + A1) of
    :func:`magnus6_exponent`: linear in the A's and in h separately."""
    b1 = scale2(a2, h)
    b2 = scale2(axpy2(wp.float64(-1.0), a1, a3), wp.float64(1.2909944487358056) * h)
    b3 = scale2(axpy2(wp.float64(-2.0), a2, axpy2(wp.float64(1.0), a3, a1)), wp.float64(3.3333333333333333) * h)
    return b1, b2, b3


@wp.func
def magnus6_exponent(a1: CMat2, a2: CMat2, a3: CMat2, h: wp.float64):
    """Omega of one cell of length h, sixth order, from A at the three Gauss points
    x + (1/2 - sqrt(15)/10, 1/2, 1/2 + sqrt(15)/10) h (Blanes, Casas & Ros, BIT 40, 2000,
    eq. 4.13): :func:`magnus6_omega` of :func:`magnus6_b`'s b1, b2, b3; the cell's matrix is exp(Omega)."""
    b1, b2, b3 = magnus6_b(a1, a2, a3, h)
    return magnus6_omega(b1, b2, b3)


# Magnus and screen coefficients as float64 constants: in a kernel, wp.float64(1.0 / 60.0)
# divides two float32 literals (1e-8 relative) before the conversion
MAGNUS_C2 = wp.constant(wp.float64(-1.0 / 60.0))
MAGNUS_BRACKET = wp.constant(wp.float64(1.0 / 240.0))
MAGNUS_B3 = wp.constant(wp.float64(1.0 / 12.0))
TWO_THIRDS = wp.constant(wp.float64(2.0 / 3.0))
FOUR_THIRDS = wp.constant(wp.float64(4.0 / 3.0))


@wp.func
def magnus6_omega(b1: CMat2, b2: CMat2, b3: CMat2):
    """Omega = b1 + b3/12 + 1/240 [-20 b1 - b3 + C1, b2 + C2] with C1 = [b1, b2],
    C2 = -1/60 [b1, 2 b3 + C1] (:func:`magnus6_exponent`), from the b's of :func:`magnus6_b`
    or :func:`magnus6_accumulate`."""
    c1 = commutator2(b1, b2)
    c2 = scale2(commutator2(b1, axpy2(wp.float64(2.0), b3, c1)), MAGNUS_C2)
    left = axpy2(wp.float64(-20.0), b1, axpy2(wp.float64(-1.0), b3, c1))
    return axpy2(
        MAGNUS_BRACKET,
        commutator2(left, axpy2(wp.float64(1.0), b2, c2)),
        axpy2(MAGNUS_B3, b3, b1),
    )


@wp.func
def magnus6_accumulate(b1: CMat2, b2: CMat2, b3: CMat2, a: CMat2, g: int, h: wp.float64):
    """:func:`magnus6_b`'s b1, b2, b3 after adding A = ``a`` at Gauss point g (0, 1, 2) of a
    cell of length h, for a caller that evaluates A one point at a time (only the b's
    are live between the points); start from :func:`zero2`. A's (1,1) entry is 0 (module
    docstring) and is never read: the b's keep a literal zero there, which the compiler
    folds through :func:`magnus6_omega`'s commutators."""
    if g == 0:
        return (
            b1,
            scale_offdiagonal(a, wp.float64(-1.2909944487358056) * h),
            scale_offdiagonal(a, wp.float64(3.3333333333333333) * h),
        )
    if g == 1:
        return scale_offdiagonal(a, h), b2, add_offdiagonal(wp.float64(-6.6666666666666667) * h, a, b3)
    return (
        b1,
        add_offdiagonal(wp.float64(1.2909944487358056) * h, a, b2),
        add_offdiagonal(wp.float64(3.3333333333333333) * h, a, b3),
    )


@wp.func
def scale_offdiagonal(a: CMat2, s: wp.float64):
    """s A for A = [[0, b], [c, d]]: a literal 0 in the (1,1) entry."""
    return cmat2(creal(wp.float64(0.0)), cscale(a.b, s), cscale(a.c, s), cscale(a.d, s))


@wp.func
def add_offdiagonal(s: wp.float64, a: CMat2, y: CMat2):
    """s A + y for A and y of the form [[0, b], [c, d]]: a literal 0 in the (1,1) entry."""
    return cmat2(creal(wp.float64(0.0)), cscale(a.b, s) + y.b, cscale(a.c, s) + y.c, cscale(a.d, s) + y.d)


@wp.func
def magnus6_tangent(a1: CMat2, a2: CMat2, a3: CMat2, h: wp.float64, d1: CMat2, d2: CMat2, d3: CMat2, dh: wp.float64):
    """The derivative of :func:`magnus6_exponent`'s Omega along a direction in which A at
    the three Gauss points moves by d1, d2, d3 and the cell length by dh: the b's are
    linear in A and in h separately (db = b(d, h) + b(A, dh)), the commutators follow the
    product rule. The value's commutators are recomputed here rather than carried: on
    the GPU registers are the scarcer resource."""
    b1, b2, b3 = magnus6_b(a1, a2, a3, h)
    e1, e2, e3 = magnus6_b(d1, d2, d3, h)
    f1, f2, f3 = magnus6_b(a1, a2, a3, dh)
    db1 = axpy2(wp.float64(1.0), e1, f1)
    db2 = axpy2(wp.float64(1.0), e2, f2)
    db3 = axpy2(wp.float64(1.0), e3, f3)
    c1 = commutator2(b1, b2)
    dc1 = axpy2(wp.float64(1.0), commutator2(db1, b2), commutator2(b1, db2))
    w = axpy2(wp.float64(2.0), b3, c1)
    dw = axpy2(wp.float64(2.0), db3, dc1)
    c2 = scale2(commutator2(b1, w), MAGNUS_C2)
    dc2 = scale2(axpy2(wp.float64(1.0), commutator2(db1, w), commutator2(b1, dw)), MAGNUS_C2)
    left = axpy2(wp.float64(-20.0), b1, axpy2(wp.float64(-1.0), b3, c1))
    dleft = axpy2(wp.float64(-20.0), db1, axpy2(wp.float64(-1.0), db3, dc1))
    right = axpy2(wp.float64(1.0), b2, c2)
    dright = axpy2(wp.float64(1.0), db2, dc2)
    bracket = axpy2(wp.float64(1.0), commutator2(dleft, right), commutator2(left, dright))
    return axpy2(MAGNUS_BRACKET, bracket, axpy2(MAGNUS_B3, db3, db1))


@wp.func
def magnus6_step(a1: CMat2, a2: CMat2, a3: CMat2, h: wp.float64):
    """exp(Omega) of one cell (:func:`magnus6_exponent`)."""
    return expm2(magnus6_exponent(a1, a2, a3, h))


@wp.func
def scale2(m: CMat2, s: wp.float64):
    return cmat2(cscale(m.a, s), cscale(m.b, s), cscale(m.c, s), cscale(m.d, s))


# -- two 2-ports side by side -------------------------------------------------------------------


@wp.func
def parallel_entries(
    a1: Any, b1: Any, c1: Any, d1: Any, l1: Any, g1: Any, a2: Any, b2: Any, c2: Any, d2: Any, l2: Any, g2: Any
):
    """(A, B, C, D) of two 2-ports side by side between the same two planes: the same p
    at each plane, the volume velocities adding, so their admittance matrices
    [U_in, U_out] = Y [p_in, p_out], Y = [[-A/B, 1/B], [-det T/B, D/B]] of
    T = [[A, B], [C, D]], add. Each 2-port comes scaled, T_j = e^(l_j) [[a_j, b_j], [c_j, d_j]]
    with det T_j = e^(g_j) (:func:`expm2_scaled`'s form); eliminating the summed Y:

        A = (a1 b2 + a2 b1) / n,  B = b1 b2 / n,  D = (d1 b2 + d2 b1) / n,
        C = (c1 b2 + c2 b1 + a1 d2 + a2 d1 - e^(g1 - l1 - l2) - e^(g2 - l1 - l2)) / n,
        n = e^(-l2) b1 + e^(-l1) b2.

    Written so, neither the scales nor a 2-port of huge entries (a slit many decay lengths
    long: its entries ~ e^(|k| L), its coupling 1/B ~ e^(-|k| L)) overflows or cancels:
    C takes the determinants as given instead of the difference C - D A/B of two
    products of that size. Needs b1, b2 != 0 (2-ports that let flow through). Complex or
    dual numbers, all of one kind (:func:`parallel2`, :func:`parallel2_tangent`)."""
    n = cmul(cexp(-l2), b1) + cmul(cexp(-l1), b2)
    ends = cexp(g1 - l1 - l2) + cexp(g2 - l1 - l2)
    return (
        cdiv(cmul(a1, b2) + cmul(a2, b1), n),
        cdiv(cmul(b1, b2), n),
        cdiv(cmul(c1, b2) + cmul(c2, b1) + cmul(a1, d2) + cmul(a2, d1) - ends, n),
        cdiv(cmul(d1, b2) + cmul(d2, b1), n),
    )


@wp.func
def parallel2(m1: CMat2, l1: wp.vec2d, g1: wp.vec2d, m2: CMat2, l2: wp.vec2d, g2: wp.vec2d):
    """The T-matrix of the 2-ports e^(l1) m1 (det e^(g1)) and e^(l2) m2 (det e^(g2)) side by
    side (:func:`parallel_entries`)."""
    a, b, c, d = parallel_entries(m1.a, m1.b, m1.c, m1.d, l1, g1, m2.a, m2.b, m2.c, m2.d, l2, g2)
    return cmat2(a, b, c, d)


@wp.func
def parallel2_tangent(
    m1: CMat2,
    dm1: CMat2,
    l1: wp.vec2d,
    g1: wp.vec2d,
    dl1: wp.vec2d,
    m2: CMat2,
    dm2: CMat2,
    l2: wp.vec2d,
    g2: wp.vec2d,
    dl2: wp.vec2d,
):
    """The derivative of :func:`parallel2` along a direction in which m_j, l_j and g_j move
    by dm_j, dl_j and 2 dl_j (a cascade's T = e^(S + sigma) E, det T = e^(2 S): only S
    moves, :func:`cosh_sinhc_scaled`'s sigma is held): :func:`parallel_entries` on dual
    numbers."""
    a, b, c, d = parallel_entries(
        dual(m1.a, dm1.a),
        dual(m1.b, dm1.b),
        dual(m1.c, dm1.c),
        dual(m1.d, dm1.d),
        dual(l1, dl1),
        dual(g1, dl1 * wp.float64(2.0)),
        dual(m2.a, dm2.a),
        dual(m2.b, dm2.b),
        dual(m2.c, dm2.c),
        dual(m2.d, dm2.d),
        dual(l2, dl2),
        dual(g2, dl2 * wp.float64(2.0)),
    )
    return cmat2(dual_tangent(a), dual_tangent(b), dual_tangent(c), dual_tangent(d))


# -- the propagation matrix A(x) ---------------------------------------------------------------
# Its physics is written once, in propagation_entries, over generic numbers
# (tawarp.kernels.cmath): float64 reals and wp.vec2d complex numbers give A at a real or
# complex angular frequency, dual numbers (wp.vec4d) its derivative along a parameter too. propagation_at (the
# forward cascade: real omega, tabulated pore functions), propagation_tangent (the tangent
# cascade) and propagation_complex (the onset's complex omega) only differ in where the
# pore functions come from.


@wp.struct
class PointCoefficients:
    """The frequency-independent factors of A at one point of a part (SI units): A at
    angular frequency w follows from them, the part's :class:`PartGeometry` and the pore
    functions alone (:func:`propagation_at`), so a parameter set's points are computed once
    for all of its frequencies (:func:`tawarp.kernels.forward.make_point_kernel`).

    ``log_nu`` = ln(r sqrt(rho/(2 mu))) and ``log_k`` = ln(r_k sqrt(rho cp/(2 kappa))):
    ln(s/sqrt(w)) of the viscous and thermal s = r/delta; ``c12`` = q^2 rho/(phi S)
    [kg/m^5]; ``c21`` = phi S/(rho c^2) [m^4 s^2/kg]; ``c22`` = (dT/dx)/(T (1 - Pr))
    [1/m]; ``rho`` [kg/m^3] (the limp frame's density)."""

    log_nu: wp.float64
    log_k: wp.float64
    c12: wp.float64
    c21: wp.float64
    c22: wp.float64
    rho: wp.float64


@wp.struct
class PartGeometry:
    """What A takes from a part beyond its :class:`PointCoefficients`: ``porosity``,
    ``tortuosity``, tube section ``area`` [m^2], ``frame_mobility`` = 1/rho_1 [m^3/kg]
    (rho_1 the frame's bulk density; 0 = rigid frame), the viscous ``shape_factor``
    r/Lambda (1 = the circular pore's own; used by circular pores only) and an annular
    bypass gap beside the pores: its share ``gap_share`` of the tube section (0: no gap)
    and ``gap_log_nu``, ``gap_log_k`` = ln(y0/r), ln(y0/r_k) of its half-spacing y0 over the
    pores' viscous and thermal radii. A is the pores' alone (``porosity``: their share of
    the section, phi (1 - gap_share) beside a gap); the gap is a second 2-port beside
    them, a slit of its own A (:func:`slit_point`, :func:`slit_geometry`), joined to them
    at the part's ends (:func:`parallel2`)."""

    porosity: wp.float64
    tortuosity: wp.float64
    area: wp.float64
    frame_mobility: wp.float64
    shape_factor: wp.float64
    gap_share: wp.float64
    gap_log_nu: wp.float64
    gap_log_k: wp.float64


@wp.struct
class PorePoint:
    """The pore functions at one point and frequency that A takes: g_nu = 1 - f_nu of the
    viscous s, f_k and g_k = 1 - f_k of the thermal s, and (tangent cascade only) the
    derivatives df/d ln s of both."""

    g_nu: wp.vec2d
    f_k: wp.vec2d
    g_k: wp.vec2d
    df_nu: wp.vec2d
    df_k: wp.vec2d


@wp.func
def point_coefficients(
    gas: wp.array(dtype=wp.float64),
    p_mean: wp.float64,
    T: wp.float64,
    dTdx: wp.float64,
    porosity: wp.float64,
    pore_radius: wp.float64,
    tortuosity: wp.float64,
    area: wp.float64,
    thermal_radius: wp.float64,
):
    """:class:`PointCoefficients` at local temperature T [K] and gradient dTdx [K/m] in a
    part of ``porosity``, ``pore_radius`` [m] (f_nu), ``thermal_radius`` [m] (f_k; the same
    for the one-radius model, a separate one is the Johnson-Champoux-Allard Lambda'/Lambda
    effect), ``tortuosity``, tube section ``area`` [m^2]. The gas laws (:mod:`.gas`) are
    combined over one common denominator: with mu = q_mu T / (T + S_mu) and kappa likewise
    (:func:`.gas.transport_scale`), rho = p / (R T) and rho c^2 = gamma p, every
    coefficient is a product of the laws' factors and one reciprocal, where the laws taken
    one by one cost fifteen divisions and four square roots a point (a float64 division is
    a reciprocal seed and its Newton steps on the GPU; the point kernel runs this at every
    Gauss point, bench/README.md)."""
    R = gas[G_R]
    cp = gas[G_CP]
    q_mu = transport_scale(T, gas[G_MU0], gas[G_MUA], gas[G_MUS])
    q_k = transport_scale(T, gas[G_K0], gas[G_KA], gas[G_KS])
    t_mu = T + gas[G_MUS]
    t_k = T + gas[G_KS]
    # 1 - Pr = 1 - mu cp / kappa = (q_k t_mu - cp q_mu t_k) / (q_k t_mu)
    prandtl_gap = q_k * t_mu - cp * q_mu * t_k
    laws = R * T * T * q_mu * q_k  # rho / p = q_mu q_k T / laws
    heat = T * prandtl_gap  # c22 = dTdx q_k t_mu / heat
    inv = wp.float64(1.0) / (laws * heat)
    inv_laws = heat * inv
    rho = p_mean * T * q_mu * q_k * inv_laws
    pc = PointCoefficients()
    # ln(r sqrt(x)) = ln(r^2 x) / 2, x = rho / (2 mu) = p t_mu q_k / (2 laws), and likewise
    # rho cp / (2 kappa) = p cp t_k q_mu / (2 laws)
    pc.log_nu = wp.float64(0.5) * wp.log(wp.float64(0.5) * pore_radius * pore_radius * p_mean * t_mu * q_k * inv_laws)
    pc.log_k = wp.float64(0.5) * wp.log(
        wp.float64(0.5) * thermal_radius * thermal_radius * p_mean * cp * t_k * q_mu * inv_laws
    )
    pc.c12 = tortuosity * tortuosity * rho / (porosity * area)
    pc.c21 = porosity * area / (gas[G_GAMMA] * p_mean)
    pc.c22 = dTdx * q_k * t_mu * laws * inv
    pc.rho = rho
    return pc


@wp.func
def part_geometry(
    porosity: wp.float64, tortuosity: wp.float64, area: wp.float64, frame_mobility: wp.float64, shape_factor: wp.float64
):
    geo = PartGeometry()
    geo.porosity = porosity
    geo.tortuosity = tortuosity
    geo.area = area
    geo.frame_mobility = frame_mobility
    geo.shape_factor = shape_factor
    geo.gap_share = wp.float64(0.0)
    geo.gap_log_nu = wp.float64(0.0)
    geo.gap_log_k = wp.float64(0.0)
    return geo


@wp.func
def with_bypass(geo: PartGeometry, share: wp.float64, log_nu: wp.float64, log_k: wp.float64):
    """``geo`` with a bypass gap of section share ``share`` and ln(y0/r) = ``log_nu``,
    ln(y0/r_k) = ``log_k`` (:class:`PartGeometry`)."""
    out = part_geometry(geo.porosity, geo.tortuosity, geo.area, geo.frame_mobility, geo.shape_factor)
    out.gap_share = share
    out.gap_log_nu = log_nu
    out.gap_log_k = log_k
    return out


@wp.func
def without_bypass(geo: PartGeometry):
    """``geo`` without its bypass gap: the pores' own part (:class:`PartGeometry`)."""
    return part_geometry(geo.porosity, geo.tortuosity, geo.area, geo.frame_mobility, geo.shape_factor)


@wp.func
def slit_geometry(geo: PartGeometry):
    """:class:`PartGeometry` of the bypass gap of ``geo``: a slit between parallel plates
    (the narrow annulus unrolled; curvature corrections O(g/R)) filling the share
    ``gap_share`` of the section, tortuosity 1, rigid walls."""
    return part_geometry(geo.gap_share, wp.float64(1.0), geo.area, wp.float64(0.0), wp.float64(1.0))


@wp.func
def slit_point(pc: PointCoefficients, geo: PartGeometry):
    """:class:`PointCoefficients` of the bypass gap of ``geo`` (:func:`slit_geometry`) at a
    point whose pores' coefficients are ``pc``: the same gas at the same temperature and
    gradient (c22, rho), its s = y0/delta from the pores' through ln(y0/r) = ``gap_log_nu``
    and ln(y0/r_k) = ``gap_log_k``, and its section x S in place of the pores' phi S:
    c12 = rho/(x S) = c12_pores phi/(q^2 x), c21 = x S/(rho c^2) = c21_pores x/phi."""
    ratio = geo.gap_share / geo.porosity
    out = PointCoefficients()
    out.log_nu = pc.log_nu + geo.gap_log_nu
    out.log_k = pc.log_k + geo.gap_log_k
    out.c12 = pc.c12 / (geo.tortuosity * geo.tortuosity * ratio)
    out.c21 = pc.c21 * ratio
    out.c22 = pc.c22
    out.rho = pc.rho
    return out


@wp.func
def johnson_factor(x2: Any, s: Any):
    """Johnson's dynamic tortuosity over alpha_inf for circular-pore resistivity
    (sigma = 8 mu alpha_inf/(phi r^2)) and viscous length Lambda = r/s, exp(-iwt), at
    x2 = (r/delta_nu)^2: J = 1 + (4 i / x2) sqrt(1 - i s^2 x2 / 8)."""
    root = csqrt(cone(x2) - cmuli(cmul(cmul(s, s), x2)) * wp.float64(0.125))
    return cone(x2) + cdiv(cmuli(root), x2) * wp.float64(4.0)


@wp.func(inline=False)  # an effect's branch: kept out of the cascade's inlined code
def shape_correction(x2: Any, s: Any):
    """J(s)/J(1) at x2 = (r/delta_nu)^2: multiplies the exact circular-pore density
    q^2 rho/(1 - f_nu). Tends to 1 at low frequency (the flow resistivity of radius r is
    kept) and to (1 + (1+i) s/x)/(1 + (1+i)/x) at high frequency: the viscous boundary
    layer then sees Lambda = r/s (a Johnson-Champoux-Allard shape factor; s = 1 is the
    circular pore)."""
    return cdiv(johnson_factor(x2, s), johnson_factor(x2, cone(s)))


@wp.func(inline=False)  # an effect's branch: kept out of the cascade's inlined code
def limp_density(rho: Any, phi: Any, q: Any, g_nu: Any, m: Any):
    """Effective density [kg/m^3] per total volume flux of a porous layer whose frame is
    limp (no stiffness) with bulk density 1/m: from the fluid and frame momentum balances
    with the rigid-frame coupling A = phi (rho_e - rho), rho_e = q^2 rho / (1 - f_nu),

        rho_w = (phi rho + A (phi rho m + 1)) / (phi^2 + phi (1 - phi)^2 rho m + A m),

    which is rho_e / phi (rigid) at m = 0 and phi rho + 1/m (frame moving with the air)
    as A grows. Complex or dual numbers, all of one kind."""
    rho_e = cdiv(cmul(cmul(q, q), rho), g_nu)
    coupling = cmul(rho_e - rho, phi)
    solid = cone(phi) - phi
    num = cmul(phi, rho) + cmul(coupling, cmul(cmul(phi, rho), m) + cone(m))
    den = cmul(phi, phi) + cmul(cmul(phi, cmul(solid, solid)), cmul(rho, m)) + cmul(coupling, m)
    return cdiv(num, den)


@wp.func
def pore_reciprocal(g: wp.vec2d):
    # one real division: 1/g = conj(g)/|g|^2 (|g_nu| ~ s^2/4 > 1e-9 at s > 1e-4: |g|^2 is
    # far from underflow, Smith's scaling is not needed)
    return cscale(cconj(g), wp.float64(1.0) / cabs2(g))


@wp.func
def pore_reciprocal(g: wp.vec4d):  # noqa: F811 (a Warp overload)
    r = pore_reciprocal(dual_value(g))
    return dual(r, -cmul(cmul(r, r), dual_tangent(g)))


@wp.func(inline=False)  # a geometry's branch: kept out of the cascade's inlined code
def screen_entries(
    omega: Any,
    log_nu: Any,
    log_k: Any,
    c12: Any,
    c21: Any,
    c22: Any,
    rho: Any,
    porosity: Any,
    tortuosity: Any,
    area: Any,
    frame_mobility: Any,
    gamma: wp.float64,
):
    """(a12, a21, a22) of A in a stack of wire screens (docs/physics.md, "Stacked wire
    screens"): the low-amplitude limit of Swift & Ward's correlations (J. Thermophys. Heat
    Transfer 10, 652, 1996), as DeltaEC's STKSCREEN writes them, in exp(-iwt), with s the
    viscous r_h/delta_nu and s_k the thermal one (one radius, r_h: s_k^2 = Pr s^2)::

        1/(1 - f_nu) = K + i c1/(16 s^2),   K = 1 + (1 - phi)^2 / (2 (2 phi - 1))
        f_k = 1/(1 - 8 i s_k^2/(b Pr^(1/3)))
        a22 = (T'/T) f_k = c22 (1 - Pr) f_k

    c1 = 1268 - 3545 phi + 2544 phi^2 (the friction factor's laminar term c1/Re),
    b = 3.81 - 11.29 phi + 9.47 phi^2 (the heat transfer's). The Prandtl number comes from
    the point's two logarithms, Pr = exp(2 (log_k - log_nu)), which holds because a screen
    stack's thermal radius is its hydraulic radius. Arguments as
    :func:`propagation_entries`'s; real, complex or dual numbers."""
    phi = ccomplex(porosity)
    one = cone(phi)
    solid = one - phi
    inertia = one + cdiv(cmul(solid, solid), phi * wp.float64(4.0) - one * wp.float64(2.0))
    c1 = one * wp.float64(1268.0) - phi * wp.float64(3545.0) + cmul(phi, phi) * wp.float64(2544.0)
    b = one * wp.float64(3.81) - phi * wp.float64(11.29) + cmul(phi, phi) * wp.float64(9.47)
    ln_nu = ccomplex(log_nu)
    ln_k = ccomplex(log_k)
    s2 = cmul(omega, cexp(ln_nu * wp.float64(2.0)))  # (r_h/delta_nu)^2
    inv_g_nu = inertia + cdiv(cmuli(c1), s2) * wp.float64(0.0625)
    density_per_area = cmul(c12, inv_g_nu)  # [kg/m^5]
    if cre(frame_mobility) > wp.float64(0.0):
        g_nu = pore_reciprocal(inv_g_nu)
        rho_w = limp_density(ccomplex(rho), phi, ccomplex(tortuosity), g_nu, ccomplex(frame_mobility))
        density_per_area = cdiv(rho_w, ccomplex(area))
    # s_k^2/Pr^(1/3) = Pr^(2/3) s^2
    heat = cmul(omega, cexp(ln_nu * TWO_THIRDS + ln_k * FOUR_THIRDS))
    f_k = pore_reciprocal(cone(heat) - cdiv(cmuli(heat), b) * wp.float64(8.0))
    a12 = cmuli(cmul(omega, density_per_area))
    a21 = cmuli(cmul(omega, cmul(c21, cone(f_k) + f_k * (gamma - wp.float64(1.0)))))
    a22 = cmul(c22, cmul(f_k, cone(f_k) - cexp((ln_k - ln_nu) * wp.float64(2.0))))
    return a12, a21, a22


@wp.func
def propagation_entries(
    omega: Any,
    root_omega: Any,
    log_nu: Any,
    log_k: Any,
    c12: Any,
    c21: Any,
    c22: Any,
    rho: Any,
    f_k: Any,
    inv_g_nu: Any,
    g_k: Any,
    porosity: Any,
    tortuosity: Any,
    area: Any,
    frame_mobility: Any,
    shape_factor: Any,
    gamma: wp.float64,
    pore_model: int,
):
    """(a12, a21, a22) of A (module docstring) at angular frequency ``omega`` [rad/s]
    (``root_omega`` its principal square root) from a point's :class:`PointCoefficients`
    (``log_nu``, ``log_k``, ``c12``, ``c21``, ``c22``, ``rho``), its pore functions (``f_k``,
    ``inv_g_nu`` = 1/g_nu = 1/(1 - f_nu), ``g_k``: A takes g_nu only through its
    reciprocal, which the plain cascade reads from the pore table,
    :func:`propagation_circular`) and its part's :class:`PartGeometry`; ``gamma`` is the gas's ratio of specific
    heats. The physics of A, written once for every kind of number
    (:mod:`tawarp.kernels.cmath`): real or complex omega with real coefficients
    (:func:`propagation_value`, :func:`propagation_complex`), or duals that carry a
    derivative (:func:`propagation_tangent`). The effects: a limp frame
    (:func:`limp_density`, frame_mobility > 0) and a viscous shape factor
    (:func:`shape_correction`, circular pores). Wire screens take their own entries
    (:func:`screen_entries`), not the pore functions. (A bypass gap is no part of A: it is
    a second 2-port beside the part's, :func:`slit_point`.)"""
    if pore_model == PORE_SCREENS:
        return screen_entries(
            omega, log_nu, log_k, c12, c21, c22, rho, porosity, tortuosity, area, frame_mobility, gamma
        )
    if pore_model == PORE_CIRCULAR and cre(shape_factor) != wp.float64(1.0) and cre(shape_factor) > wp.float64(0.0):
        s_nu = cmul(root_omega, cexp(ccomplex(log_nu)))
        # g_nu / J: its reciprocal times J
        inv_g_nu = cmul(inv_g_nu, shape_correction(cmul(s_nu, s_nu), ccomplex(shape_factor)))
    density_per_area = cmul(c12, inv_g_nu)  # [kg/m^5]
    if cre(frame_mobility) > wp.float64(0.0):
        g_nu = pore_reciprocal(inv_g_nu)
        rho_w = limp_density(ccomplex(rho), ccomplex(porosity), ccomplex(tortuosity), g_nu, ccomplex(frame_mobility))
        density_per_area = cdiv(rho_w, ccomplex(area))
    a12 = cmuli(cmul(omega, density_per_area))
    a21 = cmuli(cmul(omega, cmul(c21, cone(f_k) + f_k * (gamma - wp.float64(1.0)))))
    # (f_k - f_nu)/(1 - f_nu) = 1 - g_k/g_nu: no difference of two f close to 1 (narrow
    # pores); where both g are close to 1 (wide pores) the difference's rounding is an
    # absolute 1e-16 of c22, |T'/T|/(1 - Pr), which a cell's h takes to ~1e-16 of the T-matrix
    a22 = cmul(c22, cone(g_k) - cmul(g_k, inv_g_nu))
    return a12, a21, a22


@wp.func
def pore_point(
    pc: PointCoefficients,
    half_log_omega: wp.float64,
    pore_model: int,
    pore_table: PoreTable,
    derivatives: int,
):
    """:class:`PorePoint` at real angular frequency omega (``half_log_omega`` = ln(omega)/2,
    shared by a cascade's points), from ``pore_table``
    (:func:`tawarp.kernels.pore_table.circular_table` on the kernel's device); the
    derivatives only where ``derivatives`` != 0."""
    log_s_nu = pc.log_nu + half_log_omega
    log_s_k = pc.log_k + half_log_omega
    f_nu, g_nu = pore_functions_log(pore_model, log_s_nu, pore_table)
    f_k, g_k = pore_functions_log(pore_model, log_s_k, pore_table)
    pp = PorePoint()
    pp.g_nu = g_nu
    pp.f_k = f_k
    pp.g_k = g_k
    if derivatives != 0:
        pp.df_nu = pore_log_derivative(pore_model, log_s_nu, f_nu, g_nu)
        pp.df_k = pore_log_derivative(pore_model, log_s_k, f_k, g_k)
    return pp


@wp.func
def propagation_value(
    pp: PorePoint, pc: PointCoefficients, geo: PartGeometry, omega: wp.float64, gamma: wp.float64, pore_model: int
):
    """A at real angular frequency omega [rad/s] from the point's pore functions ``pp``
    (:func:`pore_point`), coefficients and part geometry (:func:`propagation_entries`)."""
    a12, a21, a22 = propagation_entries(
        omega,
        wp.sqrt(omega),
        pc.log_nu,
        pc.log_k,
        pc.c12,
        pc.c21,
        pc.c22,
        pc.rho,
        pp.f_k,
        pore_reciprocal(pp.g_nu),
        pp.g_k,
        geo.porosity,
        geo.tortuosity,
        geo.area,
        geo.frame_mobility,
        geo.shape_factor,
        gamma,
        pore_model,
    )
    return cmat2(creal(wp.float64(0.0)), a12, a21, a22)


@wp.func
def plain_part(geo: PartGeometry, pore_model: int):
    """True for the cascade's usual part: circular pores (or a duct), a rigid frame, no
    viscous shape factor (1, or <= 0: :func:`propagation_entries` reads both as circular)
    and no bypass gap, whose A needs no effect's branch of :func:`propagation_entries` and
    whose matrix is its own cascade's (a gap's slit is a second one, :func:`slit_point`)."""
    shape = geo.shape_factor
    return (
        pore_model == PORE_CIRCULAR
        and geo.frame_mobility <= wp.float64(0.0)
        and (shape == wp.float64(1.0) or shape <= wp.float64(0.0))
        and geo.gap_share <= wp.float64(0.0)
    )


@wp.func
def propagation_circular(
    pc: PointCoefficients,
    geo: PartGeometry,
    omega: wp.float64,
    half_log_omega: wp.float64,
    gamma: wp.float64,
    pore_table: PoreTable,
):
    """A(x) at real angular frequency omega [rad/s] (``half_log_omega`` = ln(omega)/2) at a
    point of a :func:`plain_part`: the circular pore functions from the table
    (:func:`tawarp.kernels.pore.pore_circular_tabulated`; the viscous one as 1/g_nu,
    :func:`tawarp.kernels.pore.circular_inverse_g`, which spares the cell's three Gauss
    points a division each) and :func:`propagation_entries` with the effects' neutral values
    as constants, which the compiler folds. No call: the cascade that takes only such parts
    compiles to registers alone (bench/README.md)."""
    inv_g_nu = circular_inverse_g(pore_table, pc.log_nu + half_log_omega)
    f_k, g_k = pore_circular_tabulated(pore_table, pc.log_k + half_log_omega)
    a12, a21, a22 = propagation_entries(
        omega,
        omega,  # the root is read by the shape factor alone
        pc.log_nu,
        pc.log_k,
        pc.c12,
        pc.c21,
        pc.c22,
        pc.rho,
        f_k,
        inv_g_nu,
        g_k,
        geo.porosity,
        geo.tortuosity,
        geo.area,
        wp.float64(0.0),
        wp.float64(1.0),
        gamma,
        PORE_CIRCULAR,
    )
    return cmat2(creal(wp.float64(0.0)), a12, a21, a22)


@wp.func
def propagation_at(
    pc: PointCoefficients,
    geo: PartGeometry,
    omega: wp.float64,
    half_log_omega: wp.float64,
    gamma: wp.float64,
    pore_model: int,
    pore_table: PoreTable,
):
    """A(x) of the two-port ODE at real angular frequency omega [rad/s]
    (``half_log_omega`` = ln(omega)/2) at a point of any part: :func:`propagation_circular`
    in a :func:`plain_part`, else :func:`propagation_other`, out of line, so that its code
    stays off the usual part's path."""
    if plain_part(geo, pore_model):
        return propagation_circular(pc, geo, omega, half_log_omega, gamma, pore_table)
    return propagation_other(pc, geo, omega, half_log_omega, gamma, pore_model, pore_table)


@wp.func(inline=False)  # the rare points of a cascade: kept out of its inlined code
def propagation_other(
    pc: PointCoefficients,
    geo: PartGeometry,
    omega: wp.float64,
    half_log_omega: wp.float64,
    gamma: wp.float64,
    pore_model: int,
    pore_table: PoreTable,
):
    """:func:`propagation_at` at any point: :func:`propagation_value` of :func:`pore_point`."""
    pp = pore_point(pc, half_log_omega, pore_model, pore_table, 0)
    return propagation_value(pp, pc, geo, omega, gamma, pore_model)


@wp.func
def propagation_tangent(
    pp: PorePoint,
    pc: PointCoefficients,
    dpc: PointCoefficients,
    geo: PartGeometry,
    dgeo: PartGeometry,
    omega: wp.float64,
    gamma: wp.float64,
    pore_model: int,
):
    """dA at real angular frequency omega [rad/s] in the direction in which the point's
    coefficients move by ``dpc`` and its part's geometry by ``dgeo`` (the derivatives along
    one parameter): :func:`propagation_entries` on dual numbers, the pore functions moving
    by df/d ln s times d ln s (``pp`` with its derivatives, :func:`pore_point`)."""
    a12, a21, a22 = propagation_entries(
        omega,
        wp.sqrt(omega),
        dual_real(pc.log_nu, dpc.log_nu),
        dual_real(pc.log_k, dpc.log_k),
        dual_real(pc.c12, dpc.c12),
        dual_real(pc.c21, dpc.c21),
        dual_real(pc.c22, dpc.c22),
        dual_real(pc.rho, dpc.rho),
        dual(pp.f_k, cscale(pp.df_k, dpc.log_k)),
        pore_reciprocal(dual(pp.g_nu, cscale(pp.df_nu, -dpc.log_nu))),
        dual(pp.g_k, cscale(pp.df_k, -dpc.log_k)),
        dual_real(geo.porosity, dgeo.porosity),
        dual_real(geo.tortuosity, dgeo.tortuosity),
        dual_real(geo.area, dgeo.area),
        dual_real(geo.frame_mobility, dgeo.frame_mobility),
        dual_real(geo.shape_factor, dgeo.shape_factor),
        gamma,
        pore_model,
    )
    return cmat2(creal(wp.float64(0.0)), dual_tangent(a12), dual_tangent(a21), dual_tangent(a22))


@wp.func
def propagation_complex(pc: PointCoefficients, geo: PartGeometry, omega: wp.vec2d, gamma: wp.float64, pore_model: int):
    """A(x) at complex angular frequency omega [rad/s] (re, im), with exp(-i omega t) (the
    onset's eigenvalue problem, :mod:`tawarp.kernels.onset`). Every coefficient of A is
    analytic in omega: it enters through s = r/delta = exp(log_nu) sqrt(omega) (principal
    root) and as a factor of a12, a21; at real omega this is :func:`propagation_at` to
    rounding (the pore functions computed instead of tabulated)."""
    root = csqrt(omega)
    f_nu, g_nu = pore_functions_complex(pore_model, cscale(root, wp.exp(pc.log_nu)))
    f_k, g_k = pore_functions_complex(pore_model, cscale(root, wp.exp(pc.log_k)))
    a12, a21, a22 = propagation_entries(
        omega,
        root,
        pc.log_nu,
        pc.log_k,
        pc.c12,
        pc.c21,
        pc.c22,
        pc.rho,
        f_k,
        pore_reciprocal(g_nu),
        g_k,
        geo.porosity,
        geo.tortuosity,
        geo.area,
        geo.frame_mobility,
        geo.shape_factor,
        gamma,
        pore_model,
    )
    return cmat2(creal(wp.float64(0.0)), a12, a21, a22)


@wp.func
def point_difference(plus: PointCoefficients, minus: PointCoefficients, inv_two_step: wp.float64):
    """(plus - minus) / (2 step) of every field: the central difference of a point's
    coefficients along one parameter, ``inv_two_step`` = 1/(2 step)."""
    d = PointCoefficients()
    d.log_nu = (plus.log_nu - minus.log_nu) * inv_two_step
    d.log_k = (plus.log_k - minus.log_k) * inv_two_step
    d.c12 = (plus.c12 - minus.c12) * inv_two_step
    d.c21 = (plus.c21 - minus.c21) * inv_two_step
    d.c22 = (plus.c22 - minus.c22) * inv_two_step
    d.rho = (plus.rho - minus.rho) * inv_two_step
    return d


@wp.func
def geometry_difference(plus: PartGeometry, minus: PartGeometry, inv_two_step: wp.float64):
    """(plus - minus) / (2 step) of every field of a :class:`PartGeometry`."""
    return with_bypass(
        part_geometry(
            (plus.porosity - minus.porosity) * inv_two_step,
            (plus.tortuosity - minus.tortuosity) * inv_two_step,
            (plus.area - minus.area) * inv_two_step,
            (plus.frame_mobility - minus.frame_mobility) * inv_two_step,
            (plus.shape_factor - minus.shape_factor) * inv_two_step,
        ),
        (plus.gap_share - minus.gap_share) * inv_two_step,
        (plus.gap_log_nu - minus.gap_log_nu) * inv_two_step,
        (plus.gap_log_k - minus.gap_log_k) * inv_two_step,
    )
