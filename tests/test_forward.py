"""The Warp forward engine against closed forms, exact solutions and the independent
NumPy/SciPy reference (docs/physics.md, "Checks any implementation must pass" 1-5)."""

import dataclasses

import numpy as np
import pytest

from tawarp import reference
from tawarp.model.coefficients import duct_impedance, normalize
from tawarp.model.core import Core, CoreError, core_from_dict, load_core
from tawarp.model.forward import cpu_share, distinct_columns, steady_temperature, transfer_matrices

FREQS = np.array([30.0, 120.0, 260.0, 500.0])
HEAT = {
    "ceramic": [0.0, 40.0, 80.0],
    "mesh": [0.0, 40.0, 80.0],
    "nicr_foam": [0.0, 40.0, 80.0],
    "rvc_foam": [0.0, 9.0, 18.0],
}


def relative_error(Y, Yref):
    """Max over rows of max_c |Y - Yref| / max_c |Yref| (the four dimensionless
    coefficients of one row share a scale; elementwise ratios blow up where Tpp crosses 0)."""
    return float((np.abs(Y - Yref).max(-1) / np.abs(Yref).max(-1)).max())


def cold(core: Core) -> Core:
    """The same core with no heat model: every part at T_cold, so the reference uses
    the closed form of docs/physics.md for every segment."""
    segs = tuple(dataclasses.replace(s, thermal=False, heater=False) for s in core.segments)
    return Core(segs, core.gas, core.radius, core.source)


@pytest.mark.parametrize("name", ["ceramic", "mesh"])
def test_uniform_temperature_equals_closed_form(name):
    # Check 1. At Q = 0 the thermal segments are at uniform T_cold: the Magnus cascade
    # (4 cells, exact for constant A up to rounding) must equal the closed form.
    core = load_core(name)
    T = transfer_matrices(core, FREQS, 0.0, device="cpu", cells=4).T[0]
    T_closed = reference.transfer_matrix(cold(core), FREQS)
    Zc = duct_impedance(core)
    assert relative_error(normalize(T, Zc), normalize(T_closed, Zc)) < 1e-12


def test_reciprocity_at_zero_heat_only():
    # Check 2: det T = 1 at Q = 0 (to rounding); heating breaks reciprocity.
    core = load_core("ceramic")
    det = np.linalg.det(transfer_matrices(core, FREQS, [0.0, 40.0], device="cpu").T)
    assert np.abs(det[0] - 1).max() < 1e-12
    assert np.abs(det[1] - 1).min() > 0.1


@pytest.mark.parametrize("name", ["ceramic", "rvc_foam"])
def test_passive_at_zero_heat(name):
    # Check 3: absorbed power 1/2 Re(p1 U1*) - 1/2 Re(p6 U6*) >= 0 for every input (p1, U1):
    # the Hermitian form F - T^H F T, F = [[0, 1/2], [1/2, 0]], is positive semi-definite.
    core = load_core(name)
    Zc = duct_impedance(core)
    T = transfer_matrices(core, np.linspace(30, 500, 25), 0.0, device="cpu").T[0]
    S = np.diag([1.0, 1.0 / Zc])  # scale U so both entries are O(1) before the eigenvalues
    F = np.array([[0, 0.5], [0.5, 0]])
    for Tf in T:
        M = S @ (F - Tf.conj().T @ F @ Tf) @ S * Zc
        assert np.linalg.eigvalsh(M).min() > -1e-12


@pytest.mark.parametrize("name", ["ceramic", "mesh", "nicr_foam", "rvc_foam"])
def test_heat_solve_exact_with_fitted_scheme(name):
    # Check 4: the exponentially fitted tridiagonal scheme is exact for piecewise-constant
    # coefficients at any cell count; compare the whole profile with the exact solution.
    core = load_core(name)
    Q = HEAT[name][-1]
    x = np.linspace(0, core.positions()[-1], 301)
    exact = reference.heat_profile_exact(core, Q)
    for cells in (1, 3):
        T, dT = steady_temperature(core, x, Q, device="cpu", heat_cells=cells)
        scale = exact.theta_max()[1]
        assert np.abs(T[0] - exact.temperature(x)).max() < 1e-10 * scale
        # the derivative jumps at interfaces; compare away from the planes
        away = np.min(np.abs(x[:, None] - np.array(core.positions())[None]), axis=1) > 1e-6
        assert np.abs(dT[0, away] - exact.dtemperature(x[away])).max() < 1e-8 * scale / core.segment("stack").length


def test_heat_solve_second_order_with_plain_scheme():
    # Check 4: the plain finite-volume scheme converges at second order to the exact solution.
    core = load_core("ceramic")
    x = np.array(core.positions()[1:5])  # planes x2..x5 are nodes at every cell count
    exact = reference.heat_profile_exact(core, 40.0).temperature(x)
    errors = [
        np.abs(steady_temperature(core, x, 40.0, device="cpu", heat_cells=c, fitted=False)[0][0] - exact).max()
        for c in (16, 32, 64)
    ]
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all((orders > 1.9) & (orders < 2.1)), orders


@pytest.mark.parametrize("name", ["ceramic", "mesh"])
def test_energy_balance(name):
    # Check 4: all of Q leaves through the walls, Q = sum over thermal parts of
    # int (2 h / R) theta S dx (Gauss-Legendre quadrature of the kernel's profile).
    core = load_core(name)
    Q = 60.0
    nodes, weights = np.polynomial.legendre.leggauss(40)
    pos = core.positions()
    lost = 0.0
    for i in core.thermal_indices:
        a, b = pos[i], pos[i + 1]
        sub = np.linspace(a, b, 41)  # 40 panels resolve the exponential decay
        for lo, hi in zip(sub[:-1], sub[1:]):
            x = 0.5 * (hi - lo) * nodes + 0.5 * (hi + lo)
            theta = steady_temperature(core, x, Q, device="cpu")[0][0] - core.gas.T_cold
            lost += 0.5 * (hi - lo) * np.sum(weights * theta) * 2 * core.segments[i].h / core.radius * core.area
    assert abs(lost - Q) < 1e-9 * Q


def test_magnus_converges_at_sixth_order():
    # Check 5: the cascade's error against a converged reference falls as cells^-6.
    core = load_core("ceramic")
    Y = {c: transfer_matrices(core, FREQS, 80.0, device="cpu", cells=c).dimensionless() for c in (6, 12, 24, 256)}
    e = [relative_error(Y[c], Y[256]) for c in (6, 12, 24)]
    orders = np.log2(np.array(e[:-1]) / np.array(e[1:]))
    assert np.all((orders > 5.5) & (orders < 6.6)), orders


@pytest.mark.parametrize("name", ["ceramic", "mesh", "nicr_foam", "rvc_foam"])
def test_kernels_match_reference(name):
    # Warp kernels vs the independent adaptive-ODE reference: <= 1e-8 at cells = 48
    # (the reference itself is converged to ~1e-11, rtol 1e-12).
    core = load_core(name)
    Y = transfer_matrices(core, FREQS, HEAT[name], device="cpu", cells=48).dimensionless()
    for k, Q in enumerate(HEAT[name]):
        Yref = reference.dimensionless_transfer(core, FREQS, Q)
        assert relative_error(Y[k], Yref) < 1e-8, (name, Q)


def test_default_cells_meet_accuracy_budget():
    # The default cells setting is documented as <= 1e-6 on the paper-like cores with heating.
    core = load_core("ceramic")
    Y = transfer_matrices(core, FREQS, 80.0, device="cpu").dimensionless()[0]
    assert relative_error(Y, reference.dimensionless_transfer(core, FREQS, 80.0)) < 1e-6


@pytest.mark.parametrize("gas, model", [("helium", "circular"), ("argon", "plates"), ("nitrogen", "plates")])
def test_other_gases_and_plates_match_reference(gas, model):
    d = load_core("nicr_foam").to_dict()
    d["gas"]["name"] = gas
    d["gas"]["p_mean"] = 3e5
    d["segment"][1]["pore_model"] = model
    core = core_from_dict(d, f"<{gas}/{model}>")
    Y = transfer_matrices(core, FREQS, 30.0, device="cpu", cells=48).dimensionless()[0]
    assert relative_error(Y, reference.dimensionless_transfer(core, FREQS, 30.0)) < 1e-8


def test_batch_parameters_override_core_values():
    # A batch of parameter sets equals separate runs of the changed cores.
    core = load_core("mesh")
    h = np.array([20.0, 50.0, 90.0])
    r = np.array([30e-6, 40e-6, 60e-6])
    res = transfer_matrices(
        core, FREQS, [10.0, 20.0, 40.0], params={"stack.h": h, "stack.pore_radius": r}, device="cpu", cells=8
    )
    for k in range(3):
        one = transfer_matrices(
            core.replace(**{"stack.h": h[k], "stack.pore_radius": r[k]}),
            FREQS,
            [10.0, 20.0, 40.0][k],
            device="cpu",
            cells=8,
        )
        np.testing.assert_array_equal(res.T[k], one.T[0])


# -- bad input ---------------------------------------------------------------------------
def test_bad_batch_values():
    core = load_core("ceramic")
    with pytest.raises(CoreError, match="stack.porosity"):
        transfer_matrices(core, FREQS, 0.0, params={"stack.porosity": [0.9, 1.3]}, device="cpu")
    with pytest.raises(CoreError, match="heat_input"):
        transfer_matrices(core, FREQS, [float("nan")], device="cpu")
    with pytest.raises(KeyError, match="stack.porsity"):
        transfer_matrices(core, FREQS, 0.0, params={"stack.porsity": 0.9}, device="cpu")
    with pytest.raises(ValueError, match="freqs"):
        transfer_matrices(core, [-5.0], 0.0, device="cpu")
    no_heater = cold(core)
    with pytest.raises(CoreError, match="heater"):
        transfer_matrices(no_heater, FREQS, 10.0, device="cpu")


def test_processes_share_the_cores_this_one_may_use(monkeypatch):
    # each of P processes splits its launches over cores // P threads, never none: on 16
    # cores 16 loop processes take one each, 3 take 5, and 20 still take one
    monkeypatch.setattr("tawarp.model.forward._usable_cores", lambda: 16)
    assert [cpu_share(p) for p in (1, 3, 16, 20, 0)] == [16, 5, 1, 1, 16]


def test_cpu_threads_split_the_batch_bit_for_bit():
    """On the CPU a large batch runs split over threads: the same numbers as
    one thread, to the bit, whether the table comes as NumPy or as a Warp array."""
    import warp as wp

    from tawarp.model.forward import Engine, ForwardSettings

    core = load_core("ceramic")
    freqs = np.linspace(30.0, 500.0, 50)
    rng = np.random.default_rng(3)
    table = np.stack([rng.uniform(0, 80, 120), rng.uniform(50, 250, 120)])  # 6000 models: 3 threads
    one = Engine(core, freqs, ["stack.h"], ForwardSettings(device="cpu", cpu_threads=1))
    three = Engine(core, freqs, ["stack.h"], ForwardSettings(device="cpu", cpu_threads=3))
    assert three._cpu_parts(120) == 3 and one._cpu_parts(120) == 1
    ref = [a.numpy() for a in one.evaluate(table)]
    for varying in (table, wp.array(table, dtype=wp.float64, device="cpu")):
        got = [a.numpy() for a in three.evaluate(varying)]
        for a, b in zip(got, ref):
            np.testing.assert_array_equal(a, b)
    out = wp.zeros((120, 50, 8), dtype=wp.float64, device="cpu")
    three.evaluate(table, out=out)
    np.testing.assert_array_equal(out.numpy(), ref[0])


def test_point_blocks_equal_one_launch(monkeypatch):
    """A batch whose Gauss points exceed the point buffer runs in blocks of sets (each its
    points and its cascade launch): the same numbers, to the bit, as one block; and a
    refined (error-estimate) grid's points follow the main grid's in each set's row."""
    from tawarp.model import forward

    core = load_core("mesh")
    rng = np.random.default_rng(5)
    params = {"stack.h": rng.uniform(50, 250, 7), "stack.porosity": rng.uniform(0.6, 0.8, 7)}
    whole = transfer_matrices(core, FREQS, rng.uniform(0, 80, 7), params, device="cpu", cpu_threads=1)
    # the smallest buffer: one set per block
    monkeypatch.setattr(forward, "POINT_BUFFER_BYTES", 1)
    blocks = transfer_matrices(core, FREQS, whole.heat_input, params, device="cpu", cpu_threads=1)
    np.testing.assert_array_equal(blocks.T, whole.T)


def test_cascade_runs_sets_by_decreasing_cells():
    """The cascade launch takes a batch's sets by decreasing cell steps (warps of alike
    cells): its order is a permutation of the launch's sets, each set's steps over both
    grids at least its successor's, sets of equal steps in their own order; the rows land
    in place (test_point_blocks_equal_one_launch: one set per launch, the same bits)."""
    import warp as wp

    from tawarp.model.forward import Engine, ForwardSettings

    core = load_core("mesh")
    rng = np.random.default_rng(7)
    table = np.stack([rng.uniform(0, 80, 40), rng.uniform(50, 250, 40)])
    table[0, :5] = 0.0  # unheated: one step per segment
    engine = Engine(core, FREQS, ["stack.h"], ForwardSettings(device="cpu"))
    params, theta = engine.heat(table)
    density = wp.full(40, 1.5, dtype=wp.float64, device="cpu")
    cells = engine._cell_counts(params, theta, density, 2 * len(core.segments))[0]
    steps = np.maximum(cells.numpy(), 1).sum(1)
    for set0, groups in ((0, 40), (10, 25)):
        order = engine._order(cells, set0, groups, 1).numpy()
        np.testing.assert_array_equal(np.sort(order), np.arange(groups))
        np.testing.assert_array_equal(order, np.argsort(-steps[set0 : set0 + groups], kind="stable"))
    assert len(set(steps)) >= 4  # the batch's sets differ in cells (and tie: the stable order)


def test_fixed_cells_size_the_points_on_the_host(monkeypatch):
    """With fixed cells the cascade sizes its Gauss points from counts known on the host
    (no read-back): the device's (cell_counts) for a batch with heat input, 3 points per
    Magnus cell and one per duct (mesh core: 2 + 3 (6 + 9 + 10) = 77 points, 27 slots), and
    a bound of an unheated batch's (one point per segment); sized either way, the same
    T-matrices to the bit."""
    import warp as wp

    from tawarp.model.forward import Engine, ForwardSettings

    core = load_core("mesh")
    settings = ForwardSettings(device="cpu", cells={"stack": 6, "hot_hx": 9, "tbt": 10}, cpu_threads=1)
    eng = Engine(core, FREQS, ["stack.h"], settings)
    n_seg = len(core.segments)

    def device_counts(table):
        params, theta = eng.heat(table)
        density = wp.full(params.shape[1], 1.0, dtype=wp.float64, device="cpu")
        return tuple(int(v) for v in eng._cell_counts(params, theta, density, n_seg)[2].numpy()[:2])

    heated, unheated = np.array([[0.0, 40.0], [100.0, 150.0]]), np.array([[0.0, 0.0], [100.0, 150.0]])
    assert eng._fixed_point_counts(n_seg) == device_counts(heated) == (77, 27)
    assert device_counts(unheated) == (n_seg, n_seg)
    for table in (heated, unheated):
        ref = eng.evaluate(table)[0].numpy()
        with monkeypatch.context() as m:
            counts = device_counts(table)
            m.setattr(Engine, "_fixed_point_counts", lambda self, columns: counts)
            np.testing.assert_array_equal(eng.evaluate(table)[0].numpy(), ref)


@pytest.mark.parametrize("scale", [1e-6, 1e-3, 3e-2, 0.2, 0.5, 0.9, 3.0])
def test_matrix_exponential_against_scipy(scale):
    """expm2 (a series whose length follows |delta|, exponentials beyond |delta| = 1)
    against the exponential at 40 digits (mpmath) on random complex 2x2 matrices of each
    size, to 5e-15 of the largest entry: about what float64 rounding leaves at these norms
    (scipy.linalg.expm 1.17 is off by 1.2e-14 at the largest, so it cannot be the
    reference)."""
    import mpmath
    import warp as wp

    from tawarp.kernels.acoustics import cmat2, expm2

    @wp.kernel
    def run(m: wp.array2d(dtype=wp.vec2d), e: wp.array2d(dtype=wp.vec2d)):
        i = wp.tid()
        r = expm2(cmat2(m[i, 0], m[i, 1], m[i, 2], m[i, 3]))
        e[i, 0] = r.a
        e[i, 1] = r.b
        e[i, 2] = r.c
        e[i, 3] = r.d

    rng = np.random.default_rng(int(scale * 1e6))
    a = scale * (rng.normal(size=(200, 2, 2)) + 1j * rng.normal(size=(200, 2, 2)))
    m = wp.array(
        np.ascontiguousarray(a.reshape(200, 4)).view(np.float64).reshape(200, 4, 2), dtype=wp.vec2d, device="cpu"
    )
    e = wp.empty((200, 4), dtype=wp.vec2d, device="cpu")
    wp.launch(run, dim=200, inputs=[m, e], device="cpu")
    got = e.numpy().reshape(200, 8).view(np.complex128).reshape(200, 2, 2)
    with mpmath.workdps(40):
        want = np.array([np.array(mpmath.expm(mpmath.matrix(x.tolist())).tolist(), dtype=complex) for x in a])
    err = np.abs(got - want).max(axis=(1, 2)) / np.abs(want).max(axis=(1, 2))
    assert err.max() < 5e-15, err.max()


def test_unheated_sets_take_the_closed_form():
    """A set without heat input has theta = 0 exactly, so its thermal segments take the
    closed form exp(A L) (no Magnus cell): the numbers of the same core with no heat model,
    to the bit, whatever the cells setting; a heated set of the same batch does not."""
    core = load_core("ceramic")
    for kw in ({}, {"cells": 7}):
        T = transfer_matrices(core, FREQS, [0.0, 40.0], device="cpu", **kw).T
        np.testing.assert_array_equal(T[0], transfer_matrices(cold(core), FREQS, 0.0, device="cpu").T[0])
        assert np.abs(T[1] - T[0]).max() > 1e-3 * np.abs(T[0]).max()


def test_plain_cascade_equals_the_general_one():
    """A batch whose parts are all plain (circular pores, rigid frames, no shape factor)
    takes the cascade compiled without the other parts' code: the general cascade's numbers
    (to 1e-14 of each row's largest entry: the same arithmetic, compiled apart). A batch
    that varies an effect takes the general one, and the plain cascade given a part it does
    not compute returns NaN, never a wrong T."""
    from tawarp.model import forward

    core = load_core("ceramic")
    freqs = np.linspace(30.0, 500.0, 20)
    rng = np.random.default_rng(7)
    table = np.stack([rng.uniform(0, 80, 6), rng.uniform(50, 250, 6)])
    settings = forward.ForwardSettings(device="cpu", cpu_threads=1)
    engine = forward.Engine(core, freqs, ["stack.h"], settings)
    assert forward.plain_parts(core, ["stack.h"])
    plain = engine.evaluate(table)[0].numpy()
    engine.transfer_kernel = forward._transfer_kernel(settings.max_registers)
    general = engine.evaluate(table)[0].numpy()
    scale = np.abs(general).max(axis=-1, keepdims=True)
    assert np.abs(plain - general).max() <= 1e-14 * scale.max()
    assert np.all(np.abs(plain - general) <= 1e-14 * scale)

    for name in ("stack.frame_mobility", "stack.viscous_shape_factor", "stack.bypass_gap"):
        assert not forward.plain_parts(core, [name])
    limp = forward.Engine(core, freqs, ["stack.frame_mobility"], settings)
    limp.transfer_kernel = forward._transfer_kernel(settings.max_registers, 0, True)
    out = limp.evaluate(np.stack([table[0], np.full(6, 1e-3)]))[0].numpy()
    assert np.isnan(out).all()


@pytest.mark.parametrize("name", ["ceramic", "mesh", "nicr_foam", "rvc_foam"])
def test_heat_only_fields_are_inert_without_heat_input(name):
    # Engine.distinct shares one column between sets at zero heat input that differ
    # only in HEAT_ONLY_FIELDS: with no heat the temperature rise is zero whatever they are, and
    # the kernels read them nowhere else. Every such field of every thermal segment moved
    # (x 1/e .. e, the temperature-dependent effects switched on: the heat solve iterates) must
    # leave the T-matrices bit for bit, and must change them with heat input.
    from tawarp.measure.kind import smooth_settings
    from tawarp.model.forward import HEAT_ONLY_FIELDS, Engine, ForwardSettings

    core = load_core(name)
    names = [n for n in core.parameter_names() if n.partition(".")[2] in HEAT_ONLY_FIELDS]
    on = {
        "conductivity_exponent": 0.5,
        "radiative_conductivity": 1e-9,
        "h_convection": 5.0,
        "wall_conductance": 0.01,
        "end_conductance": 10.0,
        "contact_resistance": 1e-4,
    }
    base = np.array([core.get(n) for n in names])
    moved = np.array([v if v else on.get(n.partition(".")[2], 0.0) for n, v in zip(names, base)])
    moved *= np.exp(np.random.default_rng(0).uniform(-1.0, 1.0, base.size))
    settings = smooth_settings(core, FREQS, ForwardSettings(device="cpu"), heat_input=max(HEAT[name]))
    eng = Engine(core, FREQS, names, settings)
    Q = max(HEAT[name])
    table = np.column_stack([np.r_[0.0, base], np.r_[0.0, moved], np.r_[Q, base], np.r_[Q, moved]])
    T = eng.evaluate(table)[0].numpy()
    assert np.array_equal(T[0], T[1])
    assert relative_error(T[3], T[2]) > 1e-6
    # the shared columns: each set's own T-matrices, bit for bit
    distinct, column = eng.distinct(table[:, [0, 1, 2, 3, 1, 2]])
    shared = distinct[column]
    assert np.array_equal(shared.reshape(6, -1), T.view(complex).reshape(4, -1)[[0, 1, 2, 3, 1, 2]])


def test_gauss_profile_is_the_heat_models_profile_bit_for_bit():
    """The point kernel's profile (its usual heat cell inline, the rare cases out of line)
    gives tawarp.kernels.heat.segment_profile's values bit for bit at points all along every
    thermal segment: plain cells, a wall that is a field of its own, contact resistances at
    the segments' starts, the Kirchhoff cells of a temperature-dependent conductivity (a
    heat grid of several cells)."""
    import warp as wp

    from tawarp.kernels import forward as kf
    from tawarp.kernels.heat import cell_shape, segment_heat_coeffs, segment_nonlinear, segment_profile
    from tawarp.kernels.layout import LENGTH, seg_value
    from tawarp.model.forward import Engine, ForwardSettings

    @wp.kernel
    def profiles(
        sets: kf.SetTable,
        theta: wp.array2d(dtype=wp.float64),
        first: int,
        heat_cells: int,
        segments: wp.array(dtype=wp.int32),
        share: wp.array(dtype=wp.float64),
        ours: wp.array3d(dtype=wp.float64),
        theirs: wp.array3d(dtype=wp.float64),
    ):
        i, a, b = wp.tid()
        params = sets.params
        s = segments[a]
        lam, k, sigma = segment_heat_coeffs(params, sets.flags, sets.gas, i, s)
        d = seg_value(params, i, s, LENGTH) / wp.float64(heat_cells)
        nonlin = segment_nonlinear(params, i, s)
        xi = share[b] * seg_value(params, i, s, LENGTH)
        node0 = (s - first) * heat_cells
        th, dth = kf.gauss_profile(
            params, sets.flags, sets.gas, theta, i, s, node0, heat_cells, k, sigma, d, cell_shape(k, d), nonlin, xi
        )
        ours[i, a, 2 * b] = th
        ours[i, a, 2 * b + 1] = dth
        th, dth = segment_profile(params, sets.flags, sets.gas, theta, i, s, node0, heat_cells, k, sigma, d, nonlin, xi)
        theirs[i, a, 2 * b] = th
        theirs[i, a, 2 * b + 1] = dth

    core = load_core("ceramic")
    thermal = [j for j, seg in enumerate(core.segments) if seg.thermal]
    share = np.linspace(0.0, 1.0, 41)
    wall = {f"{core.segments[j].name}.wall_conductance": 5.0 for j in thermal}
    wall.update({f"{core.segments[j].name}.wall_resistance": 1e-3 for j in thermal})
    contact = {f"{core.segments[j].name}.contact_resistance": 3e-4 for j in thermal}
    kirchhoff = {f"{core.segments[j].name}.conductivity_exponent": 0.7 for j in thermal}
    for values in ({}, contact, {**wall, **contact}, {**kirchhoff, **contact}):
        names = list(values)
        engine = Engine(core, FREQS, names, ForwardSettings(device="cpu"))
        table = np.array([[20.0, 80.0]] + [[v, v] for v in values.values()])
        params, theta = engine.heat(table)
        ours = wp.zeros((2, len(thermal), 2 * share.size), dtype=wp.float64, device="cpu")
        theirs = wp.zeros_like(ours)
        wp.launch(
            profiles,
            dim=ours.shape[:2] + (share.size,),
            inputs=[
                engine._sets(params),
                theta,
                engine.first,
                engine.heat_cells,
                wp.array(thermal, dtype=wp.int32, device="cpu"),
                wp.array(share, dtype=wp.float64, device="cpu"),
                ours,
                theirs,
            ],
            device="cpu",
        )
        assert np.isfinite(theirs.numpy()).all() and np.abs(theirs.numpy()).max() > 1.0
        np.testing.assert_array_equal(ours.numpy(), theirs.numpy())


def test_distinct_serves_the_columns_it_computed_before_bit_for_bit(monkeypatch):
    # a CPU engine keeps the columns it computed (forward.MEMO_BYTES): a later batch that
    # shares some computes only the others, and its T-matrices are those of an engine that
    # computes them all (the kernels compute each set on its own)
    from tawarp.model.forward import Engine, ForwardSettings

    core = load_core("ceramic")
    names = ["stack.porosity", "stack.h"]
    settings = ForwardSettings(device="cpu", cells=8)
    eng = Engine(core, FREQS, names, settings)
    first = np.array([[0.0, 40.0, 40.0], [0.8, 0.8, 0.85], [150.0, 150.0, 150.0]])
    eng.distinct(first)
    computed = []
    compute = Engine._computed
    monkeypatch.setattr(
        Engine, "_computed", lambda self, table: computed.append(table.shape[1]) or compute(self, table)
    )
    later = np.column_stack([first[:, [2, 0]], [40.0, 0.9, 150.0]])
    T, column = eng.distinct(later)
    assert computed == [1]
    alone, alone_column = Engine(core, FREQS, names, settings).distinct(later)
    np.testing.assert_array_equal(T[column], alone[alone_column])


def same_partition(first, column, key):
    """``distinct_columns``' (first, column) of ``key`` against ``np.unique`` along the axis:
    the same groups of equal columns, each named by its first column, in any order."""
    _, want_first, want_column = np.unique(key, axis=1, return_index=True, return_inverse=True)
    want_column = want_column.reshape(-1)
    assert first.size == want_first.size
    # a column's group is named by the same first column both ways
    np.testing.assert_array_equal(first[column], want_first[want_column])


def test_distinct_columns_are_numpys_unique_columns():
    # a batch's columns: repeats (a set asked for twice), -0.0 beside 0.0 (equal values),
    # columns that differ in a late row only, and rows alike in every column (one of 0.0
    # and -0.0), which the sort skips; against np.unique along the axis
    rng = np.random.default_rng(3)
    base = rng.integers(0, 3, (7, 40)).astype(float)
    base[:, 7] = 0.0
    base[:, 8] = -0.0
    base[1] = 2.5
    base[4] = np.where(np.arange(40) % 2, 0.0, -0.0)
    key = base[:, rng.integers(0, 40, 120)]
    first, column = distinct_columns(key)
    same_partition(first, column, key)
    # the heat inputs (the first row) in order
    assert np.all(np.diff(key[0, first]) >= 0.0)
    # every row alike: one distinct column, the first
    got_first, got_column = distinct_columns(np.ones((3, 6)))
    np.testing.assert_array_equal(got_first, [0])
    np.testing.assert_array_equal(got_column, np.zeros(6))


@pytest.mark.parametrize("seed", range(5))
def test_distinct_columns_keep_apart_what_differs_by_a_step(seed):
    # forward-difference neighbours (one value 1e-6 relative up) of points whose values
    # span many decades (a temperature of 293 K beside a pore radius of 4e-5 m and a
    # conductance that moves by 1e-9 of itself), each asked for several times: no two sets
    # that differ merged, no copies left apart
    rng = np.random.default_rng(seed)
    point = np.array([40.0, 293.15, 1.01325e5, 3.8e-5, 0.69, 1.09, 120.0, 2e-4])
    points = point[:, None] * (1.0 + 1e-9 * rng.integers(0, 3, (point.size, 6)))
    # a row that spans two decades: a step of 1e-6 of its least value is 1e-8 of its range
    points[4] = np.geomspace(0.01, 1.0, 6)
    sets = [points]
    for j in range(1, point.size):
        step = points.copy()
        step[j] *= 1.0 + 1e-6
        sets.append(step)
    table = np.concatenate(sets, axis=1)
    key = table[:, rng.integers(0, table.shape[1], 4 * table.shape[1])]
    first, column = distinct_columns(key)
    same_partition(first, column, key)
