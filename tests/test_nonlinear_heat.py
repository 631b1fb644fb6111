"""Temperature-dependent conductivity (conductivity_exponent, radiative_conductivity):
the kernels' Kirchhoff-transformed heat cells against the independent
nonlinear heat BVP of the reference (scipy solve_bvp, ~1e-11 in theta) and the reference's
adaptive acoustic integration on it."""

import dataclasses

import numpy as np
import pytest

from tawarp import reference
from tawarp.model.core import load_core
from tawarp.model.forward import DEFAULT_CELL_DENSITY, ForwardSettings, steady_temperature, transfer_matrices

FREQS = np.array([30.0, 140.0, 500.0])
Q = 40.0
EFFECTS = [("conductivity_exponent", 0.5), ("radiative_conductivity", 0.3)]
CORE = load_core("ceramic")


def relative_error(Y, Yref):
    """Max over frequencies of max_c |Y - Yref| / max_c |Yref| (dimensionless coefficients)."""
    return float((np.abs(Y - Yref).max(-1) / np.abs(Yref).max(-1)).max())


def with_stack(core, **kw):
    return dataclasses.replace(
        core, segments=tuple(dataclasses.replace(s, **kw) if s.name == "stack" else s for s in core.segments)
    )


def refined(level: int) -> ForwardSettings:
    """Default settings with the heat grid and the Magnus cell density times 2^level (the
    rule alone: the error estimate would raise the coarse levels' cells)."""
    d = ForwardSettings()
    return ForwardSettings(
        nonlinear_heat_cells=d.nonlinear_heat_cells * 2**level,
        cell_density=DEFAULT_CELL_DENSITY * 2**level,
        tolerance=None,
        device="cpu",
    )


def test_reference_bvp_reduces_to_the_exact_linear_solution():
    # The BVP route with every effect off (forced) equals the closed-form piecewise solution.
    pos = CORE.positions()
    x = np.linspace(pos[1], pos[4], 1001)
    exact = reference.heat_profile_exact(CORE, Q)
    bvp = reference.NonlinearHeatSolution(CORE, Q)
    scale = exact.theta(x).max()
    assert np.abs(bvp.theta(x) - exact.theta(x)).max() < 1e-9 * scale
    assert np.abs(bvp.dtheta(x) - exact.dtheta(x)).max() < 1e-9 * np.abs(exact.dtheta(x)).max()
    assert abs(bvp.lost() - Q) < 1e-9 * Q


@pytest.mark.parametrize("field, value, Q", [e + (Q,) for e in EFFECTS] + [("conductivity_exponent", -1.0, 20.0)])
def test_profile_matches_bvp(field, value, Q):
    # (a) theta and dtheta/dx of the kernel's profile at 128 heat cells per segment within
    # 1e-7 of the BVP (fourth order: 32 cells give ~2e-6); b = -1 takes the log branch
    # (at 20 W: at 40 W its lam halves across the stack and 128 cells give 1.1e-7).
    pos = CORE.positions()
    x = np.linspace(pos[1], pos[4], 801)
    ref = reference.heat_profile(with_stack(CORE, **{field: value}), Q)
    T, dT = steady_temperature(CORE, x, Q, params={f"stack.{field}": value}, device="cpu", nonlinear_heat_cells=128)
    th_ref = ref.theta(x)
    assert np.abs(T[0] - CORE.gas.T_cold - th_ref).max() < 1e-7 * th_ref.max()
    inner = np.all(np.abs(x[:, None] - np.array(pos)[None, 1:5]) > 1e-9, axis=1)  # dT/dx jumps at interfaces
    assert np.abs(dT[0, inner] - ref.dtheta(x[inner])).max() < 1e-6 * np.abs(ref.dtheta(x)).max()


@pytest.mark.parametrize("field, value", EFFECTS)
def test_gradient_continuous_at_heat_nodes(field, value):
    # The Kirchhoff cells carry the flux U' = lam theta': dT/dx has no jump at the heat nodes
    # inside a segment (the cell-constant conductivity of old jumped by ~1 % there).
    pos = CORE.positions()
    cells = ForwardSettings().nonlinear_heat_cells
    nodes = np.linspace(pos[1], pos[2], cells + 1)[1:-1]
    eps = 1e-9 * (pos[2] - pos[1])
    _, left = steady_temperature(CORE, nodes - eps, Q, params={f"stack.{field}": value}, device="cpu")
    _, right = steady_temperature(CORE, nodes + eps, Q, params={f"stack.{field}": value}, device="cpu")
    assert np.abs(left - right).max() < 1e-7 * np.abs(left).max()


@pytest.mark.parametrize("field, value", EFFECTS)
def test_tmatrix_matches_reference_and_converges(field, value):
    # (b) <= 1e-5 at the default settings against the converged independent solution
    # (the effect itself is 3e-3 .. 2e-2); (c) the error falls monotonically, at about
    # fourth order, as the heat grid and the Magnus cells are refined 2x and 4x.
    Yref = reference.dimensionless_transfer(with_stack(CORE, **{field: value}), FREQS, Q)
    err = [
        relative_error(
            transfer_matrices(
                CORE, FREQS, Q, params={f"stack.{field}": value}, settings=refined(level)
            ).dimensionless()[0],
            Yref,
        )
        for level in range(3)
    ]
    assert err[0] < 1e-5, err
    assert err[1] < err[0] / 8 and err[2] < err[1] / 8, err
    effect = relative_error(reference.dimensionless_transfer(CORE, FREQS, Q), Yref)
    assert effect > 100 * err[0]


@pytest.mark.parametrize(
    "name, value",
    [(f"stack.{f}", v) for f, v in EFFECTS] + [("stack.conductivity_exponent", -1.0), ("tbt.h_convection", 3.0)],
)
def test_energy_balance(name, value):
    # (d) Q = heat leaked to the walls int (2 h(theta)/R) theta S dx (12-point Gauss per heat
    # cell on the kernel's profile) + heat conducted out at the ends (0: theta' = 0 there).
    cells = ForwardSettings().nonlinear_heat_cells
    g, w = np.polynomial.legendre.leggauss(12)
    pos = CORE.positions()
    lost = 0.0
    for i in CORE.thermal_indices:
        e = np.linspace(pos[i], pos[i + 1], cells + 1)
        x = (0.5 * (e[1:] - e[:-1])[:, None] * g + 0.5 * (e[1:] + e[:-1])[:, None]).ravel()
        wx = (0.5 * (e[1:] - e[:-1])[:, None] * w).ravel()
        theta = steady_temperature(CORE, x, Q, params={name: value}, device="cpu")[0][0] - CORE.gas.T_cold
        h = CORE.segments[i].h + (
            value * np.maximum(theta, 0) ** 0.25 if name == f"{CORE.segments[i].name}.h_convection" else 0.0
        )
        lost += np.sum(wx * theta * 2 * h) / CORE.radius * CORE.area
    ends = steady_temperature(CORE, [pos[1], pos[4]], Q, params={name: value}, device="cpu")[1][0]
    assert np.abs(ends).max() < 1e-9 * Q
    assert abs(lost - Q) < 1e-9 * Q
