"""Complex float64 arithmetic for Warp: a complex number is a ``wp.vec2d`` (re, im)."""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

complex128 = wp.vec2d


@wp.func
def cplx(re: wp.float64, im: wp.float64):
    return wp.vec2d(re, im)


@wp.func
def creal(x: wp.float64):
    return wp.vec2d(x, wp.float64(0.0))


@wp.func
def cmul(a: wp.vec2d, b: wp.vec2d):
    return wp.vec2d(a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0])


@wp.func
def cconj(a: wp.vec2d):
    return wp.vec2d(a[0], -a[1])


@wp.func
def cabs2(a: wp.vec2d):
    return a[0] * a[0] + a[1] * a[1]


@wp.func
def cabs(a: wp.vec2d):
    # hypot-style scaling avoids overflow for |a| near the float64 limits
    x = wp.abs(a[0])
    y = wp.abs(a[1])
    m = wp.max(x, y)
    if m == wp.float64(0.0):
        return wp.float64(0.0)
    x = x / m
    y = y / m
    return m * wp.sqrt(x * x + y * y)


@wp.func
def cdiv(a: wp.vec2d, b: wp.vec2d):
    # Smith's algorithm: no overflow or needless loss for badly scaled b
    if wp.abs(b[0]) >= wp.abs(b[1]):
        r = b[1] / b[0]
        d = b[0] + b[1] * r
        return wp.vec2d((a[0] + a[1] * r) / d, (a[1] - a[0] * r) / d)
    r = b[0] / b[1]
    d = b[0] * r + b[1]
    return wp.vec2d((a[0] * r + a[1]) / d, (a[1] * r - a[0]) / d)


@wp.func
def cinv(b: wp.vec2d):
    return cdiv(wp.vec2d(wp.float64(1.0), wp.float64(0.0)), b)


@wp.func
def cscale(a: wp.vec2d, s: wp.float64):
    return wp.vec2d(a[0] * s, a[1] * s)


@wp.func
def cmuli(a: wp.vec2d):
    """i * a."""
    return wp.vec2d(-a[1], a[0])


@wp.func
def cexp(a: wp.vec2d):
    e = wp.exp(a[0])
    return wp.vec2d(e * wp.cos(a[1]), e * wp.sin(a[1]))


@wp.func
def csqrt(a: wp.vec2d):
    """Principal square root (Re >= 0), without cancellation."""
    m = cabs(a)
    if m == wp.float64(0.0):
        return wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    t = wp.sqrt(wp.float64(0.5) * (m + wp.abs(a[0])))
    if a[0] >= wp.float64(0.0):
        return wp.vec2d(t, a[1] / (wp.float64(2.0) * t))
    s = wp.float64(1.0)
    if a[1] < wp.float64(0.0):
        s = wp.float64(-1.0)
    return wp.vec2d(wp.abs(a[1]) / (wp.float64(2.0) * t), s * t)


# -- numbers of three kinds: real, complex, dual ------------------------------------------------
# A dual complex number x + eps dx (eps^2 = 0) is a ``wp.vec4d`` (re x, im x, re dx, im dx).
# A function written with the overloads below, ``+`` and ``-`` between numbers of one kind and
# ``* float`` (all componentwise, as the derivative is) runs on float64 reals, wp.vec2d complex
# numbers or duals alike: it gives a value, or a value and its derivative along dx, from one
# source (:func:`tawarp.kernels.acoustics.propagation_entries`). A real may multiply a number
# of any kind (``cmul(real, x)``); sums need one kind (:func:`ccomplex` lifts a real).


@wp.func
def dual(x: wp.vec2d, dx: wp.vec2d):
    """x + eps dx."""
    return wp.vec4d(x[0], x[1], dx[0], dx[1])


@wp.func
def dual_real(x: wp.float64, dx: wp.float64):
    """The real x + eps dx as a dual number."""
    return wp.vec4d(x, wp.float64(0.0), dx, wp.float64(0.0))


@wp.func
def dual_value(a: wp.vec4d):
    return wp.vec2d(a[0], a[1])


@wp.func
def dual_tangent(a: wp.vec4d):
    return wp.vec2d(a[2], a[3])


@wp.func
def cre(a: wp.float64):
    """The real part of a's value, for a real, complex or dual a."""
    return a


@wp.func
def cre(a: wp.vec2d):  # noqa: F811 (a Warp overload)
    return a[0]


@wp.func
def cre(a: wp.vec4d):  # noqa: F811 (a Warp overload)
    return a[0]


@wp.func
def ccomplex(a: wp.float64):
    """a as a number that sums with complex ones: a real becomes complex, a complex or dual
    number stays as it is."""
    return wp.vec2d(a, wp.float64(0.0))


@wp.func
def ccomplex(a: wp.vec2d):  # noqa: F811 (a Warp overload)
    return a


@wp.func
def ccomplex(a: wp.vec4d):  # noqa: F811 (a Warp overload)
    return a


@wp.func
def cone(a: wp.vec2d):
    """The complex 1, of a's kind."""
    return wp.vec2d(wp.float64(1.0), wp.float64(0.0))


@wp.func
def cone(a: wp.vec4d):  # noqa: F811 (a Warp overload)
    return wp.vec4d(wp.float64(1.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))


@wp.func
def cmul(a: wp.float64, b: wp.vec2d):  # noqa: F811 (a Warp overload)
    return cscale(b, a)


@wp.func
def cmul(a: wp.float64, b: wp.vec4d):  # noqa: F811 (a Warp overload)
    return b * a


@wp.func
def cmul(a: wp.vec4d, b: wp.vec4d):  # noqa: F811 (a Warp overload)
    x = dual_value(a)
    y = dual_value(b)
    return dual(cmul(x, y), cmul(dual_tangent(a), y) + cmul(x, dual_tangent(b)))


@wp.func
def cdiv(a: wp.vec4d, b: wp.vec4d):  # noqa: F811 (a Warp overload)
    q = cdiv(dual_value(a), dual_value(b))
    return dual(q, cdiv(dual_tangent(a) - cmul(q, dual_tangent(b)), dual_value(b)))


@wp.func
def cmuli(a: wp.vec4d):  # noqa: F811 (a Warp overload)
    return wp.vec4d(-a[1], a[0], -a[3], a[2])


@wp.func
def cexp(a: wp.vec4d):  # noqa: F811 (a Warp overload)
    e = cexp(dual_value(a))
    return dual(e, cmul(e, dual_tangent(a)))


@wp.func
def csqrt(a: wp.vec4d):  # noqa: F811 (a Warp overload)
    r = csqrt(dual_value(a))
    return dual(r, cdiv(dual_tangent(a), r * wp.float64(2.0)))
