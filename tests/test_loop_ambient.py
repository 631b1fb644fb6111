"""The ambient exchangers (a structural effect: two porous segments of free length,
porosity and pore radius) in the loop's search, on T-matrices of the mesh core from the
independent reference (:mod:`tawarp.reference`) with test_loop's noise: field effects are
looked for beside the exchangers, and a probable model's fit, which descends along the long
valley of the exchangers' geometry, is reported at its optimum, not where the iteration cap
stopped it."""

import math

import numpy as np
import pytest

from tawarp import reference
from tawarp.loop import run as loop_run
from tawarp.loop.nesting import map_cost
from tawarp.loop.run import Comparison, converge_window, default_base_params, library_for
from tawarp.measure import TMatrixKind
from tawarp.measure.files import TMatrixData
from tawarp.model.coefficients import duct_impedance
from tawarp.model.effects import with_ambient_exchangers
from tawarp.model.forward import ForwardSettings
from test_loop import FREQS, MESH, NOISE, QS, prior

#: Ambient exchangers of the validation study's range (5-15 mm, porosity 0.6-0.85, pore
#: radius 0.3-1.2 mm) and buffer-tube convection of its typical size [W/(m^2 K^1.25)].
AMBIENT = {"length": 0.012, "porosity": 0.65, "pore_radius": 0.8e-3}
CONVECTION = 2.5
SEED = 0
_DATA: dict = {}


def ambient_data(convection: float) -> TMatrixData:
    """Reference T-matrices of the mesh core with :data:`AMBIENT` exchangers and buffer-tube
    convection ``convection``, plus complex noise NOISE x rms|Y|, with sigma."""
    if convection not in _DATA:
        core = with_ambient_exchangers(MESH.replace(**{"tbt.h_convection": convection}), **AMBIENT)
        Y = np.stack([reference.dimensionless_transfer(core, FREQS, Q) for Q in QS])
        Zc = duct_impedance(MESH)
        scale = np.array([[1.0, Zc], [1.0 / Zc, 1.0]])
        rng = np.random.default_rng(SEED)
        s = NOISE * np.sqrt(np.mean(np.abs(Y) ** 2))
        T = Y.reshape(-1, 2, 2) * scale
        T = T + s * scale * (rng.standard_normal(T.shape) + 1j * rng.standard_normal(T.shape))
        _DATA[convection] = TMatrixData(
            np.repeat(QS, FREQS.size), np.tile(FREQS, len(QS)), T, np.broadcast_to(s * scale, T.shape).copy()
        )
    return _DATA[convection]


def comparison(convection: float, names: tuple[str, ...]) -> Comparison:
    """The loop's comparison on :func:`ambient_data` from test_loop's prior, the library
    cut to ``names`` (every subset of them a model)."""
    prob = TMatrixKind(ambient_data(convection), prior(SEED), ForwardSettings(device="cpu"))
    library = [e for e in library_for(prob) if e.name in names]
    sizes = {k: math.comb(len(library), k) for k in range(len(library) + 1)}
    return Comparison(prob, default_base_params(prob), {}, library, sizes, False)


def test_field_effects_are_linearized_beside_the_exchangers():
    # convection beside the exchangers: the pair is scored at the exchangers' solution, and
    # the data, which hold both, prefer it to the exchangers alone
    cmp = comparison(CONVECTION, ("convection", "ambient_exchangers"))
    ambient = cmp.effect("ambient_exchangers")
    (at,) = cmp.refit([cmp.request(cmp_base(cmp), ("ambient_exchangers",), None)])
    assert at.fit.effect is ambient
    lin = cmp.linearize(at, [(cmp.effect("convection"), ambient)])
    assert [c.effects for c in lin] == [("convection", "ambient_exchangers")]
    assert lin[0].log_posterior > at.log_posterior


def cmp_base(cmp: Comparison):
    """The base model of ``cmp`` fitted from the core file (its MAP fit)."""
    (base,) = cmp.refit([((), [np.zeros(cmp.n_base)])])
    return base


def test_a_probable_fit_is_continued_to_its_optimum(monkeypatch):
    # the exchangers alone, fitted with the iteration cap cut to 8: the fit stops on its way
    # down the valley; converge_window continues it, with the loop's own cap, to the optimum
    # of a fit that ran to convergence (the same MAP cost)
    cmp = comparison(0.0, ("ambient_exchangers",))
    base = cmp_base(cmp)
    request = cmp.request(base, ("ambient_exchangers",), None)
    (full,) = cmp.refit([request])
    assert full.fit.reason[0] != "max_iterations"
    with monkeypatch.context() as m:
        m.setattr(loop_run, "MAX_ITER", 8)
        (cut,) = cmp.refit([request])
    assert cut.fit.reason[0] == "max_iterations"
    converge_window(cmp, [base, cut])
    assert cut.fit.reason[0] != "max_iterations"
    cost = [map_cost(m.fit.residuals[0], m.fit.x[0], m.priors) for m in (cut, full)]
    assert cost[0] == pytest.approx(cost[1], rel=1e-6)
    assert cut.probability > 0.99
