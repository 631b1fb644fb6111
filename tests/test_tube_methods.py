"""Tube methods on exact (noise-free) transfer functions of the independent tube model
(tawarp.tube.synthetic): exact recovery, the time convention, the conditioning flags, the
first-order error propagation against Monte Carlo, and bad input."""

import numpy as np
import pytest

from tawarp.tube import e2611, iso10534, synthetic, terminations
from tawarp.tube.spectra import Transfers

from tube_cases import BACKED, LOAD_A, LOAD_B, MICS, SOURCE_DOWN, TUBE, core, layer, nonreciprocal

# inside the spacing band of s = 0.08 m: 0.05-0.45 wavelength is 215-1930 Hz
F = np.linspace(250.0, 1900.0, 67)


def exact(f, specimen, setup, positions=MICS.positions, thickness=MICS.thickness):
    """Noise-free transfer functions from the drive to the microphones."""
    h = synthetic.pressures(f, specimen(f), thickness, setup, TUBE, positions)
    return Transfers(f, h, np.zeros(h.shape + (h.shape[1],), dtype=complex))


def relative_error(t, truth, z0):
    """Largest error of the dimensionless coefficients (Tpp, Tpu / Zc, Tup Zc, Tuu)."""
    scale = np.stack([np.stack([np.ones_like(z0), z0], -1), np.stack([1 / z0, np.ones_like(z0)], -1)], -2)
    return np.max(np.abs((t - truth) / np.abs(scale)))


def constants(f):
    return TUBE.wavenumber(f), TUBE.impedance(f)


@pytest.mark.parametrize("method, second", [(e2611.two_load, LOAD_B), (e2611.two_source, SOURCE_DOWN)])
def test_two_state_methods_recover_the_specimen_exactly(method, second):
    """A non-reciprocal specimen from load A and load B, or from load A driven from either end."""
    k, z0 = constants(F)
    r = method(exact(F, nonreciprocal, LOAD_A), exact(F, nonreciprocal, second), MICS, k, z0)
    assert r.valid.all()
    assert relative_error(r.values, nonreciprocal(F), z0) < 1e-9
    assert np.all(r.sd == 0)


@pytest.mark.parametrize("setup", [LOAD_A, LOAD_B])
def test_one_load_recovers_a_symmetric_reciprocal_specimen_exactly(setup):
    k, z0 = constants(F)
    r = e2611.one_load(exact(F, layer, setup), MICS, k, z0)
    assert r.valid.all()
    assert relative_error(r.values, layer(F), z0) < 1e-9
    np.testing.assert_allclose(np.linalg.det(r.values), 1.0, atol=1e-12)


def test_one_load_forces_symmetry_on_a_non_reciprocal_specimen():
    """The one-load result is symmetric and reciprocal whatever the specimen (E2611's assumption)."""
    k, z0 = constants(F)
    r = e2611.one_load(exact(F, nonreciprocal, LOAD_A), MICS, k, z0)
    np.testing.assert_allclose(r.values[:, 0, 0], r.values[:, 1, 1], rtol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r.values), 1.0, atol=1e-12)
    assert relative_error(r.values, nonreciprocal(F), z0) > 0.01


def test_an_air_slab_has_the_exp_minus_iwt_signs():
    """An empty stretch of tube (the specimen is air) measures as tawarp's duct,
    Tpu = i Zc sin(kL) with Im Tpu > 0 and Im Tup > 0 at low frequency (docs/formats.md)."""
    f = np.linspace(220.0, 600.0, 20)
    k, z0 = constants(f)
    length = 0.05
    mics = e2611.FourMics(l1=0.15, s1=0.08, l2=0.15 + length, s2=0.08, thickness=length)
    km, zm = np.conj(k), np.conj(z0)  # the tube's own waves, in exp(-iwt)
    duct = np.stack(
        [
            np.stack([np.cos(km * length), 1j * zm * np.sin(km * length)], -1),
            np.stack([1j * np.sin(km * length) / zm, np.cos(km * length)], -1),
        ],
        -2,
    )
    a = exact(f, lambda f: duct, LOAD_A, mics.positions, length)
    b = exact(f, lambda f: duct, LOAD_B, mics.positions, length)
    r = e2611.two_load(a, b, mics, k, z0)
    assert relative_error(r.values, duct, z0) < 1e-9
    assert np.all(r.values[:, 0, 1].imag > 0) and np.all(r.values[:, 1, 0].imag > 0)


def test_surface_impedance_recovers_a_rigid_backed_layer_exactly():
    """ISO 10534-2 on a layer against a rigid wall: Zs = -S Tuu / Tup over rho0 c0, and the
    same number as ISO's own reflection-coefficient formula from H12."""
    k, z0 = constants(F)
    x1, x2 = 0.2, 0.12
    t = exact(F, layer, BACKED, positions=[-x1, -x2])
    rho_c = TUBE.density * TUBE.sound_speed
    r = iso10534.surface_impedance(t, x1, x2, k, z0 * TUBE.area / rho_c)
    truth = -TUBE.area * layer(F)[:, 1, 1] / layer(F)[:, 1, 0] / rho_c
    assert r.valid.all()
    np.testing.assert_allclose(r.values, truth, rtol=1e-9)
    h12 = t.values[:, 1] / t.values[:, 0]
    s = x1 - x2
    reflection = (h12 - np.exp(-1j * k * s)) / (np.exp(1j * k * s) - h12) * np.exp(2j * k * x1)
    iso = np.conj(z0 * TUBE.area / rho_c * (1 + reflection) / (1 - reflection))
    np.testing.assert_allclose(r.values, iso, rtol=1e-9)
    assert r.values[0].imag > 0  # a thin layer is stiffness-like in exp(-iwt)


@pytest.mark.filterwarnings("error")
def test_spacing_near_half_a_wavelength_is_flagged():
    """s = 0.08 m is half a wavelength at c / (2 s) = 2145 Hz: beyond 0.45 wavelength (1931 Hz)
    and below 0.05 wavelength (215 Hz) no value is written; at the half wavelength itself
    and at DC (k = 0, singular pairs) nothing raises or warns."""
    c = TUBE.sound_speed
    f = np.sort(np.append(np.linspace(100.0, 3000.0, 59), [1.0, c / (2 * MICS.s1)]))
    k, z0 = constants(f)
    k[0] = 0.0  # the DC line
    r = e2611.two_load(exact(f, nonreciprocal, LOAD_A), exact(f, nonreciprocal, LOAD_B), MICS, k, z0)
    ratio = MICS.s1 * k.real / (2 * np.pi)
    inside = (ratio >= 0.05) & (ratio <= 0.45)
    np.testing.assert_array_equal(r.valid, inside)
    assert np.all(np.isnan(r.values[~inside])) and np.all(np.isnan(r.sd[~inside]))
    assert all("mic spacing s1" in reason for reason in r.reason[~inside])
    assert all(reason == "" for reason in r.reason[inside])
    assert relative_error(r.values[inside], nonreciprocal(f)[inside], z0[inside]) < 1e-9


def test_alike_loads_are_flagged():
    """Two loads whose upstream states nearly coincide: the normalized state matrix's
    condition number exceeds the limit and no value is written."""
    k, z0 = constants(F)
    near = synthetic.Setup(length_up=0.6, length_down=0.4, reflection_up=0.3, reflection_down=0.0501)
    r = e2611.two_load(exact(F, nonreciprocal, LOAD_A), exact(F, nonreciprocal, near), MICS, k, z0)
    assert not r.valid.any()
    assert np.all(r.condition > 100)
    assert all(reason.startswith("loads too alike (cond") for reason in r.reason)


def monte_carlo_sd(method, measurements, draws=4000, seed=0):
    """Sample standard deviation of the real parts of ``method(measurements)`` over draws of
    each measurement's circular complex Gaussian error with its covariance; the draws are
    stacked along the frequency axis (the methods take the tube's constants per frequency)."""
    rng = np.random.default_rng(seed)
    nf = len(measurements[0].frequencies)

    def tile(x):
        return np.tile(x, (draws,) + (1,) * (np.ndim(x) - 1))

    noisy = []
    for t in measurements:
        n = t.values.shape[1]
        e = (rng.standard_normal((draws * nf, n)) + 1j * rng.standard_normal((draws * nf, n))) / np.sqrt(2)
        chol = tile(np.linalg.cholesky(t.covariance))
        noisy.append(
            Transfers(tile(t.frequencies), tile(t.values) + np.einsum("fij,fj->fi", chol, e), tile(t.covariance))
        )
    values = method(noisy).values
    values = values.reshape((draws, nf) + values.shape[1:])
    return np.std(np.real(values), axis=0)


def with_covariance(t, relative, seed):
    """``t`` with a random Hermitian positive-definite covariance of ``relative`` size."""
    rng = np.random.default_rng(seed)
    n = t.values.shape[1]
    m = (rng.standard_normal((len(t.frequencies), n, n)) + 1j * rng.standard_normal((len(t.frequencies), n, n))) / n
    scale = relative * np.abs(t.values)
    cov = scale[:, :, None] * (m @ np.conj(np.swapaxes(m, 1, 2)) + np.eye(n)) * scale[:, None, :]
    return Transfers(t.frequencies, t.values, cov)


def _two_load(ms):
    k, z0 = constants(ms[0].frequencies)
    return e2611.two_load(*ms, MICS, k, z0)


def _one_load(ms):
    k, z0 = constants(ms[0].frequencies)
    return e2611.one_load(*ms, MICS, k, z0)


def _surface_impedance(ms):
    k, z0 = constants(ms[0].frequencies)
    return iso10534.surface_impedance(*ms, 0.2, 0.12, k, z0)


LENGTHS = (0.1, 0.25, 0.45)


def _core_tmatrix(ms):
    f = ms[0].frequencies
    loads = [synthetic.closed_end(f, length, TUBE) for length in LENGTHS]
    return terminations.core_tmatrix(ms, loads, TUBE.impedance(f))


@pytest.mark.parametrize("method", [_two_load, _one_load, _surface_impedance, _core_tmatrix])
def test_first_order_errors_match_monte_carlo(method):
    """The linearized sd (J C J^H) against 4000 draws of correlated errors of 0.1 % size:
    within 10 % (the Monte Carlo's own scatter is 1.1 %)."""
    f = F[::6]
    if method is _two_load:
        ms = [with_covariance(exact(f, nonreciprocal, s), 1e-3, i) for i, s in enumerate((LOAD_A, LOAD_B))]
    elif method is _one_load:
        ms = [with_covariance(exact(f, layer, LOAD_A), 1e-3, 2)]
    elif method is _surface_impedance:
        ms = [with_covariance(exact(f, layer, BACKED, positions=[-0.2, -0.12]), 1e-3, 3)]
    else:
        ms = [
            with_covariance(
                Transfers(f, synthetic.sensor_pressures(core(f), load), np.zeros((f.size, 2, 2))), 1e-3, 4 + j
            )
            for j, load in enumerate(synthetic.closed_end(f, length, TUBE) for length in LENGTHS)
        ]
    r = method(ms)
    assert r.valid.all()
    np.testing.assert_allclose(monte_carlo_sd(method, ms), r.sd, rtol=0.1)


# -- the multi-termination method ----------------------------------------------------------
def test_closed_tube_is_the_wave_model_of_a_rigid_end():
    f = np.linspace(30.0, 500.0, 48)
    np.testing.assert_allclose(
        terminations.closed_tube(TUBE.wavenumber(f), TUBE.impedance(f), 0.37),
        synthetic.closed_end(f, 0.37, TUBE),
        rtol=1e-12,
    )


def test_input_impedance_alone_leaves_the_scale_free():
    """c T gives the same input impedance under every termination; only p(x6) tells them apart."""
    f = np.linspace(30.0, 500.0, 48)
    load = synthetic.closed_end(f, 0.3, TUBE)
    one, three = synthetic.sensor_pressures(core(f), load), synthetic.sensor_pressures(3.0 * core(f), load)
    np.testing.assert_allclose(one[:, 0], three[:, 0], rtol=1e-12)
    np.testing.assert_allclose(three[:, 1], 3.0 * one[:, 1], rtol=1e-12)


@pytest.mark.parametrize("lengths", [(0.1, 0.25), (0.1, 0.25, 0.45), (0.1, 0.25, 0.45, 0.7, 0.9)])
def test_core_tmatrix_recovers_a_non_reciprocal_core_exactly(lengths):
    f = np.linspace(30.0, 500.0, 48)
    z0 = TUBE.impedance(f)
    loads = [synthetic.closed_end(f, length, TUBE) for length in lengths]
    readings = [Transfers(f, synthetic.sensor_pressures(core(f), load), np.zeros((f.size, 2, 2))) for load in loads]
    r = terminations.core_tmatrix(readings, loads, z0)
    assert r.valid.all()
    assert relative_error(r.values, core(f), z0) < 1e-9
    assert np.all(np.abs(np.linalg.det(r.values) - 1.0) > 0.5)


def test_alike_terminations_are_flagged():
    f = np.linspace(30.0, 500.0, 12)
    z0 = TUBE.impedance(f)
    loads = [synthetic.closed_end(f, length, TUBE) for length in (0.3, 0.3001)]
    readings = [Transfers(f, synthetic.sensor_pressures(core(f), load), np.zeros((f.size, 2, 2))) for load in loads]
    r = terminations.core_tmatrix(readings, loads, z0)
    assert not r.valid.any() and all("terminations too alike" in reason for reason in r.reason)


# -- bad input -------------------------------------------------------------------------------
def test_bad_input_raises_clear_errors():
    k, z0 = constants(F)
    a, b = exact(F, nonreciprocal, LOAD_A), exact(F, nonreciprocal, LOAD_B)
    with pytest.raises(ValueError, match=r"shape \(67, 3\); expected \(67, 4\)"):
        e2611.two_load(Transfers(F, a.values[:, :3], a.covariance[:, :3, :3]), b, MICS, k, z0)
    nan = a.values.copy()
    nan[5, 2] = np.nan
    with pytest.raises(ValueError, match="NaN or infinite transfer functions at 1 frequencies"):
        e2611.two_load(Transfers(F, nan, a.covariance), b, MICS, k, z0)
    with pytest.raises(ValueError, match="other frequencies"):
        e2611.two_load(a, Transfers(F + 1.0, b.values, b.covariance), MICS, k, z0)
    with pytest.raises(ValueError, match="k has shape"):
        e2611.two_load(a, b, MICS, k[:5], z0)
    with pytest.raises(ValueError, match="negative real part"):
        e2611.two_load(a, b, MICS, -k, z0)
    with pytest.raises(ValueError, match="expected a Transfers"):
        e2611.one_load(a.values, MICS, k, z0)
    with pytest.raises(ValueError, match="microphone 1 upstream of 2"):
        e2611.FourMics(l1=0.15, s1=-0.08, l2=0.2, s2=0.08, thickness=0.03)
    with pytest.raises(ValueError, match="microphone 3 must lie downstream"):
        e2611.FourMics(l1=0.15, s1=0.08, l2=0.02, s2=0.08, thickness=0.03)
    with pytest.raises(ValueError, match="FourMics.l1"):
        e2611.FourMics(l1=float("nan"), s1=0.08, l2=0.2, s2=0.08, thickness=0.03)
    two = Transfers(F, a.values[:, :2], a.covariance[:, :2, :2])
    with pytest.raises(ValueError, match="microphone 1 is the one farther"):
        iso10534.surface_impedance(two, 0.1, 0.2, k, z0)
    with pytest.raises(ValueError, match="x2 = -0.1"):
        iso10534.surface_impedance(two, 0.2, -0.1, k, z0)
    load = synthetic.closed_end(F, 0.3, TUBE)
    with pytest.raises(ValueError, match="needs at least two"):
        terminations.core_tmatrix([two], [load], z0)
    with pytest.raises(ValueError, match="2 readings but 1 loads"):
        terminations.core_tmatrix([two, two], [load], z0)
    with pytest.raises(ValueError, match="load 2 contains NaN or infinite values"):
        terminations.core_tmatrix([two, two], [load, np.full(F.size, np.inf)], z0)
