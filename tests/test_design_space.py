"""Design space (tawarp.design.space): parsing, unit-cube maps, parameter tables."""

from __future__ import annotations

import numpy as np
import pytest

from tawarp.design.catalogue import default_catalogue
from tawarp.design.space import DesignSpace, parse_variable
from tawarp.model.core import CoreError, load_core


def test_parse_variable_forms():
    v = parse_variable("Q=1:9")
    assert (v.name, v.low, v.high, v.log, v.values) == ("heat_input", 1.0, 9.0, False, ())
    g = parse_variable("stack.length=0.01:0.08:8", grid=True)
    np.testing.assert_array_equal(g.grid(), np.linspace(0.01, 0.08, 8))
    lg = parse_variable("stack.pore_radius=1e-5:1e-3:3:log")
    np.testing.assert_allclose(lg.grid(), [1e-5, 1e-4, 1e-3], rtol=1e-14)
    assert parse_variable("stack.porosity=0.9,0.7,0.8").values == (0.9, 0.7, 0.8)
    assert parse_variable("material=ceramic, mesh").choices == ("ceramic", "mesh")
    with pytest.raises(ValueError, match="a sweep grid needs LOW:HIGH:COUNT"):
        parse_variable("Q=1:9", grid=True)
    with pytest.raises(ValueError, match="'Q=a:b'"):
        parse_variable("Q=a:b")


@pytest.mark.parametrize(
    "text, say",
    [
        ("stack.h=1:nan:8", "upper bound of stack.h is nan"),
        ("stack.length=0.01:nan", "upper bound of stack.length is nan"),
        ("Q=-inf:3", "lower bound of heat_input is -inf"),
        ("stack.porosity=0.9,nan", "value of stack.porosity is nan"),
    ],
)
def test_a_bound_that_is_not_finite_is_refused(text, say):
    with pytest.raises(ValueError, match=f"'{text}': the {say}; expected a finite number"):
        parse_variable(text, grid=text.count(":") == 2)


def test_unit_cube_round_trip_and_log_scale():
    space = DesignSpace(
        load_core("rvc_foam"), ["material=ceramic,rvc_foam", "stack.pore_radius=1e-5:1e-3:log", "heat_input=1:9"]
    )
    X = np.array([[0.0, 0.5, 1.0], [0.5, 0.25, 0.0]])
    pts = space.points_from_unit(X)
    # log scale: the cube's middle is the geometric mean; linear: the arithmetic one
    assert pts[1]["stack.pore_radius"] == pytest.approx(1e-4, rel=1e-14)
    assert pts[0]["heat_input"] == pytest.approx(5.0, rel=1e-15)
    assert [p["material"] for p in pts] == ["rvc_foam", "ceramic"]
    np.testing.assert_allclose(space.unit_from_points(pts), X, atol=1e-14)


def test_varying_table_puts_the_material_in_the_stack():
    cat = default_catalogue()
    space = DesignSpace(load_core("rvc_foam"), ["material=ceramic,mesh", "stack.length=0.01:0.05", "Q=1:9"])
    pts = [
        {"material": "mesh", "stack.length": 0.02, "heat_input": 3.0},
        {"material": "ceramic", "stack.length": 0.04, "heat_input": 7.0},
    ]
    table = space.varying_table(space.values_of(pts))
    rows = dict(zip(space.param_names, table[1:]))
    np.testing.assert_array_equal(table[0], [3.0, 7.0])
    np.testing.assert_array_equal(rows["stack.porosity"], [cat["mesh"].porosity, cat["ceramic"].porosity])
    np.testing.assert_array_equal(rows["stack.h"], [cat["mesh"].h_s, cat["ceramic"].h_s])
    np.testing.assert_array_equal(rows["stack.length"], [0.02, 0.04])
    core, q = space.core_for(pts[0])
    assert q == 3.0 and core.segment("stack").porosity == cat["mesh"].porosity and core.segment("stack").length == 0.02


def test_position_variable_and_errors():
    core = load_core("rvc_foam")
    space = DesignSpace(core, ["stack.position=0.01:0.2"])
    assert space.param_names == [f"{core.segments[0].name}.length"]
    with pytest.raises(KeyError, match="stack.colour"):
        DesignSpace(core, ["stack.colour=1:2"])
    with pytest.raises(CoreError, match="porosity"):
        DesignSpace(core, ["stack.porosity=0.5:1.5"])
    with pytest.raises(ValueError, match="given twice"):
        DesignSpace(core, ["Q=1:2", "heat_input=1:3"])
    with pytest.raises(ValueError, match="log scale needs low > 0"):
        DesignSpace(core, ["Q=0:2:log"])
