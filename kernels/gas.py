"""Gas laws as Warp functions.

The constants come in a float64 array in the order of
:meth:`tawarp.model.gas.GasConstants.as_tuple`: R_gas, cp, gamma, mu0, mu_exponent,
mu_sutherland, k0, k_exponent, k_sutherland. Transport laws:
``X(T) = X0 (T/T0)^a (1 + S/T0) / (1 + S/T)``, ``T0 = 273.15 K``.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})  # nothing here is differentiated: no adjoint code

G_R, G_CP, G_GAMMA, G_MU0, G_MUA, G_MUS, G_K0, G_KA, G_KS = range(9)
T_REF = wp.constant(wp.float64(273.15))
INV_T_REF = wp.constant(wp.float64(1.0 / 273.15))


@wp.func
def transport_scale(T: wp.float64, x0: wp.float64, a: wp.float64, s: wp.float64):
    """q of a transport law X(T) = q T / (T + S) (module docstring): q = X0 (1 + S/T0) (T/T0)^a,
    in the units of X0. Written apart from the ratio T / (T + S), so that a caller that
    combines several laws (:func:`tawarp.kernels.acoustics.point_coefficients`) takes one
    division for all of them; no division here (1/T0 is a constant)."""
    t = T * INV_T_REF
    # a = 1/2 is Sutherland's law: sqrt is far cheaper than pow on the GPU
    power = wp.sqrt(t)
    if a != wp.float64(0.5):
        power = wp.pow(t, a)
    return x0 * power * (wp.float64(1.0) + s * INV_T_REF)


@wp.func
def transport_law(T: wp.float64, x0: wp.float64, a: wp.float64, s: wp.float64):
    return transport_scale(T, x0, a, s) * T / (T + s)


@wp.func
def viscosity(gas: wp.array(dtype=wp.float64), T: wp.float64):
    """Dynamic viscosity mu(T) [Pa s]."""
    return transport_law(T, gas[G_MU0], gas[G_MUA], gas[G_MUS])


@wp.func
def conductivity(gas: wp.array(dtype=wp.float64), T: wp.float64):
    """Thermal conductivity k(T) [W/(m K)]."""
    return transport_law(T, gas[G_K0], gas[G_KA], gas[G_KS])


@wp.func
def density(gas: wp.array(dtype=wp.float64), T: wp.float64, p_mean: wp.float64):
    """Ideal-gas density rho = p / (R T) [kg/m^3]."""
    return p_mean / (gas[G_R] * T)


@wp.func
def sound_speed_squared(gas: wp.array(dtype=wp.float64), T: wp.float64):
    """Adiabatic sound speed squared c^2 = gamma R T [m^2/s^2]."""
    return gas[G_GAMMA] * gas[G_R] * T
