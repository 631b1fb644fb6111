"""Acoustic two-port of one part (PHYSICS.md, "Acoustics"), as Warp functions.

``d/dx (p, U) = A(x) (p, U)`` with ``A = [[0, a12], [a21, a22]]``::

    a12 = i q^2 rho w / (phi S (1 - f_nu))
    a21 = i phi S w / (rho c^2) (1 + (gamma - 1) f_k)
    a22 = (T'/T) (f_k - f_nu) / ((1 - f_nu)(1 - Pr))

Parts at uniform temperature have constant A and their exact matrix is ``exp(A L)``;
parts with a gradient are integrated with the sixth-order Magnus scheme on three Gauss
points per cell. Both use :func:`expm2`, so one code path gives the closed form of
PHYSICS.md (``exp(A L) = [[cos kL, i Zc sin kL], [i sin kL / Zc, cos kL]]``) and the
integrator.
"""

import warp as wp

from .cmath import cdiv, cexp, cmul, cmuli, creal, cscale, csqrt
from .gas import G_CP, G_GAMMA, conductivity, density, sound_speed_squared, viscosity
from .pore import pore_functions


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
def identity2():
    one = wp.vec2d(wp.float64(1.0), wp.float64(0.0))
    zero = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    return cmat2(one, zero, zero, one)


@wp.func
def matmul2(x: CMat2, y: CMat2):
    return cmat2(cmul(x.a, y.a) + cmul(x.b, y.c), cmul(x.a, y.b) + cmul(x.b, y.d),
                 cmul(x.c, y.a) + cmul(x.d, y.c), cmul(x.c, y.b) + cmul(x.d, y.d))


@wp.func
def expm2(m: CMat2):
    """exp(m) of a 2x2 complex matrix: with tau = tr/2, N = m - tau I and N^2 = delta I,
    exp(m) = e^tau (cosh(sqrt delta) I + sinh(sqrt delta)/sqrt(delta) N). Both functions
    are entire in delta: a Taylor series for |delta| < 1 (no square root, no cancellation,
    the usual case of a Magnus cell), exponentials beyond."""
    tau = cscale(m.a + m.d, wp.float64(0.5))
    na = m.a - tau
    delta = cmul(na, na) + cmul(m.b, m.c)
    ch = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    sh = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    if delta[0] * delta[0] + delta[1] * delta[1] < wp.float64(1.0):
        # Horner on sum delta^j/(2j)! and sum delta^j/(2j+1)!, 11 terms: error < 1/22! ~ 1e-21
        ch = creal(wp.float64(1.0))
        sh = creal(wp.float64(1.0))
        for jj in range(10):
            j = wp.float64(10 - jj)
            ch = creal(wp.float64(1.0)) + cscale(cmul(delta, ch), wp.float64(1.0) / ((wp.float64(2.0) * j) * (wp.float64(2.0) * j - wp.float64(1.0))))
            sh = creal(wp.float64(1.0)) + cscale(cmul(delta, sh), wp.float64(1.0) / ((wp.float64(2.0) * j) * (wp.float64(2.0) * j + wp.float64(1.0))))
    else:
        r = csqrt(delta)
        ep = cexp(r)
        em = cexp(-r)
        ch = cscale(ep + em, wp.float64(0.5))
        sh = cdiv(cscale(ep - em, wp.float64(0.5)), r)
    et = cexp(tau)
    ch = cmul(et, ch)
    sh = cmul(et, sh)
    return cmat2(ch + cmul(sh, na), cmul(sh, m.b), cmul(sh, m.c), ch - cmul(sh, na))


@wp.func
def propagation_matrix(gas: wp.array(dtype=wp.float64), p_mean: wp.float64, omega: wp.float64,
                       T: wp.float64, dTdx: wp.float64, porosity: wp.float64, pore_radius: wp.float64,
                       tortuosity: wp.float64, pore_model: int, area: wp.float64):
    """A(x) of the two-port ODE at local temperature T [K], gradient dTdx [K/m],
    angular frequency omega [rad/s], tube section area [m^2]."""
    rho = density(gas, T, p_mean)
    c2 = sound_speed_squared(gas, T)
    mu = viscosity(gas, T)
    kappa = conductivity(gas, T)
    cp = gas[G_CP]
    gamma = gas[G_GAMMA]
    prandtl = mu * cp / kappa
    # r/delta with delta_nu = sqrt(2 mu/(rho w)), delta_k = sqrt(2 k/(rho cp w))
    s_nu = pore_radius * wp.sqrt(rho * omega / (wp.float64(2.0) * mu))
    s_k = pore_radius * wp.sqrt(rho * cp * omega / (wp.float64(2.0) * kappa))
    f_nu, g_nu = pore_functions(pore_model, s_nu)
    f_k, g_k = pore_functions(pore_model, s_k)
    a12 = cmuli(cdiv(creal(tortuosity * tortuosity * rho * omega / (porosity * area)), g_nu))
    a21 = cmuli(cscale(creal(wp.float64(1.0)) + cscale(f_k, gamma - wp.float64(1.0)), porosity * area * omega / (rho * c2)))
    # f_k - f_nu = g_nu - g_k: no cancellation when both f are close to 1 (narrow pores)
    a22 = cscale(cdiv(g_nu - g_k, g_nu), dTdx / (T * (wp.float64(1.0) - prandtl)))
    zero = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    return cmat2(zero, a12, a21, a22)


@wp.func
def axpy2(s: wp.float64, x: CMat2, y: CMat2):
    """s x + y."""
    return cmat2(cscale(x.a, s) + y.a, cscale(x.b, s) + y.b, cscale(x.c, s) + y.c, cscale(x.d, s) + y.d)


@wp.func
def commutator2(x: CMat2, y: CMat2):
    """[x, y] = x y - y x."""
    return axpy2(wp.float64(-1.0), matmul2(y, x), matmul2(x, y))


@wp.func
def magnus6_step(a1: CMat2, a2: CMat2, a3: CMat2, h: wp.float64):
    """exp(Omega) of one cell of length h, sixth order, from A at the three Gauss points
    x + (1/2 - sqrt(15)/10, 1/2, 1/2 + sqrt(15)/10) h (Blanes, Casas & Ros, BIT 40, 2000,
    eq. 4.13): with b1 = h A2, b2 = sqrt(15) h/3 (A3 - A1), b3 = 10 h/3 (A3 - 2 A2 + A1),
    C1 = [b1, b2], C2 = -1/60 [b1, 2 b3 + C1],
    Omega = b1 + b3/12 + 1/240 [-20 b1 - b3 + C1, b2 + C2]."""
    b1 = scale2(a2, h)
    b2 = scale2(axpy2(wp.float64(-1.0), a1, a3), wp.float64(1.2909944487358056) * h)
    b3 = scale2(axpy2(wp.float64(-2.0), a2, axpy2(wp.float64(1.0), a3, a1)), wp.float64(3.3333333333333333) * h)
    c1 = commutator2(b1, b2)
    c2 = scale2(commutator2(b1, axpy2(wp.float64(2.0), b3, c1)), wp.float64(-1.0 / 60.0))
    left = axpy2(wp.float64(-20.0), b1, axpy2(wp.float64(-1.0), b3, c1))
    om = axpy2(wp.float64(1.0 / 240.0), commutator2(left, axpy2(wp.float64(1.0), b2, c2)), axpy2(wp.float64(1.0 / 12.0), b3, b1))
    return expm2(om)


@wp.func
def scale2(m: CMat2, s: wp.float64):
    return cmat2(cscale(m.a, s), cscale(m.b, s), cscale(m.c, s), cscale(m.d, s))
