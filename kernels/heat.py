"""Steady heat model (docs/physics.md, paper Eqs. 10-12) as Warp functions.

In each thermal segment ``lam theta'' - lam k^2 theta = -lam sigma`` with
``k^2 = 2 h / (R lam)`` and ``sigma = Q / (l_heater S lam)`` in the heater, 0 elsewhere;
``theta' = 0`` at both ends, ``theta`` and ``lam theta'`` continuous. With the effect
``end_conductance`` H [W/(m^2 K)] of the first (last) thermal segment, its outer end loses
``H theta`` per section area to an exchanger at T_cold (``lam theta' = H theta`` at the left
end, ``-lam theta' = H theta`` at the right): the ambient exchangers' thermal role,
adiabatic at H = 0 (the paper's model), T_cold held there as H -> inf. With the effect
``contact_resistance`` R_c [m^2 K/W] of a thermal segment other than the first, the
temperature jumps at its start by R_c times the heat flux density through it (a thermal
contact resistance against the previous segment; :func:`contact_rows`). With a
``wall_conductance`` lam_w and a ``wall_resistance`` R_w = 1/h_w > 0 the tube wall of a
segment is a temperature field of its own, coupled by 2 h_w/R (:func:`solve_heat_wall`,
block-tridiagonal in (theta, theta_w)); R_w = 0 adds lam_w to the segment's conductivity.

Discretisation: nodes on a uniform grid in each segment, interfaces on nodes. Each cell
couples its two nodes through the *exact* two-point relation of a constant-coefficient
cell (cosh/sinh), giving a symmetric tridiagonal system (Thomas algorithm). For
piecewise-constant coefficients this "exponentially fitted" scheme is exact at the nodes
for any number of cells; between nodes the profile is the exact cell solution, so the
acoustic integration sees the exact temperature. ``fitted = 0`` selects the plain
second-order finite-volume scheme (lumped sink), kept to show the order and as the
baseline; coefficients that vary inside a cell (a nonlinear heat model) make both
schemes second order.

Temperature-dependent effects (``conductivity_exponent``, ``radiative_conductivity``,
``h_convection``) make the model nonlinear. The conductivity is then handled exactly by a
Kirchhoff transform (U = int lam dtheta; :func:`nonlinear_cell`): each heat cell is the
fitted cell of the linear model written in U, with the sink linearised about the cell's
mid temperature and its remainder's cell mean added to the source, so the nodal error
is fourth order, T(x) and dT/dx are continuous at the nodes, and the heat leaked equals
Q to ~1e-13; :func:`solve_heat_nonlinear` iterates to the fixed point. ``h_convection``
enters the same way (the sink (2/R)(h + h_c theta^(1/4)) theta, :func:`wall_sink`, is
expanded like the conductivity's). With every effect off
nothing changes (one linear solve, the same code as before).
:func:`cell_heat_coeffs` / :func:`cell_coeffs_at` give the older cell-constant
approximation (lam at the cell's mean temperature) that the design metrics use.
"""

import warp as wp

from .layout import (
    BYPASS_GAP,
    CONDUCTIVITY_EXPONENT,
    CONTACT_RESISTANCE,
    END_CONDUCTANCE,
    F_HEATER,
    F_POROUS,
    H,
    H_CONVECTION,
    HEAT_INPUT,
    LENGTH,
    POROSITY,
    RADIATIVE_CONDUCTIVITY,
    RADIUS,
    SOLID_CONDUCTIVITY,
    T_COLD,
    WALL_CONDUCTANCE,
    WALL_RESISTANCE,
    seg_value,
)
from .gas import conductivity

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

PI = wp.constant(wp.float64(3.141592653589793))


@wp.func
def shx(x: wp.float64):
    """sinh(x)/x, accurate at small x."""
    if wp.abs(x) < wp.float64(1.0e-3):
        x2 = x * x
        return wp.float64(1.0) + x2 / wp.float64(6.0) * (wp.float64(1.0) + x2 / wp.float64(20.0))
    return wp.sinh(x) / x


@wp.func
def x_coth(x: wp.float64):
    """x / tanh(x) (-> 1 at 0)."""
    if wp.abs(x) < wp.float64(1.0e-3):
        x2 = x * x
        return wp.float64(1.0) + x2 / wp.float64(3.0) * (wp.float64(1.0) - x2 / wp.float64(15.0))
    return x / wp.tanh(x)


@wp.func
def tanhx_x(x: wp.float64):
    """tanh(x) / x (-> 1 at 0)."""
    if wp.abs(x) < wp.float64(1.0e-3):
        x2 = x * x
        return wp.float64(1.0) - x2 / wp.float64(3.0) * (wp.float64(1.0) - wp.float64(0.4) * x2)
    return wp.tanh(x) / x


@wp.func
def cell_coupling(lam: wp.float64, k: wp.float64, sigma: wp.float64, d: wp.float64, fitted: int):
    """Coefficients (a, b, e) of one cell of length d [m]: the flux into the cell at its
    left node is ``a theta_r - b theta_l + e`` (and symmetrically at the right node)."""
    x = k * d
    if fitted == 0:
        return lam / d, lam / d * (wp.float64(1.0) + wp.float64(0.5) * x * x), wp.float64(0.5) * lam * sigma * d
    return lam / (d * shx(x)), lam / d * x_coth(x), wp.float64(0.5) * lam * sigma * d * tanhx_x(wp.float64(0.5) * x)


@wp.func
def hyperbolic_ratios(u: wp.float64, v: wp.float64, inv: wp.float64):
    """(cosh(u)/cosh(v), sinh(u)/cosh(v)) for |u| <= v, without overflow, from the two
    exponentials they share and ``inv`` = 1/(1 + e^(-2v)) (:func:`cell_shape`)."""
    au = wp.abs(u)
    e = wp.exp(au - v)
    eu = wp.exp(wp.float64(-2.0) * au)
    cr = e * (wp.float64(1.0) + eu) * inv
    sr = e * (wp.float64(1.0) - eu) * inv
    if u < wp.float64(0.0):
        sr = -sr
    return cr, sr


@wp.func
def cell_shape(k: wp.float64, d: wp.float64):
    """The factors of :func:`profile_at` that depend on the cell alone (decay rate k
    [1/m], length d [m]), as a wp.vec4d: for v = k d/2 < 1/2, (1/cosh v, 1/(d/2 shx(v)),
    0, 0); else (e^(-2v), 1/(1 + e^(-2v)), 1/tanh v, 1/k). Their divisions and
    exponential are taken once for all the points of a cell (the point kernel's three
    Gauss points, :func:`tawarp.kernels.forward.gauss_profile`), not at each."""
    v = wp.float64(0.5) * k * d
    if v < wp.float64(0.5):
        return wp.vec4d(
            wp.float64(1.0) / wp.cosh(v),
            wp.float64(1.0) / (wp.float64(0.5) * d * shx(v)),
            wp.float64(0.0),
            wp.float64(0.0),
        )
    ev = wp.exp(wp.float64(-2.0) * v)
    return wp.vec4d(
        ev,
        wp.float64(1.0) / (wp.float64(1.0) + ev),
        (wp.float64(1.0) + ev) / (wp.float64(1.0) - ev),
        wp.float64(1.0) / k,
    )


@wp.func
def profile_at(
    shape: wp.vec4d,
    theta_l: wp.float64,
    theta_r: wp.float64,
    k: wp.float64,
    sigma: wp.float64,
    d: wp.float64,
    xi: wp.float64,
):
    """:func:`cell_profile` given the cell's :func:`cell_shape` ``shape`` of (k, d)."""
    m = xi - wp.float64(0.5) * d
    v = wp.float64(0.5) * k * d
    u = k * m
    mean = wp.float64(0.5) * (theta_l + theta_r)
    half = wp.float64(0.5) * (theta_r - theta_l)
    if v < wp.float64(0.5):
        # small k d: series-safe forms of the same expressions
        inv_ch = shape[0]
        inv_span = shape[1]
        theta = mean * wp.cosh(u) * inv_ch + half * (m * shx(u)) * inv_span
        dtheta = mean * k * k * m * shx(u) * inv_ch + half * wp.cosh(u) * inv_span
        # particular part w = (cosh v - cosh u)/(k^2 cosh v), w' = -sinh(u)/(k cosh v)
        w = (
            wp.float64(0.5)
            * (wp.float64(0.25) * d * d - m * m)
            * shx(wp.float64(0.5) * (v + u))
            * shx(wp.float64(0.5) * (v - u))
            * inv_ch
        )
        theta = theta + sigma * w
        dtheta = dtheta - sigma * m * shx(u) * inv_ch
        return theta, dtheta
    cr, sr = hyperbolic_ratios(u, v, shape[1])
    inv_th = shape[2]
    inv_k = shape[3]
    # sinh(u)/sinh(v) = (sinh(u)/cosh(v)) / tanh(v), cosh(u)/sinh(v) likewise
    theta = mean * cr + half * sr * inv_th + sigma * (wp.float64(1.0) - cr) * (inv_k * inv_k)
    dtheta = k * (mean * sr + half * cr * inv_th) - sigma * sr * inv_k
    return theta, dtheta


@wp.func
def cell_profile(
    theta_l: wp.float64, theta_r: wp.float64, k: wp.float64, sigma: wp.float64, d: wp.float64, xi: wp.float64
):
    """Exact solution (theta, dtheta/dx) inside a constant-coefficient cell [0, d] at xi,
    given its end values. Written about the cell centre (m = xi - d/2) so that every
    ratio stays bounded for large k d and every small-k limit is taken analytically
    (:func:`profile_at` on :func:`cell_shape`)."""
    return profile_at(cell_shape(k, d), theta_l, theta_r, k, sigma, d, xi)


@wp.func
def segment_lambda(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
):
    """Axial conductivity [W/(m K)]: phi lam_gas + (1 - phi) lam_solid, gas at T_cold,
    plus the wall's axial conductance (``wall_conductance`` = lam_wall A_wall / S, 0 = off)
    where the wall is in perfect contact (``wall_resistance`` 0; else the wall is a field of
    its own, :func:`wall_field_on`)."""
    lam = material_lambda(params, flags, gas, i, s)
    wall = seg_value(params, i, s, WALL_CONDUCTANCE)
    if wall != wp.float64(0.0) and seg_value(params, i, s, WALL_RESISTANCE) == wp.float64(0.0):
        lam = lam + wall
    return lam


@wp.func
def wall_field_on(params: wp.array2d(dtype=wp.float64), i: int, s: int):
    """1 when the wall of segment s is a temperature field of its own: a conducting wall
    (``wall_conductance`` > 0) behind a finite lateral coupling (``wall_resistance`` = 1/h_w
    > 0); else 0 (no wall, or a wall at the gas temperature: its conductance is added to
    the segment's, :func:`segment_lambda`)."""
    if seg_value(params, i, s, WALL_CONDUCTANCE) > wp.float64(0.0):
        if seg_value(params, i, s, WALL_RESISTANCE) > wp.float64(0.0):
            return 1
    return 0


@wp.func
def gap_share(gap: wp.float64, radius: wp.float64):
    """Share of the tube section [-] of an annular gap of width ``gap`` [m] at the wall of a
    tube of ``radius`` [m]: (R^2 - (R - g)^2)/R^2 = g (2R - g)/R^2."""
    return gap * (wp.float64(2.0) * radius - gap) / (radius * radius)


@wp.func
def material_lambda(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
):
    """Conductivity of the gas and solid of segment s at T_cold [W/(m K)]; a bypass gap's
    gas replaces its share of the section (:func:`gap_share`)."""
    lam_gas = conductivity(gas, params[T_COLD, i])
    if flags[s, F_POROUS] == 0:
        return lam_gas
    phi = seg_value(params, i, s, POROSITY)
    lam = phi * lam_gas + (wp.float64(1.0) - phi) * seg_value(params, i, s, SOLID_CONDUCTIVITY)
    gap = seg_value(params, i, s, BYPASS_GAP)
    if gap > wp.float64(0.0):
        x = gap_share(gap, params[RADIUS, i])
        lam = (wp.float64(1.0) - x) * lam + x * lam_gas
    return lam


@wp.func
def heat_coeffs(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    i: int,
    s: int,
    lam: wp.float64,
    h: wp.float64,
):
    """(lam, k, sigma) from a conductivity lam and an exchange coefficient h."""
    R = params[RADIUS, i]
    k = wp.sqrt(wp.float64(2.0) * h / (R * lam))
    sigma = wp.float64(0.0)
    if flags[s, F_HEATER] != 0:
        sigma = params[HEAT_INPUT, i] / (seg_value(params, i, s, LENGTH) * PI * R * R * lam)
    return lam, k, sigma


@wp.func
def segment_heat_coeffs(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
):
    """(lam, k, sigma) of thermal segment s: k = sqrt(2 h/(R lam)) [1/m], sigma [K/m^2]
    (the linear model: temperature-dependent effects off). Where the wall is a field of its
    own (:func:`wall_field_on`) lam and sigma are the gas/solid's and k bounds the faster of
    the two fields' decay rates (:func:`wall_modes`; the Magnus cell count reads it), the
    profile being :func:`wall_cell_profile`'s."""
    lam, k, sigma = heat_coeffs(
        params, flags, i, s, segment_lambda(params, flags, gas, i, s), seg_value(params, i, s, H)
    )
    if wall_field_on(params, i, s) != 0:
        c = wp.float64(2.0) / (params[RADIUS, i] * seg_value(params, i, s, WALL_RESISTANCE))
        k = wp.sqrt(k * k + c / lam + c / seg_value(params, i, s, WALL_CONDUCTANCE))
    return lam, k, sigma


@wp.func
def segment_nonlinear(params: wp.array2d(dtype=wp.float64), i: int, s: int):
    """1 when a temperature-dependent effect is on in segment s (the heat solve iterates)."""
    if seg_value(params, i, s, CONDUCTIVITY_EXPONENT) != wp.float64(0.0):
        return 1
    if seg_value(params, i, s, RADIATIVE_CONDUCTIVITY) != wp.float64(0.0):
        return 1
    if seg_value(params, i, s, H_CONVECTION) != wp.float64(0.0):
        return 1
    return 0


@wp.func
def cell_heat_coeffs(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
    theta_mean: wp.float64,
):
    """(lam, k, sigma) of a heat cell of segment s whose mean temperature excess is
    theta_mean [K]. With the temperature-dependent effects off this is exactly
    :func:`segment_heat_coeffs`; on, with T = T_cold + theta_mean:

        lam = lam_material (T/T_cold)^conductivity_exponent
              + radiative_conductivity (T/T_cold)^3 + wall_conductance
        h   = h + h_convection max(theta_mean, 0)^(1/4)
    """
    if segment_nonlinear(params, i, s) == 0:
        return segment_heat_coeffs(params, flags, gas, i, s)
    lam, h = cell_law(params, flags, gas, i, s, theta_mean)
    if wall_field_on(params, i, s) == 0:
        lam = lam + seg_value(params, i, s, WALL_CONDUCTANCE)
    return heat_coeffs(params, flags, i, s, lam, h)


@wp.func
def cell_law(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
    theta_mean: wp.float64,
):
    """(lam [W/(m K)], h [W/(m^2 K)]) of the gas/solid of segment s at the temperature excess
    theta_mean [K] (T = T_cold + theta_mean): lam_material (T/T_cold)^conductivity_exponent +
    radiative_conductivity (T/T_cold)^3 (no wall) and h + h_convection max(theta_mean, 0)^(1/4)."""
    Tc = params[T_COLD, i]
    t = (Tc + wp.max(theta_mean, wp.float64(0.0))) / Tc
    lam = material_lambda(params, flags, gas, i, s)
    b = seg_value(params, i, s, CONDUCTIVITY_EXPONENT)
    if b != wp.float64(0.0):
        lam = lam * wp.pow(t, b)
    lam = lam + seg_value(params, i, s, RADIATIVE_CONDUCTIVITY) * t * t * t
    h = seg_value(params, i, s, H)
    hc = seg_value(params, i, s, H_CONVECTION)
    if hc != wp.float64(0.0):
        h = h + hc * wp.sqrt(wp.sqrt(wp.max(theta_mean, wp.float64(0.0))))
    return lam, h


# --- temperature-dependent conductivity: Kirchhoff transform on fitted cells -------------
#
# With lam = lam(theta) the heat equation (lam theta')' = sink(theta) - q (sink = a theta,
# a = 2 h(theta)/R, :func:`wall_sink`) becomes, for the Kirchhoff variable
# U = int_0^theta lam(T_cold + t) dt [W/m],
#     U'' = sink(theta(U)) - q,
# linear in its conduction term. In each heat cell the sink is expanded about the cell's
# mid temperature theta* = (theta_l + theta_r)/2: sink(theta(U)) = sink* + k^2 (U - U*) + r(U)
# with k^2 = sink'(theta*) / lam(theta*) (d theta/dU = 1/lam) and a remainder r quadratic in
# U - U*. The cell then solves U'' - k^2 U = -sigma exactly (the fitted cell of the linear
# model, in U) with sigma = q - mean_cell(sink(theta(U)) - k^2 U): the remainder enters through its cell
# mean (4-point Gauss on the cell's own profile; sigma appears on both sides, solved
# linearised), so the zero-mean rest of r is the only local error (fourth order at the nodes) and the heat the model
# leaks, int sink(theta(U(x))) dx, equals Q up to the Gauss error of the remainder (~1e-13).
# U' = lam theta' is the flux, continuous at every node by the nodal equations, so T(x) and
# dT/dx = U'/lam(T) are continuous (no jumps at the nodes for the acoustic Gauss points).

# 4-point Gauss-Legendre on [0, 1]: points 1/2 -+ XI_A/2, 1/2 -+ XI_B/2 with weights W_A, W_B
# (3 points leave ~1e-9 of Q: the remainder holds exp(+-2 k x))
HEAT_XI_A = wp.constant(wp.float64(0.3399810435848563))
HEAT_XI_B = wp.constant(wp.float64(0.8611363115940526))
HEAT_W_A = wp.constant(wp.float64(0.32607257743127305))
HEAT_W_B = wp.constant(wp.float64(0.17392742256872692))


@wp.struct
class ConductivityLaw:
    """lam(T) = lam_m t^b + c t^3 + wall, t = T/T_cold, of one segment (see :func:`kirchhoff`)."""

    T_cold: wp.float64
    lam_m: wp.float64
    b: wp.float64
    c: wp.float64
    wall: wp.float64


@wp.func
def conductivity_law(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
):
    """The conductivity law of segment s of set i (evaluated once per cell: the gas
    conductivity at T_cold costs a pow)."""
    law = ConductivityLaw()
    law.T_cold = params[T_COLD, i]
    law.lam_m = material_lambda(params, flags, gas, i, s)
    law.b = seg_value(params, i, s, CONDUCTIVITY_EXPONENT)
    law.c = seg_value(params, i, s, RADIATIVE_CONDUCTIVITY)
    law.wall = seg_value(params, i, s, WALL_CONDUCTANCE)
    return law


@wp.func
def kirchhoff(law: ConductivityLaw, theta: wp.float64):
    """(U [W/m], lam [W/(m K)]) at temperature excess theta [K]: the Kirchhoff variable
    U = int_0^theta lam(T_cold + t) dt and the conductivity

        lam(T) = lam_material t^b + radiative_conductivity t^3 + wall_conductance,  t = T/T_cold."""
    Tc = law.T_cold
    t = (Tc + theta) / Tc
    lam_m = law.lam_m
    b = law.b
    c = law.c
    wall = law.wall
    # e = int_1^t u^b du = (t^(b+1) - 1)/(b+1), its limit ln t at b = -1; t - 1 at b = 0
    tb = wp.float64(1.0)
    e = theta / Tc
    if b != wp.float64(0.0):
        lt = wp.log(t)
        tb = wp.exp(b * lt)
        p = b + wp.float64(1.0)
        y = p * lt
        if wp.abs(y) < wp.float64(1.0e-3):
            e = lt * (
                wp.float64(1.0)
                + y
                / wp.float64(2.0)
                * (wp.float64(1.0) + y / wp.float64(3.0) * (wp.float64(1.0) + y / wp.float64(4.0)))
            )
        else:
            e = (tb * t - wp.float64(1.0)) / p
    # (t^4 - 1)/4 = (t - 1)(t + 1)(t^2 + 1)/4 with t - 1 = theta/T_cold: no cancellation
    U = lam_m * Tc * e + c * theta * (t + wp.float64(1.0)) * (t * t + wp.float64(1.0)) / wp.float64(4.0) + wall * theta
    lam = lam_m * tb + c * t * t * t + wall
    return U, lam


@wp.func
def kirchhoff_inverse(law: ConductivityLaw, U: wp.float64, guess: wp.float64):
    """(theta [K], lam [W/(m K)]) with kirchhoff(theta) = U [W/m]: Newton from ``guess``
    (lam > 0, so U is increasing), to the last bits of T. Newton's next error is
    (lam'/2 lam) step^2 with |lam'/lam| ~ |b|/T or 3/T, so it stops after a step below
    1e-8 T (error then <~ 1e-15 |b| T); lam is that of the last iterate but one."""
    th = guess
    lam = wp.float64(1.0)
    done = int(0)
    for _it in range(30):
        if done == 0:
            Ug, lam_g = kirchhoff(law, th)
            lam = lam_g
            step = (Ug - U) / lam_g
            th = th - step
            if wp.abs(step) <= wp.float64(1.0e-8) * (law.T_cold + wp.abs(th)):
                done = 1
    return th, lam


@wp.func
def wall_sink(h: wp.float64, hc: wp.float64, R: wp.float64, theta: wp.float64):
    """Heat leaked to the wall per unit volume (2/R) (h + h_c theta^(1/4)) theta [W/m^3] at
    temperature excess theta [K] (theta^(1/4) of max(theta, 0)), and its derivative in
    theta [W/(m^3 K)]."""
    a = wp.float64(2.0) * h / R
    if hc == wp.float64(0.0) or theta <= wp.float64(0.0):
        return a * theta, a
    f = hc * wp.sqrt(wp.sqrt(theta)) * wp.float64(2.0) / R
    return (a + f) * theta, a + wp.float64(1.25) * f


@wp.func
def nonlinear_cell(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
    law: ConductivityLaw,
    theta_l: wp.float64,
    theta_r: wp.float64,
    d: wp.float64,
):
    """Kirchhoff form of a heat cell of length d [m] of segment s (conductivity ``law``,
    :func:`conductivity_law`) with nodal excesses theta_l, theta_r [K] (see the comment
    block above): returns (U_l, U_r [W/m], lam_l,
    lam_r [W/(m K)], k [1/m], sigma [W/m^3]), the cell solving U'' - k^2 U = -sigma."""
    U_l, lam_l = kirchhoff(law, theta_l)
    U_r, lam_r = kirchhoff(law, theta_r)
    th_c = wp.float64(0.5) * (theta_l + theta_r)
    U_c, lam_c = kirchhoff(law, th_c)
    R = params[RADIUS, i]
    h = seg_value(params, i, s, H)
    hc = seg_value(params, i, s, H_CONVECTION)
    sink_c, a = wall_sink(h, hc, R, th_c)
    k = wp.sqrt(a / lam_c)
    q = wp.float64(0.0)
    if flags[s, F_HEATER] != 0:
        q = params[HEAT_INPUT, i] / (seg_value(params, i, s, LENGTH) * PI * R * R)
    # start: the remainder's mean from its nodal values, Simpson with r(U*) = 0 (r quadratic
    # in U - U*)
    sink_l, a_l = wall_sink(h, hc, R, theta_l)
    sink_r, a_r = wall_sink(h, hc, R, theta_r)
    r_l = sink_l - sink_c - k * k * (U_l - U_c)
    r_r = sink_r - sink_c - k * k * (U_r - U_c)
    sigma0 = q - (sink_c - k * k * U_c) - (r_l + r_r) / wp.float64(6.0)
    # sigma = q - m(sigma), m the 4-point Gauss mean of sink(theta(U)) - k^2 U on the cell's
    # profile U = U_hom + sigma w (w: U'' - k^2 U = -1, zero ends). One set of inversions at
    # sigma0, then m(sigma) = m0 + (sigma - sigma0) D with D = mean (sink'/lam - k^2) w
    # (dtheta/dU = 1/lam): sigma = (q - m0 + sigma0 D) / (1 + D); what it leaves is second
    # order in sigma - sigma0 (~1e-5 relative) times the curvature of theta(U) (~1e-3 / K).
    # D is itself a small correction (sink'/lam - k^2 vanishes at theta*), so w is taken at
    # k -> 0, x (d - x)/2 (relative error (k d)^2/12 in D).
    m0 = wp.float64(0.0)
    D = wp.float64(0.0)
    for g in range(4):
        xg = HEAT_XI_A
        wg = HEAT_W_A
        if g >= 2:
            xg = HEAT_XI_B
            wg = HEAT_W_B
        if g % 2 == 0:
            xg = -xg
        xg = wp.float64(0.5) * (wp.float64(1.0) + xg) * d
        Ug, dUg = cell_profile(U_l, U_r, k, sigma0, d, xg)
        w = wp.float64(0.5) * xg * (d - xg)
        thg, lam_g = kirchhoff_inverse(law, Ug, th_c + (Ug - U_c) / lam_c)
        sink_g, a_g = wall_sink(h, hc, R, thg)
        m0 = m0 + wg * (sink_g - k * k * Ug)
        D = D + wg * (a_g / lam_g - k * k) * w
    sigma = (q - m0 + sigma0 * D) / (wp.float64(1.0) + D)
    return U_l, U_r, lam_l, lam_r, k, sigma


@wp.func
def nonlinear_profile(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
    theta_l: wp.float64,
    theta_r: wp.float64,
    d: wp.float64,
    xi: wp.float64,
):
    """(theta [K], dtheta/dx [K/m]) at xi [m] in a heat cell [0, d] of segment s with a
    temperature-dependent conductivity: the cell's exact U(xi), U'(xi), then theta(U) and
    U'/lam."""
    law = conductivity_law(params, flags, gas, i, s)
    U_l, U_r, lam_l, lam_r, k, sigma = nonlinear_cell(params, flags, gas, i, s, law, theta_l, theta_r, d)
    U, dU = cell_profile(U_l, U_r, k, sigma, d, xi)
    # first guess: the secant of theta(U) through the cell's nodes
    guess = theta_l
    if U_r != U_l:
        guess = theta_l + (theta_r - theta_l) * (U - U_l) / (U_r - U_l)
    th, lam = kirchhoff_inverse(law, U, guess)
    return th, dU / lam


@wp.func
def end_sink(params: wp.array2d(dtype=wp.float64), i: int, first: int, count: int, r: int, n_nodes: int):
    """H [W/(m^2 K)] drawn at node r: the first thermal segment's end conductance at the
    first node, the last one's at the last node, 0 inside (a heat flux H theta leaves there)."""
    H_end = wp.float64(0.0)
    if r == 0:
        H_end = seg_value(params, i, first, END_CONDUCTANCE)
    if r == n_nodes - 1:
        H_end = H_end + seg_value(params, i, first + count - 1, END_CONDUCTANCE)
    return H_end


@wp.func
def contact_at(params: wp.array2d(dtype=wp.float64), i: int, s: int, node0: int, c: int):
    """R_c [m^2 K/W] of the contact at the left node of cell c of segment s, whose first
    node is node0: the segment's ``contact_resistance`` at its first cell unless it is the
    first thermal segment (node0 = 0: an end, not an interface), else 0."""
    if c != 0 or node0 == 0:
        return wp.float64(0.0)
    return seg_value(params, i, s, CONTACT_RESISTANCE)


@wp.func
def contact_rows(
    a: wp.float64,
    b: wp.float64,
    e: wp.float64,
    lam_l: wp.float64,
    lam_r: wp.float64,
    c_l: wp.float64,
    c_r: wp.float64,
    Rc: wp.float64,
):
    """Rows of a heat cell in the nodal flux balance, with a contact resistance Rc
    [m^2 K/W] between its left node and its left end.

    The cell gives its end nodes the fluxes [W/m^2] F_l = a U(t_r) - b U(t_l) + e and
    F_r = a U(t_l) - b U(t_r) + e, t_l and t_r its end temperatures, U linearised as U = c + lam t (Kirchhoff cells; the linear model has lam = 1, c = 0 and
    (a, b, e) from the segment's conductivity). Its right end is the right node,
    t_r = theta_r; its left end sits behind the contact, t_l = theta_l + Rc F_l (the
    temperature jumps by Rc times the flux density crossing it), so with beta = b lam_l Rc:

        F_l = (a lam_r theta_r - b lam_l theta_l + E) / (1 + beta),   E = e + a c_r - b c_l
        F_r = a lam_l/(1 + beta) theta_l - (b lam_r - a^2 lam_l lam_r Rc/(1 + beta)) theta_r
              + e + a c_l - b c_r + a lam_l Rc E/(1 + beta)

    (Rc = 0: the plain cell, the same arithmetic as without the effect). Returns (diag_r, sup, rhs_r) of the left node's row and (sub_next,
    diag_next, rhs_next) of the right node's, flux into the node = 0 as
    ``sub theta_{r-1} + diag theta_r + sup theta_{r+1} = rhs``."""
    E = e + a * c_r - b * c_l
    if Rc == wp.float64(0.0):
        return -b * lam_l, a * lam_r, -E, a * lam_l, -b * lam_r, -(e + a * c_l - b * c_r)
    den = wp.float64(1.0) + b * lam_l * Rc
    return (
        -b * lam_l / den,
        a * lam_r / den,
        -E / den,
        a * lam_l / den,
        -b * lam_r + a * a * lam_l * lam_r * Rc / den,
        -(e + a * c_l - b * c_r + a * lam_l * Rc * E / den),
    )


@wp.func
def contact_start_linear(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
    Rc: wp.float64,
    theta_l: wp.float64,
    theta_r: wp.float64,
    d: wp.float64,
):
    """Temperature excess [K] at the left end of the first cell (length d [m], nodal
    excesses theta_l, theta_r [K]) of segment s behind a contact Rc [m^2 K/W], in the
    linear model: t_l = theta_l + Rc F_l = (theta_l + Rc (a theta_r + e)) / (1 + b Rc)
    with the exact cell's (a, b, e)."""
    lam, k, sigma = segment_heat_coeffs(params, flags, gas, i, s)
    a, b, e = cell_coupling(lam, k, sigma, d, 1)
    return (theta_l + Rc * (a * theta_r + e)) / (wp.float64(1.0) + b * Rc)


@wp.func
def contact_start_nonlinear(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
    Rc: wp.float64,
    theta_l: wp.float64,
    theta_r: wp.float64,
    d: wp.float64,
    fitted: int,
):
    """:func:`contact_start_linear` for a Kirchhoff cell (:func:`nonlinear_cell`): t_l
    solves t_l = theta_l + Rc F_l(t_l) by Newton (dF_l/dt_l = -b lam(t_l)); exact in
    one step when the cell's law is linear (no temperature-dependent effect in s), else
    until a step is below 1e-12 (1 + |t_l|) K."""
    law = conductivity_law(params, flags, gas, i, s)
    t = theta_l
    done = int(0)
    for _it in range(20):
        if done == 0:
            U_l, U_r, lam_l, lam_r, k, sigma = nonlinear_cell(params, flags, gas, i, s, law, t, theta_r, d)
            a, b, e = cell_coupling(wp.float64(1.0), k, sigma, d, fitted)
            step = (t - theta_l - Rc * (a * U_r - b * U_l + e)) / (wp.float64(1.0) + Rc * b * lam_l)
            t = t - step
            if wp.abs(step) <= wp.float64(1.0e-12) * (wp.float64(1.0) + wp.abs(t)):
                done = 1
    return t


@wp.func
def linear_rows(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
    d: wp.float64,
    fitted: int,
    Rc: wp.float64,
):
    """:func:`contact_rows` of a heat cell of length d [m] of segment s in the linear model
    (the segment's constants; contact Rc [m^2 K/W] at its left end)."""
    lam, k, sigma = segment_heat_coeffs(params, flags, gas, i, s)
    a, b, e = cell_coupling(lam, k, sigma, d, fitted)
    zero = wp.float64(0.0)
    one = wp.float64(1.0)
    return contact_rows(a, b, e, one, one, zero, zero, Rc)


@wp.func
def kirchhoff_rows(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
    d: wp.float64,
    fitted: int,
    Rc: wp.float64,
    theta_l: wp.float64,
    theta_r: wp.float64,
):
    """:func:`contact_rows` of a Kirchhoff heat cell (:func:`nonlinear_cell`) of length d [m]
    of segment s, U linearised at the previous iterate's nodal excesses theta_l, theta_r [K]
    (behind a contact Rc, at the cell's own left-end temperature)."""
    tl = theta_l
    if Rc != wp.float64(0.0):
        tl = contact_start_nonlinear(params, flags, gas, i, s, Rc, theta_l, theta_r, d, fitted)
    U_l, U_r, lam_l, lam_r, k, sigma = nonlinear_cell(
        params, flags, gas, i, s, conductivity_law(params, flags, gas, i, s), tl, theta_r, d
    )
    a, b, e = cell_coupling(wp.float64(1.0), k, sigma, d, fitted)
    # the flux into the cell at its left node a U_r - b U_l + e (row r), at its right node
    # a U_l - b U_r + e (row r + 1)
    return contact_rows(a, b, e, lam_l, lam_r, U_l - lam_l * tl, U_r - lam_r * theta_r, Rc)


@wp.func
def cell_rows(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    first: int,
    cells: int,
    fitted: int,
    nonlin: int,
    r: int,
    theta_l: wp.float64,
    theta_r: wp.float64,
):
    """Rows of heat cell r (nodes r and r + 1, ``cells`` per thermal segment from segment
    ``first``) in the single-field flux balance, (diag_r, sup, rhs_r) of node r and
    (sub_next, diag_next, rhs_next) of node r + 1 (:func:`contact_rows`): the linear
    model's (:func:`linear_rows`), or with ``nonlin`` a Kirchhoff cell's
    (:func:`kirchhoff_rows`) linearised at the previous iterate's excesses theta_l, theta_r
    [K] where a temperature-dependent effect is on in its segment (:func:`segment_nonlinear`;
    a Kirchhoff cell of constant conductivity and h is the linear cell to rounding, at
    several times its cost, and the acoustic profile of such a segment is the linear
    cell's, :func:`segment_profile`)."""
    s = first + r // cells
    d = seg_value(params, i, s, LENGTH) / wp.float64(cells)
    Rc = contact_at(params, i, s, (s - first) * cells, r % cells)
    diag_r = wp.float64(0.0)
    sup = wp.float64(0.0)
    rhs_r = wp.float64(0.0)
    sub_next = wp.float64(0.0)
    diag_next = wp.float64(0.0)
    rhs_next = wp.float64(0.0)
    if nonlin != 0 and segment_nonlinear(params, i, s) != 0:
        diag_r, sup, rhs_r, sub_next, diag_next, rhs_next = kirchhoff_rows(
            params, flags, gas, i, s, d, fitted, Rc, theta_l, theta_r
        )
    else:
        diag_r, sup, rhs_r, sub_next, diag_next, rhs_next = linear_rows(params, flags, gas, i, s, d, fitted, Rc)
    return diag_r, sup, rhs_r, sub_next, diag_next, rhs_next


#: Values per heat cell in a table of stored rows (:func:`cell_rows`, :func:`heat_sweep`).
ROW_VALUES = wp.constant(6)


@wp.func
def heat_sweep(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    first: int,
    count: int,
    cells: int,
    fitted: int,
    nonlin: int,
    theta: wp.array2d(dtype=wp.float64),
    scratch: wp.array2d(dtype=wp.float64),
    rows: wp.array2d(dtype=wp.float64),
    stored: int,
):
    """One Thomas solve of the single-field heat model's nodal theta [K] into theta[i, :],
    the modified super-diagonal in scratch[i, :n_nodes], each cell's rows
    (:func:`cell_rows`, with ``nonlin`` linearised at the previous iterate in
    scratch[i, n_nodes:]) computed here, or with ``stored`` read from rows[i, :] (
    :data:`ROW_VALUES` per cell, as :func:`cell_rows` returns them: computed by a thread
    per cell, the same numbers). Row r is sub theta_{r-1} + (diag_l + diag_r) theta_r +
    sup theta_{r+1} = rhs_l + rhs_r, the left cell's terms carried from the previous row
    (without a contact, linear: a_l theta_{r-1} - (b_l + b_r) theta_r + a_r theta_{r+1} =
    -(e_l + e_r))."""
    n_nodes = count * cells + 1
    sub = wp.float64(0.0)
    diag_l = wp.float64(0.0)
    rhs_l = wp.float64(0.0)
    c_prev = wp.float64(0.0)
    d_prev = wp.float64(0.0)
    for r in range(n_nodes):
        diag_r = wp.float64(0.0)
        sup = wp.float64(0.0)
        rhs_r = wp.float64(0.0)
        sub_next = wp.float64(0.0)
        diag_next = wp.float64(0.0)
        rhs_next = wp.float64(0.0)
        if r < n_nodes - 1:
            if stored != 0:
                k = ROW_VALUES * r
                diag_r = rows[i, k]
                sup = rows[i, k + 1]
                rhs_r = rows[i, k + 2]
                sub_next = rows[i, k + 3]
                diag_next = rows[i, k + 4]
                rhs_next = rows[i, k + 5]
            else:
                diag_r, sup, rhs_r, sub_next, diag_next, rhs_next = cell_rows(
                    params,
                    flags,
                    gas,
                    i,
                    first,
                    cells,
                    fitted,
                    nonlin,
                    r,
                    scratch[i, n_nodes + r],
                    scratch[i, n_nodes + r + 1],
                )
        # an end's exchanger draws H theta (flux balance in W/m^2, as the rows)
        diag = diag_l + diag_r - end_sink(params, i, first, count, r, n_nodes) - sub * c_prev
        c_prev = sup / diag
        d_prev = (rhs_l + rhs_r - sub * d_prev) / diag
        scratch[i, r] = c_prev
        theta[i, r] = d_prev
        sub = sub_next
        diag_l = diag_next
        rhs_l = rhs_next
    for rr in range(n_nodes - 1):
        r = n_nodes - 2 - rr
        theta[i, r] = theta[i, r] - scratch[i, r] * theta[i, r + 1]


@wp.func
def picard_step(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    first: int,
    count: int,
    cells: int,
    fitted: int,
    tol: wp.float64,
    theta: wp.array2d(dtype=wp.float64),
    scratch: wp.array2d(dtype=wp.float64),
    rows: wp.array2d(dtype=wp.float64),
    stored: int,
):
    """One iteration of :func:`solve_heat_nonlinear` on set i: the current iterate kept in
    scratch[i, n_nodes:], one :func:`heat_sweep` (``rows``, ``stored`` as there) from it;
    returns 1 when the largest nodal change is at most ``tol`` times the largest theta."""
    n_nodes = count * cells + 1
    for r in range(n_nodes):
        scratch[i, n_nodes + r] = theta[i, r]
    heat_sweep(params, flags, gas, i, first, count, cells, fitted, 1, theta, scratch, rows, stored)
    change = wp.float64(0.0)
    size = wp.float64(0.0)
    for r in range(n_nodes):
        change = wp.max(change, wp.abs(theta[i, r] - scratch[i, n_nodes + r]))
        size = wp.max(size, wp.abs(theta[i, r]))
    converged = int(0)
    if change <= tol * size:
        converged = 1
    return converged


@wp.func
def solve_heat_nonlinear(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    first: int,
    count: int,
    cells: int,
    fitted: int,
    max_iter: int,
    tol: wp.float64,
    theta: wp.array2d(dtype=wp.float64),
    scratch: wp.array2d(dtype=wp.float64),
    rows: wp.array2d(dtype=wp.float64),
):
    """Nodal theta [K] of the nonlinear model (Kirchhoff cells, :func:`nonlinear_cell`):
    iterations (:func:`picard_step`) that re-solve the tridiagonal flux balance with each
    cell's (k, sigma) and U = U(theta_p) + lam(theta_p) (theta - theta_p) linearised at the
    previous iterate theta_p (Newton for the conduction term, k and sigma lagged), from the
    start iterate in theta[i, :] (:func:`solve_heat`), until the largest nodal change is
    below ``tol`` times the largest theta (or ``max_iter``). A thread per set runs them
    all here; :func:`tawarp.kernels.forward.heat_rows_kernel` and
    :func:`tawarp.kernels.forward.picard_kernel` run the same iterations with a thread per
    cell computing its rows."""
    done = int(0)
    for _it in range(max_iter):
        if done == 0:
            done = picard_step(params, flags, gas, i, first, count, cells, fitted, tol, theta, scratch, rows, 0)


# --- the wall as a temperature field of its own ---------------------------------------
#
# Where a segment's wall conducts (lam_w = wall_conductance > 0) behind a finite lateral
# coupling h_w = 1/wall_resistance, the wall's excess theta_w is a second field:
#     lam theta''   = (a + c) theta - c theta_w - q,   a = 2 h/R, c = 2 h_w/R
#     lam_w theta_w'' = -c theta + c theta_w,
# i.e. Lam Y'' = K Y - (q, 0) for Y = (theta, theta_w), Lam = diag(lam, lam_w), K symmetric.
# With Z = Lam^(1/2) Y and N = Lam^(-1/2) K Lam^(-1/2) = V diag(k1^2, k2^2) V^T (V orthogonal)
# the modes w = V^T Z = P^T Y (P = Lam^(1/2) V) obey w'' = k_j^2 w_j - sigma_j, each the
# scalar fitted cell (cell_coupling with lam = 1), and the fluxes Lam Y' = P w': a
# constant-coefficient cell couples its nodes exactly through 2x2 blocks
# A = P diag(a_j) P^T, B = P diag(b_j) P^T, e = P (e_j), and the heat model is
# block-tridiagonal (block Thomas). Where the coupling is perfect (wall_resistance 0) the
# wall is at the gas temperature, its conductance added to the segment's (the scalar cell
# in the gas rows); a node such a cell touches carries one balance of both fields and
# theta_w = theta (the limit h_w -> inf of the two-field cell). The wall is adiabatic at the
# ends of the heat model; an end's exchanger (end_conductance) and a contact resistance act
# on the gas/solid. A temperature-dependent effect in a two-field segment takes its cells'
# coefficients at their mean gas temperature (second order in the cell size, the iterations
# of the nonlinear model; the Kirchhoff cells stay the single field's).


@wp.func
def wall_modes(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    s: int,
    theta_mean: wp.float64,
    nonlin: int,
):
    """Modes of a two-field heat cell of segment s (see the comment block above): returns
    (P = Lam^(1/2) V, M = Lam^(-1/2) V, k = (k1, k2) [1/m], sigma [W/m^3 / sqrt(W/(m K))]),
    Y = M w, w = P^T Y. With ``nonlin`` the gas/solid's lam at the cell's mean excess
    ``theta_mean`` [K] (:func:`cell_law`) and its sink to the room (:func:`wall_sink`) by
    its tangent there (a slope and a source), else the segment's constants."""
    R = params[RADIUS, i]
    lam = material_lambda(params, flags, gas, i, s)
    a = wp.float64(2.0) * seg_value(params, i, s, H) / R
    q = wp.float64(0.0)
    if flags[s, F_HEATER] != 0:
        q = params[HEAT_INPUT, i] / (seg_value(params, i, s, LENGTH) * PI * R * R)
    if nonlin != 0:
        # lam at the mean; the sink (2/R)(h + h_c theta^(1/4)) theta by its tangent there
        lam, _h = cell_law(params, flags, gas, i, s, theta_mean)
        sink, a = wall_sink(seg_value(params, i, s, H), seg_value(params, i, s, H_CONVECTION), R, theta_mean)
        q = q - (sink - a * theta_mean)
    lam_w = seg_value(params, i, s, WALL_CONDUCTANCE)
    c = wp.float64(2.0) / (R * seg_value(params, i, s, WALL_RESISTANCE))
    sl = wp.sqrt(lam)
    sw = wp.sqrt(lam_w)
    n11 = (a + c) / lam
    n22 = c / lam_w
    n12 = -c / (sl * sw)
    half = wp.float64(0.5) * (n11 - n22)
    rad = wp.sqrt(half * half + n12 * n12)
    mu2 = wp.float64(0.5) * (n11 + n22) + rad
    mu1 = a * c / (lam * lam_w) / mu2  # det N / mu2: no cancellation when mu1 << mu2
    # eigenvector of mu2 from the row without cancellation: (half + rad, n12) or (n12, rad - half)
    v0 = n12
    v1 = rad - half
    if half >= wp.float64(0.0):
        v0 = half + rad
        v1 = n12
    norm = wp.sqrt(v0 * v0 + v1 * v1)
    v0 = v0 / norm
    v1 = v1 / norm
    # columns: mode 1 (-v1, v0), mode 2 (v0, v1)
    P = wp.mat22d(-sl * v1, sl * v0, sw * v0, sw * v1)
    M = wp.mat22d(-v1 / sl, v0 / sl, v0 / sw, v1 / sw)
    k = wp.vec2d(wp.sqrt(mu1), wp.sqrt(mu2))
    sigma = wp.vec2d(-v1 * q / sl, v0 * q / sl)
    return P, M, k, sigma


@wp.func
def wall_cell_blocks(P: wp.mat22d, k: wp.vec2d, sigma: wp.vec2d, d: wp.float64, fitted: int):
    """(A, B, e) of a two-field cell of length d [m] with modes (P, k, sigma)
    (:func:`wall_modes`): the flux [W/m^2] into the cell at its left node is
    A Y_r - B Y_l + e, at its right node A Y_l - B Y_r + e (Y = (theta, theta_w))."""
    a1, b1, e1 = cell_coupling(wp.float64(1.0), k[0], sigma[0], d, fitted)
    a2, b2, e2 = cell_coupling(wp.float64(1.0), k[1], sigma[1], d, fitted)
    Pt = wp.transpose(P)
    A = P @ wp.diag(wp.vec2d(a1, a2)) @ Pt
    B = P @ wp.diag(wp.vec2d(b1, b2)) @ Pt
    return A, B, P @ wp.vec2d(e1, e2)


@wp.func
def contact_gain(B: wp.mat22d, Rc: wp.float64):
    """(D, G): D = diag(Rc, 0) (the contact jumps the gas/solid's temperature alone, the wall
    runs through) and G = (I + B D)^-1, the factor of the flux through a contact Rc
    [m^2 K/W] at a two-field cell's left end, F_l = G (A Y_r - B Y_l + e)."""
    D = wp.diag(wp.vec2d(Rc, wp.float64(0.0)))
    return D, wp.inverse(wp.identity(n=2, dtype=wp.float64) + B @ D)


@wp.func
def contact_blocks(A: wp.mat22d, B: wp.mat22d, e: wp.vec2d, Rc: wp.float64):
    """Block rows of a two-field cell (:func:`contact_rows` with Y = (theta, theta_w)): its
    left end behind a contact, Y_l' = Y_l + D F_l (:func:`contact_gain`), so
    F_l = G (A Y_r - B Y_l + e) and F_r = (A - A D G B) Y_l + (A D G A - B) Y_r + (I + A D G) e.
    Returns (diag_r, sup, rhs_r, sub_next, diag_next, rhs_next)."""
    if Rc == wp.float64(0.0):
        return -B, A, -e, A, -B, -e
    D, G = contact_gain(B, Rc)
    ADG = A @ D @ G
    return -(G @ B), G @ A, -(G @ e), A - ADG @ B, ADG @ A - B, -(e + ADG @ e)


@wp.func
def gas_block(x: wp.float64):
    """A 2x2 block with x in its gas/solid entry alone (a single-field cell's row term)."""
    return wp.mat22d(x, wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))


#: Values per heat cell in a table of stored two-field rows (:func:`wall_cell_rows`,
#: :func:`wall_sweep`): four 2x2 blocks, two 2-vectors and the cell's tie.
WALL_ROW_VALUES = wp.constant(21)


@wp.func
def wall_cell_rows(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    first: int,
    cells: int,
    fitted: int,
    r: int,
    theta_l: wp.float64,
    theta_r: wp.float64,
):
    """Block rows of heat cell r (``cells`` per thermal segment from segment ``first``) in
    the two-field flux balance, linearised at the previous iterate's gas excesses theta_l,
    theta_r [K] of its nodes: (diag_r, sup, rhs_r, sub_next, diag_next, rhs_next) as
    :func:`contact_blocks` returns them, and ``tied`` = 1 where the cell's wall is at the
    gas temperature (the single-field cell, :func:`cell_rows`, in the blocks' gas/solid
    entries)."""
    zero = wp.float64(0.0)
    s = first + r // cells
    d = seg_value(params, i, s, LENGTH) / wp.float64(cells)
    Rc = contact_at(params, i, s, (s - first) * cells, r % cells)
    seg_nonlin = segment_nonlinear(params, i, s)
    if wall_field_on(params, i, s) != 0:
        P, M, k, sigma = wall_modes(params, flags, gas, i, s, wp.float64(0.5) * (theta_l + theta_r), seg_nonlin)
        A, B, e = wall_cell_blocks(P, k, sigma, d, fitted)
        diag_r, sup, rhs_r, sub_next, diag_next, rhs_next = contact_blocks(A, B, e, Rc)
        return diag_r, sup, rhs_r, sub_next, diag_next, rhs_next, int(0)
    x0 = zero
    x1 = zero
    x2 = zero
    x3 = zero
    x4 = zero
    x5 = zero
    if seg_nonlin != 0:
        x0, x1, x2, x3, x4, x5 = kirchhoff_rows(params, flags, gas, i, s, d, fitted, Rc, theta_l, theta_r)
    else:
        x0, x1, x2, x3, x4, x5 = linear_rows(params, flags, gas, i, s, d, fitted, Rc)
    return gas_block(x0), gas_block(x1), wp.vec2d(x2, zero), gas_block(x3), gas_block(x4), wp.vec2d(x5, zero), int(1)


@wp.func
def store_wall_rows(
    rows: wp.array2d(dtype=wp.float64),
    i: int,
    r: int,
    diag_r: wp.mat22d,
    sup: wp.mat22d,
    rhs_r: wp.vec2d,
    sub_next: wp.mat22d,
    diag_next: wp.mat22d,
    rhs_next: wp.vec2d,
    tied: int,
):
    """Cell r's :func:`wall_cell_rows` into rows[i, WALL_ROW_VALUES r:]."""
    k = WALL_ROW_VALUES * r
    for j in range(4):
        rows[i, k + j] = diag_r[j // 2, j % 2]
        rows[i, k + 4 + j] = sup[j // 2, j % 2]
        rows[i, k + 10 + j] = sub_next[j // 2, j % 2]
        rows[i, k + 14 + j] = diag_next[j // 2, j % 2]
    rows[i, k + 8] = rhs_r[0]
    rows[i, k + 9] = rhs_r[1]
    rows[i, k + 18] = rhs_next[0]
    rows[i, k + 19] = rhs_next[1]
    rows[i, k + 20] = wp.float64(tied)


@wp.func
def stored_block(rows: wp.array2d(dtype=wp.float64), i: int, k: int):
    """The 2x2 block stored row-major at rows[i, k:k + 4]."""
    return wp.mat22d(rows[i, k], rows[i, k + 1], rows[i, k + 2], rows[i, k + 3])


@wp.func
def stored_wall_rows(rows: wp.array2d(dtype=wp.float64), i: int, r: int):
    """Cell r's :func:`wall_cell_rows` as :func:`store_wall_rows` left them."""
    k = WALL_ROW_VALUES * r
    return (
        stored_block(rows, i, k),
        stored_block(rows, i, k + 4),
        wp.vec2d(rows[i, k + 8], rows[i, k + 9]),
        stored_block(rows, i, k + 10),
        stored_block(rows, i, k + 14),
        wp.vec2d(rows[i, k + 18], rows[i, k + 19]),
        int(rows[i, k + 20]),
    )


@wp.func
def wall_sweep(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    first: int,
    count: int,
    cells: int,
    fitted: int,
    theta: wp.array2d(dtype=wp.float64),
    scratch: wp.array2d(dtype=wp.float64),
    rows: wp.array2d(dtype=wp.float64),
    stored: int,
):
    """One block Thomas solve of the two fields' nodal (theta, theta_w) [K] into theta[i, :2 n]
    (n nodes), the modified super-diagonal blocks in scratch[i, :4 n], each cell's rows
    (:func:`wall_cell_rows` at the previous iterate in scratch[i, 4 n:5 n]) computed here, or
    with ``stored`` read from rows[i, :] (:func:`store_wall_rows`: computed by a thread per
    cell, the same numbers). Row r: Sub Y_{r-1} + Diag Y_r + Sup Y_{r+1} = Rhs, the left
    cell's terms carried from the previous row."""
    n = count * cells + 1
    zero = wp.float64(0.0)
    sub = wp.mat22d()
    diag_l = wp.mat22d()
    rhs_l = wp.vec2d()
    c_prev = wp.mat22d()
    d_prev = wp.vec2d()
    tied_l = int(0)
    for r in range(n):
        diag_r = wp.mat22d()
        sup = wp.mat22d()
        rhs_r = wp.vec2d()
        sub_next = wp.mat22d()
        diag_next = wp.mat22d()
        rhs_next = wp.vec2d()
        tied_r = int(0)
        if r < n - 1:
            if stored != 0:
                diag_r, sup, rhs_r, sub_next, diag_next, rhs_next, tied_r = stored_wall_rows(rows, i, r)
            else:
                diag_r, sup, rhs_r, sub_next, diag_next, rhs_next, tied_r = wall_cell_rows(
                    params, flags, gas, i, first, cells, fitted, r, scratch[i, 4 * n + r], scratch[i, 4 * n + r + 1]
                )
        sb = sub
        dg = diag_l + diag_r - gas_block(end_sink(params, i, first, count, r, n))
        sp = sup
        rh = rhs_l + rhs_r
        if tied_l + tied_r != 0:
            # the wall at the gas temperature here: one balance of both fields (the
            # wall's row added to the gas's) and theta_w = theta
            sb = wp.mat22d(sb[0, 0] + sb[1, 0], sb[0, 1] + sb[1, 1], zero, zero)
            sp = wp.mat22d(sp[0, 0] + sp[1, 0], sp[0, 1] + sp[1, 1], zero, zero)
            dg = wp.mat22d(dg[0, 0] + dg[1, 0], dg[0, 1] + dg[1, 1], wp.float64(-1.0), wp.float64(1.0))
            rh = wp.vec2d(rh[0] + rh[1], zero)
        inv = wp.inverse(dg - sb @ c_prev)
        c_prev = inv @ sp
        d_prev = inv @ (rh - sb @ d_prev)
        for j in range(4):
            scratch[i, 4 * r + j] = c_prev[j // 2, j % 2]
        theta[i, r] = d_prev[0]
        theta[i, n + r] = d_prev[1]
        sub = sub_next
        diag_l = diag_next
        rhs_l = rhs_next
        tied_l = tied_r
    for rr in range(n - 1):
        r = n - 2 - rr
        c = stored_block(scratch, i, 4 * r)
        y = wp.vec2d(theta[i, r], theta[i, n + r]) - c @ wp.vec2d(theta[i, r + 1], theta[i, n + r + 1])
        theta[i, r] = y[0]
        theta[i, n + r] = y[1]


@wp.func
def wall_step(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    first: int,
    count: int,
    cells: int,
    fitted: int,
    nonlin: int,
    tol: wp.float64,
    theta: wp.array2d(dtype=wp.float64),
    scratch: wp.array2d(dtype=wp.float64),
    rows: wp.array2d(dtype=wp.float64),
    stored: int,
):
    """One solve of :func:`solve_heat_wall` on set i: the current iterate of both fields kept
    in scratch[i, 4 n:6 n], one :func:`wall_sweep` (``rows``, ``stored`` as there) from it;
    returns 1 for a linear set, else when the largest nodal change of both fields is at most
    ``tol`` times their largest excess."""
    n = count * cells + 1
    for r in range(2 * n):
        scratch[i, 4 * n + r] = theta[i, r]
    wall_sweep(params, flags, gas, i, first, count, cells, fitted, theta, scratch, rows, stored)
    converged = int(1)
    if nonlin != 0:
        change = wp.float64(0.0)
        size = wp.float64(0.0)
        for r in range(2 * n):
            change = wp.max(change, wp.abs(theta[i, r] - scratch[i, 4 * n + r]))
            size = wp.max(size, wp.abs(theta[i, r]))
        if change > tol * size:
            converged = 0
    return converged


@wp.func
def solve_heat_wall(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    first: int,
    count: int,
    cells: int,
    fitted: int,
    nonlin: int,
    max_iter: int,
    tol: wp.float64,
    theta: wp.array2d(dtype=wp.float64),
    scratch: wp.array2d(dtype=wp.float64),
    rows: wp.array2d(dtype=wp.float64),
):
    """Nodal theta [K] (columns 0..nodes-1) and theta_w [K] (columns nodes..2 nodes-1) of a
    set whose wall is a field of its own in some segment (the comment block above): block
    Thomas on the two fields (:func:`wall_step`); ``scratch`` (6 x nodes columns) holds the
    modified super-diagonal blocks and the previous iterate. One solve for a linear set;
    with a temperature-dependent effect (``nonlin``), iterations as
    :func:`solve_heat_nonlinear`'s from the start iterate in theta[i, :2 nodes] on both
    fields (Kirchhoff cells where the wall is at the gas temperature, the two-field cells'
    coefficients at their mean gas temperature). A thread per set runs them all here;
    :func:`tawarp.kernels.forward.heat_rows_kernel` and
    :func:`tawarp.kernels.forward.picard_kernel` run the same iterations with a thread per
    cell computing its rows (``rows``, unread here)."""
    done = int(0)
    for _it in range(max_iter):
        if done == 0:
            done = wall_step(params, flags, gas, i, first, count, cells, fitted, nonlin, tol, theta, scratch, rows, 0)


@wp.func
def solve_heat(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    i: int,
    first: int,
    count: int,
    cells: int,
    fitted: int,
    max_iter: int,
    tol: wp.float64,
    theta: wp.array2d(dtype=wp.float64),
    scratch: wp.array2d(dtype=wp.float64),
    rows: wp.array2d(dtype=wp.float64),
    defer: int,
):
    """Nodal temperature excess theta [K] of set i on the thermal segments
    first..first+count-1 (``cells`` per segment), written to theta[i, :]; ``scratch[i, :]``
    (2 x nodes columns) holds the Thomas algorithm's modified super-diagonal and the
    previous iterate.

    With a temperature-dependent effect on (:func:`segment_nonlinear`), the iterations
    of :func:`solve_heat_nonlinear` (at most ``max_iter`` solves, relative nodal change
    ``tol``) from the start iterate that theta[i, :] holds on entry: zeros (the cold start,
    whose first solve is the model linearised at T_cold) or the converged excess of a
    nearby set (a warm start: a finite-difference neighbour's takes a few solves where the
    cold start takes about ten; the fixed point and the stopping rule are the same,
    tests/test_heat_warm_start.py); with every effect off, one linear solve (the start
    is not read). Where the wall is a field of its own
    in a segment (:func:`wall_field_on`), :func:`solve_heat_wall`: theta then needs 2 x nodes
    columns (the wall's excess in the second half) and scratch 6 x nodes, else the set's
    theta is NaN.

    With ``defer``, a set that iterates is left to
    :func:`tawarp.kernels.forward.heat_rows_kernel` and
    :func:`tawarp.kernels.forward.picard_kernel` (its start iterate untouched): returns 1
    for a set of the single-field iterations, 2 for one of the two-field iterations where
    ``rows`` (those kernels' table, unread here) has :data:`WALL_ROW_VALUES` columns a
    cell, else 0."""
    n_nodes = count * cells + 1
    nonlin = int(0)
    wall = int(0)
    deferred = int(0)
    for s in range(first, first + count):
        if segment_nonlinear(params, i, s) != 0:
            nonlin = 1
        if wall_field_on(params, i, s) != 0:
            wall = 1
    if wall != 0:
        if theta.shape[1] < 2 * n_nodes or scratch.shape[1] < 6 * n_nodes:
            for r in range(theta.shape[1]):
                theta[i, r] = wp.float64(wp.nan)
        elif nonlin != 0 and defer != 0 and rows.shape[1] >= WALL_ROW_VALUES * (n_nodes - 1):
            deferred = 2
        else:
            solve_heat_wall(
                params, flags, gas, i, first, count, cells, fitted, nonlin, max_iter, tol, theta, scratch, rows
            )
    elif nonlin != 0:
        if defer != 0:
            deferred = 1
        else:
            solve_heat_nonlinear(
                params, flags, gas, i, first, count, cells, fitted, max_iter, tol, theta, scratch, rows
            )
    else:
        heat_sweep(params, flags, gas, i, first, count, cells, fitted, 0, theta, scratch, rows, 0)
    return deferred


@wp.func
def cell_coeffs_at(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    theta: wp.array2d(dtype=wp.float64),
    i: int,
    s: int,
    node: int,
    nonlin: int,
):
    """(lam, k, sigma) of the heat cell of segment s starting at node ``node``: the
    segment's constants, or with a temperature-dependent effect on, the cell-constant
    approximation at the cell's mean temperature (second order; the heat solve and the
    cascade use the Kirchhoff cell, :func:`nonlinear_cell`)."""
    if nonlin != 0:
        return cell_heat_coeffs(params, flags, gas, i, s, wp.float64(0.5) * (theta[i, node] + theta[i, node + 1]))
    return segment_heat_coeffs(params, flags, gas, i, s)


@wp.func
def wall_cell_profile(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    theta: wp.array2d(dtype=wp.float64),
    i: int,
    s: int,
    node0: int,
    cells: int,
    d: wp.float64,
    xi: wp.float64,
):
    """(theta [K], dtheta/dx [K/m]) of the gas/solid at local position xi [m] of a segment
    whose wall is a field of its own (:func:`solve_heat_wall`; its heat cells of length d
    start at node0): each mode's exact cell profile (:func:`cell_profile`) between the nodal
    (theta, theta_w), the first cell's left end behind a contact resistance at
    Y_l + D F_l (:func:`contact_blocks`). theta holds the wall in its second half; NaN
    where it has no room for it (the heat solve's NaN)."""
    n = theta.shape[1] // 2
    c = wp.min(int(xi / d), cells - 1)
    if n + node0 + c + 1 >= theta.shape[1]:
        return wp.float64(wp.nan), wp.float64(wp.nan)
    Y_l = wp.vec2d(theta[i, node0 + c], theta[i, n + node0 + c])
    Y_r = wp.vec2d(theta[i, node0 + c + 1], theta[i, n + node0 + c + 1])
    P, M, k, sigma = wall_modes(
        params, flags, gas, i, s, wp.float64(0.5) * (Y_l[0] + Y_r[0]), segment_nonlinear(params, i, s)
    )
    Rc = contact_at(params, i, s, node0, c)
    if Rc != wp.float64(0.0):
        A, B, e = wall_cell_blocks(P, k, sigma, d, 1)
        D, G = contact_gain(B, Rc)
        Y_l = Y_l + D @ (G @ (A @ Y_r - B @ Y_l + e))
    w_l = wp.transpose(P) @ Y_l
    w_r = wp.transpose(P) @ Y_r
    x = xi - wp.float64(c) * d
    w1, dw1 = cell_profile(w_l[0], w_r[0], k[0], sigma[0], d, x)
    w2, dw2 = cell_profile(w_l[1], w_r[1], k[1], sigma[1], d, x)
    return M[0, 0] * w1 + M[0, 1] * w2, M[0, 0] * dw1 + M[0, 1] * dw2


@wp.func
def segment_profile(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    theta: wp.array2d(dtype=wp.float64),
    i: int,
    s: int,
    node0: int,
    cells: int,
    k: wp.float64,
    sigma: wp.float64,
    d: wp.float64,
    nonlin: int,
    xi: wp.float64,
):
    """(theta [K], dtheta/dx [K/m]) at local position xi [m] of thermal segment s, whose
    heat cells (length d) start at node0; (k, sigma) are the segment's, unused when
    ``nonlin`` (a temperature-dependent effect is on: the Kirchhoff cell,
    :func:`nonlinear_profile`). Behind a contact resistance at the segment's start the
    first cell starts from its own end temperature (:func:`contact_start_linear`), not
    the interface node's (the previous segment's end). Where the wall is a field of its own
    (:func:`wall_field_on`), :func:`wall_cell_profile` (k, sigma and ``nonlin`` unused)."""
    if wall_field_on(params, i, s) != 0:
        return wall_cell_profile(params, flags, gas, theta, i, s, node0, cells, d, xi)
    c = wp.min(int(xi / d), cells - 1)
    theta_l = theta[i, node0 + c]
    theta_r = theta[i, node0 + c + 1]
    Rc = contact_at(params, i, s, node0, c)
    if nonlin != 0:
        if Rc != wp.float64(0.0):
            theta_l = contact_start_nonlinear(params, flags, gas, i, s, Rc, theta_l, theta_r, d, 1)
        return nonlinear_profile(params, flags, gas, i, s, theta_l, theta_r, d, xi - wp.float64(c) * d)
    if Rc != wp.float64(0.0):
        theta_l = contact_start_linear(params, flags, gas, i, s, Rc, theta_l, theta_r, d)
    return cell_profile(theta_l, theta_r, k, sigma, d, xi - wp.float64(c) * d)


@wp.func
def temperature_at(
    params: wp.array2d(dtype=wp.float64),
    flags: wp.array2d(dtype=wp.int32),
    gas: wp.array(dtype=wp.float64),
    theta: wp.array2d(dtype=wp.float64),
    i: int,
    s: int,
    first: int,
    cells: int,
    xi: wp.float64,
):
    """(T [K], dT/dx [K/m]) at local position xi [m] in thermal segment s of set i."""
    lam, k, sigma = segment_heat_coeffs(params, flags, gas, i, s)
    d = seg_value(params, i, s, LENGTH) / wp.float64(cells)
    th, dth = segment_profile(
        params, flags, gas, theta, i, s, (s - first) * cells, cells, k, sigma, d, segment_nonlinear(params, i, s), xi
    )
    return params[T_COLD, i] + th, dth
