"""The core description: TOML loading, validation against the parameter table, names."""

import numpy as np
import pytest

from tawarp.model.core import (
    CoreError,
    Segment,
    bundled_cores,
    core_from_dict,
    dump_core,
    load_core,
    paper_cores,
    segment_parameter_fields,
)
from tawarp.model.fields import SEGMENT_FIELD_TABLE, takes


BAD_CORES = [
    ("stack.porosity", {"porosity": 1.3}, "porosity"),
    ("pore radius", {"pore_radius": -1e-4}, "pore_radius"),
    ("nan", {"h": float("nan")}, "h"),
    ("unknown key", {"porosiy": 0.5}, "porosiy"),
]


@pytest.mark.parametrize("label, change, key", BAD_CORES)
def test_bad_segment_values_name_the_key(label, change, key):
    d = load_core("ceramic").to_dict()
    d["segment"][1].update(change)
    with pytest.raises(CoreError, match=key) as err:
        core_from_dict(d, "bad.toml")
    assert "bad.toml" in str(err.value) and "'stack'" in str(err.value)


def test_core_structure_errors(tmp_path):
    d = load_core("ceramic").to_dict()
    d["segment"][2].pop("heater")
    with pytest.raises(CoreError, match="heater"):
        core_from_dict(d, "x.toml")
    d = load_core("ceramic").to_dict()
    d["segment"][3]["thermal"] = False  # tbt no longer thermal, but duct_right not either: still contiguous
    d["segment"][4].update(thermal=True, h=0.2)
    with pytest.raises(CoreError, match="contiguous"):
        core_from_dict(d, "x.toml")
    d = load_core("ceramic").to_dict()
    d["segment"][0]["porosity"] = 0.5
    with pytest.raises(CoreError, match="duct"):
        core_from_dict(d, "x.toml")
    p = tmp_path / "broken.toml"
    p.write_text("[gas\nname = 'air'")
    with pytest.raises(CoreError, match="broken.toml"):
        load_core(p)


@pytest.mark.parametrize("f", [f for f in SEGMENT_FIELD_TABLE if f.applies != "thermal_porous"], ids=lambda f: f.name)
def test_every_field_rejects_a_value_outside_its_range(f):
    """Validation reads the table: a value just outside each field's physical range is
    refused with the file, the segment and the field's unit in the message."""
    d = load_core("ceramic").to_dict()
    seg = d["segment"][1]  # the stack: porous and thermal, takes every field but radiative only as thermal porous
    seg[f.name] = f.lower if f.lower_open else f.lower - 1.0
    with pytest.raises(CoreError) as err:
        core_from_dict(d, "bad.toml")
    msg = str(err.value)
    assert "bad.toml" in msg and "'stack'" in msg and f.name in msg and f.unit in msg


def test_parameter_names_follow_the_table():
    """A duct has its length; a thermal duct h and the thermal effects; a porous
    segment its geometry and the porous effects; a segment with imposed temperatures
    T_start and T_end; in the table's order."""
    duct = Segment("d", "duct", 0.03)
    hot_duct = Segment("t", "duct", 0.1, thermal=True, h=0.2)
    stack = Segment("s", "porous", 0.04, porosity=0.8, pore_radius=1e-4, thermal=True, h=50.0)
    assert segment_parameter_fields(duct) == ("length",)
    assert segment_parameter_fields(hot_duct) == (
        "length",
        "h",
        "conductivity_exponent",
        "h_convection",
        "wall_conductance",
        "wall_resistance",
        "end_conductance",
        "contact_resistance",
    )
    assert segment_parameter_fields(stack) == tuple(f.name for f in SEGMENT_FIELD_TABLE if f.applies != "imposed")
    imposed = Segment("i", "porous", 0.04, porosity=0.8, pore_radius=1e-4, T_start=300.0, T_end=600.0)
    assert segment_parameter_fields(imposed)[-2:] == ("T_start", "T_end")
    passive = Segment("p", "porous", 0.04, porosity=0.8, pore_radius=1e-4)
    assert "radiative_conductivity" not in segment_parameter_fields(passive)
    assert all(takes(f, True, False) for f in SEGMENT_FIELD_TABLE if f.name in segment_parameter_fields(passive))


@pytest.mark.parametrize("name", bundled_cores())
def test_toml_round_trip_is_exact(name, tmp_path):
    core = load_core(name)
    p = tmp_path / f"{name}.toml"
    p.write_text(dump_core(core))
    again = load_core(p)
    assert again.segments == core.segments and again.gas == core.gas and again.radius == core.radius


def test_get_and_replace_by_parameter_name():
    core = load_core("ceramic")
    c2 = core.replace(**{"stack.porosity": 0.7, "gas.T_cold": 300.0, "tube.radius": 0.02})
    assert (c2.get("stack.porosity"), c2.get("gas.T_cold"), c2.get("tube.radius")) == (0.7, 300.0, 0.02)
    assert c2.get("duct_left.pore_radius") == 0.02  # a duct's pore radius is the tube's
    np.testing.assert_allclose(c2.positions(), core.positions(), rtol=0, atol=0)
    with pytest.raises(KeyError, match="no segment named 'nope'"):
        core.get("nope.length")


def test_replace_refuses_unknown_names_by_name():
    # a misspelt parameter is a KeyError that names it, for gas fields too (was a TypeError
    # from the Gas dataclass)
    core = load_core("ceramic")
    for name in ("gas.T_hot", "stack.porosty", "tube.length"):
        with pytest.raises(KeyError, match=name.partition(".")[2] if name != "tube.length" else "tube"):
            core.replace(**{name: 1.0})
    assert core.replace(**{"gas.T_cold": 300.0}).gas.T_cold == 300.0


def test_paper_cores_are_the_papers_four_materials():
    # the thermoacoustic bundled cores are the paper's four materials; passive samples are
    # bundled too but take no heat input
    assert sorted(paper_cores()) == ["ceramic", "mesh", "nicr_foam", "rvc_foam"]
    assert set(paper_cores()) < set(bundled_cores())
    assert all(not load_core(n).thermal_indices for n in set(bundled_cores()) - set(paper_cores()))
