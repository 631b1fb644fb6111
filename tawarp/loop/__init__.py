"""Closing the loop with measured data (issue #4): residual diagnosis, a library of
effects, the error before and after.

Steps of :func:`run_loop`:

1. **Base fit** of the given free parameters on the package's one LM
   (:func:`tawarp.fit.problems.fit_one`; the Jacobian is one batched forward launch of
   1 + p parameter sets: forward differences, step 1e-6 in the scaled variables of
   :class:`tawarp.model.effects.Param`, bounds and scaling from :mod:`tawarp.model.fields`).
   Data with ``sigma`` are weighted by it (chi^2); without, by 1/rms|Y| (the error measure).
2. **Residual structure**: the weighted residual per coefficient against frequency and
   heat input (or layer); ``structured_fraction`` is the part of it that a cubic in
   frequency per (coefficient, group, re/im) explains (white noise gives about
   ``n_poly / N``).
3. **Screening**: every candidate effect's sensitivity columns at the base solution, all
   in one batched launch (structural candidates: one launch each); its *score* is the
   fraction of the residual that a linearized step along those columns, orthogonalized
   against the base columns, explains: ``||P_(C perp B) r||^2 / ||r||^2``. Pure noise
   gives about ``k / (N - p)`` for k columns; the linearized F statistic gives a p-value.
4. **Augmented fits** of the promising candidates (linearized p < 0.01, best ``top`` by
   score), two starts each with the effect off (the base solution, the core's values), all
   in one batch (:func:`tawarp.fit.problems.fit_batch`: :func:`tawarp.fit.lm.levenberg_marquardt` on all of
   them at once, one forward launch per iteration for every candidate's trial point and
   Jacobian); when none of them is
   accepted, the other candidates too (the screening is only linear).
5. **Choice.** An effect is accepted when all of:
   a. ``Delta BIC < -10`` (BIC = chi^2 + p ln N with known sigma, else N ln(RSS/N) + p ln N;
      "very strong" on Kass & Raftery's scale);
   b. F-test ``F = ((RSS0 - RSS1)/k) / (RSS1/(N - p - k))`` beyond the 99 % quantile of
      F(k, N - p - k): the cost drop exceeds what noise would give (p < 0.01);
   c. prediction: refitted without the held-out rows (the highest heat input, or every
      third frequency when there is one group), the augmented model predicts them better
      than the base model;
   d. with known sigma: the residual after is noise: its chi^2 lies below the 99.9 %
      quantile of chi^2(N - p - k), and the error after is within 1.5 times the noise floor
      (otherwise the effect explains only part of a structure it does not describe: no
      claim).
   Among accepted candidates the lowest BIC wins; none accepted: ``chosen_effect = None``.
6. **Drift**: with several heat inputs, the heat-exchange coefficients ``*.h`` are refitted
   at each heat input alone (everything else fixed) before and after; the paper's model
   says they should not drift with Q.

Measurement kinds: any :class:`tawarp.measure.MeasurementKind` (core T-matrices, also
from a scattering matrix, and the surface impedance of rigid-backed layers built in; the
held-out rows and the drift need T-matrix data). Modules: :mod:`.screen` (residual
structure, screening), :mod:`.run` (the loop), :mod:`.report` (report.json/md, figures).
"""

from .goodness import goodness_of_fit, noise_sigma, residual_location
from .report import write_report
from .run import (DELTA_BIC, F_TEST_P, STABILITY, WRONG_MODEL_CHI2, base_names, default_base_params, drift, fit_base,
                  holdout_blocks, holm, impedance_loop, library_for, resamplings, run_loop)
from .screen import residual_structure, screen

__all__ = ["goodness_of_fit", "noise_sigma", "residual_location", "write_report", "DELTA_BIC", "F_TEST_P",
           "STABILITY", "WRONG_MODEL_CHI2", "base_names", "default_base_params", "drift", "fit_base", "holdout_blocks",
           "holm", "impedance_loop", "library_for", "resamplings", "run_loop", "residual_structure", "screen"]
