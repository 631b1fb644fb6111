"""Warm starts of the temperature-dependent heat solve (kernels/heat.py, ``solve_heat``;
:mod:`tawarp.model.warm_starts`): a set whose iterations start from a nearby set's
converged excess reaches the cold start's fixed point to the solve's own tolerance, and
neither stops early nor on another solution; the host's store and the device's pick the
same kept set by the documented rule."""

import numpy as np
import pytest
import warp as wp

from tawarp.model.core import load_core, segment_parameter_fields
from tawarp.model.effects import graded_parts
from tawarp.model.fields import NONLINEAR_FIELDS, field
from tawarp.model.forward import Engine, ForwardSettings
from tawarp.model.warm_starts import WARM_RADIUS, DeviceWarmStarts, WarmStarts

FREQS = np.array([40.0, 130.0, 400.0])
Q = 40.0
#: the cold start's fixed point, to which every start must converge (the iterations stop
#: at a nodal change of picard_tol = 1e-12 of the largest excess; they contract ~1e3-fold
#: per solve near the solution, so a converged excess is within ~1e-14 of it)
AGREE = 1e-10
SETTINGS = ForwardSettings(device="cpu", cells=12, cpu_threads=1)


def convection_core():
    """The ceramic core with natural convection on its buffer tube and a temperature-dependent
    stack conductivity: the single-field Kirchhoff cells."""
    return load_core("ceramic").replace(**{"tbt.h_convection": 3.0, "stack.conductivity_exponent": 0.5})


def wall_core():
    """:func:`convection_core` with the buffer tube's wall a temperature field of its own:
    the two-field iterations (``solve_heat_wall``)."""
    return convection_core().replace(**{"tbt.wall_conductance": 2e-3, "tbt.wall_resistance": 0.05})


def graded_core():
    """The ceramic stack graded in porosity (8 parts, ten thermal segments) with a
    temperature-dependent conductivity, as a loop's porosity-gradient fits compute it."""
    core = load_core("ceramic").replace(**{"stack.conductivity_exponent": 0.5})
    return graded_parts(core, {"stack.porosity_gradient": np.array([0.1])}, 1)


def batch(core, values=None):
    """(engine, table): the point of ``values`` {name: value} at Q = 40 W, its forward-difference
    neighbours (each value 1e-6 relative up) and a set 5 % off in every value, all varying."""
    values = dict(values or {})
    for name in ("tbt.h", "stack.porosity", "stack.pore_radius", "tbt.h_convection", "stack.conductivity_exponent"):
        if name in core.parameter_names():
            values.setdefault(name, core.get(name))
    names = sorted(values)
    point = np.array([Q] + [float(np.ravel(values[k])[0]) for k in names])
    sets = [point]
    for j in range(1, point.size):
        sets.append(point.copy())
        sets[-1][j] *= 1.0 + 1e-6
    sets.append(point * np.r_[1.0, np.full(len(names), 1.05)])
    return Engine(core, FREQS, names, SETTINGS), np.array(sets).T


def relative(a, b):
    return float(np.abs(a - b).max() / np.abs(b).max())


CORES = {"convection": lambda: (convection_core(), None), "wall": lambda: (wall_core(), None), "graded": graded_core}


@pytest.mark.parametrize("name", sorted(CORES))
def test_warm_start_reaches_the_cold_fixed_point(name):
    # every set of the batch started from the point's converged excess (the neighbours as a
    # loop's fits start them; the 5 % set from farther than a loop would) and from that excess
    # 10 % too high (a start the first solve does not confirm): the T-matrices and the excess
    # of the cold start within AGREE, set by set
    eng, table = batch(*CORES[name]())
    assert eng.nonlinear
    T_cold, _, theta_cold = (a.numpy() for a in eng.evaluate(table))
    for factor in (1.0, 1.1):
        start = np.repeat(factor * theta_cold[:1], table.shape[1], axis=0)
        T_warm, _, theta_warm = (a.numpy() for a in eng.evaluate(table, start=start))
        for i in range(table.shape[1]):
            assert relative(theta_warm[i], theta_cold[i]) < AGREE, (factor, i)
            assert relative(T_warm[i], T_cold[i]) < AGREE, (factor, i)


@pytest.mark.parametrize("name", sorted(CORES))
def test_warm_start_takes_fewer_solves(name):
    # the neighbours started from their point's excess converge within two solves (the
    # cold start's two are > 1e-6 off: it takes four to six), so the warm start is what
    # saves the solves
    core, values = CORES[name]()
    eng, table = batch(core, values)
    _, _, theta = (a.numpy() for a in eng.evaluate(table))
    short = Engine(core, FREQS, eng.names, ForwardSettings(device="cpu", cells=12, cpu_threads=1, picard_iterations=2))
    neighbours = table[:, 1:-1]
    start = np.repeat(theta[:1], neighbours.shape[1], axis=0)
    warm = short.heat(neighbours, start)[1].numpy()
    cold = short.heat(neighbours)[1].numpy()
    assert relative(warm, theta[1:-1]) < AGREE
    assert relative(cold, theta[1:-1]) > 1e-6


def test_distinct_starts_neighbours_from_their_point():
    # the loop's order: the points, then their neighbours; the engine keeps the points'
    # excesses and starts each neighbour from its own point's (a second point's neighbours
    # must not take the first's), and the T-matrices are the cold engine's within AGREE
    core = convection_core()
    eng, table = batch(core)
    other = table.copy()
    other[1:] *= 1.03  # a second point, 3 % away: within WARM_RADIUS of the first
    assert 0.03 < WARM_RADIUS
    points = np.concatenate([table[:, :1], other[:, :1]], axis=1)
    neighbours = np.concatenate([table[:, 1:-1], other[:, 1:-1]], axis=1)
    eng.distinct(points)
    start = eng.warm.starts(neighbours)
    half = neighbours.shape[1] // 2
    theta_points = Engine(core, FREQS, eng.names, SETTINGS).evaluate(points)[2].numpy()
    assert np.array_equal(start[:half], np.repeat(theta_points[:1], half, axis=0))
    assert np.array_equal(start[half:], np.repeat(theta_points[1:], half, axis=0))
    T, column = eng.distinct(neighbours)
    cold, cold_column = Engine(core, FREQS, eng.names, SETTINGS).distinct(neighbours)
    assert relative(T[column], cold[cold_column]) < AGREE


@pytest.mark.parametrize("name", CORES)
def test_an_engine_with_its_kept_sets_on_the_device_computes_as_with_them_on_the_host(name):
    # a GPU's engine keeps its sets in a DeviceWarmStarts: given to a CPU engine (its kernels
    # on Warp's CPU device), the points' excesses start their neighbours and a second point's
    # as the host's store starts them, so the T-matrices are the same to the bit
    core, values = CORES[name]()
    host, table = batch(core, values)
    device, _ = batch(core, values)
    w = host.warm
    device.warm = DeviceWarmStarts(w.limit, w.rows, w.columns, w.switches, w.always, device="cpu")
    other = table.copy()
    other[1:] *= 1.03
    points = np.concatenate([table[:, :1], other[:, :1]], axis=1)
    neighbours = np.concatenate([table[:, 1:], other[:, 1:]], axis=1)
    for eng in (host, device):
        eng.distinct(points)
    np.testing.assert_array_equal(starts(device.warm, neighbours), starts(host.warm, neighbours))
    assert np.any(starts(host.warm, neighbours))
    (T_host, column_host), (T_device, column_device) = (eng.distinct(neighbours) for eng in (host, device))
    np.testing.assert_array_equal(T_device[column_device], T_host[column_host])


def test_no_warm_start_across_heat_inputs_far_sets_or_unheated_sets():
    # a kept set starts only sets at its own heat input within WARM_RADIUS: others, and every
    # set without heat input (its excess is 0 exactly, from a zero start), start cold
    eng, table = batch(convection_core())
    eng.distinct(table[:, :1])
    cases = np.repeat(table[:, 1:2], 4, axis=1)
    cases[0, 1] = 20.0  # another heat input
    cases[1:, 2] *= 1.0 + 2 * WARM_RADIUS  # far in every value
    cases[0, 3] = 0.0  # no heat input
    start = eng.warm.starts(cases)
    assert np.any(start[0] != 0.0)
    assert not np.any(start[1:])


#: the two stores of kept sets: the host's, and the device's kernels on Warp's CPU device
#: and, where there is one, on a CUDA device
STORES = {
    "host": WarmStarts,
    "device": lambda *args: DeviceWarmStarts(*args, device="cpu"),
    "cuda": lambda *args: DeviceWarmStarts(*args, device="cuda"),
}
KINDS = [
    "host",
    "device",
    pytest.param("cuda", marks=pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device")),
]


def put(warm, table, theta):
    """``warm.put`` of host arrays, each store given its kind of array."""
    if isinstance(warm, DeviceWarmStarts):
        warm.put(
            table,
            wp.array(table, dtype=wp.float64, device=warm.device),
            wp.array(theta, dtype=wp.float64, device=warm.device),
        )
    else:
        warm.put(table, None, theta)


def starts(warm, table):
    """``warm.starts`` as a host array (n, columns), zeros where it gives None."""
    got = warm.starts(table, wp.array(table, dtype=wp.float64, device=getattr(warm, "device", "cpu")))
    if got is None:
        return np.zeros((table.shape[1], warm.columns))
    return got.numpy() if isinstance(got, wp.array) else got


@pytest.mark.parametrize("kind", KINDS)
def test_a_start_is_the_nearest_kept_excess_by_the_documented_distance(kind):
    # WarmStarts.starts against the rule written out set by set: per row over the kept and
    # the batch's heated sets together, ln v where every value is positive, else v over the
    # row's largest |v|; the largest |difference| over the rows; the nearest kept set within
    # WARM_RADIUS. The table has rows alike in every set (which the fast path skips), a
    # signed row and two heat inputs; zeros where a set is not heated or has no kept set near
    rng = np.random.default_rng(11)
    rows, kept, new = 12, 300, 80
    base = rng.uniform(0.5, 2.0, rows)

    def table(n):
        t = np.repeat(base[:, None], n, axis=1)
        t[0] = rng.choice([0.0, 20.0, 40.0], n)
        t[2:6] *= np.exp(rng.normal(0.0, 0.06, (4, n)))
        t[6] = rng.normal(0.0, 1e-3, n)
        return t

    warm = STORES[kind](kept, rows, 5, np.array([1]), True)
    kept_table, kept_theta = table(kept), rng.normal(size=(kept, 5))
    put(warm, kept_table, kept_theta)
    cases = table(new)
    start = starts(warm, cases)
    held = kept_table[:, kept_table[0] > 0]
    held_theta = kept_theta[kept_table[0] > 0]
    heated = np.flatnonzero(cases[0] > 0)
    both = np.concatenate([held, cases[:, heated]], axis=1)
    positive = np.all(both > 0, axis=1)[:, None]
    u = np.where(positive, np.log(np.abs(both)), both / np.abs(both).max(axis=1)[:, None])
    expected = np.zeros((new, 5))
    for k, i in enumerate(heated):
        distance = np.abs(u[:, : held.shape[1]] - u[:, held.shape[1] + k, None]).max(axis=0)
        if distance.min() <= WARM_RADIUS:
            expected[i] = held_theta[np.argmin(distance)]
    assert np.count_nonzero(expected.any(axis=1)) > new // 4  # the rule starts some sets warm
    np.testing.assert_array_equal(start, expected)


@pytest.mark.parametrize("kind", KINDS)
def test_the_kept_sets_are_the_last_limit_put_in_order(kind):
    # puts of 3, 5, 1 and 9 sets into a store of 7: a set asked for again starts from its own
    # excess exactly while it is among the last 7 put, and cold after
    limit, rows = 7, 3
    values = np.exp(np.arange(18) * 2.5 * WARM_RADIUS)  # 18 sets, none near another
    assert np.min(np.diff(np.log(values))) > WARM_RADIUS
    sets = np.vstack([np.full(18, 40.0), values, np.full(18, 0.5)])
    theta = np.arange(18.0)[:, None] + np.zeros((18, 2))
    warm = STORES[kind](limit, rows, 2, np.array([2]), False)
    done = 0
    for m in (3, 5, 1, 9):
        put(warm, sets[:, done : done + m], theta[done : done + m])
        done += m
        kept = set(range(max(0, done - limit), done))
        start = starts(warm, sets[:, :done])
        for i in range(done):
            want = theta[i] if i in kept else np.zeros(2)
            np.testing.assert_array_equal(start[i], want, err_msg=f"set {i} after {done} put")


@pytest.mark.parametrize("kind", KINDS[1:])
def test_of_equally_near_kept_sets_the_oldest_starts_a_set(kind):
    # the device's rule (the host's k-d tree takes any of equals): 40 sets put four times
    # over (each copy its own excess) into a ring of 150, which has then wrapped: every set
    # has three or four equal copies kept, far apart in age (the search's parts hold
    # different copies), and its start is the excess of the oldest copy still kept
    rows, distinct, limit = 3, 40, 150
    values = np.exp(np.arange(distinct) * 2.5 * WARM_RADIUS)  # none near another
    sets = np.vstack([np.full(distinct, 40.0), values, np.full(distinct, 0.5)])
    warm = STORES[kind](limit, rows, 2, np.array([1]), False)
    for copy in range(4):
        put(warm, sets, np.full((distinct, 2), float(copy)) + np.arange(distinct)[:, None])
    # puts 0..159 into a ring of 150: the first ten sets' first copies are gone
    oldest = np.where(np.arange(distinct) < 4 * distinct - limit, 1.0, 0.0)
    np.testing.assert_array_equal(starts(warm, sets), (oldest + np.arange(distinct))[:, None] + np.zeros((1, 2)))


def test_the_sets_that_iterate_are_those_with_a_temperature_dependent_field_on():
    # every field of the ceramic core's stack moved off its core value, one per set (the
    # first set the core's own): the heat solve iterates (one solve is not its converged
    # result) exactly in the sets whose moved field is in NONLINEAR_FIELDS, and those are the
    # sets the engine warm-starts (WarmStarts.iterating): a field the kernel reads at the
    # local temperature without the fields' table saying so fails here
    core = load_core("ceramic")
    seg = next(s for s in core.segments if s.name == "stack")
    names = [f"stack.{f}" for f in segment_parameter_fields(seg)]
    table = np.tile(np.r_[Q, [core.get(n) for n in names]][:, None], (1, 1 + len(names)))
    for j, name in enumerate(names):
        f = field(name)
        v = table[1 + j, 0]
        moved = v * 1.1 if f.log else (v + 0.1 * f.scale if v else 0.1 * f.scale)
        assert f.check(moved), name
        table[1 + j, 1 + j] = moved
    one, full = (
        Engine(core, FREQS, names, ForwardSettings(device="cpu", cells=12, cpu_threads=1, picard_iterations=k))
        for k in (1, 100)
    )
    theta_one, theta_full = (e.heat(table)[1].numpy() for e in (one, full))
    iterates = [i for i in range(table.shape[1]) if not np.array_equal(theta_one[i], theta_full[i], equal_nan=True)]
    expected = [1 + j for j, n in enumerate(names) if n.partition(".")[2] in NONLINEAR_FIELDS]
    assert sorted(expected) and iterates == sorted(expected)
    assert full.warm.iterating(table).tolist() == iterates


def test_threads_take_each_sets_own_start():
    # a batch split over two CPU threads (its sets dealt like cards) gives each set its own
    # start: the same bits as one thread, where every set starts from a different excess
    core = convection_core()
    eng, table = batch(core)
    table = np.tile(table, (1, 10))
    table[1] *= np.linspace(1.0, 1.05, table.shape[1])
    theta = eng.evaluate(table)[2].numpy()
    start = theta * np.linspace(0.9, 1.1, table.shape[1])[:, None]
    two = Engine(core, FREQS, eng.names, ForwardSettings(device="cpu", cells=12, cpu_threads=2))
    assert two._cpu_parts(table.shape[1]) == 2
    T_one, T_two = (e.evaluate(table, start=start)[0].numpy() for e in (eng, two))
    assert np.array_equal(T_one, T_two)
