"""The independent reference (tawarp.reference) reads every field of a core or refuses it with
a ValueError that names it: it never answers for a different core than the one it is given.

The fields are enumerated from the one table (tawarp.model.fields) and the core's dataclasses,
so a field added there is checked here without a new test: each is moved away from its value
on every kind of segment that takes it, and the reference's T-matrix and heat profile must
change, or the reference must refuse the core naming ``SEGMENT.FIELD``.
"""

from __future__ import annotations

import dataclasses
import inspect

import numpy as np
import pytest

from tawarp import reference as ref
from tawarp.model.core import Core, CoreError, Gas, Segment, load_core
from tawarp.model.effects import with_ambient_exchangers
from tawarp.model.fields import GLOBAL_FIELD_TABLE, SEGMENT_FIELD_TABLE, takes
from tawarp.model.forward import HEAT_ONLY_FIELDS
from tawarp.reference_effects import LabEffects, lab_transfer_matrix

Q = 40.0
FREQS = np.array([60.0, 300.0])
#: DOP853 tolerance: a change that the reference reads moves its answer far above it
RTOL = 1e-8
#: the smallest relative change of the answer that counts as read
READ = 1e-6


def _base() -> Core:
    """Every kind of segment: ducts and porous segments, thermal and not (the ambient
    exchangers); a wall on the thermal segments, in perfect contact, so that its
    ``wall_resistance`` acts."""
    core = with_ambient_exchangers(load_core("ceramic"), 5e-3)
    return core.replace(**{f"{core.segments[i].name}.wall_conductance": 0.05 for i in core.thermal_indices})


CORE = _base()


def _cases():
    """(field, segment or None for a global, {parameter: value}): each field once on the
    first segment of each structure (porous or not, thermal or not) that takes it; an
    imposed temperature on every non-thermal structure (both ends: a segment has both or
    neither)."""
    out = [(f.name, None, {name: CORE.get(name) * 1.2}) for name, f in GLOBAL_FIELD_TABLE.items()]
    for f in SEGMENT_FIELD_TABLE:
        seen = set()
        for s in CORE.segments:
            structure = (s.is_porous, s.thermal)
            if structure in seen:
                continue
            if f.applies == "imposed":
                if s.thermal:
                    continue
                change = {f"{s.name}.T_start": 350.0, f"{s.name}.T_end": 400.0}
            elif takes(f, s.is_porous, s.thermal):
                change = _moved(s, f)
            else:
                continue
            seen.add(structure)
            out.append((f.name, s.name, change))
    return out


def _moved(s: Segment, f) -> dict:
    """``SEGMENT.FIELD`` moved to the first valid value of x 1.2, + its scale, - its scale."""
    name = f"{s.name}.{f.name}"
    v = CORE.get(name)
    for new in (v * 1.2, v + f.scale, v - f.scale):
        if new == v:
            continue
        try:
            CORE.replace(**{name: new})
        except CoreError:
            continue
        return {name: new}
    raise AssertionError(f"{name}: no valid value near {v}")


CASES = _cases()


def _answer(core: Core, heat_input: float):
    """The reference's T-matrix and, with heat input, its temperature on 41 points."""
    T = ref.transfer_matrix(core, FREQS, heat_input, rtol=RTOL)
    if heat_input == 0.0:
        return T, np.zeros(0)
    x = np.linspace(0.0, core.positions()[-1], 41)
    return T, ref.heat_profile(core, heat_input).temperature(x)


BASE = {q: _answer(CORE, q) for q in (0.0, Q)}


def _change(a, b) -> float:
    return max(float(np.max(np.abs(x - y) / np.maximum(np.abs(y), 1e-300))) if y.size else 0.0 for x, y in zip(a, b))


def test_every_field_of_the_table_is_enumerated():
    """Every segment field of tawarp.model.fields is moved on at least one segment."""
    assert {c[0] for c in CASES} >= {f.name for f in SEGMENT_FIELD_TABLE}


@pytest.mark.parametrize("heat_input", [Q, 0.0])
@pytest.mark.parametrize("field, segment, change", CASES, ids=[f"{c[1]}.{c[0]}" for c in CASES])
def test_a_field_is_read_or_refused_by_name(field, segment, change, heat_input):
    """Every field moved changes the reference's T-matrix or temperature by more than 1e-6
    (relative), or the reference refuses the core with a ValueError naming ``SEGMENT.FIELD``;
    but a field that only the heat solve reads (tawarp.model.forward.HEAT_ONLY_FIELDS: the
    kernels read it nowhere else), without heat input or outside the heat model's segments,
    acts on nothing: the reference's answer stays bit for bit and it is not refused."""
    core = CORE.replace(**change)
    inert = segment is not None and field in HEAT_ONLY_FIELDS and not (heat_input and CORE.segment(segment).thermal)
    try:
        got = _answer(core, heat_input)
    except ValueError as e:
        assert segment is not None and f"{segment}.{field} = " in str(e), str(e)
        assert "tawarp.reference does not model" in str(e) and "it models" in str(e)
        assert not inert, f"{segment}.{field} refused where it acts on nothing"
        return
    if inert:
        for a, b in zip(got, BASE[heat_input]):
            np.testing.assert_array_equal(a, b)
    else:
        assert _change(got, BASE[heat_input]) > READ, f"{segment}.{field} moved but the reference's answer did not"


def test_the_base_models_fields_are_read():
    """The paper's own fields (no neutral value) and the globals are never refused."""
    base = {f.name for f in SEGMENT_FIELD_TABLE if not f.is_effect and f.applies != "imposed"}
    for field, segment, change in CASES:
        if field in base or segment is None:
            _answer(CORE.replace(**change), Q)


#: entry points of the reference that take a core, called with it
CALLS = {
    "segment_conductivity": lambda c: ref.segment_conductivity(c, "stack"),
    "HeatSolution": lambda c: ref.HeatSolution(c, Q),
    "heat_profile_exact": lambda c: ref.heat_profile_exact(c, Q),
    "energy_balance": lambda c: ref.energy_balance(c, Q),
    "NonlinearHeatSolution": lambda c: ref.NonlinearHeatSolution(c, Q),
    "FieldHeatSolution": lambda c: ref.FieldHeatSolution(c, Q),
    "heat_profile": lambda c: ref.heat_profile(c, Q),
    "segment_transfer_matrices": lambda c: ref.segment_transfer_matrices(c, FREQS, 0.0),
    "transfer_matrix": lambda c: ref.transfer_matrix(c, FREQS, 0.0),
    "transfer_matrix_omega": lambda c: ref.transfer_matrix_omega(c, 2 * np.pi * FREQS * (1 + 0.01j), 0.0),
    "dimensionless_transfer": lambda c: ref.dimensionless_transfer(c, FREQS, 0.0),
}
#: entry points that take a core but answer about its structure, not with the model
STRUCTURAL = {"wall_field_indices", "tied_walls", "core_wall_fields"}


def _takes_a_core(obj) -> bool:
    try:
        return "core" in inspect.signature(obj).parameters
    except (TypeError, ValueError):
        return False


def test_every_entry_point_that_takes_a_core_refuses_a_bypass_gap():
    """Every name of tawarp.reference.__all__ that takes a core is either a model entry
    point (:data:`CALLS`) or structural; each model entry point refuses a stack with a
    bypass gap (it changes the acoustics and the conductivity) with the message that names
    it, its value and the reference's own gap."""
    entry = {name for name in ref.__all__ if _takes_a_core(getattr(ref, name))}
    assert entry == set(CALLS) | STRUCTURAL
    gap = CORE.replace(**{"stack.bypass_gap": 2e-4})
    want = (
        "does not model stack.bypass_gap = 0.0002 m; it models no gap; use "
        "tawarp.reference_effects.LabEffects(bypass_gap=0.0002, gap_segment='stack')"
    )
    for name, call in CALLS.items():
        with pytest.raises(ValueError) as refused:
            call(gap)
        assert want in str(refused.value), name
    assert ref.wall_field_indices(gap) == [] and ref.tied_walls(gap) is gap


def test_contact_resistance_points_to_the_labs_contact():
    """The refusal of a contact resistance gives the lab's contact at that interface: the
    thermal segment before it is ``contact_left``."""
    core = CORE.replace(**{"hot_hx.contact_resistance": 3e-4})
    with pytest.raises(ValueError, match=r"LabEffects\(contact_resistance=0\.0003, contact_left='stack'\)"):
        ref.heat_profile(core, Q)


def test_the_lab_extension_refuses_the_cores_fields_and_keeps_its_own():
    """The lab extension reads the core through the reference: a core's limp frame is
    refused there too, while its own effects (LabEffects) on a core without them work."""
    core = load_core("ceramic")
    with pytest.raises(ValueError, match=r"stack\.frame_mobility = 0\.01 m\^3/kg; it models a rigid frame"):
        lab_transfer_matrix(core.replace(**{"stack.frame_mobility": 0.01}), LabEffects(), FREQS, 0.0)
    lab = LabEffects(bypass_gap=2e-4, contact_resistance=3e-4, contact_left="stack")
    T = lab_transfer_matrix(core, lab, FREQS, Q, rtol=RTOL)
    assert _change((T,), (ref.transfer_matrix(core, FREQS, Q, rtol=RTOL),)) > READ


#: attributes of the core's dataclasses that are not model parameters (tawarp.model.fields)
#: and what the reference does with them
STRUCTURE = {
    Segment: {
        "name": "names the segment",
        "kind": "duct or porous (_pore)",
        "pore_model": "selects the pore functions (thermoviscous_function, the screens' correlations)",
        "aspect_ratio": "the rectangular channels' shape (Segment.pore_shape)",
        "outer_radius_ratio": "the pin arrays' shape (Segment.pore_shape)",
        "thermal": "part of the heat model",
        "heater": "takes the heat input",
    },
    Gas: {"name": "the gas constants (GASES)"},
    Core: {
        "segments": "the cascade",
        "gas": "the gas",
        "source": "names the core in errors",
        "pinned": "a fit's setting",
        "priors": "a fit's setting",
    },
}


def test_every_attribute_of_a_core_is_a_field_or_structure():
    """A new attribute of Segment, Gas or Core must enter tawarp.model.fields (and then the
    enumeration above) or be named here with what the reference does with it."""
    fields = {f.name for f in SEGMENT_FIELD_TABLE} | {f.name for f in GLOBAL_FIELD_TABLE.values()}
    for cls, structure in STRUCTURE.items():
        for a in dataclasses.fields(cls):
            assert a.name in fields or a.name in structure, f"{cls.__name__}.{a.name}: classify it"
