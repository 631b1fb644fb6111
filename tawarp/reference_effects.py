"""Lab effects in the independent reference: what a real rig adds to the paper's core,
each written from its physics (the oracle's own code, no kernel, no forward model).

The reference (:mod:`tawarp.reference`) models the paper's core. A built rig also has
(:class:`LabEffects`, each off at its default):

* **thermal contact resistance** ``R_c`` [m^2 K/W] at one interface of the heat model (the
  stack against the hot exchanger): the temperature jumps by ``R_c`` times the heat flux
  density through the tube section, ``theta(right) - theta(left) = R_c lam theta'``;
* **a conducting tube wall as a second temperature field** ``theta_w`` along the thermal
  parts, its axial conductance (the wall material's conductivity times the wall's section)
  written per tube section as ``lam_w`` = ``wall_conductance`` [W/(m K)] (the library's
  field's unit), coupled to the gas/solid temperature by a lateral coefficient ``h_w``
  [W/(m^2 K)] on the perimeter (the porous parts' solid touching the wall, the buffer
  tube's gas by laminar conduction), adiabatic at both ends of the thermal domain. The
  losses to the room stay the h's of the gas/solid, so that the wall only carries heat
  along the tube:

      lam theta'' - (2 h/R) theta - (2 h_w/R)(theta - theta_w) + q = 0
      lam_w theta_w''             + (2 h_w/R)(theta - theta_w)     = 0

  (lam_w = 0: the paper's model; h_w -> infinity: theta_w = theta, the sum of the two is
  the library's "added conductivity" ``lam + wall_conductance``). The core's own wall field
  (``SEGMENT.wall_resistance`` = 1/h_w > 0 with a ``wall_conductance``, per segment) is the
  same BVP (:class:`LabHeatSolution`, :func:`wall_fields`); the reference's
  :func:`tawarp.reference.heat_profile` solves it there;
* **an annular bypass gap** of width ``g`` between the stack and the tube: the stack of
  radius R - g and a parallel-plate channel of spacing g and area S g (2R - g)/R^2 (the
  narrow annulus unrolled; curvature corrections O(g/R)), at the stack's temperature, side
  by side between the same two planes: their admittance matrices add
  (:func:`parallel`). In the heat model the gap's gas replaces that share of the stack. A
  gap far below the viscous depth (microns in a wire-mesh stack) makes the slit a diffusion
  path many decay lengths long, whose T-matrix entries grow like e^{|k| L} so that the
  parallel combination loses its digits; a real gap of 0.1 mm and more is far from it;
* **a side branch (leak)**: a hole of diameter ``d`` through the wall of a duct, neck length
  ``l``, to the room or to a closed cavity of volume ``V``: a shunt admittance
  ``Y = 1/Z_branch`` (:func:`side_branch_impedance`), ``(p, U) -> (p, U - Y p)``;
* **a gain/phase mismatch inside one microphone pair** (the measurement chain): one
  microphone of the upstream or downstream pair reads ``G = g e^{i phi}`` times its
  pressure; the two-microphone wave decomposition then reports a face state
  ``E (p, U)`` with ``E = P^-1 diag(1, G) P`` (:func:`microphone_error`), and the
  two-load method the T-matrix ``E_down T E_up^-1`` whatever the loads;
* **axially varying porosity** ``phi(x) = phi0 (1 + a (x - x_mid)/L)`` in one porous
  segment, pore radius and tortuosity held: in the acoustic ODE (a12 ~ 1/phi, a21 ~ phi)
  and in the heat model's conductivity ``phi k_gas + (1 - phi) lam_solid``.

Buffer-tube convection (h growing with the temperature rise) is the core field
``h_convection`` of the reference's :class:`tawarp.reference.NonlinearHeatSolution`; the
heat model here (:class:`LabHeatSolution`) keeps it and every other temperature law of
that class. Conventions: :mod:`tawarp.reference` (exp(-i w t), ``(p, U)(x6) = T (p, U)(x1)``,
U the volume velocity).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .model.core import Core, Segment
from .reference import (
    HEAT_TOL,
    FieldHeatSolution,
    _material_conductivity,
    core_wall_fields,
    _ode_matrix,
    _uniform_matrix,
    duct_waves,
    gas_properties,
    heat_profile,
    thermoviscous_function,
    wall_field_indices,
)

__all__ = [
    "LabEffects",
    "LabHeatSolution",
    "lab_heat_profile",
    "lab_segment_matrices",
    "lab_transfer_matrix",
    "microphone_error",
    "parallel",
    "side_branch_impedance",
    "wall_fields",
]

#: Rayleigh's end correction of a flanged opening, 8 a/(3 pi) per end (a the hole's radius).
END_CORRECTION = 8.0 / (3.0 * math.pi)


@dataclass(frozen=True)
class LabEffects:
    """The lab effects of the module docstring; each is off at its default.

    * ``contact_resistance`` R_c [m^2 K/W] between segment ``contact_left`` and the next one;
    * ``wall_conductance`` lam_w A_w / S [W/(m K)] of the wall field (0: no wall field),
      coupled by ``wall_coupling_porous`` / ``wall_coupling_duct`` h_w [W/(m^2 K)] in the
      porous / duct thermal segments;
    * ``bypass_gap`` g [m] around segment ``gap_segment``;
    * ``leak_diameter`` d [m] (0: no leak) of a hole at ``leak_position`` [m from x1] inside
      a duct, neck length ``leak_length`` [m], into ``leak_volume`` [m^3] (inf: the room);
    * ``mic_gain`` g [-] and ``mic_phase`` phi [rad] of the far microphone of the
      ``mic_pair`` ("upstream" or "downstream") relative to its partner; the pair's
      microphones sit ``mic_distance`` and ``mic_distance + mic_spacing`` [m] from their
      face (x1 upstream, x6 downstream), in the tube at T_cold;
    * ``porosity_gradient`` a [-] of segment ``graded_segment``.
    """

    contact_resistance: float = 0.0
    contact_left: str = "stack"
    wall_conductance: float = 0.0
    wall_coupling_porous: float = 300.0
    wall_coupling_duct: float = 3.0
    bypass_gap: float = 0.0
    gap_segment: str = "stack"
    leak_diameter: float = 0.0
    leak_position: float = 0.015
    leak_length: float = 1.5e-3
    leak_volume: float = math.inf
    mic_gain: float = 1.0
    mic_phase: float = 0.0
    mic_pair: str = "downstream"
    mic_distance: float = 0.1
    mic_spacing: float = 0.1
    porosity_gradient: float = 0.0
    graded_segment: str = "stack"

    def __post_init__(self):
        for name in (
            "contact_resistance",
            "wall_conductance",
            "wall_coupling_porous",
            "wall_coupling_duct",
            "bypass_gap",
            "leak_diameter",
            "leak_length",
            "leak_volume",
            "mic_gain",
            "mic_distance",
            "mic_spacing",
        ):
            v = getattr(self, name)
            if not (v >= 0.0):
                raise ValueError(f"LabEffects.{name} = {v!r}: must be >= 0")
        if self.mic_pair not in ("upstream", "downstream"):
            raise ValueError(f"LabEffects.mic_pair = {self.mic_pair!r}: expected 'upstream' or 'downstream'")
        if self.mic_spacing == 0.0:
            raise ValueError("LabEffects.mic_spacing = 0: the two microphones of a pair must be apart")

    @property
    def heat_on(self) -> bool:
        """True when an effect changes the steady heat model."""
        return bool(self.contact_resistance or self.wall_conductance or self.bypass_gap or self.porosity_gradient)

    @property
    def microphones_on(self) -> bool:
        return self.mic_gain != 1.0 or self.mic_phase != 0.0


def gap_area_fraction(core: Core, gap: float) -> float:
    """Share of the tube section [-] of an annular gap of width ``gap`` [m] at the wall."""
    R = core.radius
    return gap * (2.0 * R - gap) / R**2


def porosity_profile(core: Core, lab: LabEffects, seg: Segment):
    """``x -> phi(x)`` of ``seg`` (x [m] from x1) when it is the graded segment, else None.
    The porosity must stay inside (0, 1) over the segment."""
    if not lab.porosity_gradient or seg.name != lab.graded_segment:
        return None
    i = [s.name for s in core.segments].index(seg.name)
    x0 = core.positions()[i]
    L, a, phi0 = seg.length, lab.porosity_gradient, seg.porosity
    ends = phi0 * (1.0 - abs(a) / 2), phi0 * (1.0 + abs(a) / 2)
    if not seg.is_porous or ends[0] <= 0.0 or ends[1] >= 1.0:
        raise ValueError(f"segment {seg.name!r}: porosity {phi0} with gradient {a} spans {ends}, outside (0, 1)")
    return lambda x: phi0 * (1.0 + a * (np.asarray(x, dtype=float) - x0 - L / 2) / L)


def material_conductivity(core: Core, lab: LabEffects, index: int):
    """``x -> lam_m(x)`` [W/(m K)] of segment ``index`` at T_cold, gas and solid (no wall):
    the reference's law with the lab's porosity gradient and bypass gap."""
    seg = core.segments[index]
    k_gas = float(gas_properties(core.gas.name, core.gas.T_cold, core.gas.p_mean).k)
    phi = porosity_profile(core, lab, seg)
    gap = gap_area_fraction(core, lab.bypass_gap) if (lab.bypass_gap and seg.name == lab.gap_segment) else 0.0
    base = _material_conductivity(core, seg)

    def lam(x):
        x = np.asarray(x, dtype=float)
        m = base + 0.0 * x if phi is None else phi(x) * k_gas + (1.0 - phi(x)) * seg.solid_conductivity
        return (1.0 - gap) * m + gap * k_gas

    return lam


def wall_fields(core: Core, lab: LabEffects) -> tuple[np.ndarray, np.ndarray]:
    """Per thermal segment of ``core``, the wall's axial conductance lam_w [W/(m K)] and its
    lateral coupling h_w [W/(m^2 K)] where the wall is a temperature field of its own, 0 where
    it is not: the lab's wall (``LabEffects.wall_conductance``, coupled by
    ``wall_coupling_porous`` / ``wall_coupling_duct``) in every thermal segment, else the
    core's (``SEGMENT.wall_conductance`` behind ``wall_resistance`` = 1/h_w > 0,
    :func:`tawarp.reference.wall_field_indices`). Both walls at once are refused: the lab's
    is the core's written from the physics, not a second one."""
    segs = [core.segments[i] for i in core.thermal_indices]
    if lab.wall_conductance > 0.0:
        own = [core.segments[i].name for i in wall_field_indices(core)]
        if own:
            raise ValueError(
                f"{core.source}: LabEffects.wall_conductance = {lab.wall_conductance} beside the core's own wall "
                f"field (wall_resistance > 0 in {own}): give the wall once, in the lab effects or in the core"
            )
        h_w = [lab.wall_coupling_porous if s.is_porous else lab.wall_coupling_duct for s in segs]
        return np.full(len(segs), lab.wall_conductance), np.array(h_w)
    return core_wall_fields(core)


class LabHeatSolution(FieldHeatSolution):
    """Steady temperature with the lab effects' heat physics (contact resistance, wall
    field, porosity gradient, bypass gap) and the core's own wall fields: the reference's
    two-field BVP :class:`tawarp.reference.FieldHeatSolution` given the lab's material
    conductivities (:func:`material_conductivity`), walls (:func:`wall_fields`) and
    contact; ``lab`` kept as an attribute."""

    def __init__(self, core: Core, lab: LabEffects, heat_input: float, tol: float = HEAT_TOL):
        self.lab = lab
        names = [core.segments[i].name for i in core.thermal_indices]
        contact = None
        if lab.contact_resistance:
            if lab.contact_left not in names[:-1]:
                raise ValueError(
                    f"{core.source}: contact_left = {lab.contact_left!r} is not a thermal segment followed "
                    f"by another (thermal: {names})"
                )
            contact = (names.index(lab.contact_left), lab.contact_resistance)
        super().__init__(
            core,
            heat_input,
            tol,
            material=[material_conductivity(core, lab, i) for i in core.thermal_indices],
            walls=wall_fields(core, lab),
            contact=contact,
        )


def lab_heat_profile(core: Core, lab: LabEffects, heat_input: float, tol: float = HEAT_TOL):
    """Steady temperature with the lab effects: :class:`LabHeatSolution` when one of them
    acts on the heat model and Q != 0, else the reference's :func:`tawarp.reference.heat_profile`."""
    if heat_input != 0.0 and lab.heat_on:
        return LabHeatSolution(core, lab, heat_input, tol)
    return heat_profile(core, heat_input, tol)


def side_branch_impedance(
    gas_name: str, p_mean: float, T: float, diameter: float, neck_length: float, omega, volume: float = math.inf
) -> np.ndarray:
    """Acoustic impedance p/U [Pa s/m^3] (arrays like ``omega`` [rad/s]) of a hole of
    ``diameter`` [m] through a wall of thickness ``neck_length`` [m], gas at ``T`` [K], into
    a closed cavity of ``volume`` [m^3] or, at inf, the room (exp(-i w t)):

        Z = -i w rho (l/(1 - f_nu) + 2 (8 a/(3 pi))) / A  +  Z_end
        Z_end = i rho c^2/(w V)     (cavity: its compliance)
        Z_end = rho c k^2/(2 pi)    (room: radiation resistance of a flanged opening, k a << 1)

    The neck is a circular pore of radius a = d/2 (viscous function f_nu, the reference's),
    A = pi a^2, the end corrections Rayleigh's for a flanged opening at each end. The gas in
    the neck is incompressible (its volume A l is far below the cavity's)."""
    w = np.atleast_1d(np.asarray(omega, dtype=float))
    a = diameter / 2.0
    A = math.pi * a * a
    g = gas_properties(gas_name, T, p_mean)
    _, omf_nu = thermoviscous_function("circular", a, np.sqrt(2.0 * g.mu / (g.rho * w)))
    Z = -1j * w * g.rho * (neck_length / omf_nu + 2.0 * END_CORRECTION * a) / A
    if math.isinf(volume):
        return Z + g.rho * g.c * (w / g.c) ** 2 / (2.0 * math.pi)
    return Z + 1j * g.rho * g.c**2 / (w * volume)


def parallel(Ta: np.ndarray, Tb: np.ndarray) -> np.ndarray:
    """T-matrix (..., 2, 2) of two 2-ports side by side between the same two planes (same
    p at each plane, volume velocities adding): their admittance matrices
    ``[U_in, U_out] = Y [p_in, p_out]``, ``Y = [[-A/B, 1/B], [C - D A/B, D/B]]`` of
    ``T = [[A, B], [C, D]]``, add. Needs B != 0 in both (a 2-port that lets flow through)."""

    def admittance(T):
        A, B, C, D = T[..., 0, 0], T[..., 0, 1], T[..., 1, 0], T[..., 1, 1]
        return -A / B, 1.0 / B, C - D * A / B, D / B

    y11, y12, y21, y22 = (a + b for a, b in zip(admittance(Ta), admittance(Tb)))
    out = np.empty(np.broadcast_shapes(Ta.shape, Tb.shape), dtype=complex)
    out[..., 0, 0] = -y11 / y12
    out[..., 0, 1] = 1.0 / y12
    out[..., 1, 0] = y21 - y22 * y11 / y12
    out[..., 1, 1] = y22 / y12
    return out


def microphone_error(core: Core, lab: LabEffects, omega) -> np.ndarray:
    """``E`` (m, 2, 2): the face state that the two-microphone wave decomposition of the
    mismatched pair reports is ``E (p, U)`` of the true one (module docstring).

    Plane waves in the measurement tube (the reference's duct at T_cold, radius of the
    core's tube, :func:`tawarp.reference.duct_waves`): the pressure at a microphone at
    signed distance x from its face (+ downstream of x6, - upstream of x1) is
    ``p(x) = cos(k x) p + i Zc sin(k x) U``, i.e. ``p_mics = P (p, U)``; the far microphone
    reads G times its pressure, and the decomposition (exact otherwise) inverts P:
    ``E = P^-1 diag(1, G) P``."""
    w = np.atleast_1d(np.asarray(omega, dtype=float))
    k, Zc = duct_waves(core.gas.name, core.gas.p_mean, core.gas.T_cold, core.radius, w)
    side = 1.0 if lab.mic_pair == "downstream" else -1.0
    P = np.empty(w.shape + (2, 2), dtype=complex)
    for m, x in enumerate((side * lab.mic_distance, side * (lab.mic_distance + lab.mic_spacing))):
        P[:, m, 0] = np.cos(k * x)
        P[:, m, 1] = 1j * Zc * np.sin(k * x)
    G = np.array([[1.0, 0.0], [0.0, lab.mic_gain * np.exp(1j * lab.mic_phase)]])
    return np.linalg.solve(P, G @ P)


def _leak_segment(core: Core, lab: LabEffects) -> int | None:
    if not lab.leak_diameter:
        return None
    pos = core.positions()
    for i, seg in enumerate(core.segments):
        if pos[i] < lab.leak_position < pos[i + 1]:
            if seg.kind != "duct":
                raise ValueError(
                    f"leak_position {lab.leak_position} m lies in the porous segment {seg.name!r}; "
                    "place the leak in a duct"
                )
            return i
    raise ValueError(f"leak_position {lab.leak_position} m is not inside the core (0 to {pos[-1]} m)")


def lab_segment_matrices(
    core: Core, lab: LabEffects, freqs, heat_input: float = 0.0, rtol: float = 1e-12, heat_tol: float = HEAT_TOL
) -> list[np.ndarray]:
    """T-matrix of every segment with the lab effects of the core (not the microphones),
    a list of complex arrays (m, 2, 2), raw SI units; arguments as
    :func:`tawarp.reference.segment_transfer_matrices`. A segment at uniform T_cold with
    uniform porosity uses the closed form, every other is integrated by DOP853."""
    f = np.atleast_1d(np.asarray(freqs, dtype=float))
    if f.ndim != 1 or np.any(f <= 0):
        raise ValueError("freqs must be positive frequencies [Hz], scalar or 1-D")
    w = 2.0 * np.pi * f
    hs = lab_heat_profile(core, lab, heat_input, heat_tol)
    heated = set(hs.indices) if heat_input != 0.0 else set()
    pos = core.positions()
    leak_at = _leak_segment(core, lab)
    out = []
    for i, seg in enumerate(core.segments):
        profile = hs.segment_profile(i)

        def piece(s: Segment, x0: float, uniform_porosity: bool = False, i=i, profile=profile) -> np.ndarray:
            phi = None if uniform_porosity else porosity_profile(core, lab, s)
            if i not in heated and phi is None:
                return _uniform_matrix(core, s, w)
            return np.stack([_ode_matrix(core, s, x0, wk, profile, rtol, phi) for wk in w])

        if lab.bypass_gap and seg.name == lab.gap_segment:
            share = gap_area_fraction(core, lab.bypass_gap)
            inner = dataclasses.replace(seg, porosity=seg.porosity * (1.0 - share))
            slit = Segment(
                "bypass_gap",
                "porous",
                seg.length,
                pore_model="plates",
                porosity=share,
                pore_radius=lab.bypass_gap / 2.0,
                tortuosity=1.0,
            )
            out.append(parallel(piece(inner, pos[i]), piece(slit, pos[i], uniform_porosity=True)))
        elif i == leak_at:
            xl = lab.leak_position
            first = piece(dataclasses.replace(seg, length=xl - pos[i]), pos[i])
            second = piece(dataclasses.replace(seg, length=pos[i + 1] - xl), xl)
            Y = 1.0 / side_branch_impedance(
                core.gas.name,
                core.gas.p_mean,
                float(profile(xl)[0]),
                lab.leak_diameter,
                lab.leak_length,
                w,
                lab.leak_volume,
            )
            shunt = np.zeros(w.shape + (2, 2), dtype=complex)
            shunt[:, 0, 0] = shunt[:, 1, 1] = 1.0
            shunt[:, 1, 0] = -Y
            out.append(second @ shunt @ first)
        else:
            out.append(piece(seg, pos[i]))
    return out


def lab_transfer_matrix(
    core: Core, lab: LabEffects, freqs, heat_input: float = 0.0, rtol: float = 1e-12, heat_tol: float = HEAT_TOL
) -> np.ndarray:
    """The core T-matrix (m, 2, 2) that the rig with the lab effects measures:
    ``T = T_last ... T_first`` of :func:`lab_segment_matrices`, then the microphones:
    ``E_down T E_up^-1`` (:func:`microphone_error`; the mismatched pair's E, identity for
    the other)."""
    mats = lab_segment_matrices(core, lab, freqs, heat_input, rtol, heat_tol)
    T = mats[0]
    for M in mats[1:]:
        T = M @ T
    if lab.microphones_on:
        E = microphone_error(core, lab, 2.0 * np.pi * np.atleast_1d(np.asarray(freqs, dtype=float)))
        T = E @ T if lab.mic_pair == "downstream" else T @ np.linalg.inv(E)
    return T
