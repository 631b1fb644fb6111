"""Where the model holds, and what the engine says when a parameter set leaves it.

The forward model of docs/physics.md is a plane-wave, linear, steady-heat model with
tabulated gas laws. Each check names the parameter set (its index in the batch and its
varying values) so that a sweep or a fit over thousands of sets says which one failed:

- **Refused before solving** (:class:`ModelValidityError`, a :class:`~tawarp.model.core.CoreError`):
  a value outside its trusted range (each field's in
  :data:`tawarp.model.fields.TRUSTED_RANGE`, checked with the physical range; frequencies
  outside [:data:`F_MIN`, :data:`F_MAX`], heat inputs above :data:`Q_MAX`;
  docs/trusted_ranges.md); a pore radius wider than the tube; heat put in with no heat
  sink (every thermal ``h`` and ``h_convection`` zero: the heat model's ends are
  adiabatic, so no steady state exists); an adaptive Magnus cascade that would need more
  than :data:`MAX_CELLS` cells in a segment (a segment thousands of wavelengths or
  heat-decay lengths long: the run would not end; the kernels cap the count and the
  engine refuses the set, whatever the path that sized it).
- **Refused after solving** (:class:`NonFiniteError`): a T-matrix or temperature that is
  not finite. The usual cause is overflow: a stack so lossy (pore radius far below the
  viscous penetration depth, a huge tortuosity or length) that its matrix entries exceed
  the float64 range. Such a core transmits nothing measurable.
- **Checked after solving** (:func:`check_precision`): at uniform temperature (no heat
  input) the core is a reciprocal two-port and ``det T = 1`` exactly; the computed
  deviation, relative to the size of the products it cancels (``|Tpp Tuu| + |Tpu Tup|``),
  is the relative error that rounding left in the cascade's entries. Above the requested
  tolerance it is a :class:`ValidityWarning`, above :data:`PRECISION_LOST` a
  :class:`PrecisionLostError`. (The unscaled ``|det T - 1|`` is no measure: in a strongly
  attenuating core the products ``Tpp Tuu`` and ``Tpu Tup`` are huge and their float64
  difference misses 1 by eps times their size, 8e45 for the RVC foam with 1 um pores,
  whose entries equal the reference to 1e-13: tests/test_validity_precision.py.)
- **Warned** (:class:`ValidityWarning`): a temperature above :data:`T_LIMIT` (the gas
  laws are Sutherland fits to about 1000-1500 K, and the paper's linear heat model
  ignores radiation and convection that dominate long before); a frequency above the
  plane-wave cut-on of the tube, ``f_c = 1.8412 c / (2 pi R)`` at the cold temperature
  (the first non-planar mode propagates above it).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from ..kernels.forward import MAX_CELLS
from .core import Core, CoreError
from .gas import GASES

#: Highest temperature [K] the model is trusted at (module doc).
T_LIMIT = 1500.0
#: First zero of J1': the (1,1) mode of a circular duct cuts on at k R = 1.8412.
CUT_ON_KR = 1.8412
#: Relative error (:func:`check_precision`) beyond which no significant digit is left.
PRECISION_LOST = 0.1
#: Frequency range [Hz] the model is evaluated in. Above: the plane-wave cut-on of a tube
#: of 0.1 mm radius in air at 293 K is 1 MHz; far beyond, the phase of a metre of duct
#: (~2e5 rad at 1e7 Hz) leaves too few digits in its sine for the rest of the answer.
#: Below: checked against the reference's closed forms to 1e-20 Hz; at 1e-300 Hz the
#: pore functions' arguments underflow.
F_MIN, F_MAX = 1e-9, 1e7
#: Largest heat input [W] the model is evaluated at: a megawatt heats a bundled core's
#: hot exchanger to ~1e6 K at its own h (~1e9 K at h = 0.01), far beyond
#: :data:`T_LIMIT` already; at 1e11 W the gas laws' float64 arithmetic gave NaN.
Q_MAX = 1e6


class ModelValidityError(CoreError):
    """A parameter set lies outside what the model can describe (module doc)."""


class NonFiniteError(ModelValidityError):
    """The engine produced a non-finite result for some parameter sets."""


class PrecisionLostError(ModelValidityError):
    """Rounding left no significant digit in some parameter sets' T-matrices."""


class ValidityWarning(UserWarning):
    """A parameter set is at the edge of the model's validity (module doc)."""


def describe_set(i: int, heat_input: np.ndarray, values: dict[str, np.ndarray]) -> str:
    """``set i (heat_input = .. W, stack.porosity = .., ...)`` for messages."""
    parts = [f"heat_input = {heat_input[i]:g} W"] + [f"{k} = {v[i]:.6g}" for k, v in values.items()]
    return f"set {i} ({', '.join(parts)})"


def _value(core: Core, values: dict, name: str, n: int) -> np.ndarray:
    v = values.get(name)
    return np.broadcast_to(np.asarray(core.get(name) if v is None else v, dtype=float), (n,))


def check_sets(
    core: Core, heat_input: np.ndarray, values: dict[str, np.ndarray], freqs=None, cell_density: float | None = None
) -> None:
    """Refuse parameter sets outside the model before solving (module doc).

    ``values`` {name: (n,)} are the varying parameters, ``heat_input`` (n,) [W]; ``freqs``
    [Hz] and ``cell_density`` (adaptive cells; None when the cells are fixed) size the
    cascade check."""
    n = heat_input.shape[0]
    if n == 0:
        return
    R = _value(core, values, "tube.radius", n)
    for s in core.segments:
        if s.is_porous:
            r = _value(core, values, f"{s.name}.pore_radius", n)
            bad = np.flatnonzero(r > R)
            if bad.size:
                i = int(bad[0])
                raise ModelValidityError(
                    f"{core.source}: {describe_set(i, heat_input, values)}: {s.name}.pore_radius = {r[i]:.4g} m is "
                    f"wider than the tube (radius {R[i]:.4g} m); {bad.size} of {n} sets"
                )
            gap = _value(core, values, f"{s.name}.bypass_gap", n)
            bad = np.flatnonzero(gap >= R)
            if bad.size:
                i = int(bad[0])
                raise ModelValidityError(
                    f"{core.source}: {describe_set(i, heat_input, values)}: {s.name}.bypass_gap = {gap[i]:.4g} m is "
                    f"not narrower than the tube (radius {R[i]:.4g} m); {bad.size} of {n} sets"
                )
    thermal = [core.segments[k] for k in core.thermal_indices]
    if thermal:
        sink = sum(
            _value(core, values, f"{s.name}.h", n) + _value(core, values, f"{s.name}.h_convection", n) for s in thermal
        )
        bad = np.flatnonzero((heat_input > 0) & (sink <= 0))
        if bad.size:
            raise ModelValidityError(
                f"{core.source}: {describe_set(int(bad[0]), heat_input, values)}: heat is put in but every thermal "
                f"segment has h = 0 and h_convection = 0; with adiabatic ends no steady temperature exists "
                f"(give some segment h > 0); {bad.size} of {n} sets"
            )
    if freqs is not None and cell_density is not None and thermal:
        c = cold_sound_speed(core, values, n)
        w = 2 * math.pi * float(np.max(freqs))
        for s in thermal:
            cells = cell_density * w * _value(core, values, f"{s.name}.length", n) / c
            bad = np.flatnonzero(cells > MAX_CELLS)
            if bad.size:
                i = int(bad[0])
                raise ModelValidityError(
                    f"{core.source}: {describe_set(i, heat_input, values)}: {s.name} is {cells[i] / cell_density:.3g} "
                    f"radians of acoustic phase long at {np.max(freqs):g} Hz: the adaptive cascade would need "
                    f"more than {MAX_CELLS} cells (pass ForwardSettings(cells=...) to force a count)"
                )


def check_frequencies(freqs: np.ndarray) -> None:
    """Refuse frequencies [Hz] outside [:data:`F_MIN`, :data:`F_MAX`]
    (:class:`ModelValidityError`, naming the first one): beyond, the cascade's cell count
    and its phases leave the float64 range the kernels are trusted in
    (docs/trusted_ranges.md)."""
    f = np.asarray(freqs, dtype=float)
    bad = np.flatnonzero(~(np.isfinite(f) & (f >= F_MIN) & (f <= F_MAX)))
    if bad.size:
        raise ModelValidityError(
            f"frequency {f[bad[0]]:g} Hz lies outside the trusted range [{F_MIN:g}, {F_MAX:g}] "
            f"Hz (docs/trusted_ranges.md); {bad.size} of {f.size} frequencies"
        )


def check_heat_inputs(heat_input: np.ndarray) -> None:
    """Refuse heat inputs [W] outside [0, :data:`Q_MAX`] (:class:`ModelValidityError`,
    naming the first one; docs/trusted_ranges.md)."""
    q = np.asarray(heat_input, dtype=float)
    bad = np.flatnonzero(~(np.isfinite(q) & (q >= 0) & (q <= Q_MAX)))
    if bad.size:
        raise ModelValidityError(
            f"heat input {q.flat[bad[0]]:g} W lies outside the trusted range [0, {Q_MAX:g}] W "
            f"(docs/trusted_ranges.md); {bad.size} of {q.size} heat inputs"
        )


def precision_error(T: np.ndarray) -> np.ndarray:
    """Relative rounding error (k,) of k sets of reciprocal T-matrices ``T`` (k, m, 2, 2):
    the largest over the m frequencies of ``|det T - 1| / (|Tpp Tuu| + |Tpu Tup|)``
    (module doc), each matrix first divided by its largest entry (no product overflows)."""
    s = np.abs(T).max(axis=(-2, -1), keepdims=True)
    s = np.where(s > 0, s, 1.0)
    M = T / s
    a, b, c, d = M[..., 0, 0], M[..., 0, 1], M[..., 1, 0], M[..., 1, 1]
    with np.errstate(over="ignore", under="ignore", invalid="ignore"):
        one = 1.0 / s[..., 0, 0] ** 2  # det of the scaled matrix; underflows to 0 beside rounding
        rel = np.abs(a * d - b * c - one) / (np.abs(a * d) + np.abs(b * c))
    return np.max(rel, axis=1, initial=0.0)


def check_precision(
    core: Core, heat_input: np.ndarray, values: dict[str, np.ndarray], T: np.ndarray, tolerance: float, offset: int = 0
) -> None:
    """Warn (:class:`ValidityWarning`) for the unheated sets ``offset .. offset + k`` of
    ``T`` (k, m, 2, 2) whose :func:`precision_error` exceeds ``tolerance``; raise
    :class:`PrecisionLostError` above :data:`PRECISION_LOST`. Heated sets, and those with
    imposed temperatures that vary along a segment, are left to the
    cells' error estimate: their exact determinant is the cascade's own exp(integral of
    tr A), not known here; their products are those of the same kernels."""
    k = T.shape[0]
    uniform = heat_input[offset : offset + k] == 0
    for seg in core.segments:  # imposed temperatures that differ at a segment's ends: det T != 1
        if seg.imposed:
            t0, t1 = (
                np.broadcast_to(values.get(f"{seg.name}.{f}", getattr(seg, f)), heat_input.shape)
                for f in ("T_start", "T_end")
            )
            uniform &= t0[offset : offset + k] == t1[offset : offset + k]
    unheated = np.flatnonzero(uniform)
    if not unheated.size:
        return
    err = precision_error(T[unheated])
    worst = int(np.argmax(err))
    i = offset + int(unheated[worst])
    lost = np.flatnonzero(err > PRECISION_LOST)
    where = f"{core.source}: {describe_set(i, heat_input, values)}"
    if lost.size:
        raise PrecisionLostError(
            f"{where}: rounding in the T-matrix cascade left a relative error of {err[worst]:.2g} (det T = 1 checked "
            f"at uniform temperature; {lost.size} of {k} sets): no significant digit is left; the core attenuates "
            f"too strongly for float64 (docs/trusted_ranges.md)"
        )
    above = np.flatnonzero(err > tolerance)
    if above.size:
        warnings.warn(
            f"{where}: rounding in the T-matrix cascade leaves a relative error of {err[worst]:.2g} above "
            f"the tolerance {tolerance:g} (det T = 1 checked at uniform temperature; {above.size} of {k} "
            f"sets)",
            ValidityWarning,
            stacklevel=3,
        )


def cold_sound_speed(core: Core, values: dict, n: int) -> np.ndarray:
    """Adiabatic sound speed [m/s] at the cold temperature, per set."""
    g = GASES[core.gas.name]
    return np.sqrt(g.gamma * g.R_gas * _value(core, values, "gas.T_cold", n))


def check_results(
    core: Core,
    heat_input: np.ndarray,
    values: dict[str, np.ndarray],
    T: np.ndarray | None,
    theta: np.ndarray,
    offset: int = 0,
    freqs=None,
) -> None:
    """Raise :class:`NonFiniteError` for non-finite T-matrices ``T`` (k, m, 2, 2) or nodal
    temperatures ``theta`` (k, nodes) of the sets ``offset .. offset + k``; warn
    (:class:`ValidityWarning`) above :data:`T_LIMIT` and above the cut-on frequency."""
    k = theta.shape[0]
    rows = slice(offset, offset + k)
    finite = np.all(np.isfinite(theta), axis=1)
    if T is not None:
        finite &= np.all(np.isfinite(T.reshape(k, -1)), axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        i = offset + int(bad[0])
        raise NonFiniteError(
            f"{core.source}: {describe_set(i, heat_input, values)} gives a non-finite "
            f"{'T-matrix' if T is not None else 'temperature'} ({bad.size} of {k} sets in this chunk); usually an "
            f"overflow: the core attenuates by more than e^700 (a pore radius far below the viscous penetration "
            f"depth, a huge tortuosity or length), so it transmits nothing measurable"
        )
    T_cold = _value(core, values, "gas.T_cold", heat_input.shape[0])[rows]
    T_max = T_cold + (theta.max(axis=1) if theta.shape[1] else 0.0)
    hot = np.flatnonzero(T_max > T_LIMIT)
    if hot.size:
        i = offset + int(hot[0])
        warnings.warn(
            f"{core.source}: {describe_set(i, heat_input, values)}: T_max = {T_max[hot[0]]:.0f} K is above "
            f"the model's limit of {T_LIMIT:g} K ({hot.size} of {k} sets); the gas laws and the linear heat "
            f"model are not trusted there",
            ValidityWarning,
            stacklevel=3,
        )
    if freqs is not None and offset == 0:
        R = _value(core, values, "tube.radius", heat_input.shape[0])
        f_c = CUT_ON_KR * cold_sound_speed(core, values, heat_input.shape[0]) / (2 * math.pi * R)
        above = np.flatnonzero(float(np.max(freqs)) > f_c)
        if above.size:
            i = int(above[0])
            warnings.warn(
                f"{core.source}: {describe_set(i, heat_input, values)}: frequencies up to "
                f"{np.max(freqs):g} Hz exceed the plane-wave cut-on {f_c[i]:.0f} Hz of the tube; the "
                f"plane-wave model does not hold there",
                ValidityWarning,
                stacklevel=3,
            )
