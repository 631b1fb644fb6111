"""The core's wall field in the independent reference (``SEGMENT.wall_resistance`` = 1/h_w
with a ``wall_conductance``; :func:`tawarp.reference.heat_profile`): the lab's two-field
BVP with the core's couplings, the kernel's profile, its limits, and the closed form's
refusal."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tawarp import reference as ref
from tawarp.model.core import load_core
from tawarp.model.forward import steady_temperature
from tawarp.reference_effects import LabEffects, LabHeatSolution, lab_heat_profile, lab_transfer_matrix

Q = 40.0
FREQS = np.array([40.0, 200.0, 400.0])
#: lam_w A_w/S [W/(m K)]; h_w of the porous parts and of the buffer tube [W/(m^2 K)], powers of
#: two apart from 1/h_w so that the core's R_w gives the lab's h_w exactly
LAM_W, H_POROUS, H_DUCT = 0.6, 256.0, 3.125


@pytest.fixture(scope="module")
def core():
    return load_core("nicr_foam")


def walled(core, lam_w=LAM_W, h_porous=H_POROUS, h_duct=H_DUCT, **extra):
    """``core`` with a wall on every thermal segment (h = inf: perfect contact, R_w 0)."""
    values = {}
    for i in core.thermal_indices:
        s = core.segments[i]
        h = h_porous if s.is_porous else h_duct
        values[f"{s.name}.wall_conductance"] = lam_w
        values[f"{s.name}.wall_resistance"] = 0.0 if math.isinf(h) else 1.0 / h
    return core.replace(**{**values, **extra})


def thermal_x(core, n=801):
    """Points across the thermal domain, off its interfaces (dtheta/dx jumps there)."""
    pos = np.array(core.positions())
    x = np.linspace(pos[1], pos[4], n)
    return x[np.all(np.abs(x[:, None] - pos[None, 1:5]) > 1e-9, axis=1)]


def test_core_wall_field_is_the_lab_wall_field(core):
    # The core's per-segment couplings solve the lab's two-field BVP: with the lab's couplings
    # the same equations, so the same profile to round-off (1e-12 of the peak rise; measured
    # 1e-16) for the gas and the wall, and the same T-matrix (1e-10 of its entries, the DOP853
    # integrations of one profile).
    lab = LabEffects(wall_conductance=LAM_W, wall_coupling_porous=H_POROUS, wall_coupling_duct=H_DUCT)
    want = lab_heat_profile(core, lab, Q)
    got = ref.heat_profile(walled(core), Q)
    x = thermal_x(core)
    peak = want.theta(x).max()
    assert np.abs(got.theta(x) - want.theta(x)).max() < 1e-12 * peak
    assert np.abs(got.dtheta(x) - want.dtheta(x)).max() < 1e-12 * np.abs(want.dtheta(x)).max()
    tbt = core.thermal_indices[-1]
    xt = x[x > core.positions()[tbt]]
    assert np.abs(got.wall_theta_in(tbt, xt) - want.wall_theta_in(tbt, xt)).max() < 1e-12 * peak
    assert abs(got.lost() / Q - 1.0) < 1e-9
    T = ref.transfer_matrix(walled(core), FREQS, Q)
    np.testing.assert_allclose(T, lab_transfer_matrix(core, lab, FREQS, Q), rtol=1e-10, atol=0)
    # the field is not the added conductivity: the buffer tube's laminar coupling leaves the
    # wall apart from the gas, and the profile several % of the peak rise off the tied one
    tied = ref.heat_profile(walled(core, h_porous=math.inf, h_duct=math.inf), Q)
    assert isinstance(tied, ref.HeatSolution)
    assert np.abs(got.theta(x) - tied.theta(x)).max() > 0.01 * peak
    assert np.abs(got.wall_theta_in(tbt, xt) - got.theta_in(tbt, xt)).max() > 1.0


@pytest.mark.parametrize("h_porous, h_duct", [(H_POROUS, H_DUCT), (math.inf, H_DUCT), (H_POROUS, math.inf)])
def test_reference_wall_field_matches_the_kernel(core, h_porous, h_duct):
    # The kernel's two-field cells are exact at the nodes for piecewise-constant coefficients,
    # its profile the exact cell solution between them (tests/test_wall_field.py): with every
    # wall a field, or the porous parts' or the buffer tube's in perfect contact (the field
    # tied to the gas where it meets them), theta and dtheta/dx within 1e-9 of the peak rise
    # and of the largest gradient (the BVP converged to ~1e-10; measured 1e-11 to 1e-10).
    c = walled(core, h_porous=h_porous, h_duct=h_duct)
    hs = ref.heat_profile(c, Q)
    x = thermal_x(core)
    values = {
        f"{c.segments[i].name}.{f}": getattr(c.segments[i], f)
        for i in c.thermal_indices
        for f in ("wall_conductance", "wall_resistance")
    }
    T, dT = steady_temperature(core, x, Q, params=values, device="cpu")
    assert np.abs(T[0] - core.gas.T_cold - hs.theta(x)).max() < 1e-9 * hs.theta(x).max()
    assert np.abs(dT[0] - hs.dtheta(x)).max() < 1e-9 * np.abs(hs.dtheta(x)).max()


def test_wall_field_ends_adiabatic_at_a_wall_that_conducts_nothing(core):
    # A wall field beside a segment whose wall conducts nothing behind a finite coupling
    # (wall_resistance > 0, wall_conductance 0) passes it no heat: the limit of a conductance
    # lam_w -> 0 there, which takes up the field's flux over its coupling length
    # sqrt(lam_w R/(2 h_w)), i.e. a flux ~ sqrt(lam_w): 10x less conductance, sqrt(10)x closer
    # (+-15 %; measured 2.95 from 3e-3 to 3e-4 W/(m K), whose coupling length of 0.1 mm the
    # collocation still resolves). A perfect contact there instead ties the field to the gas
    # (6 % of the peak off).
    end = walled(core, **{"stack.wall_conductance": 0.0})
    adiabatic = ref.heat_profile(end, Q)
    x = thermal_x(core)
    peak = adiabatic.theta(x).max()
    gaps = [
        np.abs(ref.heat_profile(end.replace(**{"stack.wall_conductance": g}), Q).theta(x) - adiabatic.theta(x)).max()
        for g in (3e-3, 3e-4)
    ]
    assert gaps[0] / gaps[1] == pytest.approx(math.sqrt(10.0), rel=0.15), gaps
    tied = ref.heat_profile(end.replace(**{"stack.wall_resistance": 0.0}), Q)
    assert gaps[1] < 0.1 * np.abs(tied.theta(x) - adiabatic.theta(x)).max()
    assert abs(adiabatic.lost() / Q - 1.0) < 1e-9 and peak > 0


def test_without_a_field_the_reference_is_unchanged_bit_for_bit(core):
    # A wall in perfect contact (wall_resistance 0) is the closed form's added conductivity,
    # and a wall_resistance without a conductance no wall at all: the numbers of the core
    # without the field. At Q = 0 nothing heats, the wall field's core is cold too.
    tied = walled(core, h_porous=math.inf, h_duct=math.inf)
    hs = ref.heat_profile(tied, Q)
    assert isinstance(hs, ref.HeatSolution)
    np.testing.assert_array_equal(
        hs.lam, [ref._material_conductivity(core, core.segments[i]) + LAM_W for i in core.thermal_indices]
    )
    loose = walled(core, lam_w=0.0)
    np.testing.assert_array_equal(ref.transfer_matrix(loose, FREQS, Q), ref.transfer_matrix(core, FREQS, Q))
    np.testing.assert_array_equal(ref.transfer_matrix(walled(core), FREQS, 0.0), ref.transfer_matrix(core, FREQS, 0.0))


def test_paths_without_the_field_refuse_it(core):
    c = walled(core)
    for call in (
        lambda: ref.heat_profile_exact(c, Q),
        lambda: ref.energy_balance(c, Q),
        lambda: ref.segment_conductivity(c, "tbt"),
        lambda: ref.NonlinearHeatSolution(c, Q),
    ):
        with pytest.raises(ValueError, match="wall_resistance"):
            call()
    with pytest.raises(ValueError, match="give the wall once"):
        LabHeatSolution(c, LabEffects(wall_conductance=0.3), Q)
    with pytest.raises(ValueError, match="contact resistance after 'hot_hx'"):
        LabHeatSolution(walled(core, h_porous=math.inf), LabEffects(contact_resistance=1e-4, contact_left="hot_hx"), Q)
