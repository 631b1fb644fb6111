"""The secant (Broyden) iteration of the batched fit (``jacobian="broyden"``, the default
where the problems cascade): it recovers the truth from reference data (tawarp.reference,
not the Warp kernels), ends within 0.1 standard deviations of the forward-difference fit
(its confirm rule, :data:`tawarp.fit.lm.SECANT_CONFIRM`) with the same covariance, and
spends a stated number of cascades per fit."""

import numpy as np
import pytest
import warp as wp

from tawarp import reference
from tawarp.fit.estimate import fit
from tawarp.fit.lm import SECANT_CONFIRM
from tawarp.measure.synthetic import paper_frequencies
from tawarp.model.core import load_core
from tawarp.model.forward import ForwardSettings, transfer_matrices

HEAT = ["stack.h", "hot_hx.h", "tbt.h"]
Q = 40.0


@pytest.fixture(scope="module")
def heated_reference():
    """The mesh core's dimensionless coefficients at 40 W from the NumPy/SciPy reference
    (16 paper frequencies) and their sigma (0.5 % complex noise)."""
    core = load_core("mesh")
    freqs = paper_frequencies("mesh", 16)
    Y0 = reference.dimensionless_transfer(core, freqs, Q, rtol=1e-10)
    return core, freqs, Y0, 0.005 * np.abs(Y0) / np.sqrt(2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_secant_fits_recover_the_truth_from_reference_data(heated_reference, seed):
    # 4 noise draws, each problem started 10-30 % off every h (random signs); the secant
    # fit recovers the truth within 3 std (the reference is independent of the Warp
    # kernels: their difference, < 1e-6, is far below the noise) and lands within
    # SECANT_CONFIRM std of the forward-difference fit, whose last steps end far inside
    # xtol (a small margin: the confirm rule measures the step in the linearization);
    # the std agree to 1e-3 (both come from a forward-difference Jacobian at the solution)
    core, freqs, Y0, sd = heated_reference
    rng = np.random.default_rng(seed)
    n = 4
    Y = Y0 + sd * (rng.standard_normal((n,) + Y0.shape) + 1j * rng.standard_normal((n,) + Y0.shape))
    truth = np.array([core.get(k) for k in HEAT])
    start = truth * (1 + rng.uniform(0.1, 0.3, (n, 3)) * rng.choice([-1.0, 1.0], (n, 3)))
    kw = dict(heat_input=Q, weights=1 / sd, device="cpu", warn=False)
    secant = fit(core, freqs, Y, HEAT, start, jacobian="broyden", **kw)
    difference = fit(core, freqs, Y, HEAT, start, jacobian="difference", **kw)
    assert secant.converged.all() and difference.converged.all()
    assert np.all(np.abs(secant.values - truth) < 3 * secant.std)
    assert np.max(np.abs(secant.values - difference.values) / difference.std) < 1.2 * SECANT_CONFIRM
    assert np.max(np.abs(secant.std / difference.std - 1)) < 1e-3


def test_secant_cascades_per_fit_of_the_heat_workload():
    # bench/fit.py's heat workload (100 frequencies, data from 48 Magnus cells, every
    # start 30 % off): forward differences take 1 + p = 4 cascades per problem at the
    # start and at each of the 4 trials, 20 in all. The secant iteration: the start shared
    # by the batch (the same set: 4 cascades, and 9 for its second derivatives), 3 trials
    # of one cascade (the first step geodesically accelerated, its Jacobian Taylor-updated)
    # and p = 3 for the fresh Jacobian at the solution: 6 + 13/n, below 6.5 with n = 32
    core = load_core("mesh")
    freqs = np.linspace(30.0, 500.0, 100)
    Y0 = transfer_matrices(core, freqs, Q, cells=48, device="cpu").dimensionless()[0]
    sd = 0.005 * np.abs(Y0) / np.sqrt(2)
    rng = np.random.default_rng(0)
    n = 32
    Y = Y0 + sd * (rng.standard_normal((n,) + Y0.shape) + 1j * rng.standard_normal((n,) + Y0.shape))
    truth = np.array([core.get(k) for k in HEAT])
    kw = dict(heat_input=Q, weights=1 / sd, settings=ForwardSettings(device="cpu"), warn=False)
    secant = fit(core, freqs, Y, HEAT, truth * [1.3, 0.7, 1.3], **kw)
    difference = fit(core, freqs, Y, HEAT, truth * [1.3, 0.7, 1.3], jacobian="difference", **kw)
    assert secant.converged.all() and difference.converged.all()
    assert difference.evaluations == 20 * n
    assert secant.evaluations / n < 6.5 and secant.iterations.max() == 3
    assert np.max(np.abs(secant.values - difference.values) / difference.std) < 1.2 * SECANT_CONFIRM


def _heat_problems(n, seed, freqs, cells=12):
    """n noise draws of the mesh core at 40 W (model data on ``cells`` Magnus cells), all
    but the last two started from one point (its second derivatives shared), those two
    from another."""
    core = load_core("mesh")
    Y0 = transfer_matrices(core, freqs, Q, cells=cells, device="cpu").dimensionless()[0]
    sd = 0.005 * np.abs(Y0) / np.sqrt(2)
    rng = np.random.default_rng(seed)
    Y = Y0 + sd * (rng.standard_normal((n,) + Y0.shape) + 1j * rng.standard_normal((n,) + Y0.shape))
    truth = np.array([core.get(k) for k in HEAT])
    start = truth * np.where(np.arange(n)[:, None] < n - 2, [1.3, 0.7, 1.3], [0.8, 1.2, 0.9])
    return core, Y, sd, start


def test_secant_launches_split_by_max_sets_give_the_same_fits():
    # at most 5 sets per launch: the starts, their second differences, the trials and the
    # refreshes run in several launches each; every slot's arithmetic is its own, so the
    # fits are the same to the bit, and so is the number of sets evaluated
    freqs = paper_frequencies("mesh", 12)
    core, Y, sd, start = _heat_problems(20, 4, freqs)
    kw = dict(heat_input=Q, weights=1 / sd, settings=ForwardSettings(cells=8, device="cpu"), warn=False)
    one = fit(core, freqs, Y, HEAT, start, jacobian="broyden", **kw)
    split = fit(core, freqs, Y, HEAT, start, jacobian="broyden", max_sets=5, **kw)
    assert one.converged.all() and split.launches > one.launches
    for f in ("values", "std", "cost", "iterations"):
        assert np.array_equal(getattr(split, f), getattr(one, f)), f
    assert split.evaluations == one.evaluations


@pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device")
def test_secant_fits_on_cuda_match_the_cpu():
    # the same problems on both devices: the cascades agree to rounding, so the decisions
    # (iterations, cascades) agree but where a test sits on its threshold (then the two
    # solutions still lie within SECANT_CONFIRM std of the minimum), and the values of
    # the others to 1e-6 std
    freqs = paper_frequencies("mesh", 16)
    core, Y, sd, start = _heat_problems(64, 5, freqs)
    res = {
        dev: fit(
            core,
            freqs,
            Y,
            HEAT,
            start,
            heat_input=Q,
            weights=1 / sd,
            jacobian="broyden",
            warn=False,
            settings=ForwardSettings(cells=8, device=dev),
        )
        for dev in ("cpu", "cuda")
    }
    cpu, gpu = res["cpu"], res["cuda"]
    assert cpu.converged.all() and gpu.converged.all()
    same = cpu.iterations == gpu.iterations
    assert same.mean() >= 0.95 and abs(gpu.evaluations / cpu.evaluations - 1) < 0.05
    dv = np.abs(gpu.values - cpu.values) / cpu.std
    assert np.max(dv[same]) < 1e-6 and np.max(dv) < 2 * SECANT_CONFIRM
    assert np.max(np.abs(gpu.std / cpu.std - 1)[same]) < 1e-6
