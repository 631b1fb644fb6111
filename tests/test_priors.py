"""Priors: the core file's declared uncertainties, the default physical priors, the
effects' priors, and the prior's densities against scipy.stats' closed forms."""

import dataclasses
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from scipy import integrate, stats

from tawarp.model.core import (
    CoreError,
    bundled_cores,
    core_from_dict,
    dump_core,
    load_core,
    paper_cores,
)
from tawarp.model.effects import Param, base_params, impedance_library, tmatrix_library
from tawarp.model.layer import layer_core
from tawarp.model.prior import TENSION_SD, Z95, Prior, tension
from tawarp.model.priors import DEFAULT_PRIORS, EFFECT_WIDTH, effect_priors, prior_for, segment_role


def _ceramic_with(path, raw: dict[tuple[str, str], str]):
    """The bundled ceramic core written to ``path`` with the raw TOML text ``raw``
    {(table, key): text} in place of a value or added; ``table`` a segment's name, ``gas``
    or ``tube``."""
    blocks = []
    for block in dump_core(load_core("ceramic")).strip().split("\n\n"):
        lines = block.splitlines()
        name = next((line.partition(" = ")[2].strip('"') for line in lines if line.startswith("name = ")), "")
        table = lines[0].strip("[]") if lines[0] in ("[gas]", "[tube]") else name
        keys = {line.partition(" = ")[0]: k for k, line in enumerate(lines)}
        for (where, key), text in raw.items():
            if where == table and key in keys:
                lines[keys[key]] = f"{key} = {text}"
            elif where == table:
                lines.append(f"{key} = {text}")
        blocks.append("\n".join(lines))
    path.write_text("\n\n".join(blocks) + "\n")
    return path


# -- the syntax -------------------------------------------------------------------------
def test_sd_rel_and_range_syntax(tmp_path):
    """Each form gives a Gaussian in the field's fit scale: h (log-scaled) a log-normal,
    porosity (linear) a normal; a range is the central 95 % interval."""
    p = _ceramic_with(
        tmp_path / "c.toml",
        {
            ("stack", "h"): "{value = 150, sd = 30}",
            ("hot_hx", "h"): "{value = 100, range = [50, 300]}",
            ("stack", "porosity"): "{value = 0.9, rel = 0.05}",
            ("stack", "tortuosity"): "{value = 1.0, sd = 0.05}",
            ("tbt", "h"): "{value = 0.3, center = 0.2, rel = 0.5}",
            ("gas", "T_cold"): "{value = 295.0, sd = 2}",
        },
    )
    core = load_core(p)
    assert core.get("stack.h") == 150.0 and core.get("hot_hx.h") == 100.0 and core.get("stack.porosity") == 0.9
    assert core.get("gas.T_cold") == 295.0 and core.get("tbt.h") == 0.3
    pr = core.priors
    assert set(pr) == {"stack.h", "hot_hx.h", "stack.porosity", "stack.tortuosity", "tbt.h", "gas.T_cold"}
    # sd on a log-scaled field: relative width sd/center in ln
    assert pr["stack.h"] == Prior(150.0, 0.2, True, 0.0, math.inf)
    # rel on a linear field: sd = rel * center, truncated to the physical range (0, 1]
    assert pr["stack.porosity"] == Prior(0.9, 0.05 * 0.9, False, 0.0, 1.0)
    assert pr["stack.tortuosity"] == Prior(1.0, 0.05, False, 1.0, math.inf)
    assert pr["tbt.h"] == Prior(0.2, 0.5, True, 0.0, math.inf)
    assert pr["gas.T_cold"].log and pr["gas.T_cold"].sd == pytest.approx(2 / 295.0, rel=1e-15)
    # range: 50 and 300 W/(m^2 K) are the log-normal's 2.5 % and 97.5 % quantiles
    hx = pr["hot_hx.h"]
    assert hx.log and Z95 == pytest.approx(stats.norm.ppf(0.975), rel=1e-15)
    q = stats.lognorm(s=hx.sd, scale=hx.center).ppf([0.025, 0.975])
    np.testing.assert_allclose(q, [50.0, 300.0], rtol=1e-12)


def test_range_of_a_linear_field_is_a_normal(tmp_path):
    core = load_core(_ceramic_with(tmp_path / "c.toml", {("stack", "porosity"): "{value = 0.9, range = [0.8, 0.95]}"}))
    pr = core.priors["stack.porosity"]
    assert not pr.log
    np.testing.assert_allclose(stats.norm(pr.center, pr.sd).ppf([0.025, 0.975]), [0.8, 0.95], rtol=1e-13)


def test_old_files_stay_valid():
    for name in bundled_cores():
        assert load_core(name).priors == {}


BAD_SYNTAX = [
    (("stack", "h"), "{value = 150, sd = -30}", "sd must be > 0"),
    (("stack", "h"), "{value = 150, sd = 0}", "sd must be > 0"),
    (("stack", "h"), "{value = 150, rel = 0}", "rel must be > 0"),
    (("stack", "h"), "{value = 150, rel = -0.2}", "rel must be > 0"),
    (("stack", "h"), "{value = 150, range = [300, 50]}", "reversed"),
    (("stack", "h"), "{value = 400, range = [50, 300]}", "outside its range"),
    (("stack", "h"), "{value = 150, range = [0, 300]}", "must be positive"),
    (("stack", "h"), "{value = 150, range = [50]}", "two finite numbers"),
    (("stack", "h"), "{value = 150, sigma = 30}", "unknown key"),
    (("stack", "h"), "{value = 150}", "exactly one of sd, rel, range"),
    (("stack", "h"), "{value = 150, sd = 30, rel = 0.2}", "exactly one of sd, rel, range"),
    (("stack", "h"), "{sd = 30}", "needs value"),
    (("stack", "h"), "{value = 'a', sd = 30}", "finite number"),
    (("stack", "h"), "{value = 150, center = -5, sd = 30}", "outside the physical range"),
    (("stack", "h"), "{value = 150, center = 100, range = [50, 300]}", "range sets the center"),
    (("stack", "porosity"), "{value = 0.9, center = 0, sd = 0.1}", "outside the physical range"),
    (("stack", "porosity"), "{value = 0.9, center = 0, rel = 0.1}", "relative to the center, which is 0"),
    (("stack", "pore_model"), "{value = 1, sd = 1}", "plain value"),
]


@pytest.mark.parametrize("where, text, message", BAD_SYNTAX, ids=[t for _, t, _ in BAD_SYNTAX])
def test_syntax_errors_name_the_file_and_key(tmp_path, where, text, message):
    path = _ceramic_with(tmp_path / "bad.toml", {where: text})
    with pytest.raises(CoreError, match=message) as err:
        load_core(path)
    assert "bad.toml" in str(err.value) and where[1] in str(err.value)


def test_any_parameter_of_a_segment_takes_a_prior(tmp_path):
    """An effect field the file adds (the stack's thermal radius ratio at "off") and a
    duct's length take the syntax too."""
    core = load_core(
        _ceramic_with(
            tmp_path / "c.toml",
            {
                ("stack", "thermal_radius_ratio"): "{value = 1, sd = 0.3}",
                ("duct_left", "length"): "{value = 0.03, sd = 0.002}",
            },
        )
    )
    assert core.priors == {
        "stack.thermal_radius_ratio": Prior(1.0, 0.3, False, 0.0, math.inf),
        "duct_left.length": Prior(0.03, 0.002 / 0.03, True, 0.0, math.inf),
    }


def test_prior_on_a_field_the_segment_does_not_use_is_refused():
    """An effect field at its "off" value passes validation in any segment; a prior on it
    where the segment does not take it (convection in a duct outside the heat model) is
    refused."""
    d = load_core("ceramic").to_dict()
    d["segment"][0]["h_convection"] = {"value": 0.0, "sd": 1.0}
    with pytest.raises(CoreError, match="duct_left.h_convection") as err:
        core_from_dict(d, "x.toml")
    assert "x.toml" in str(err.value)


def test_round_trip_keeps_declared_priors(tmp_path):
    """dump_core writes each prior back (rel for a log-normal, sd for a normal, center when
    the value moved): reloading gives the same priors exactly, also for a fitted copy."""
    p = _ceramic_with(
        tmp_path / "c.toml",
        {
            ("stack", "h"): "{value = 150, sd = 30}",
            ("hot_hx", "h"): "{value = 100, range = [50, 300]}",
            ("stack", "porosity"): "{value = 0.9, rel = 0.05}",
            ("gas", "p_mean"): "{value = 101325.0, rel = 0.01}",
            ("tube", "radius"): "{value = 0.0167, sd = 1e-4}",
        },
    )
    core = load_core(p)
    again = tmp_path / "again.toml"
    again.write_text(dump_core(core))
    back = load_core(again)
    assert back.priors == core.priors and back == dataclasses.replace(core, source=str(again))
    fitted = core.replace(**{"stack.h": 80.0, "hot_hx.h": 500.0})  # 500 is outside the declared range
    assert fitted.priors == core.priors
    again.write_text(dump_core(fitted))
    back = load_core(again)
    assert back.get("stack.h") == 80.0 and back.get("hot_hx.h") == 500.0 and back.priors == core.priors


def test_cores_differing_in_priors_are_not_equal_but_hash():
    core = load_core("ceramic")
    declared = dataclasses.replace(core, priors={"stack.h": Prior(150.0, 0.2, True)})
    assert core != declared and hash(core) == hash(declared)


# -- the Prior against closed forms -------------------------------------------------------
PRIORS = {
    "normal": (Prior(0.5, 0.1, False), stats.norm(0.5, 0.1)),
    "truncated normal": (
        Prior(0.9, 0.1, False, 0.0, 1.0),
        stats.truncnorm((0.0 - 0.9) / 0.1, (1.0 - 0.9) / 0.1, loc=0.9, scale=0.1),
    ),
    "half-normal": (Prior(0.0, 0.0134, False, 0.0), stats.halfnorm(0.0, 0.0134)),
}


@pytest.mark.parametrize("name", PRIORS)
def test_normal_priors_match_scipy(name):
    prior, ref = PRIORS[name]
    v = np.linspace(*ref.ppf([1e-6, 1 - 1e-6]), 41)
    for x in v:
        assert prior.log_density(x) == pytest.approx(ref.logpdf(x), rel=1e-12, abs=1e-12)
        assert prior.z(x) == pytest.approx((x - prior.center) / prior.sd, rel=1e-15)
    lo, hi = ref.support()
    assert prior.log_density(hi + 1.0) == -math.inf if math.isfinite(hi) else True
    assert prior.log_density(lo - 1.0) == -math.inf if math.isfinite(lo) else True


def test_half_normal_is_the_gaussian_plus_ln2():
    prior = Prior(0.0, 2.0, False, 0.0)
    for v in (0.0, 0.7, 5.0):
        assert prior.log_density(v) == pytest.approx(stats.norm(0, 2).logpdf(v) + math.log(2.0), rel=1e-14)


def test_log_normal_priors_match_scipy():
    """A log-normal: density in v with the 1/v Jacobian (scipy's lognorm); truncated at
    q >= 1: the truncated normal in ln q; z is the standard-normal quantile of the CDF."""
    prior, ref = Prior(150.0, math.log(3.0), True, 0.0), stats.lognorm(s=math.log(3.0), scale=150.0)
    for v in (1.0, 50.0, 150.0, 2000.0):
        assert prior.log_density(v) == pytest.approx(ref.logpdf(v), rel=1e-12)
        assert prior.z(v) == pytest.approx(stats.norm.ppf(ref.cdf(v)), rel=1e-9)
    assert prior.log_density(0.0) == -math.inf and prior.log_density(-1.0) == -math.inf
    q = Prior(1.06, 0.2, True, 1.0)
    tn = stats.truncnorm((0.0 - math.log(1.06)) / 0.2, math.inf, loc=math.log(1.06), scale=0.2)
    for v in (1.0, 1.1, 1.5, 3.0):
        assert q.log_density(v) == pytest.approx(tn.logpdf(math.log(v)) - math.log(v), rel=1e-12)
    assert q.log_density(0.99) == -math.inf


@pytest.mark.parametrize(
    "prior",
    [
        Prior(0.9, 0.1, False, 0.0, 1.0),
        Prior(1.0, 0.2, True, 1.0),
        Prior(0.0, 1.85, False, 0.0),
        Prior(0.2, math.log(3.0), True, 0.0),
    ],
    ids=["porosity", "q on its bound", "half-normal", "log-normal"],
)
def test_densities_integrate_to_one(prior):
    """Truncation normalisation: the density integrates to 1 over its support (in the
    prior's variable u = ln v or v, with dv/du = v or 1)."""
    if prior.log:
        lo = math.log(prior.lower) if prior.lower > 0 else math.log(prior.center) - 12 * prior.sd
        hi = min(math.log(prior.upper), math.log(prior.center) + 12 * prior.sd)
        total, _ = integrate.quad(lambda u: math.exp(prior.log_density(math.exp(u)) + u), lo, hi, limit=200)
    else:
        lo, hi = max(prior.lower, prior.center - 12 * prior.sd), min(prior.upper, prior.center + 12 * prior.sd)
        total, _ = integrate.quad(lambda v: math.exp(prior.log_density(v)), lo, hi, limit=200)
    assert total == pytest.approx(1.0, abs=1e-10)


def test_density_of_x_is_the_density_of_v_times_dv_dx():
    """log_density_x is the change of variables of log_density: + ln(dv/dx), with
    dv/dx = v for a log Param and its scale for a linear one."""
    prior = Prior(0.9, 0.1, False, 0.0, 1.0)
    for par in (Param("p", ("p",), 0.8, 0.5), Param("p", ("p",), 0.8, log=True)):
        for v in (0.3, 0.85, 0.999):
            dvdx = v if par.log else par.scale
            assert prior.log_density_x(float(par.x_of(v)), par) == pytest.approx(
                prior.log_density(v) + math.log(dvdx), rel=1e-13
            )


def test_x_moments_exact_against_param_x_of():
    """Same scale: mu_x = x_of(center), sd_x = x_of(center shifted by one sd) - mu_x,
    exactly; the density of x is then N(mu_x, sd_x) (untruncated log-normal)."""
    core = load_core("ceramic")
    h, phi = base_params(core, ["stack.h", "stack.porosity"])
    assert h.log and not phi.log
    lp = Prior(120.0, 0.4, True, 0.0)
    mu, sd = lp.x_moments(h)
    assert mu == float(h.x_of(120.0)) and sd == pytest.approx(float(h.x_of(120.0 * math.exp(0.4))) - mu, rel=1e-14)
    for x in (-1.0, 0.0, 0.7):
        assert lp.log_density_x(x, h) == pytest.approx(stats.norm(mu, sd).logpdf(x), rel=1e-12)
    np_ = Prior(0.85, 0.1, False)
    mu, sd = np_.x_moments(phi)
    assert mu == pytest.approx(float(phi.x_of(0.85)), rel=1e-15)
    assert sd == pytest.approx(float(phi.x_of(0.95)) - float(phi.x_of(0.85)), rel=1e-12)


def test_x_moments_linearised_across_scales():
    """Different scales: the width is the derivative dx/dv at the center times the
    prior's sd in v (log-normal: center * sd), checked by a central difference of x_of."""
    core = load_core("ceramic")
    h, phi = base_params(core, ["stack.h", "stack.porosity"])
    for prior, par in ((Prior(0.85, 0.05, True), phi), (Prior(140.0, 10.0, False), h)):
        c, eps = prior.center, 1e-6 * prior.center
        dxdv = (float(par.x_of(c + eps)) - float(par.x_of(c - eps))) / (2 * eps)
        sd_v = c * prior.sd if prior.log else prior.sd
        mu, sd = prior.x_moments(par)
        assert mu == pytest.approx(float(par.x_of(c)), rel=1e-14)
        assert sd == pytest.approx(dxdv * sd_v, rel=1e-9)


def test_describe():
    assert Prior(150.0, math.log(3.0), True, 0.0).describe("W/(m^2 K)") == "150 W/(m^2 K) x/÷ 3"
    assert Prior(0.8, 0.1, False, 0.0, 1.0).describe() == "0.8 +- 0.1, <= 1"
    assert Prior(0.0, 0.0134, False, 0.0).describe("W/(m K)") == "0 +- 0.0134 W/(m K), >= 0"


def test_invalid_priors():
    for args in (
        (1.0, 0.0, False),
        (1.0, -1.0, True),
        (0.0, 1.0, True),
        (2.0, 0.1, False, 0.0, 1.0),
        (math.nan, 0.1, False),
    ):
        with pytest.raises(ValueError):
            Prior(*args)


# -- defaults and roles -------------------------------------------------------------------
@pytest.mark.parametrize("name", paper_cores())
def test_roles_and_h_priors_on_the_bundled_cores(name):
    core = load_core(name)
    roles = {s.name: segment_role(core, s.name) for s in core.segments}
    assert roles == {
        "duct_left": None,
        "stack": "stack",
        "hot_hx": "hot_exchanger",
        "tbt": "buffer_tube",
        "duct_right": None,
    }
    for seg, role in (("stack", "stack"), ("hot_hx", "hot_exchanger"), ("tbt", "buffer_tube")):
        p = prior_for(core, f"{seg}.h")
        row = DEFAULT_PRIORS["h", role]
        assert p == Prior(core.get(f"{seg}.h"), row.sd, True, 0.0, math.inf) and role.replace("_", " ") in p.source
    assert prior_for(core, "tbt.h").sd == pytest.approx(1.0, rel=1e-15)  # a factor e: 20x is 3 sd
    assert prior_for(core, "hot_hx.h").sd == pytest.approx(math.log(2.0), rel=1e-15)


def test_roles_follow_the_structure_not_the_names():
    """Renamed segments keep their roles: the heater, the porous thermal segment before
    it, the thermal duct after it."""
    d = load_core("mesh").to_dict()
    for seg, new in zip(d["segment"], ("a", "b", "c", "d", "e")):
        seg["name"] = new
    core = core_from_dict(d, "renamed.toml")
    assert [segment_role(core, n) for n in "abcde"] == [None, "stack", "hot_exchanger", "buffer_tube", None]
    with pytest.raises(KeyError, match="'f'"):
        segment_role(core, "f")


def test_default_priors_of_base_fields():
    core = load_core("nicr_foam")
    assert prior_for(core, "stack.porosity") == Prior(0.92, 0.1, False, 0.0, 1.0)
    assert prior_for(core, "stack.tortuosity") == Prior(1.3, 0.2, True, 1.0, math.inf)
    assert prior_for(core, "stack.pore_radius") == Prior(3.1e-4, math.log(1.5), True, 0.0, math.inf)
    assert prior_for(core, "duct_left.length") == Prior(0.03, 2e-3, False, 0.0, math.inf)
    assert prior_for(core, "gas.T_cold") == Prior(293.15, 5.0, False, 0.0, math.inf)
    assert prior_for(core, "gas.p_mean") == Prior(101325.0, 0.03, True, 0.0, math.inf)
    broad = prior_for(core, "stack.solid_conductivity")
    assert broad == Prior(12.0, math.log(3.0), True, 0.0, math.inf) and broad.source == "default"
    # a log-normal cannot centre on 0: a porous sample's unused solid conductivity gets a
    # half-normal of the field's linear fit scale
    foam = load_core("foam_sample")
    assert prior_for(foam, "foam.solid_conductivity") == Prior(0.0, 1.0, False, 0.0, math.inf)


def test_declared_prior_wins_over_the_default(tmp_path):
    core = load_core(_ceramic_with(tmp_path / "c.toml", {("tbt", "h"): "{value = 0.2, rel = 0.5}"}))
    assert prior_for(core, "tbt.h") == Prior(0.2, 0.5, True, 0.0, math.inf)
    assert "c.toml" in prior_for(core, "tbt.h").source
    assert prior_for(core, "stack.h") == Prior(150.0, math.log(3.0), True, 0.0, math.inf)
    # and for an effect's parameter
    d = core.to_dict()
    d["segment"][3]["h_convection"] = {"value": 0.0, "sd": 1.0}
    core = core_from_dict(d, "conv.toml")
    conv = next(e for e in tmatrix_library(core) if e.name == "convection")
    assert effect_priors(conv, core)["tbt.h_convection"] == Prior(0.0, 1.0, False, 0.0, math.inf)
    assert effect_priors(conv)["tbt.h_convection"].sd == pytest.approx(
        EFFECT_WIDTH * conv.typical["tbt.h_convection"], rel=1e-15
    )


def test_tension_names_the_parameter():
    prior = prior_for(load_core("ceramic"), "tbt.h")
    assert tension("tbt.h", prior, 0.2 * 2.0) is None
    msg = tension("tbt.h", prior, 0.2 * 40.0, "W/(m^2 K)")
    assert msg.startswith("tbt.h = 8 W/(m^2 K) is 40x its prior 0.2 W/(m^2 K) x/÷ 2.72 (+3.7 prior sd)")
    assert prior.z(8.0) == pytest.approx(math.log(40.0), rel=1e-14) and prior.z(8.0) > TENSION_SD
    wall = Prior(0.0, 1.85, False, 0.0)
    assert tension("wall_conductance", wall, 5.0) is None
    assert tension("wall_conductance", wall, 10.0, "W/(m K)") == (
        "wall_conductance = 10 W/(m K) is 5.4 prior sd above its prior 0 +- 1.85 W/(m K), >= 0"
    )


# -- effect priors ------------------------------------------------------------------------
def _libraries():
    for name in bundled_cores():
        yield f"tmatrix:{name}", tmatrix_library(load_core(name))
    yield "impedance:layer", impedance_library(layer_core(0.03))


@pytest.mark.parametrize("lib", list(_libraries()), ids=lambda lib: lib[0])
def test_every_library_effect_has_finite_priors(lib):
    """Every parameter of every effect: a prior with finite moments in its fit variable,
    a finite density at "off" (its start) and at its typical size, in the Param's own
    scale; one-sided where "off" is the field's physical bound."""
    _, effects = lib
    for eff in effects:
        priors = effect_priors(eff)
        assert set(priors) == {p.label for p in eff.params}, eff.name
        for par in eff.params:
            prior = priors[par.label]
            mu, sd = prior.x_moments(par)
            assert np.isfinite([mu, sd]).all() and sd > 0, (eff.name, par.label)
            assert prior.log == par.log, (eff.name, par.label)
            for v in (par.start, eff.typical.get(par.label, par.start)):
                assert math.isfinite(prior.log_density(v)), (eff.name, par.label, v)


HALF_NORMAL = {
    "radiation": "stack.radiative_conductivity",
    "convection": "tbt.h_convection",
    "wall_conduction": "wall_conductance",
    "ambient_exchanger_thermal": "ambient_hx.end_conductance",
    "contact_resistance": "hot_hx.contact_resistance",
    "ambient_exchangers": "ambient_hx.length",
}


def test_effect_switches_are_off_plus_minus_their_typical_size():
    """A switch's typical size is 1/EFFECT_WIDTH prior sd from "off"; where "off" is the
    physical bound the prior is a half-normal (density ln 2 above the Gaussian at "off")."""
    core = load_core("nicr_foam")
    lib = {e.name: e for e in tmatrix_library(core)}
    for name in ("thermal_radius_ratio", "conductivity_T", "calibration", *HALF_NORMAL):
        eff = lib[name]
        for label, prior in effect_priors(eff).items():
            par = next(p for p in eff.params if p.label == label)
            if label in ("ambient_hx.porosity", "ambient_hx.pore_radius") or label.endswith(".wall_resistance"):
                continue  # shape parameters of the effect, typical at their physical start, not switches
            assert prior.center == par.start
            assert abs(prior.z(eff.typical[label])) == pytest.approx(1.0 / EFFECT_WIDTH, rel=1e-12)
    for name, label in HALF_NORMAL.items():
        prior = effect_priors(lib[name])[label]
        assert prior.lower == prior.center == 0.0
        assert prior.log_density(0.0) == pytest.approx(stats.norm(0, prior.sd).logpdf(0) + math.log(2), rel=1e-14)
    # calibration gain and phase, the conductivity exponent: "off" inside the range, two-sided
    for name, label in (("conductivity_T", "stack.conductivity_exponent"), ("calibration", "calibration.phase")):
        prior = effect_priors(lib[name])[label]
        assert prior.mass == pytest.approx(1.0, abs=1e-12)


def test_effects_that_free_base_parameters_use_the_base_defaults():
    core = load_core("rvc_foam")
    lib = {e.name: effect_priors(e) for e in tmatrix_library(core)}
    assert lib["plane_offsets"]["duct_left.length"] == Prior(0.03, 2e-3, False, 0.0, math.inf)
    assert lib["T_cold"]["gas.T_cold"] == Prior(293.15, 5.0, False, 0.0, math.inf)
    # p_mean's effect Param is linear: the +-3 % log-normal as a normal of 3 % of p_mean
    assert lib["p_mean"]["gas.p_mean"] == Prior(101325.0, 0.03 * 101325.0, False, 0.0, math.inf)
    # shape parameters of the ambient exchangers: their fields' defaults
    assert lib["ambient_exchangers"]["ambient_hx.porosity"] == Prior(0.8, 0.1, False, 0.0, 1.0)
    assert lib["ambient_exchangers"]["ambient_hx.pore_radius"] == Prior(1e-3, math.log(1.5), True, 0.0, math.inf)


def test_elastic_frame_prior_spans_its_stated_starts():
    """The frame's E is stated from 1e4 to 1e7 Pa (its refit starts): the prior's sd
    covers that span (EFFECT_WIDTH times it), so a fitted 3e6 Pa is not in tension."""
    core = load_core("foam_sample")
    frame = next(e for e in tmatrix_library(core) if e.name == "elastic_frame")
    prior = effect_priors(frame)["foam.frame_modulus"]
    assert prior.sd == EFFECT_WIDTH * 1e7 and abs(prior.z(3e6)) < TENSION_SD


def test_layer_frame_prior_is_even_per_decade_of_its_wave_speed():
    """The layer's elastic frame: its mobility switch has the limp frame's half-normal prior
    (one frame, two models), its wave speed is a scale whose stated span (12-1200 m/s: E
    1e4-1e7 Pa over 10-100 kg/m^3) is the log-normal's central 95 %; foam2's fitted frame
    (349 m/s, docs/elastic_frame.md's direct Biot fit 351 m/s) is inside it."""
    from tawarp.model.effects import FRAME_WAVE_SPEED_RANGE, P_WAVE_FACTOR, impedance_library
    from tawarp.model.layer import layer_core
    from tawarp.model.prior import Z95

    lib = {e.name: e for e in impedance_library(layer_core(0.03))}
    frame = effect_priors(lib["elastic_frame"])
    assert frame["layer.frame_mobility"] == effect_priors(lib["limp_frame"])["layer.frame_mobility"]
    c = frame["layer.frame_wave_speed"]
    lo, hi = FRAME_WAVE_SPEED_RANGE
    assert c.log and c.z(lo) == pytest.approx(-Z95, rel=1e-12) and c.z(hi) == pytest.approx(Z95, rel=1e-12)
    assert lo == pytest.approx(math.sqrt(1e4 * P_WAVE_FACTOR / 100)) and hi == pytest.approx(
        math.sqrt(1e6 * P_WAVE_FACTOR)
    )
    assert abs(c.z(349.0)) < TENSION_SD


# -- the documentation --------------------------------------------------------------------
DOCS = Path(__file__).resolve().parents[1] / "docs" / "priors.md"
#: each default row as docs/priors.md states it: (row text, sd, log)
DOC_ROWS = {
    ("h", "buffer_tube"): ("`h` (buffer tube) | log-normal, factor e per sd", 1.0, True),
    ("h", "stack"): ("`h` (stack) | log-normal, factor 3 per sd", math.log(3.0), True),
    ("h", "hot_exchanger"): ("`h` (hot exchanger) | log-normal, factor 2 per sd", math.log(2.0), True),
    ("porosity", None): ("`porosity` | normal, sd 0.1, in (0, 1]", 0.1, False),
    ("pore_radius", None): ("`pore_radius` | log-normal, factor 1.5 per sd", math.log(1.5), True),
    ("tortuosity", None): ("`tortuosity` | log-normal, sd 0.2 in ln, >= 1", 0.2, True),
    ("length", None): ("`length` | normal, sd 2 mm", 2e-3, False),
    ("wall_resistance", None): ("`wall_resistance` | log-normal, factor 2 per sd", math.log(2.0), True),
    ("T_cold", None): ("`gas.T_cold` | normal, sd 5 K", 5.0, False),
    ("p_mean", None): ("`gas.p_mean` | log-normal, sd 0.03 in ln", 0.03, True),
    ("radius", None): ("`tube.radius` | log-normal, sd 0.02 in ln", 0.02, True),
}


def test_docs_state_the_default_table():
    text = DOCS.read_text()
    assert set(DOC_ROWS) == set(DEFAULT_PRIORS)
    for key, (row, sd, log) in DOC_ROWS.items():
        assert f"| {row}" in text, row
        assert DEFAULT_PRIORS[key].sd == pytest.approx(sd, rel=1e-15) and DEFAULT_PRIORS[key].log == log, key


def test_docs_example_core_loads():
    """The core file example of docs/priors.md (its [gas] and stack, in the ceramic core)
    gives the priors the page describes."""
    block = DOCS.read_text().split("```toml\n")[1].split("```")[0]
    example = tomllib.loads(block)
    d = load_core("ceramic").to_dict()
    d["gas"] = example["gas"]
    d["segment"][1] = example["segment"][0]
    core = core_from_dict(d, "docs/priors.md")
    pr = core.priors
    assert set(pr) == {"gas.T_cold", "stack.length", "stack.porosity", "stack.pore_radius", "stack.h"}
    assert pr["gas.T_cold"] == Prior(295.0, 2.0 / 295.0, True, 0.0, math.inf)
    assert pr["stack.porosity"] == Prior(0.92, 0.01, False, 0.0, 1.0)
    assert pr["stack.pore_radius"] == Prior(3.1e-4, 0.15, True, 0.0, math.inf)
    h = pr["stack.h"]
    np.testing.assert_allclose(stats.lognorm(s=h.sd, scale=h.center).ppf([0.025, 0.975]), [5.0, 150.0], rtol=1e-12)
    assert core.get("stack.h") == 30.0 and prior_for(core, "stack.tortuosity").source.startswith("default")
