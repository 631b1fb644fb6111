"""Property-based tests of the core loader: whatever a core file holds, the
loader returns a valid Core or raises CoreError naming the file; never another exception."""

import copy
import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tawarp.model.core import Core, CoreError, core_from_dict, load_core

BASE = load_core("ceramic").to_dict()
SOURCE = "fuzz.toml"
# every value a TOML file can hold
toml_scalars = st.one_of(st.text(max_size=8), st.integers(-10**6, 10**6), st.floats(allow_nan=True),
                         st.booleans())
toml_values = st.recursive(toml_scalars, lambda inner: st.one_of(st.lists(inner, max_size=3),
                                                                 st.dictionaries(st.text(max_size=6), inner, max_size=3)),
                           max_leaves=6)


def _paths(d, prefix=()):
    if isinstance(d, dict):
        for k, v in d.items():
            yield prefix + (k,)
            yield from _paths(v, prefix + (k,))
    elif isinstance(d, list):
        for i, v in enumerate(d):
            yield prefix + (i,)
            yield from _paths(v, prefix + (i,))


PATHS = list(_paths(BASE))


def _mutate(data, path, action, value):
    d = copy.deepcopy(data)
    parent = d
    for k in path[:-1]:
        parent = parent[k]
    if action == "set":
        parent[path[-1]] = value
    elif isinstance(parent, dict):
        parent.pop(path[-1])
    else:
        del parent[path[-1]]
    return d


def _loads_or_names_the_file(data):
    try:
        core = core_from_dict(data, SOURCE)
    except CoreError as e:
        assert SOURCE in str(e)
        return None
    assert isinstance(core, Core)
    for s in core.segments:       # accepted values are physical
        assert math.isfinite(s.length) and s.length > 0
        if s.is_porous:
            assert 0 < s.porosity <= 1 and 0 < s.pore_radius <= core.radius
    return core


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(PATHS), st.sampled_from(["set", "delete"]), toml_values)
def test_any_single_change_loads_or_is_named(path, action, value):
    _loads_or_names_the_file(_mutate(BASE, path, action, value))


@settings(max_examples=100, deadline=None)
@given(st.dictionaries(st.sampled_from(["gas", "tube", "segment", "other"]), toml_values, max_size=4))
def test_any_structure_loads_or_is_named(data):
    _loads_or_names_the_file(data)


@settings(max_examples=100, deadline=None)
@given(st.text(max_size=200))
def test_any_text_file_loads_or_is_named(tmp_path_factory, text):
    p = tmp_path_factory.mktemp("core") / "fuzz.toml"
    p.write_text(text)
    try:
        load_core(p)
    except CoreError as e:
        assert "fuzz.toml" in str(e)


@pytest.mark.parametrize("change", [{"length": ""}, {"porosity": [0.9]}, {"h": "1"}, {"tortuosity": None}])
def test_strings_and_lists_as_values_are_refused(change):
    """They passed the loader before and failed in the engine."""
    d = copy.deepcopy(BASE)
    d["segment"][1].update({k: v for k, v in change.items() if v is not None})
    if None in change.values():
        d["segment"][1]["tortuosity"] = [[]]
    with pytest.raises(CoreError, match=f"{SOURCE}: segment 'stack': {next(iter(change))}"):
        core_from_dict(d, SOURCE)
