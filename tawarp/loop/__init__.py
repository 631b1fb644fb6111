"""Closing the loop with measured data (issues #4, #9): the paper's base fit, its goodness
of fit, then effects from a library one at a time, each step reported.

Steps of :func:`run_loop` (docs/loop.md states the rules with their numbers):

1. **Base fit**: the paper's full method (:func:`base_names`: the porosity, pore
   radius, tortuosity of every porous segment but the heater and every thermal segment's h, less the core file's
   ``[fit] pinned``), with the paper's two steps when Q = 0 and Q > 0 rows exist
   (:func:`fit_base`), on the package's one LM (:func:`tawarp.fit.problems.fit_batch`).
2. **Goodness of fit** (:mod:`.goodness`): reduced chi^2 and p-value against the data's
   sigma, or against noise estimated from the second differences along frequency of the
   residual; parameters at bounds flagged; an F-test of the residual's smooth structure
   along frequency (a fit explains the data only when its residual is also white).
3. **One effect at a time** while the fit is not adequate, or adequate but not white (a
   step then must leave it white) (:func:`run_loop`, ``_step``):
   screening of every candidate at the current solution in one batched launch
   (:mod:`.screen`: sign-constrained for one-sided effects, candidates degenerate with a
   current parameter to first order named, and refitted all the same), augmented fits of
   the promising ones in one lockstep batch,
   acceptance by Delta BIC, Holm-Bonferroni F-tests at a level halving with each step,
   held-out blocks (frequency bands, groups), no parameter at a bound, and stability over
   resamplings (decimations, block bootstraps); candidates within the BIC margin or with
   correlated changes are a group, accepted as one step and never claimed alone; held-out and
   resampled refits are linearized (:func:`linear_refit`).
4. **Verdict** (adequate, explained, indistinguishable,
   unexplained_residual with where it lives, wrong_model) and, with several heat inputs,
   the drift of the h's refitted per heat input before and after.

Modules: :mod:`.goodness`, :mod:`.screen`, :mod:`.run`, :mod:`.report` (report.json/md,
residual and drift figures).
"""

from .goodness import goodness_of_fit, noise_sigma, residual_location
from .report import write_report
from .run import (DELTA_BIC, F_TEST_P, STABILITY, WRONG_MODEL_CHI2, base_names, default_base_params, drift, fit_base,
                  holdout_blocks, holm, impedance_loop, library_for, linear_refit, resamplings, run_loop)
from .screen import residual_structure, screen

__all__ = ["goodness_of_fit", "noise_sigma", "residual_location", "write_report", "DELTA_BIC", "F_TEST_P",
           "STABILITY", "WRONG_MODEL_CHI2", "base_names", "default_base_params", "drift", "fit_base", "holdout_blocks",
           "holm", "impedance_loop", "library_for", "linear_refit", "resamplings", "run_loop", "residual_structure", "screen"]
