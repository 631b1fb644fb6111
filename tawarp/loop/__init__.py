"""Closing the loop with measured data: the paper's base fit, then a Bayesian comparison of
every model the library of effects makes, its verdict and the next measurement.

Steps of :func:`run_loop` (docs/loop.md states the rules with their numbers):

1. **Priors** (:mod:`tawarp.model.priors`): each parameter's prior from the core file's
   declared uncertainty or the documented default; an effect's parameters around "off".
2. **Base fit**, maximum a posteriori: the paper's full method (:func:`base_names`), with
   the paper's two steps when Q = 0 and Q > 0 rows exist (:func:`fit_base`). Without sigma
   columns the noise is estimated once from the least-squares base fit
   (:func:`tawarp.loop.goodness.noise_sigma`) and every model's likelihood uses it.
3. **Evidence** (:mod:`.evidence`): every subset of the library up to three effects,
   linearized at the base solution; the base, every single effect and the most probable
   subsets refitted (one lockstep batch) and scored by their Laplace log-evidence; posterior
   model probabilities and each effect's inclusion probability; effects the data cannot
   separate as groups.
4. **Checks and verdict**: the most probable model must pass the posterior predictive
   checks (chi^2 and whiteness, :mod:`.goodness`) with no parameter more than 3 prior sd
   from its prior; only then are effects claimed (inclusion >= 0.95, or a group's joint
   probability >= 0.95). Prior tension is reported by name.
5. **Next measurement** (:mod:`.plans`) when the top models are within 20:1, and the drift
   of the h's refitted per heat input.

Modules: :mod:`.evidence`, :mod:`.goodness` (the checks and the residual's structure),
:mod:`.plans`, :mod:`.run`, :mod:`.records` (the report as a record, :class:`LoopReport`),
:mod:`.report` (report.json/md and figures).
"""

from .goodness import goodness_of_fit, noise_sigma, residual_location, residual_structure
from .records import LoopReport
from .report import write_report
from .run import (
    MAX_EFFECTS,
    WRONG_MODEL_CHI2,
    base_names,
    default_base_params,
    drift,
    fit_base,
    impedance_loop,
    library_for,
    run_loop,
    run_loops,
)

__all__ = [
    "LoopReport",
    "goodness_of_fit",
    "noise_sigma",
    "residual_location",
    "write_report",
    "MAX_EFFECTS",
    "WRONG_MODEL_CHI2",
    "base_names",
    "default_base_params",
    "drift",
    "fit_base",
    "impedance_loop",
    "library_for",
    "run_loop",
    "run_loops",
    "residual_structure",
]
