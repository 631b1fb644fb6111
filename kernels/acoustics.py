"""Acoustic two-port of one part (docs/physics.md, "Acoustics"), as Warp functions.

``d/dx (p, U) = A(x) (p, U)`` with ``A = [[0, a12], [a21, a22]]``::

    a12 = i q^2 rho w / (phi S (1 - f_nu))
    a21 = i phi S w / (rho c^2) (1 + (gamma - 1) f_k)
    a22 = (T'/T) (f_k - f_nu) / ((1 - f_nu)(1 - Pr))

Parts at uniform temperature have constant A and their exact matrix is ``exp(A L)``;
parts with a gradient are integrated with the sixth-order Magnus scheme on three Gauss
points per cell. Both use :func:`expm2`, so one code path gives the closed form of
docs/physics.md (``exp(A L) = [[cos kL, i Zc sin kL], [i sin kL / Zc, cos kL]]``) and the
integrator.
"""

import warp as wp

from .cmath import cabs2, cconj, cdiv, cexp, cmul, cmuli, cplx, creal, cscale, csqrt
from .gas import G_CP, G_GAMMA, conductivity, density, sound_speed_squared, viscosity
from .pore import pore_functions_complex, pore_functions_log, pore_log_derivative

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


@wp.func
def cosh_sinhc(delta: wp.vec2d):
    """(cosh(sqrt delta), sinh(sqrt delta)/sqrt(delta)) of a complex delta: both entire in
    delta, a Taylor series for |delta| < 1 (no square root, no cancellation, the usual case
    of a Magnus cell), exponentials beyond."""
    size = cabs2(delta)
    if size < wp.float64(1.0):
        # Horner on sum delta^j/(2j)! and sum delta^j/(2j+1)!, j <= terms: the first
        # omitted term |delta|^(terms+1)/(2 terms + 2)! is below 1e-17 (a Magnus cell's
        # |delta| is mostly far below 1: few of the 9 terms |delta| near 1 needs)
        terms = taylor_terms(size)
        ch = creal(wp.float64(1.0))
        sh = creal(wp.float64(1.0))
        for jj in range(9):  # a fixed count: unrolled, its divisions folded to constants
            if 9 - jj <= terms:
                j = wp.float64(9 - jj)
                ch = creal(wp.float64(1.0)) + cscale(
                    cmul(delta, ch), wp.float64(1.0) / ((wp.float64(2.0) * j) * (wp.float64(2.0) * j - wp.float64(1.0)))
                )
                sh = creal(wp.float64(1.0)) + cscale(
                    cmul(delta, sh), wp.float64(1.0) / ((wp.float64(2.0) * j) * (wp.float64(2.0) * j + wp.float64(1.0)))
                )
        return ch, sh
    r = csqrt(delta)
    ep = cexp(r)
    em = cexp(-r)
    return cscale(ep + em, wp.float64(0.5)), cdiv(cscale(ep - em, wp.float64(0.5)), r)


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


@wp.struct
class PointCoefficients:
    """The frequency-independent factors of A at one point of a part (SI units): A at
    angular frequency w follows from them and the pore functions alone
    (:func:`propagation_at`), so a parameter set's points are computed once for all of its
    frequencies (:func:`tawarp.kernels.forward.make_point_kernel`).

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
    effect), ``tortuosity``, tube section ``area`` [m^2]."""
    rho = density(gas, T, p_mean)
    mu = viscosity(gas, T)
    kappa = conductivity(gas, T)
    cp = gas[G_CP]
    pc = PointCoefficients()
    pc.log_nu = wp.log(pore_radius * wp.sqrt(rho / (wp.float64(2.0) * mu)))
    pc.log_k = wp.log(thermal_radius * wp.sqrt(rho * cp / (wp.float64(2.0) * kappa)))
    pc.c12 = tortuosity * tortuosity * rho / (porosity * area)
    pc.c21 = porosity * area / (rho * sound_speed_squared(gas, T))
    pc.c22 = dTdx / (T * (wp.float64(1.0) - mu * cp / kappa))
    pc.rho = rho
    return pc


@wp.func
def propagation_at(
    pc: PointCoefficients,
    omega: wp.float64,
    half_log_omega: wp.float64,
    gamma: wp.float64,
    porosity: wp.float64,
    tortuosity: wp.float64,
    pore_model: int,
    area: wp.float64,
    frame_mobility: wp.float64,
    shape_factor: wp.float64,
    pore_table: wp.array(dtype=wp.float64),
):
    """A(x) of the two-port ODE at angular frequency omega [rad/s] (``half_log_omega`` =
    ln(omega)/2, shared by a cascade's points) from the point's :class:`PointCoefficients`.
    ``frame_mobility`` = 1/rho_1 [m^3/kg] (rho_1 the frame's bulk density) makes the frame
    limp: 0 = rigid. ``shape_factor`` s != 1 (circular pores only) gives the viscous
    function its own high-frequency length Lambda = r/s at the same flow resistivity
    (:func:`shape_correction`). ``pore_table`` is
    :func:`tawarp.kernels.pore_table.circular_table` on the kernel's device."""
    log_s_nu = pc.log_nu + half_log_omega
    f_nu, g_nu = pore_functions_log(pore_model, log_s_nu, pore_table)
    f_k, g_k = pore_functions_log(pore_model, pc.log_k + half_log_omega, pore_table)
    if shape_factor != wp.float64(1.0) and shape_factor > wp.float64(0.0) and pore_model == 0:
        g_nu = cdiv(g_nu, shape_correction(wp.exp(log_s_nu), shape_factor))
    # one real division per point: a12 and a22 both divide by g_nu, and 1/g = conj(g)/|g|^2
    # (|g_nu| ~ s^2/4 > 1e-9 at s > 1e-4: |g|^2 is far from underflow, Smith's scaling not needed)
    inv_g_nu = cscale(cconj(g_nu), wp.float64(1.0) / cabs2(g_nu))
    a12 = cmuli(cscale(inv_g_nu, pc.c12 * omega))
    if frame_mobility > wp.float64(0.0):
        a12 = cmuli(cscale(limp_density(pc.rho, porosity, tortuosity, g_nu, frame_mobility), omega / area))
    a21 = cmuli(cscale(creal(wp.float64(1.0)) + cscale(f_k, gamma - wp.float64(1.0)), pc.c21 * omega))
    # f_k - f_nu = g_nu - g_k: no cancellation when both f are close to 1 (narrow pores)
    a22 = cscale(cmul(g_nu - g_k, inv_g_nu), pc.c22)
    zero = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    return cmat2(zero, a12, a21, a22)


@wp.struct
class PropagationPartials:
    """A at a point of a rigid-frame part with circular (shape factor 1) or slit pores, as
    its partial derivatives in the :class:`PointCoefficients` (complex, SI units): A is
    linear in c12, c21 and c22, so ``a12 = a12_c12 c12``, ``a21 = a21_c21 c21``,
    ``a22 = a22_c22 c22``; ``a12_nu`` = d a12/d log_nu, ``a21_k`` = d a21/d log_k,
    ``a22_nu``, ``a22_k`` likewise (:func:`propagation_partials`)."""

    a12_c12: wp.vec2d
    a12_nu: wp.vec2d
    a21_c21: wp.vec2d
    a21_k: wp.vec2d
    a22_c22: wp.vec2d
    a22_nu: wp.vec2d
    a22_k: wp.vec2d


@wp.func
def propagation_partials(
    pc: PointCoefficients,
    omega: wp.float64,
    half_log_omega: wp.float64,
    gamma: wp.float64,
    pore_model: int,
    pore_table: wp.array(dtype=wp.float64),
):
    """:class:`PropagationPartials` at angular frequency omega [rad/s] (arguments as
    :func:`propagation_at`, whose A they give for a rigid frame and shape factor 1): with
    f' = df/d ln s (:func:`tawarp.kernels.pore.pore_log_derivative`) and dg = -df,
    d(1/g_nu) = f_nu'/g_nu^2 d log_nu and d((g_nu - g_k)/g_nu) = (f_k' g_nu d log_k - g_k f_nu' d log_nu)/g_nu^2."""
    log_s_nu = pc.log_nu + half_log_omega
    log_s_k = pc.log_k + half_log_omega
    f_nu, g_nu = pore_functions_log(pore_model, log_s_nu, pore_table)
    f_k, g_k = pore_functions_log(pore_model, log_s_k, pore_table)
    df_nu = pore_log_derivative(pore_model, log_s_nu, f_nu, g_nu)
    df_k = pore_log_derivative(pore_model, log_s_k, f_k, g_k)
    inv_g_nu = cscale(cconj(g_nu), wp.float64(1.0) / cabs2(g_nu))
    inv_g2 = cmul(inv_g_nu, inv_g_nu)
    out = PropagationPartials()
    out.a12_c12 = cmuli(cscale(inv_g_nu, omega))
    out.a12_nu = cmuli(cscale(cmul(inv_g2, df_nu), pc.c12 * omega))
    out.a21_c21 = cmuli(cscale(creal(wp.float64(1.0)) + cscale(f_k, gamma - wp.float64(1.0)), omega))
    out.a21_k = cmuli(cscale(df_k, pc.c21 * omega * (gamma - wp.float64(1.0))))
    out.a22_c22 = cmul(g_nu - g_k, inv_g_nu)
    out.a22_nu = cscale(cmul(cmul(g_k, inv_g2), df_nu), -pc.c22)
    out.a22_k = cscale(cmul(df_k, inv_g_nu), pc.c22)
    return out


@wp.func
def propagation_value(d: PropagationPartials, pc: PointCoefficients):
    """A from its :class:`PropagationPartials` at the point ``pc``."""
    zero = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    return cmat2(zero, cscale(d.a12_c12, pc.c12), cscale(d.a21_c21, pc.c21), cscale(d.a22_c22, pc.c22))


@wp.func
def propagation_tangent(d: PropagationPartials, dpc: PointCoefficients):
    """dA in the direction ``dpc`` of the point coefficients (their derivatives along one
    parameter; ``rho`` is not used)."""
    zero = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    return cmat2(
        zero,
        cscale(d.a12_c12, dpc.c12) + cscale(d.a12_nu, dpc.log_nu),
        cscale(d.a21_c21, dpc.c21) + cscale(d.a21_k, dpc.log_k),
        cscale(d.a22_c22, dpc.c22) + cscale(d.a22_nu, dpc.log_nu) + cscale(d.a22_k, dpc.log_k),
    )


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
def johnson_factor(x: wp.float64, s: wp.float64):
    """Johnson's dynamic tortuosity over alpha_inf for circular-pore resistivity
    (sigma = 8 mu alpha_inf/(phi r^2)) and viscous length Lambda = r/s, exp(-iwt):
    J = 1 + (4 i / x^2) sqrt(1 - i s^2 x^2 / 8), x = r/delta_nu."""
    x2 = x * x
    root = csqrt(cplx(wp.float64(1.0), -s * s * x2 / wp.float64(8.0)))
    return creal(wp.float64(1.0)) + cscale(cmuli(root), wp.float64(4.0) / x2)


@wp.func
def shape_correction(x: wp.float64, s: wp.float64):
    """J(s)/J(1): multiplies the exact circular-pore density q^2 rho/(1 - f_nu). Tends to 1
    at low frequency (the flow resistivity of radius r is kept) and to
    (1 + (1+i) s/x)/(1 + (1+i)/x) at high frequency: the viscous boundary layer then sees
    Lambda = r/s (a Johnson-Champoux-Allard shape factor; s = 1 is the circular pore)."""
    return cdiv(johnson_factor(x, s), johnson_factor(x, wp.float64(1.0)))


@wp.func
def limp_density(rho: wp.float64, phi: wp.float64, q: wp.float64, g_nu: wp.vec2d, m: wp.float64):
    """Effective density [kg/m^3] per total volume flux of a porous layer whose frame is
    limp (no stiffness) with bulk density 1/m: from the fluid and frame momentum balances
    with the rigid-frame coupling A = phi (rho_e - rho), rho_e = q^2 rho / (1 - f_nu),

        rho_w = (phi rho + A (phi rho m + 1)) / (phi^2 + phi (1 - phi)^2 rho m + A m),

    which is rho_e / phi (rigid) at m = 0 and phi rho + 1/m (frame moving with the air)
    as A grows."""
    rho_e = cdiv(creal(q * q * rho), g_nu)
    A = cscale(rho_e - creal(rho), phi)
    one_m = wp.float64(1.0) - phi
    num = creal(phi * rho) + cscale(A, phi * rho * m + wp.float64(1.0))
    den = creal(phi * phi + phi * one_m * one_m * rho * m) + cscale(A, m)
    return cdiv(num, den)


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
    eq. 4.13): with b1, b2, b3 of :func:`magnus6_b`, C1 = [b1, b2], C2 = -1/60 [b1, 2 b3 + C1],
    Omega = b1 + b3/12 + 1/240 [-20 b1 - b3 + C1, b2 + C2]; the cell's matrix is exp(Omega)."""
    b1, b2, b3 = magnus6_b(a1, a2, a3, h)
    c1 = commutator2(b1, b2)
    c2 = scale2(commutator2(b1, axpy2(wp.float64(2.0), b3, c1)), wp.float64(-1.0 / 60.0))
    left = axpy2(wp.float64(-20.0), b1, axpy2(wp.float64(-1.0), b3, c1))
    return axpy2(
        wp.float64(1.0 / 240.0),
        commutator2(left, axpy2(wp.float64(1.0), b2, c2)),
        axpy2(wp.float64(1.0 / 12.0), b3, b1),
    )


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
    c2 = scale2(commutator2(b1, w), wp.float64(-1.0 / 60.0))
    dc2 = scale2(axpy2(wp.float64(1.0), commutator2(db1, w), commutator2(b1, dw)), wp.float64(-1.0 / 60.0))
    left = axpy2(wp.float64(-20.0), b1, axpy2(wp.float64(-1.0), b3, c1))
    dleft = axpy2(wp.float64(-20.0), db1, axpy2(wp.float64(-1.0), db3, dc1))
    right = axpy2(wp.float64(1.0), b2, c2)
    dright = axpy2(wp.float64(1.0), db2, dc2)
    bracket = axpy2(wp.float64(1.0), commutator2(dleft, right), commutator2(left, dright))
    return axpy2(wp.float64(1.0 / 240.0), bracket, axpy2(wp.float64(1.0 / 12.0), db3, db1))


@wp.func
def magnus6_step(a1: CMat2, a2: CMat2, a3: CMat2, h: wp.float64):
    """exp(Omega) of one cell (:func:`magnus6_exponent`)."""
    return expm2(magnus6_exponent(a1, a2, a3, h))


@wp.func
def scale2(m: CMat2, s: wp.float64):
    return cmat2(cscale(m.a, s), cscale(m.b, s), cscale(m.c, s), cscale(m.d, s))


# -- complex angular frequency (tawarp.model.onset) ------------------------------------------
# Every coefficient of A is analytic in omega: omega enters through s = r/delta ~ sqrt(omega)
# (principal root) and as a factor of a12, a21. These are propagation_at and its helpers
# with omega complex; at real omega they agree with them to rounding.


@wp.func
def johnson_factor_complex(x: wp.vec2d, s: wp.float64):
    """:func:`johnson_factor` at complex x = r/delta_nu."""
    x2 = cmul(x, x)
    root = csqrt(creal(wp.float64(1.0)) - cmuli(cscale(x2, s * s / wp.float64(8.0))))
    return creal(wp.float64(1.0)) + cscale(cdiv(cmuli(root), x2), wp.float64(4.0))


@wp.func
def propagation_matrix_complex(
    gas: wp.array(dtype=wp.float64),
    p_mean: wp.float64,
    omega: wp.vec2d,
    T: wp.float64,
    dTdx: wp.float64,
    porosity: wp.float64,
    pore_radius: wp.float64,
    tortuosity: wp.float64,
    pore_model: int,
    area: wp.float64,
    thermal_radius: wp.float64,
    frame_mobility: wp.float64,
    shape_factor: wp.float64,
):
    """A(x) at complex angular frequency omega [rad/s] (re, im): :func:`propagation_at`'s
    matrix from the same :class:`PointCoefficients` (arguments as :func:`point_coefficients`),
    with s = r/delta = exp(log_nu) sqrt(omega) complex."""
    pc = point_coefficients(gas, p_mean, T, dTdx, porosity, pore_radius, tortuosity, area, thermal_radius)
    root_w = csqrt(omega)
    s_nu = cscale(root_w, wp.exp(pc.log_nu))
    s_k = cscale(root_w, wp.exp(pc.log_k))
    f_nu, g_nu = pore_functions_complex(pore_model, s_nu)
    f_k, g_k = pore_functions_complex(pore_model, s_k)
    if shape_factor != wp.float64(1.0) and shape_factor > wp.float64(0.0) and pore_model == 0:
        g_nu = cdiv(
            g_nu, cdiv(johnson_factor_complex(s_nu, shape_factor), johnson_factor_complex(s_nu, wp.float64(1.0)))
        )
    a12 = cmuli(cscale(cdiv(omega, g_nu), pc.c12))
    if frame_mobility > wp.float64(0.0):
        a12 = cmuli(
            cscale(
                cmul(limp_density(pc.rho, porosity, tortuosity, g_nu, frame_mobility), omega), wp.float64(1.0) / area
            )
        )
    a21 = cmuli(cscale(cmul(omega, creal(wp.float64(1.0)) + cscale(f_k, gas[G_GAMMA] - wp.float64(1.0))), pc.c21))
    a22 = cscale(cdiv(g_nu - g_k, g_nu), pc.c22)
    zero = wp.vec2d(wp.float64(0.0), wp.float64(0.0))
    return cmat2(zero, a12, a21, a22)
