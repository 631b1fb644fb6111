"""Independent NumPy/SciPy reference forward model of the thermoacoustic core T-matrix.

This module is the *oracle* for the Warp kernels' tests and the CPU peer for the
benchmarks. It shares no physics code with the kernels (``kernels/``): it only reads
the gas constants (:data:`tawarp.model.gas.GASES`) and the core description
(:class:`tawarp.model.core.Core`). Everything is float64 / complex128; accuracy comes first,
speed second.

Conventions (docs/physics.md):

* time dependence ``exp(-i w t)``;
* state ``(p, U)``: complex pressure amplitude [Pa] and complex volume velocity
  [m^3/s] through the whole tube section, positive towards +x;
* ``(p, U)(x6) = T (p, U)(x1)`` and ``T = T_last ... T_first``;
* ``x`` [m] is measured from plane x1 (``core.positions()``).

Physics:

* gas: ideal gas, ``rho = p_m/(R_gas T)``, ``c^2 = gamma R_gas T``, transport law
  ``X(T) = X0 (T/T0)^a (1 + S/T0)/(1 + S/T)``, ``T0 = 273.15 K`` (:mod:`tawarp.model.gas`);
* steady heat model (paper Eqs. 10-12) on the contiguous ``thermal`` segments, solved
  exactly (:func:`heat_profile_exact`); with a temperature-dependent effect, or a wall that
  is a temperature field of its own (``wall_resistance`` > 0 with a ``wall_conductance``),
  by collocation (:func:`heat_profile`);
* acoustics: Rott's two-port ODE ``d(p,U)/dx = A(x) (p,U)``, closed form where the
  temperature is uniform, DOP853 on the 2x2 fundamental matrix where it is not
  (:func:`transfer_matrix`).

A core field the reference does not model (a limp frame, a viscous shape factor, a bypass
gap, a contact resistance, an end conductance, imposed temperatures) is refused with a
ValueError that names it wherever it would change the answer, never ignored
(:data:`_UNMODELLED`); :mod:`tawarp.reference_effects` has the reference's own gap and contact.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np
import scipy.special as sp
from scipy.integrate import solve_ivp

from .model.coefficients import duct_impedance, normalize
from .model.core import Core, Segment
from .model.fields import EFFECT_OFF, SEGMENT_FIELDS
from .model.gas import GASES, T_REF

__all__ = [
    "GasProperties",
    "gas_properties",
    "segment_conductivity",
    "HeatSolution",
    "heat_profile_exact",
    "energy_balance",
    "NonlinearHeatSolution",
    "FieldHeatSolution",
    "core_wall_fields",
    "heat_profile",
    "wall_field_indices",
    "tied_walls",
    "thermoviscous_function",
    "rott_coefficients",
    "segment_transfer_matrices",
    "transfer_matrix",
    "transfer_matrix_omega",
    "duct_waves",
    "duct_matrix_omega",
    "dimensionless_transfer",
]

# ======================================================================================
# Gas properties
# ======================================================================================

GasProperties = namedtuple("GasProperties", "rho c mu k cp gamma Pr R_gas")
GasProperties.__doc__ = """Gas properties at temperature T (arrays broadcast like T).

rho [kg/m^3], c sound speed [m/s], mu dynamic viscosity [Pa s], k thermal conductivity
[W/(m K)], cp [J/(kg K)], gamma [-], Pr = mu cp / k [-], R_gas [J/(kg K)]."""


def _transport(X0: float, a: float, S: float, T):
    """``X0 (T/T0)^a (1 + S/T0)/(1 + S/T)``; S = 0 is a plain power law."""
    return X0 * (T / T_REF) ** a * (1.0 + S / T_REF) / (1.0 + S / T)


def gas_properties(gas_name: str, T, p_mean: float) -> GasProperties:
    """Properties of gas ``gas_name`` at temperature ``T`` [K] (scalar or array) and
    mean pressure ``p_mean`` [Pa].

    Returns a :data:`GasProperties` namedtuple: ``rho`` [kg/m^3] = p/(R_gas T),
    ``c`` [m/s] = sqrt(gamma R_gas T), ``mu`` [Pa s], ``k`` [W/(m K)], ``cp`` [J/(kg K)],
    ``gamma`` [-], ``Pr`` [-], ``R_gas`` [J/(kg K)].
    """
    g = GASES[gas_name]
    T = np.asarray(T, dtype=float)
    if np.any(T <= 0):
        raise ValueError(f"gas_properties: temperature must be > 0 K, got min {T.min()}")
    rho = p_mean / (g.R_gas * T)
    c = np.sqrt(g.gamma * g.R_gas * T)
    mu = _transport(g.mu0, g.mu_exponent, g.mu_sutherland, T)
    k = _transport(g.k0, g.k_exponent, g.k_sutherland, T)
    Pr = mu * g.cp / k
    return GasProperties(rho, c, mu, k, g.cp, g.gamma, Pr, g.R_gas)


def _segment_of(core: Core, seg) -> Segment:
    if isinstance(seg, Segment):
        return seg
    if isinstance(seg, (int, np.integer)):
        return core.segments[int(seg)]
    return core.segment(seg)


#: Core fields the reference does not model: {field: (parts, what it models instead)}. The
#: parts of an answer a field changes: "acoustics" (a segment's T-matrix, at any heat input),
#: "conductivity" (a thermal segment's conductivity in the heat model), "heated" (the steady
#: temperature with heat input: at Q = 0 the core is at T_cold whatever the field) and
#: "temperature" (the mean temperature at any heat input). An entry point refuses such a
#: field, set away from its neutral value, where it computes a part the field changes
#: (:func:`_refuse_unmodelled`); tests/test_reference_fields.py checks every kernel field
#: is read here or refused.
_IMPOSED = (
    frozenset({"temperature"}),
    "T_cold and the heat model's temperatures, no imposed ones ({name}.T_start = {seg.T_start:g} K, "
    "{name}.T_end = {seg.T_end:g} K)",
)
_UNMODELLED: dict[str, tuple[frozenset, str]] = {
    "frame_mobility": (frozenset({"acoustics"}), "a rigid frame (frame_mobility 0)"),
    "viscous_shape_factor": (
        frozenset({"acoustics"}),
        "the viscous function at the pore radius (viscous_shape_factor 1)",
    ),
    "bypass_gap": (
        frozenset({"acoustics", "conductivity"}),
        "no gap; use tawarp.reference_effects.LabEffects(bypass_gap={value}, gap_segment={name!r}) for the "
        "reference's own gap",
    ),
    "contact_resistance": (
        frozenset({"heated"}),
        "perfect contact; use tawarp.reference_effects.LabEffects(contact_resistance={value}, "
        "contact_left={previous!r}) for the reference's own contact",
    ),
    "end_conductance": (
        frozenset({"heated"}),
        "adiabatic ends of the heat model (theta' = 0; no lab effect has an end conductance)",
    ),
    "T_start": _IMPOSED,
    "T_end": _IMPOSED,
}


def _refuse_unmodelled(core: Core, parts: set, segments=None) -> None:
    """Raise ValueError naming the first field of ``segments`` (default: all of ``core``'s)
    that the reference does not model and that changes one of the answer's ``parts``
    (:data:`_UNMODELLED`), with its value and what the reference models instead."""
    for s in core.segments if segments is None else segments:
        for name, (acts, instead) in _UNMODELLED.items():
            value = getattr(s, name)
            # set: an effect away from its neutral value, an imposed temperature not NaN (unset)
            if not (acts & parts) or value != value or value == EFFECT_OFF.get(name):
                continue
            thermal = [core.segments[i].name for i in core.thermal_indices]
            k = thermal.index(s.name) if s.name in thermal else 0
            previous = thermal[k - 1] if k > 0 else "none: no thermal segment before it"
            unit = SEGMENT_FIELDS[name].unit
            raise ValueError(
                f"{core.source}: tawarp.reference does not model {s.name}.{name} = {value:g}"
                f"{'' if unit == '-' else ' ' + unit}; it models "
                + instead.format(value=f"{value:g}", name=s.name, previous=previous, seg=s)
            )


def segment_conductivity(core: Core, seg) -> float:
    """Axial conductivity ``lam`` [W/(m K)] of the heat model for segment ``seg``
    (a :class:`Segment`, its index or its name).

    Porous: ``phi k_gas(T_cold) + (1 - phi) solid_conductivity``; duct: ``k_gas(T_cold)``;
    plus the wall's ``wall_conductance`` (0 = off) where the wall is at the gas temperature
    (``wall_resistance`` 0). The gas conductivity is taken at the cold temperature and held
    constant (the heat model is linear; the temperature-dependent effects are
    :class:`NonlinearHeatSolution`'s). A thermal segment whose wall is a field of its own
    (:func:`wall_field_indices`) has no such single conductivity: ValueError. A field the
    reference does not model (a bypass gap) is refused.
    """
    s = _segment_of(core, seg)
    _refuse_unmodelled(core, {"conductivity"}, [s])
    if _wall_is_field(s):
        raise ValueError(
            f"{core.source}: segment {s.name!r}: wall_resistance = {s.wall_resistance} m^2 K/W with "
            f"wall_conductance = {s.wall_conductance} W/(m K) makes the wall a temperature field of its own, "
            "which the closed-form heat solution (heat_profile_exact, energy_balance) does not model: "
            "use heat_profile"
        )
    return _material_conductivity(core, s) + s.wall_conductance


def _wall_is_field(s: Segment) -> bool:
    return s.thermal and s.wall_conductance > 0.0 and s.wall_resistance > 0.0


def wall_field_indices(core: Core) -> list[int]:
    """Core indices of the thermal segments whose tube wall is a temperature field of its own:
    a ``wall_conductance`` lam_w > 0 behind a finite lateral coupling ``wall_resistance``
    R_w = 1/h_w > 0 (docs/physics.md, "The wall as a second temperature field"). Elsewhere
    the wall is at the gas temperature, its conductance added to the segment's
    (:func:`segment_conductivity`)."""
    return [i for i in core.thermal_indices if _wall_is_field(core.segments[i])]


def tied_walls(core: Core) -> Core:
    """``core`` with every wall at the gas temperature (``wall_resistance`` 0 where it is a
    field of its own): the same model at Q = 0, and the two-field BVP's first guess."""
    own = wall_field_indices(core)
    return core.replace(**{f"{core.segments[i].name}.wall_resistance": 0.0 for i in own}) if own else core


def _material_conductivity(core: Core, s: Segment) -> float:
    """Gas and solid conductivity of segment ``s`` at T_cold [W/(m K)] (no wall)."""
    k_gas = float(gas_properties(core.gas.name, core.gas.T_cold, core.gas.p_mean).k)
    if s.is_porous:
        return s.porosity * k_gas + (1.0 - s.porosity) * s.solid_conductivity
    return k_gas


# ======================================================================================
# Exact steady heat solution
# ======================================================================================
#
# In one thermal segment of length L, centre c, with s = x - c in [-L/2, L/2],
#     lam theta'' - (2h/R) theta = -q          (q = Q/(l_h S) in the heater, else 0)
# i.e. theta'' - m^2 theta = -q/lam with m^2 = 2h/(R lam). We write
#     theta = (q/lam) P(s) + alpha E(s) + beta O(s)
# with the bounded basis (all stable for any m >= 0, including m = 0 and m L >> 700):
#     E(s) = cosh(m s)/cosh(m L/2)                      (E = 1 at both ends, E -> 1 as m -> 0)
#     O(s) = sinh(m s)/(m cosh(m L/2))                  (O -> s as m -> 0)
#     P(s) = (1 - E(s))/m^2                             (P = 0 at both ends, -> (L^2/4 - s^2)/2)
# and E' = m^2 O, O' = E, P' = -O. Each is evaluated from decaying exponentials and
# expm1 only, so nothing overflows and nothing cancels:
#     with G(a) = -expm1(-2 m a)/(2 m)  (= sinh(m a) e^{-m a}/m, G(a) -> a as m -> 0):
#     E(s) = e^{m(|s| - L/2)} (1 + e^{-2m|s|}) / (1 + e^{-mL})
#     O(s) = sign(s) e^{m(|s| - L/2)} 2 G(|s|) / (1 + e^{-mL})
#     P(s) = 4 G((L/2 + s)/2) G((L/2 - s)/2) / (1 + e^{-mL})
# At the ends s = +-L/2: theta = alpha +- beta ell, theta' = +-(m^2 alpha - q/lam) ell + beta,
# with ell = O(L/2) = tanh(mL/2)/m (-> L/2 as m -> 0).


def _G(m: float, a):
    """``-expm1(-2 m a)/(2 m)`` for a >= 0, with the limit ``a`` at m = 0."""
    a = np.maximum(a, 0.0)
    if m == 0.0:
        return a
    return -np.expm1(-2.0 * m * a) / (2.0 * m)


def _basis(m: float, L: float, s):
    """E(s), O(s), P(s) of the comment block above (arrays like s)."""
    s = np.clip(s, -L / 2, L / 2)
    a = np.abs(s)
    den = 1.0 + math.exp(-m * L)
    grow = np.exp(m * (a - L / 2))
    E = grow * (1.0 + np.exp(-2.0 * m * a)) / den
    O = np.sign(s) * grow * 2.0 * _G(m, a) / den
    P = 4.0 * _G(m, (L / 2 + s) / 2) * _G(m, (L / 2 - s) / 2) / den
    return E, O, P


def _ell(m: float, L: float) -> float:
    """O(L/2) = tanh(mL/2)/m, limit L/2 at m = 0."""
    if m == 0.0:
        return L / 2
    return math.tanh(m * L / 2) / m


class HeatSolution:
    """Exact piecewise solution of the steady heat model (docs/physics.md, Eqs. 10-12).

    On every thermal segment ``lam theta'' - (2 h / R) theta = -Q/(l_h S)`` (source only
    in the heater), ``theta = T - T_cold`` [K], ``theta' = 0`` at both ends of the thermal
    domain, ``theta`` and ``lam theta'`` continuous at the interfaces. Built by
    :func:`heat_profile_exact`.

    Positions ``x`` [m] are measured from plane x1. Outside the thermal domain
    ``theta = 0`` (``T = T_cold``). At an interface ``theta`` is continuous but its
    derivative jumps; the global functions take the segment on the right there (the
    last segment at the right end). Use the ``*_in(index, x)`` forms to evaluate one
    segment's formula on its closed interval (e.g. at its end planes).

    Attributes: ``core``, ``heat_input`` [W], ``T_cold`` [K], ``indices`` (core segment
    indices of the thermal segments), ``x_left``/``x_right`` [m] (their end planes),
    ``lam`` [W/(m K)], ``h`` [W/(m^2 K)], ``m`` [1/m] (= sqrt(2h/(R lam))), ``q`` [W/m^3]
    (volumetric source), ``alpha`` [K], ``beta`` [K/m] (coefficients of E and O).

    A core field the heat model here does not have (imposed temperatures; in a thermal
    segment a bypass gap, and with heat input a contact resistance or an end conductance)
    is a ValueError that names it (:data:`_UNMODELLED`).
    """

    def __init__(self, core: Core, heat_input: float):
        _refuse_unmodelled(core, {"temperature"})
        thermal = [core.segments[i] for i in core.thermal_indices]
        _refuse_unmodelled(core, {"conductivity", "heated"} if heat_input != 0.0 else {"conductivity"}, thermal)
        self.core = core
        self.heat_input = float(heat_input)
        self.T_cold = float(core.gas.T_cold)
        pos = core.positions()
        self.indices = list(core.thermal_indices)
        n = len(self.indices)
        self.x_left = np.array([pos[i] for i in self.indices], dtype=float)
        self.x_right = np.array([pos[i + 1] for i in self.indices], dtype=float)
        self.length = self.x_right - self.x_left
        self.center = 0.5 * (self.x_left + self.x_right)
        R, S = core.radius, core.area
        self.lam = np.array([segment_conductivity(core, i) for i in self.indices], dtype=float)
        self.h = np.array([core.segments[i].h for i in self.indices], dtype=float)
        self.m = np.sqrt(2.0 * self.h / (R * self.lam))
        self.q = np.zeros(n)
        if n:
            j = self.indices.index(core.heater_index)
            self.q[j] = self.heat_input / (self.length[j] * S)
        self.alpha = np.zeros(n)
        self.beta = np.zeros(n)
        if n and self.heat_input != 0.0:
            if not np.any(self.h > 0):
                raise ValueError(
                    f"{core.source}: heat input {self.heat_input} W but every thermal segment has "
                    "h = 0: the heat cannot leave, the steady heat model has no solution"
                )
            self._solve()

    # -- the 2N linear system --------------------------------------------------------
    def _solve(self) -> None:
        n = len(self.indices)
        src = self.q / self.lam  # K/m^2
        ell = np.array([_ell(m, L) for m, L in zip(self.m, self.length)])
        m2 = self.m**2
        A = np.zeros((2 * n, 2 * n))
        b = np.zeros(2 * n)
        # unknowns: alpha_j at 2j, beta_j at 2j + 1
        # left end: theta'(-L/2) = -(m^2 alpha - src) ell + beta = 0
        A[0, 0], A[0, 1], b[0] = -m2[0] * ell[0], 1.0, -src[0] * ell[0]
        row = 1
        for j in range(n - 1):
            # theta continuous: alpha_j + beta_j ell_j - alpha_{j+1} + beta_{j+1} ell_{j+1} = 0
            A[row, 2 * j], A[row, 2 * j + 1] = 1.0, ell[j]
            A[row, 2 * j + 2], A[row, 2 * j + 3] = -1.0, ell[j + 1]
            row += 1
            # lam theta' continuous:
            # lam_j[(m_j^2 alpha_j - src_j) ell_j + beta_j] = lam_{j+1}[-(m^2 alpha - src) ell + beta]_{j+1}
            lj, lk = self.lam[j], self.lam[j + 1]
            A[row, 2 * j], A[row, 2 * j + 1] = lj * m2[j] * ell[j], lj
            A[row, 2 * j + 2], A[row, 2 * j + 3] = lk * m2[j + 1] * ell[j + 1], -lk
            b[row] = lj * src[j] * ell[j] + lk * src[j + 1] * ell[j + 1]
            row += 1
        # right end: (m^2 alpha - src) ell + beta = 0
        A[row, 2 * n - 2], A[row, 2 * n - 1], b[row] = m2[-1] * ell[-1], 1.0, src[-1] * ell[-1]
        # Equilibrate rows and columns (units differ: K, K/m, W/m^2), then one step of
        # iterative refinement: the system is tiny, so this costs nothing.
        cs = 1.0 / np.maximum(np.abs(A).max(axis=0), 1e-300)
        As = A * cs
        rs = 1.0 / np.maximum(np.abs(As).max(axis=1), 1e-300)
        As = As * rs[:, None]
        bs = b * rs
        y = np.linalg.solve(As, bs)
        y = y + np.linalg.solve(As, bs - As @ y)
        sol = y * cs
        self.alpha = sol[0::2].copy()
        self.beta = sol[1::2].copy()

    # -- one segment's formula -------------------------------------------------------
    def _local(self, j: int, x):
        return _basis(self.m[j], self.length[j], np.asarray(x, dtype=float) - self.center[j])

    def _j(self, index: int) -> int:
        try:
            return self.indices.index(index)
        except ValueError:
            raise ValueError(f"segment #{index} is not a thermal segment (thermal: {self.indices})") from None

    def theta_in(self, index: int, x):
        """theta [K] from the formula of thermal segment ``index`` (core index) at ``x`` [m]."""
        j = self._j(index)
        E, O, P = self._local(j, x)
        return (self.q[j] / self.lam[j]) * P + self.alpha[j] * E + self.beta[j] * O

    def dtheta_in(self, index: int, x):
        """dtheta/dx [K/m] from the formula of thermal segment ``index`` at ``x`` [m]."""
        j = self._j(index)
        E, O, _ = self._local(j, x)
        return (self.alpha[j] * self.m[j] ** 2 - self.q[j] / self.lam[j]) * O + self.beta[j] * E

    def d2theta_in(self, index: int, x):
        """d2theta/dx2 [K/m^2] from the formula of thermal segment ``index`` at ``x`` [m]."""
        j = self._j(index)
        E, O, _ = self._local(j, x)
        m2 = self.m[j] ** 2
        return (self.alpha[j] * m2 - self.q[j] / self.lam[j]) * E + self.beta[j] * m2 * O

    # -- global functions ------------------------------------------------------------
    def _dispatch(self, fn, x):
        x = np.asarray(x, dtype=float)
        out = np.zeros_like(x)
        if not self.indices or self.heat_input == 0.0:
            return out
        seg = np.searchsorted(self.x_left, x, side="right") - 1
        inside = (x >= self.x_left[0]) & (x <= self.x_right[-1])
        seg = np.clip(seg, 0, len(self.indices) - 1)
        for j, idx in enumerate(self.indices):
            sel = inside & (seg == j)
            if np.any(sel):
                out[sel] = fn(idx, x[sel])
        return out

    def theta(self, x):
        """Temperature excess theta = T - T_cold [K] at ``x`` [m] (0 outside the thermal domain)."""
        return self._dispatch(self.theta_in, x)

    def dtheta(self, x):
        """dtheta/dx [K/m] at ``x`` [m] (right-hand segment at interfaces; 0 outside)."""
        return self._dispatch(self.dtheta_in, x)

    def d2theta(self, x):
        """d2theta/dx2 [K/m^2] at ``x`` [m] (right-hand segment at interfaces; 0 outside)."""
        return self._dispatch(self.d2theta_in, x)

    def temperature(self, x):
        """Mean temperature T = T_cold + theta [K] at ``x`` [m], anywhere in the core."""
        return self.T_cold + self.theta(x)

    def dtemperature(self, x):
        """dT/dx [K/m] at ``x`` [m] (= dtheta/dx)."""
        return self.dtheta(x)

    def segment_profile(self, index: int):
        """Callable ``x -> (T(x), dT/dx(x))`` [K], [K/m] of core segment ``index``, valid on
        its closed interval (uniform ``T_cold`` for a non-thermal segment)."""
        Tc = self.T_cold
        if index not in self.indices or self.heat_input == 0.0:

            def uniform(x):
                z = 0.0 * np.asarray(x, dtype=float)
                return Tc + z, z

            return uniform
        j = self._j(index)
        m2, src, al, be = self.m[j] ** 2, self.q[j] / self.lam[j], self.alpha[j], self.beta[j]

        def profile(x):
            E, O, P = self._local(j, x)
            return Tc + src * P + al * E + be * O, (al * m2 - src) * O + be * E

        return profile

    def theta_max(self) -> tuple[float, float]:
        """``(x_max [m], theta_max [K])``: location and value of the largest theta.

        Candidates: every segment end and every root of theta' inside a segment (found by
        sign changes on a fine grid refined with Brent's method)."""
        from scipy.optimize import brentq

        if not self.indices or self.heat_input == 0.0:
            return 0.0, 0.0
        best = (-math.inf, 0.0)
        for j, idx in enumerate(self.indices):
            a, b = self.x_left[j], self.x_right[j]
            xs = np.linspace(a, b, 2001)
            th = self.theta_in(idx, xs)
            dth = self.dtheta_in(idx, xs)
            cand = [(float(th[0]), a), (float(th[-1]), b)]
            for k in np.nonzero(np.sign(dth[:-1]) * np.sign(dth[1:]) < 0)[0]:
                xr = brentq(lambda t: float(self.dtheta_in(idx, t)), xs[k], xs[k + 1], xtol=1e-15, rtol=1e-15)
                cand.append((float(self.theta_in(idx, xr)), xr))
            best = max(best, max(cand))
        return float(best[1]), float(best[0])


def heat_profile_exact(core: Core, heat_input: float) -> HeatSolution:
    """Exact steady temperature profile for heat input ``heat_input`` [W] in the heater.

    Any number of contiguous thermal segments; a core with none gives ``T = T_cold``
    everywhere. See :class:`HeatSolution` for the model and the evaluators."""
    return HeatSolution(core, heat_input)


def energy_balance(core: Core, heat_input: float) -> float:
    """Heat lost to the wall, ``sum over thermal segments of integral (2h/R) theta S dx`` [W].

    In steady state it equals the heat input Q. Analytic: with ``ell = tanh(mL/2)/m``,
    ``integral E = 2 ell``, ``integral O = 0``, ``integral P = (L - 2 ell)/m^2``, so
    segment j gives ``S [q_j (L_j - 2 ell_j) + lam_j m_j^2 alpha_j 2 ell_j]``.
    """
    hs = heat_profile_exact(core, heat_input)
    S = core.area
    total = 0.0
    for j in range(len(hs.indices)):
        m, L = hs.m[j], hs.length[j]
        ell = _ell(m, L)
        total += S * (hs.q[j] * (L - 2.0 * ell) + hs.lam[j] * m**2 * hs.alpha[j] * 2.0 * ell)
    return float(total)


# ======================================================================================
# Temperature-dependent (nonlinear) heat model, solved as a BVP
# ======================================================================================
#
# With the temperature-dependent effects on (docs/physics.md "Effects"; core fields
# conductivity_exponent b, radiative_conductivity c, h_convection h_c), on every thermal segment
#     (lam(T) theta')' - (2 h(theta)/R) theta + q = 0,   T = T_cold + theta,
#     lam(T) = lam_m (T/T_cold)^b + c (T/T_cold)^3 + wall_conductance,
#     h(theta) = h + h_c max(theta, 0)^(1/4),
# theta' = 0 at both ends, theta and lam theta' continuous at the interfaces. Solved on the
# state (theta_j, F_j = lam theta'_j) of every segment j mapped to s in [0, 1] with
# scipy.integrate.solve_bvp (collocation, residual tolerance ``tol``); nothing is shared
# with the kernels' discretisation (they use a Kirchhoff transform on fitted cells).


class NonlinearHeatSolution:
    """Steady temperature of the nonlinear heat model above (built by :func:`heat_profile`).

    Same evaluators as :class:`HeatSolution` (``theta``, ``dtheta``, ``temperature``,
    ``theta_in``, ``dtheta_in``, ``segment_profile``); dtheta/dx comes from the solution's
    own flux state, ``F / lam(T)``, not from differentiating an interpolant. ``lost()``
    [W] is the heat leaked to the walls, ``∫ (2 h(theta)/R) theta S dx`` (= Q).
    Attributes as :class:`HeatSolution` (``lam`` the conductivities at T_cold) plus
    ``exponent``, ``radiative``, ``wall``, ``h_conv``, the BVP result ``bvp`` and ``tol``.
    """

    def __init__(self, core: Core, heat_input: float, tol: float = 1e-8):
        from scipy.integrate import solve_bvp

        lin = HeatSolution(core, heat_input)
        for k in ("core", "heat_input", "T_cold", "indices", "x_left", "x_right", "length", "h", "q"):
            setattr(self, k, getattr(lin, k))
        segs = [core.segments[i] for i in self.indices]
        self.lam_m = np.array([_material_conductivity(core, s) for s in segs])
        self.lam = self.lam_m + np.array([s.wall_conductance for s in segs])
        self.exponent = np.array([s.conductivity_exponent for s in segs])
        self.radiative = np.array([s.radiative_conductivity for s in segs])
        self.wall = np.array([s.wall_conductance for s in segs])
        self.h_conv = np.array([s.h_convection for s in segs])
        self.R, self.S, self.tol = core.radius, core.area, tol
        n = len(self.indices)
        L = self.length[:, None]

        def fun(s, y):
            th, F = y[0::2], y[1::2]
            out = np.empty_like(y)
            out[0::2] = L * F / self._conductivity(th)
            out[1::2] = L * (2.0 * self._h(th) / self.R * th - self.q[:, None])
            return out

        def bc(ya, yb):
            r = [ya[1]]
            for j in range(n - 1):
                r += [yb[2 * j] - ya[2 * j + 2], yb[2 * j + 1] - ya[2 * j + 3]]
            return np.array(r + [yb[2 * n - 1]])

        s = np.linspace(0.0, 1.0, 201)
        y0 = np.empty((2 * n, s.size))
        for j, idx in enumerate(self.indices):
            x = self.x_left[j] + s * self.length[j]
            y0[2 * j] = lin.theta_in(idx, x)
            y0[2 * j + 1] = lin.lam[j] * lin.dtheta_in(idx, x)
        self.bvp = solve_bvp(fun, bc, s, y0, tol=tol, bc_tol=tol, max_nodes=200000)
        if not self.bvp.success:
            raise RuntimeError(f"{core.source}: nonlinear heat BVP (Q = {heat_input} W): {self.bvp.message}")

    def _conductivity(self, theta, j=None):
        """lam(T) [W/(m K)] per segment (rows) or of segment j."""
        sl = slice(None) if j is None else j
        ex = lambda a: a[sl] if j is not None else a[:, None]
        t = 1.0 + np.asarray(theta) / self.T_cold
        return ex(self.lam_m) * t ** ex(self.exponent) + ex(self.radiative) * t**3 + ex(self.wall)

    def _h(self, theta, j=None):
        sl = slice(None) if j is None else j
        ex = lambda a: a[sl] if j is not None else a[:, None]
        return ex(self.h) + ex(self.h_conv) * np.maximum(theta, 0.0) ** 0.25

    def _state(self, j: int, x):
        s = (np.asarray(x, dtype=float) - self.x_left[j]) / self.length[j]
        y = self.bvp.sol(np.clip(s, 0.0, 1.0))
        return y[2 * j], y[2 * j + 1]

    def _j(self, index: int) -> int:
        return HeatSolution._j(self, index)

    def theta_in(self, index: int, x):
        """theta [K] of thermal segment ``index`` (core index) at ``x`` [m] on its closed interval."""
        return self._state(self._j(index), x)[0]

    def dtheta_in(self, index: int, x):
        """dtheta/dx [K/m] of thermal segment ``index`` at ``x`` [m]: F / lam(T)."""
        j = self._j(index)
        th, F = self._state(j, x)
        return F / self._conductivity(th, j)

    def _dispatch(self, fn, x):
        return HeatSolution._dispatch(self, fn, x)

    theta = HeatSolution.theta
    dtheta = HeatSolution.dtheta
    temperature = HeatSolution.temperature
    dtemperature = HeatSolution.dtemperature

    def segment_profile(self, index: int):
        """Callable ``x -> (T(x), dT/dx(x))`` of core segment ``index`` on its closed interval."""
        Tc = self.T_cold
        if index not in self.indices or self.heat_input == 0.0:
            return HeatSolution.segment_profile(self, index)
        return lambda x: (Tc + self.theta_in(index, x), self.dtheta_in(index, x))

    def lost(self) -> float:
        """Heat leaked to the walls ``sum_j ∫ (2 h(theta)/R) theta S dx`` [W] (Gauss-Legendre
        on 400 panels per segment)."""
        g, w = np.polynomial.legendre.leggauss(8)
        total = 0.0
        for j, idx in enumerate(self.indices):
            e = np.linspace(self.x_left[j], self.x_right[j], 401)
            x = (0.5 * (e[1:] - e[:-1])[:, None] * g + 0.5 * (e[1:] + e[:-1])[:, None]).ravel()
            wx = (0.5 * (e[1:] - e[:-1])[:, None] * w).ravel()
            th = self.theta_in(idx, x)
            total += np.sum(wx * 2.0 * self._h(th, j) / self.R * th) * self.S
        return float(total)


#: Residual tolerance of the first, loose solve of :class:`FieldHeatSolution`'s BVP.
LOOSE_TOL = 1e-6
#: Default residual tolerance of :class:`FieldHeatSolution`: theta is converged to ~1e-10 of its
#: maximum there (a 10x looser solve moves it by less than 1e-8, test_wall_field_tends_to_the_
#: added_conductivity); tighter, the wall field's collocation runs into round-off and the
#: mesh refinement may not end.
HEAT_TOL = 1e-7


def core_wall_fields(core: Core) -> tuple[np.ndarray, np.ndarray]:
    """Per thermal segment of ``core``, the axial conductance lam_w [W/(m K)] and the lateral
    coupling h_w = 1/``wall_resistance`` [W/(m^2 K)] of its wall where the wall is a
    temperature field of its own (:func:`wall_field_indices`), 0 where it is not."""
    own = set(wall_field_indices(core))
    lam_w = [core.segments[i].wall_conductance if i in own else 0.0 for i in core.thermal_indices]
    h_w = [1.0 / core.segments[i].wall_resistance if i in own else 0.0 for i in core.thermal_indices]
    return np.array(lam_w), np.array(h_w)


def _uniform(value: float):
    """``x -> value`` over arrays like ``x``: a material conductivity that does not vary."""
    return lambda x: value + 0.0 * np.asarray(x, dtype=float)


class FieldHeatSolution(NonlinearHeatSolution):
    """Steady temperature of the two-field heat model: every wall that is a temperature field
    of its own beside its segment's gas/solid, a contact resistance at one interface, a
    material conductivity varying along a segment, and every temperature law of
    :class:`NonlinearHeatSolution` (its evaluators, ``lost()`` included). The core's own
    wall fields (``wall_resistance``, :func:`wall_field_indices`) by default;
    :class:`tawarp.reference_effects.LabHeatSolution` passes the lab effects'.

    Solved on the state (theta_j, F_j = lam theta'_j) of every thermal segment j, plus
    (theta_w, F_w = lam_w theta_w') in every segment whose wall is a field of its own, mapped
    to s in [0, 1], by scipy.integrate.solve_bvp (residual tolerance ``tol``, reached from a
    solve at :data:`LOOSE_TOL`). Interfaces: F, theta_w and F_w continuous; theta continuous
    but at the contact, where it jumps by R_c F. Where a wall field meets a segment whose
    wall is in perfect contact (``wall_resistance`` 0, with a conductance or none), the wall
    runs on at the gas temperature: theta_w = theta there and one balance of both fluxes
    (the limit h_w -> inf of that neighbour); where it meets a wall that conducts nothing
    behind a finite coupling (``wall_resistance`` > 0, ``wall_conductance`` 0), no flux
    passes: its end is adiabatic.

    Arguments beside the core, the heat input [W] and ``tol``: ``material``, per thermal
    segment, ``x -> lam_m(x)`` [W/(m K)] at T_cold, gas and solid without the wall
    (default: the core's, constant); ``walls``, per thermal segment, (lam_w [W/(m K)], h_w
    [W/(m^2 K)]) of the wall fields, 0 where there is none (default:
    :func:`core_wall_fields`); ``contact`` (j, R_c [m^2 K/W]): a contact resistance between
    the j-th thermal segment and the next (default: none).

    Attributes beside :class:`NonlinearHeatSolution`'s (``wall``: the conductances of the
    walls at the gas temperature): ``wall_field`` lam_w [W/(m K)] of each thermal segment's
    wall field (0: none), ``coupling`` 2 h_w/R [W/(m^3 K)], ``wall_rows`` {segment's position
    among the thermal ones: its wall's row in the BVP state}.
    """

    def __init__(
        self, core: Core, heat_input: float, tol: float = HEAT_TOL, *, material=None, walls=None, contact=None
    ):
        from scipy.integrate import solve_bvp

        # the first guess: the paper model's exact profile, every wall at the gas temperature
        lin = HeatSolution(tied_walls(core), heat_input)
        for k in ("heat_input", "T_cold", "indices", "x_left", "x_right", "length", "h", "q"):
            setattr(self, k, getattr(lin, k))
        self.core = core
        segs = [core.segments[i] for i in self.indices]
        if material is None:
            material = [_uniform(_material_conductivity(core, s)) for s in segs]
        self.material = list(material)
        self.lam_m = np.array([lam((a + b) / 2) for lam, a, b in zip(self.material, self.x_left, self.x_right)])
        self.wall_field, h_w = core_wall_fields(core) if walls is None else walls
        own = set(wall_field_indices(core))
        # the walls at the gas temperature: their conductance added to the segment's
        self.wall = np.array([0.0 if i in own else core.segments[i].wall_conductance for i in self.indices])
        self.lam = self.lam_m + self.wall
        # a wall in perfect contact (wall_resistance 0, any conductance, 0 included) is at the
        # gas temperature up to its ends: a wall field beside it is tied to the gas there
        tied = [core.segments[i].wall_resistance == 0.0 for i in self.indices]
        self.exponent = np.array([s.conductivity_exponent for s in segs])
        self.radiative = np.array([s.radiative_conductivity for s in segs])
        self.h_conv = np.array([s.h_convection for s in segs])
        self.R, self.S, self.tol = core.radius, core.area, tol
        n = len(self.indices)
        names = [s.name for s in segs]
        # state rows of each wall field, after the gas/solid's
        field = {int(j): 2 * n + 2 * k for k, j in enumerate(np.flatnonzero(self.wall_field > 0.0))}
        self.wall_rows = field
        self.contact, contact_resistance = contact if contact else (None, 0.0)
        if self.contact is not None and (self.contact in field) != (self.contact + 1 in field):
            raise ValueError(
                f"{core.source}: a contact resistance after {names[self.contact]!r}, where a wall field meets a "
                "segment without one, is not modelled: give both segments a wall_resistance or neither"
            )
        # lateral coupling to the wall per unit volume of tube, 2 h_w / R [W/(m^3 K)]
        self.coupling = 2.0 * h_w / self.R
        L, xl = self.length, self.x_left

        def fun(s, y):
            out = np.empty_like(y)
            for j in range(n):
                th, F = y[2 * j], y[2 * j + 1]
                lam = self._conductivity_at(th, j, xl[j] + s * L[j])
                out[2 * j] = L[j] * F / lam
                exchange = 2.0 * self._h(th, j) / self.R * th - self.q[j]
                if j in field:
                    o = field[j]
                    to_wall = self.coupling[j] * (th - y[o])
                    exchange = exchange + to_wall
                    out[o] = L[j] * y[o + 1] / self.wall_field[j]
                    out[o + 1] = -L[j] * to_wall
                out[2 * j + 1] = L[j] * exchange
            return out

        def bc(ya, yb):
            r, walls = [ya[1]], []
            for j in range(n - 1):
                k = j + 1
                jump = contact_resistance * yb[2 * j + 1] if j == self.contact else 0.0
                r.append(ya[2 * k] - yb[2 * j] - jump)
                a, b = field.get(j), field.get(k)
                if (a is None) == (b is None):
                    r.append(yb[2 * j + 1] - ya[2 * k + 1])
                    if a is not None:
                        walls += [yb[a] - ya[b], yb[a + 1] - ya[b + 1]]
                    continue
                # one side's wall is a field: tied to the other's wall in perfect contact
                # (theta_w = theta, one balance of the fluxes), or its end adiabatic
                if a is not None:
                    r.append(yb[2 * j + 1] + (yb[a + 1] if tied[k] else 0.0) - ya[2 * k + 1])
                    walls.append(yb[a] - ya[2 * k] if tied[k] else yb[a + 1])
                else:
                    r.append(yb[2 * j + 1] - ya[2 * k + 1] - (ya[b + 1] if tied[j] else 0.0))
                    walls.append(ya[b] - yb[2 * j] if tied[j] else ya[b + 1])
            r.append(yb[2 * n - 1])
            # the wall adiabatic at the ends of the thermal domain
            first, last = ([ya[field[0] + 1]] if 0 in field else []), ([yb[field[n - 1] + 1]] if n - 1 in field else [])
            return np.array(r + first + walls + last)

        s = np.linspace(0.0, 1.0, 201)
        y0 = np.empty((2 * n + 2 * len(field), s.size))
        for j, idx in enumerate(self.indices):
            x = self.x_left[j] + s * self.length[j]
            y0[2 * j] = lin.theta_in(idx, x)
            y0[2 * j + 1] = lin.lam[j] * lin.dtheta_in(idx, x)
            if j in field:
                y0[field[j]] = y0[2 * j]
                y0[field[j] + 1] = self.wall_field[j] * lin.dtheta_in(idx, x)
        # continuation in the tolerance: from the paper model's profile, a loose solve first
        # (a direct tight one can wander off to the node limit when the wall field is on)
        for t in dict.fromkeys((max(tol, LOOSE_TOL), tol)):
            self.bvp = solve_bvp(fun, bc, s, y0, tol=t, bc_tol=t, max_nodes=100000)
            if not self.bvp.success:
                break
            s, y0 = self.bvp.x, self.bvp.y
        if not self.bvp.success:
            raise RuntimeError(f"{core.source}: two-field heat BVP (Q = {heat_input} W): {self.bvp.message}")

    def _conductivity_at(self, theta, j: int, x):
        """lam(x, T) [W/(m K)] of thermal segment j (position x [m] from x1)."""
        t = 1.0 + np.asarray(theta) / self.T_cold
        return self.material[j](x) * t ** self.exponent[j] + self.radiative[j] * t**3 + self.wall[j]

    def dtheta_in(self, index: int, x):
        """dtheta/dx [K/m] of thermal segment ``index`` at ``x`` [m]: F / lam(x, T)."""
        j = self._j(index)
        th, F = self._state(j, x)
        return F / self._conductivity_at(th, j, np.asarray(x, dtype=float))

    def wall_theta_in(self, index: int, x):
        """The wall's temperature excess theta_w [K] in thermal segment ``index`` at ``x`` [m],
        where the wall is a field of its own."""
        j = self._j(index)
        if j not in self.wall_rows:
            raise ValueError(
                f"segment {self.core.segments[index].name!r}: its wall is no field of its own "
                "(LabEffects.wall_conductance 0 and no wall_resistance > 0 with a wall_conductance)"
            )
        s = (np.asarray(x, dtype=float) - self.x_left[j]) / self.length[j]
        return self.bvp.sol(np.clip(s, 0.0, 1.0))[self.wall_rows[j]]


def nonlinear_effects_on(core: Core) -> bool:
    """True when a temperature-dependent effect is on in a thermal segment of ``core``."""
    return any(
        core.segments[i].conductivity_exponent != 0.0
        or core.segments[i].radiative_conductivity != 0.0
        or core.segments[i].h_convection != 0.0
        for i in core.thermal_indices
    )


def heat_profile(core: Core, heat_input: float, tol: float = 1e-8):
    """Steady temperature for heat input ``heat_input`` [W]: the exact linear solution
    (:func:`heat_profile_exact`) or, with a temperature-dependent effect on, the BVP
    solution :class:`NonlinearHeatSolution` (residual tolerance ``tol``). Where a wall is a
    temperature field of its own (:func:`wall_field_indices`), the two-field BVP
    :class:`FieldHeatSolution` (the same temperature laws; residual tolerance
    ``max(tol, HEAT_TOL)``: its collocation reaches no tighter); at Q = 0 the cold core,
    wall or not."""
    if wall_field_indices(core):
        if heat_input == 0.0:
            return heat_profile_exact(tied_walls(core), 0.0)
        return FieldHeatSolution(core, heat_input, max(tol, HEAT_TOL))
    if heat_input != 0.0 and nonlinear_effects_on(core):
        return NonlinearHeatSolution(core, heat_input, tol)
    return heat_profile_exact(core, heat_input)


# ======================================================================================
# Thermoviscous functions
# ======================================================================================


def _bernoulli_even(nmax: int) -> list:
    """Exact B_0 .. B_(nmax) (fractions; Akiyama-Tanigawa). scipy's float version loses
    ~1e-12 already in the first coefficients, which would show in 1 - tanh(w)/w."""
    from fractions import Fraction

    a, out = [], []
    for m in range(nmax + 1):
        a.append(Fraction(1, m + 1))
        for j in range(m, 0, -1):
            a[j - 1] = j * (a[j - 1] - a[j])
        out.append(a[0])  # B_1 = +1/2 here; only even indices are used
    return out


_B = _bernoulli_even(50)
# Series of tanh(w)/w = sum_n c_n w^(2n-2), c_n = 2^(2n) (2^(2n) - 1) B_(2n) / (2n)!
_TANH_COEF = np.array(
    [float(2 ** (2 * n) * (2 ** (2 * n) - 1) * _B[2 * n] / math.factorial(2 * n)) for n in range(1, 26)]
)
# 1 - 2 J1(z)/(z J0(z)) = [sum_{k>=1} (-1)^k k t^(2k) / ((k+1) (k!)^2)] / J0(z), t = z/2
_BESSEL_COEF = np.array([(-1.0) ** k * k / ((k + 1) * math.factorial(k) ** 2) for k in range(1, 26)])


def thermoviscous_function(pore_model: str, r, delta, shape: float = 1.0):
    """Rott's function f and 1 - f for pores of radius ``r`` [m] (``plates``: half
    spacing; ``rectangular``: half the narrow side; ``pins``: the pin radius) and
    penetration depth ``delta`` [m], convention exp(-i w t); ``shape`` a rectangular
    channel's aspect ratio or a pin array's outer radius ratio.

    * circular: ``f = 2 J1(z)/(z J0(z))``, ``z = (1 + i) r/delta``;
    * plates: ``f = tanh(w)/w``, ``w = (1 - i) r/delta``;
    * rectangular (Stinson 1991), s = r/delta: the cosine series across the narrow side
      with the wide side solved exactly, its terms summed directly (docs/physics.md):
      ``f = f_plates(s) + R``, ``1 - f = 1 - f_plates(s) - R``,
      ``R = sum_m 8/(m pi)^2 tanh(z)/z E_m``, ``E_m = 2 s^2/(2 s^2 + i q_m)``,
      ``q_m = (m pi/2)^2``, ``z^2 = alpha^2 (q_m - 2 i s^2)``;
    * pins, x = (1 - i) s, R = ``shape``: ``f = 2/(x (R^2 - 1)) [I1(Rx) K1(x) - K1(Rx)
      I1(x)] / [I1(Rx) K0(x) + K1(Rx) I0(x)]`` with SciPy's scaled ``ive``, ``kve``.

    Returns ``(f, one_minus_f)`` (complex arrays, shape of ``r/delta``), each to full
    relative precision (checked against mpmath): for small arguments (|z| < 2, |w| < 0.5)
    ``1 - f`` comes from its power series (no cancellation as f -> 1) and f = 1 - (1 - f);
    otherwise f comes directly from the exponentially scaled Bessel ratio
    ``jve(1, z)/jve(0, z)`` (no overflow up to r/delta ~ 1e4 and beyond; keeps the relative
    precision of f ~ 1/z) or from ``tanh`` written with ``exp(-2w)``, and 1 - f = 1 - f.
    """
    x = np.asarray(r / np.asarray(delta))
    # complex r/delta: a complex frequency (delta ~ omega^-1/2), for :func:`transfer_matrix_omega`
    x = x.astype(complex if np.iscomplexobj(x) else float)
    if pore_model == "circular":
        z = (1.0 + 1.0j) * x
        small = np.abs(z) < 2.0
        f = np.empty(z.shape, dtype=complex)
        one_minus = np.empty(z.shape, dtype=complex)
        if np.any(small):
            zs = z[small]
            t2 = (zs / 2) ** 2
            acc = np.zeros_like(zs)
            for c in _BESSEL_COEF[::-1]:  # Horner in t^2
                acc = acc * t2 + c
            one_minus[small] = acc * t2 / sp.jv(0, zs)
            f[small] = 1.0 - one_minus[small]
        if np.any(~small):
            zl = z[~small]
            # f -> 0 like 1/z: computed directly so it keeps its relative accuracy
            f[~small] = 2.0 * (sp.jve(1, zl) / sp.jve(0, zl)) / zl
            one_minus[~small] = 1.0 - f[~small]
    elif pore_model == "plates":
        w = (1.0 - 1.0j) * x
        small = np.abs(w) < 0.5
        f = np.empty(w.shape, dtype=complex)
        one_minus = np.empty(w.shape, dtype=complex)
        if np.any(small):
            w2 = w[small] ** 2
            acc = np.zeros_like(w2)
            for c in _TANH_COEF[:0:-1]:  # c_25 ... c_2: 1 - tanh(w)/w = -sum_{n>=2} c_n w^(2n-2)
                acc = acc * w2 + c
            one_minus[small] = -acc * w2
            f[small] = 1.0 - one_minus[small]
        if np.any(~small):
            wl = w[~small]
            e = np.exp(-2.0 * wl)  # Re w > 0: tanh(w) = (1 - e^{-2w})/(1 + e^{-2w}) never overflows
            f[~small] = (1.0 - e) / (1.0 + e) / wl
            one_minus[~small] = 1.0 - f[~small]
    elif pore_model == "rectangular":
        f, one_minus = _rectangular_function(x, shape)
    elif pore_model == "pins":
        xx = (1.0 - 1.0j) * x.astype(complex)
        R = shape
        e = np.exp(-2.0 * (R - 1.0) * xx)

        def i_scaled(n, z):  # exp(-z) I_n(z): SciPy's ive scales by exp(-|Re z|) only
            return sp.ive(n, z) * np.exp(-1j * z.imag)

        i0, i1 = i_scaled(0, xx), i_scaled(1, xx)
        k0, k1 = sp.kve(0, xx), sp.kve(1, xx)
        i1o, k1o = i_scaled(1, R * xx), sp.kve(1, R * xx)
        f = 2.0 / (xx * (R * R - 1.0)) * (i1o * k1 - e * k1o * i1) / (i1o * k0 + e * k1o * i0)
        one_minus = 1.0 - f
    else:
        raise ValueError(f"unknown pore_model {pore_model!r}; expected circular, plates, rectangular or pins")
    return f, one_minus


#: Terms of the rectangular channel's series beyond 40 |s| (past |s| they fall as m^-5).
_RECT_TERMS = 2000


def _rectangular_function(s, alpha: float):
    """(f, 1 - f) of rectangular channels of aspect ratio ``alpha`` at s (array):
    f = f_plates + R, 1 - f = (1 - f_plates) - R with the plates' pair of
    :func:`thermoviscous_function` and R = sum_m 8/(m pi)^2 tanh(z)/z E_m summed to
    _RECT_TERMS + 40 |s| terms (its tail is below 1e-11 of f for |s| <= 100)."""
    s = np.asarray(s)
    flat = s.ravel()
    f_pl, g_pl = thermoviscous_function("plates", flat, np.ones(flat.shape))
    rest = np.empty(flat.shape, dtype=complex)
    for k, sk in enumerate(flat):
        m = np.arange(1, 2 * (_RECT_TERMS + 40 * int(abs(sk))), 2, dtype=float)[::-1]
        q = (m * np.pi / 2) ** 2
        z = alpha * np.sqrt(q - 2j * sk * sk)
        rest[k] = np.sum(8.0 / (m * np.pi) ** 2 * (2 * sk * sk) / (2 * sk * sk + 1j * q) * np.tanh(z) / z)
    return (f_pl + rest).reshape(s.shape), (g_pl - rest).reshape(s.shape)


def _pore(core: Core, seg: Segment):
    """(phi, r, q, pore_model, r_k, shape) of a segment: ducts are one circular pore of the
    tube radius; ``r_k`` is the radius of the thermal function, ``thermal_radius_ratio * r``
    in a porous segment (JCA's Lambda'/Lambda; 1 = the paper's single radius); ``shape``
    the pores' shape number (:attr:`Segment.pore_shape`)."""
    if seg.is_porous:
        r_k = seg.thermal_radius_ratio * seg.pore_radius
        return seg.porosity, seg.pore_radius, seg.tortuosity, seg.pore_model, r_k, seg.pore_shape
    return 1.0, core.radius, 1.0, "circular", core.radius, 1.0


def rott_coefficients(
    gas_name: str, p_mean: float, w, T, dTdx, phi, S, r, q, pore_model: str, r_k=None, shape: float = 1.0
):
    """Rott's ODE coefficients a12 [Pa s/m^4], a21 [m^3/(Pa s m)], a22 [1/m] of gas
    ``gas_name`` at ``p_mean`` [Pa], angular frequency ``w`` [rad/s], temperature ``T`` [K]
    and gradient ``dTdx`` [K/m], in pores of radius ``r`` [m] (``plates``: half spacing)
    filling a fraction ``phi`` of the section ``S`` [m^2], tortuosity ``q`` (all broadcast
    together):

        dp/dx = a12 U,  dU/dx = a21 p + a22 U
        a12 = i q^2 rho w / (phi S (1 - f_nu))
        a21 = i phi S w (1 + (gamma - 1) f_k) / (rho c^2)
        a22 = (dT/dx / T) (f_k - f_nu) / ((1 - f_nu)(1 - Pr))

    f_nu at the pore radius r, f_k at the thermal radius ``r_k`` (None: r); ``shape`` the
    pores' shape number (:attr:`tawarp.model.core.Segment.pore_shape`).
    """
    r_k = r if r_k is None else r_k
    g = gas_properties(gas_name, T, p_mean)
    if pore_model == "screens":
        return _screen_coefficients(g, phi, r, q, S, w, T, dTdx)
    d_nu = np.sqrt(2.0 * g.mu / (g.rho * w))
    d_k = np.sqrt(2.0 * g.k / (g.rho * g.cp * w))
    # one call for both depths (halves the per-call overhead inside the ODE right-hand side);
    # the thermal depth is scaled by r/r_k so that the one radius r serves both functions
    d_nu, d_k = np.broadcast_arrays(d_nu, d_k * (r / r_k))
    f, omf = thermoviscous_function(pore_model, r, np.stack([d_nu, d_k]), shape)
    f_nu, f_k, omf_nu, omf_k = f[0], f[1], omf[0], omf[1]
    a12 = 1j * q**2 * g.rho * w / (phi * S * omf_nu)
    a21 = 1j * phi * S * w * (1.0 + (g.gamma - 1.0) * f_k) / (g.rho * g.c**2)
    # f_k - f_nu from whichever pair is accurate: near f = 1 (narrow pores) the 1 - f
    # values carry the information, near f = 0 (wide ducts) the f values do.
    diff = np.where(np.abs(omf_nu) < np.abs(f_nu), omf_nu - omf_k, f_k - f_nu)
    a22 = (dTdx / T) * diff / (omf_nu * (1.0 - g.Pr))
    return a12, a21, a22


def _coefficients(core: Core, seg: Segment, w, T, dTdx):
    """:func:`rott_coefficients` of segment ``seg`` of ``core`` (pores of :func:`_pore`)."""
    phi, r, q, model, r_k, shape = _pore(core, seg)
    return rott_coefficients(core.gas.name, core.gas.p_mean, w, T, dTdx, phi, core.area, r, q, model, r_k, shape)


def screen_correlations(phi):
    """Swift & Ward's stacked-screen coefficients at porosity ``phi`` (J. Thermophys. Heat
    Transfer 10, 652, 1996; DeltaEC's STKSCREEN): the friction factor's laminar and inertial
    terms c1, c2 (dp/dx = -(f/r_h) rho u^2/2, f = c1/Re + c2, Re = 4 r_h |u| rho/mu, u the
    mean pore velocity), the heat transfer's low-Reynolds Nusselt number Nu = 4 h r_h/k =
    b Pr^(1/3) and the inertia factor K = 1 + (1 - phi)^2/(2 (2 phi - 1)); returns
    (c1, c2, b, K)."""
    c1 = 1268.0 - 3545.0 * phi + 2544.0 * phi**2
    c2 = -2.82 + 10.7 * phi - 8.6 * phi**2
    b = 3.81 - 11.29 * phi + 9.47 * phi**2
    K = 1.0 + (1.0 - phi) ** 2 / (2.0 * (2.0 * phi - 1.0))
    return c1, c2, b, K


def _screen_coefficients(g, phi, r_h, q, S, w, T, dTdx):
    """Rott's coefficients' counterparts in a stack of wire screens of hydraulic radius
    ``r_h`` (DeltaEC's STKSCREEN at low amplitude, no solid heat capacity, in exp(-iwt)):
    the momentum equation dp/dx = -(mu c1/(8 r_h^2) - i w rho K) U/(phi S) and the
    continuity equation with the thermal relaxation eps_h = -8 i r_h^2/(b Pr^(1/3) delta_k^2):
    dU/dx = i w phi S/(gamma p) (1 + (gamma - 1)/(1 + eps_h)) p + (dT/dx/T) U/(1 + eps_h)."""
    c1, _, b, K = screen_correlations(phi)
    a12 = (1j * w * g.rho * K - g.mu * c1 / (8.0 * r_h**2)) * q**2 / (phi * S)
    delta_k2 = 2.0 * g.k / (g.rho * g.cp * w)
    relaxed = 1.0 / (1.0 - 8j * r_h**2 / (b * g.Pr ** (1.0 / 3.0) * delta_k2))
    p_mean = g.rho * g.c**2 / g.gamma
    a21 = 1j * w * phi * S / (g.gamma * p_mean) * (1.0 + (g.gamma - 1.0) * relaxed)
    a22 = (dTdx / T) * relaxed
    return a12, a21, a22


def _uniform_matrix(core: Core, seg: Segment, w: np.ndarray) -> np.ndarray:
    """Closed-form T-matrix (m, 2, 2) of a segment at uniform T_cold.

    k^2 = -a12 a21 (Im k > 0), Zc = a12/(i k) (this keeps the branches of k and Zc
    consistent whatever sqrt returns); T = [[cos kL, i Zc sin kL], [i sin kL/Zc, cos kL]].
    """
    _refuse_unmodelled(core, {"acoustics"}, [seg])
    a12, a21, _ = _coefficients(core, seg, w, core.gas.T_cold, 0.0)
    k = np.sqrt(-a12 * a21)
    k = np.where(k.imag < 0, -k, k)
    Zc = a12 / (1j * k)
    kL = k * seg.length
    cs, sn = np.cos(kL), np.sin(kL)
    out = np.empty(w.shape + (2, 2), dtype=complex)
    out[:, 0, 0] = cs
    out[:, 0, 1] = 1j * Zc * sn
    out[:, 1, 0] = 1j * sn / Zc
    out[:, 1, 1] = cs
    return out


def _ode_matrix(core: Core, seg: Segment, x0: float, w: float, profile, rtol: float, porosity=None) -> np.ndarray:
    """T-matrix (2, 2) of one segment by DOP853 on dM/dx = A(x) M, M(x0) = I.

    Integrated on the scaled state (p, Z0 U), Z0 = rho0 c0/S at T_cold, so the four
    entries are O(1) and one absolute tolerance fits all; as a real 8-vector.
    ``porosity``: None (the segment's), or a callable ``x -> phi(x)`` of a porosity varying
    along the segment, the pore radius and tortuosity held: the flow area phi S enters
    a12 as 1/phi and a21 as phi, a22 not at all.
    """
    _refuse_unmodelled(core, {"acoustics"}, [seg])
    g0 = gas_properties(core.gas.name, core.gas.T_cold, core.gas.p_mean)
    Z0 = float(g0.rho * g0.c) / core.area

    def rhs(x, y):
        M = (y[:4] + 1j * y[4:]).reshape(2, 2)
        T, dT = profile(x)
        a12, a21, a22 = _coefficients(core, seg, w, float(T), float(dT))
        if porosity is not None:
            ratio = float(porosity(x)) / seg.porosity
            a12, a21 = a12 / ratio, a21 * ratio
        A = np.array([[0.0, a12 / Z0], [a21 * Z0, a22]], dtype=complex)
        dM = (A @ M).ravel()
        return np.concatenate([dM.real, dM.imag])

    y0 = np.array([1.0, 0, 0, 1.0, 0, 0, 0, 0])
    sol = solve_ivp(rhs, (x0, x0 + seg.length), y0, method="DOP853", rtol=rtol, atol=rtol * 1e-2)
    if not sol.success:
        raise RuntimeError(f"segment {seg.name!r}, f = {w / (2 * math.pi)} Hz: {sol.message}")
    yf = sol.y[:, -1]
    Ms = (yf[:4] + 1j * yf[4:]).reshape(2, 2)
    # back to (p, U): M = D^-1 Ms D with D = diag(1, Z0)
    return np.array([[Ms[0, 0], Ms[0, 1] * Z0], [Ms[1, 0] / Z0, Ms[1, 1]]])


def segment_transfer_matrices(
    core: Core, freqs, heat_input: float = 0.0, rtol: float = 1e-12, heat_tol: float = 1e-8, *, _force_ode: bool = False
) -> list[np.ndarray]:
    """T-matrix of every segment, a list of complex arrays (m, 2, 2), raw SI units.

    ``freqs`` [Hz] (scalar or 1-D), ``heat_input`` Q [W]. A segment at uniform T_cold
    (not thermal, or Q = 0) uses the closed form; a heated thermal segment is integrated
    by DOP853 with relative tolerance ``rtol`` using the exact heat profile, or with a
    temperature-dependent effect on, the BVP solution of tolerance ``heat_tol``
    (:func:`heat_profile`). A core field the reference does not model (a limp frame, a
    viscous shape factor, a bypass gap, imposed temperatures; with heat input a contact
    resistance or an end conductance) is a ValueError that names it.
    ``_force_ode`` (private, for tests): integrate every segment numerically.
    """
    f = np.atleast_1d(np.asarray(freqs, dtype=float))
    if f.ndim != 1 or np.any(f <= 0):
        raise ValueError("freqs must be positive frequencies [Hz], scalar or 1-D")
    return _segment_matrices(core, 2.0 * np.pi * f, heat_input, rtol, heat_tol, _force_ode)


def _segment_matrices(
    core: Core, w: np.ndarray, heat_input: float, rtol: float, heat_tol: float, _force_ode: bool
) -> list[np.ndarray]:
    """:func:`segment_transfer_matrices` at angular frequencies ``w`` [rad/s], real or complex."""
    hs = heat_profile(core, heat_input, heat_tol)
    heated = set(hs.indices) if heat_input != 0.0 else set()
    pos = core.positions()
    out = []
    for i, seg in enumerate(core.segments):
        if i not in heated and not _force_ode:
            out.append(_uniform_matrix(core, seg, w))
            continue
        profile = hs.segment_profile(i)
        Tmin = profile(np.linspace(pos[i], pos[i + 1], 201))[0].min()
        if Tmin <= 0:
            raise ValueError(f"segment {seg.name!r}: temperature {Tmin} K <= 0 (heat input {heat_input} W)")
        out.append(np.stack([_ode_matrix(core, seg, pos[i], wk, profile, rtol) for wk in w]))
    return out


def transfer_matrix(
    core: Core, freqs, heat_input: float = 0.0, rtol: float = 1e-12, heat_tol: float = 1e-8, *, _force_ode: bool = False
) -> np.ndarray:
    """Core T-matrix, complex array (m, 2, 2), with ``(p, U)(x6) = T (p, U)(x1)``.

    ``freqs`` [Hz] (scalar or 1-D, m values), ``heat_input`` Q [W] dissipated in the
    heater, ``rtol`` the DOP853 relative tolerance for heated segments. Units: T_pp [-],
    T_pU [Pa s/m^3], T_Up [m^3/(Pa s)], T_UU [-]; convention exp(-i w t).
    ``T = T_last ... T_first`` (see :func:`segment_transfer_matrices`).
    """
    mats = segment_transfer_matrices(core, freqs, heat_input, rtol, heat_tol, _force_ode=_force_ode)
    T = mats[0]
    for M in mats[1:]:
        T = M @ T
    return T


def transfer_matrix_omega(
    core: Core, omega, heat_input: float = 0.0, rtol: float = 1e-12, heat_tol: float = 1e-8
) -> np.ndarray:
    """Core T-matrix (m, 2, 2) at complex angular frequencies ``omega`` [rad/s] (scalar or
    1-D): every model function is analytic in omega (docs/physics.md, "Onset"), so the closed
    forms and the ODE of :func:`transfer_matrix` hold as written with omega complex
    (Bessel functions of complex argument, DOP853 on the complex system). Im omega > 0 is
    a growing oscillation in exp(-i omega t)."""
    w = np.atleast_1d(np.asarray(omega, dtype=complex))
    if w.ndim != 1 or np.any(w.real <= 0):
        raise ValueError("omega must have a positive real part [rad/s], scalar or 1-D")
    mats = _segment_matrices(core, w, heat_input, rtol, heat_tol, False)
    T = mats[0]
    for M in mats[1:]:
        T = M @ T
    return T


def duct_waves(gas_name: str, p_mean: float, T: float, radius: float, omega) -> tuple[np.ndarray, np.ndarray]:
    """Plane waves of an empty duct of ``radius`` [m] at uniform temperature ``T`` [K]:
    wavenumber ``k`` [1/m] and characteristic impedance ``Zc`` [Pa s/m^3] (arrays like
    ``omega`` [rad/s], 1-D): k = (w/c) sqrt((1 + (gamma-1) f_k)/(1 - f_nu)),
    Zc = rho c/(S sqrt((1 - f_nu)(1 + (gamma-1) f_k))) (docs/physics.md, "Acoustics");
    p = A e^{ikx} + B e^{-ikx}, U = (A e^{ikx} - B e^{-ikx})/Zc."""
    w = np.atleast_1d(np.asarray(omega, dtype=complex))
    g = gas_properties(gas_name, T, p_mean)
    f_nu, omf_nu = thermoviscous_function("circular", radius, np.sqrt(2.0 * g.mu / (g.rho * w)))
    f_k, _ = thermoviscous_function("circular", radius, np.sqrt(2.0 * g.k / (g.rho * g.cp * w)))
    bulk = 1.0 + (g.gamma - 1.0) * f_k
    k = w / g.c * np.sqrt(bulk / omf_nu)
    Zc = g.rho * g.c / (math.pi * radius**2) / np.sqrt(omf_nu * bulk)
    return k, Zc


def duct_matrix_omega(gas_name: str, p_mean: float, T: float, radius: float, length: float, omega) -> np.ndarray:
    """Closed-form T-matrix (m, 2, 2) of an empty duct of ``radius`` [m] and ``length`` [m]
    at uniform temperature ``T`` [K], at complex angular frequencies ``omega`` [rad/s]:
    k = (w/c) sqrt((1 + (gamma-1) f_k)/(1 - f_nu)), Zc = rho c/(S sqrt((1 - f_nu)(1 + (gamma-1) f_k))),
    T = [[cos kL, i Zc sin kL], [i sin kL/Zc, cos kL]] (docs/physics.md, "Acoustics")."""
    k, Zc = duct_waves(gas_name, p_mean, T, radius, omega)
    kL = k * length
    out = np.empty(kL.shape + (2, 2), dtype=complex)
    out[:, 0, 0] = np.cos(kL)
    out[:, 0, 1] = 1j * Zc * np.sin(kL)
    out[:, 1, 0] = 1j * np.sin(kL) / Zc
    out[:, 1, 1] = np.cos(kL)
    return out


def dimensionless_transfer(core: Core, freqs, heat_input: float = 0.0, rtol: float = 1e-12) -> np.ndarray:
    """Dimensionless coefficients (m, 4): ``Tpp, Tpu/Zc, Tup*Zc, Tuu`` with
    ``Zc = rho0 c0/S`` at T_cold (:func:`tawarp.model.coefficients.normalize`)."""
    return normalize(transfer_matrix(core, freqs, heat_input, rtol), duct_impedance(core))
