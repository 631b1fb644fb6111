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
