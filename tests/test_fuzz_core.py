"""Property-based tests of the core loader and the forward model: whatever a core file
holds, the loader returns a valid Core or raises CoreError naming the file, never another
exception; and the forward model of whatever it returns is a clear error or a finite,
self-consistent result, never a signal or a traceback."""

import copy
import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tawarp.model.core import Core, CoreError, core_from_dict, load_core

BASE = load_core("ceramic").to_dict()
SOURCE = "fuzz.toml"
# every value a TOML file can hold
toml_scalars = st.one_of(st.text(max_size=8), st.integers(-(10**6), 10**6), st.floats(allow_nan=True), st.booleans())
toml_values = st.recursive(
    toml_scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=6), inner, max_size=3)),
    max_leaves=6,
)


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
    for s in core.segments:  # accepted values are physical
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


# -- the forward model of any core that loads -------------------------------------------
# Run in a child process: a crash of the kernels (SIGSEGV: an extreme h or frequency once
# overflowed the cascade's cell count) is then an exit code that fails this test, with the
# example printed just before it, not the end of the test run.
_FORWARD_FUZZ = r"""
import math, sys, warnings
import numpy as np
from hypothesis import HealthCheck, given, settings, strategies as st
from tawarp import reference
from tawarp.model.core import CoreError, core_from_dict, load_core
from tawarp.model.forward import transfer_matrices
from tawarp.model.validity import ModelValidityError, ValidityWarning, precision_error

BASE = load_core("ceramic")
NAMES = BASE.parameter_names()
TOL = 1e-6
magnitude = st.builds(lambda sign, e: sign * 10.0 ** e, st.sampled_from([1.0, -1.0]), st.floats(-320, 308))
near = st.floats(-4, 4)
values = st.one_of(magnitude, st.sampled_from([0.0, math.inf, -math.inf, math.nan, 5e-324, 1.7e308]))
changes = st.lists(st.tuples(st.sampled_from(NAMES), st.one_of(values, near.map(lambda e: ("x", 10.0 ** e)))),
                   min_size=1, max_size=3)


@settings(max_examples=int(sys.argv[1]), deadline=None, derandomize=True, database=None,
          suppress_health_check=list(HealthCheck))
@given(changes, st.sampled_from([[30.0, 500.0], [1e-3, 2e4], [100.0]]), st.floats(0, 1e3))
def forward(changes, freqs, Q):
    values = {k: BASE.get(k) * v[1] if isinstance(v, tuple) else v for k, v in changes}
    print(values, freqs, Q, flush=True)
    try:
        core = BASE.replace(**values)
        core = core_from_dict(core.to_dict(), "fuzz.toml")
    except CoreError as e:
        return
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ValidityWarning)
            T = transfer_matrices(core, freqs, [0.0, Q], device="cpu").T
    except ModelValidityError as e:     # a CoreError: a clear error that names the core
        assert "fuzz.toml" in str(e) or "frequency" in str(e), e
        return
    assert np.all(np.isfinite(T))
    warned = any(issubclass(w.category, ValidityWarning) for w in caught)
    assert warned or precision_error(T[:1])[0] <= TOL
    # the reference has no limp frame, no shape factor and no bypass gap: it refuses them
    if warned or any(s.frame_mobility != 0 or s.viscous_shape_factor != 1 or s.bypass_gap != 0 for s in core.segments):
        return
    with np.errstate(all="ignore"):
        R = reference.transfer_matrix(core, freqs, 0.0)    # closed forms at uniform temperature
    if np.all(np.isfinite(R)):
        scale = np.abs(R).max(axis=(1, 2), keepdims=True)
        assert np.max(np.abs(T[0] - R) / scale) < 1e-8, (np.max(np.abs(T[0] - R) / scale))


forward()
print("done")
"""


def test_any_core_that_loads_forwards_to_a_clear_error_or_a_sound_result():
    """Random changes of one to three parameters (any magnitude and sign, inf, NaN, or the
    core's value times 1e-4 .. 1e4), at Q = 0 and a random Q, on three frequency grids:
    CoreError/ModelValidityError naming the file, or finite T-matrices whose Q = 0 set
    passes det T = 1 (tawarp.model.validity.check_precision) and equals the reference's
    closed forms to 1e-8 of its largest entry (where the reference has the model: no limp
    frame, no viscous shape factor, no bypass gap)."""
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-c", _FORWARD_FUZZ, "400"], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0 and run.stdout.rstrip().endswith("done"), (
        f"rc {run.returncode}; last example: {run.stdout.strip().splitlines()[-1:]}\n{run.stderr[-3000:]}"
    )
