"""The next measurement: which further data would best decide between the models the
present data leave close.

When the most probable models are within :data:`ODDS` in posterior odds, candidate
measurement plans (the kind's extra groups, :meth:`MeasurementKind.extra_groups`: higher
heat inputs, a second sample length; frequency bands of the measured range at twice the
density; the measured range at twice the density; the band above it) are evaluated by the
batched forward model at each model's maximum a posteriori. A plan's worth is the expected
log Bayes factor between the best model A and a rival B if A is true: for Gaussian noise
of the data's level it is the Kullback-Leibler divergence of their predictions,
``E[ln B_AB] = sum (y_A - y_B)^2 / (2 sigma^2)`` over the plan's real residuals (Box & Hill,
Technometrics 9 (1967) 57; Lindley, Ann. Math. Stat. 27 (1956) 986: the expected
information of an experiment for discriminating models). The plans with the largest
smallest gain over the rivals are reported.
"""

from __future__ import annotations

import numpy as np

from ..fit.problems import KindProblems, predict_sets
from ..measure.kind import MeasurementKind
from .evidence import Model

#: Models within these posterior odds of the best are rivals a next measurement should separate.
ODDS = 20.0
#: Plans reported.
PLANS = 3
#: A rival is separable when some plan is expected to move the odds against it by at least
#: this (ln Bayes factor 1: a factor e); a rival that predicts the same data (an effect
#: fitted at its "off") is not separable by any measurement of the same kind.
MIN_GAIN = 1.0


def candidate_plans(problem: MeasurementKind) -> list[tuple[str, list[float], np.ndarray]]:
    """(description, groups, frequencies [Hz]) of each candidate plan."""
    f = np.unique(problem.freq)
    groups = [float(g) for g in np.unique(problem.group)]
    n = len(f)
    out = [(f"{problem.group_name} = {g:.4g} at the measured frequencies", [g], f) for g in problem.extra_groups()]
    for band in np.array_split(f, 3):
        if len(band) > 1:
            dense = np.linspace(band[0], band[-1], 2 * len(band))
            out.append(
                (f"{band[0]:.4g}-{band[-1]:.4g} Hz at twice the density, every {problem.group_name}", groups, dense)
            )
    out.append(
        (
            f"{f[0]:.4g}-{f[-1]:.4g} Hz at twice the density, every {problem.group_name}",
            groups,
            np.linspace(f[0], f[-1], 2 * n),
        )
    )
    out.append(
        (
            f"{f[-1]:.4g}-{1.5 * f[-1]:.4g} Hz, every {problem.group_name}",
            groups,
            np.linspace(f[-1], 1.5 * f[-1], max(n // 2, 4))[1:],
        )
    )
    return out


def _noise(problem: MeasurementKind) -> np.ndarray:
    """(coefficients, 2) noise sd of each coefficient's re and im parts in the data's units
    (the median over the measured rows of 1/w, w in units of the noise)."""
    return np.array(
        [[np.median(1.0 / problem.w[problem.coef == c, k]) for k in range(2)] for c in range(len(problem.coef_names))]
    )


def next_measurement(problem: MeasurementKind, models: list[Model], fixed: dict) -> list[dict]:
    """The :data:`PLANS` best plans (module doc) as report entries {description,
    heat_inputs_W / groups, frequencies_Hz, separates, expected_gain}; [] when the best model
    is more than :data:`ODDS` times as probable as every other, no plan separates a rival by
    :data:`MIN_GAIN`, or the kind cannot plan."""
    best = models[0]
    rivals = [m for m in models[1:] if m.probability > 0 and best.probability / m.probability <= ODDS][:3]
    if not rivals:
        return []
    sd = _noise(problem)
    plans, jobs, parts = [], [], []
    compared = [best] + rivals
    for text, groups, freqs in candidate_plans(problem):
        kind = problem.at_rows(groups, freqs)
        if kind is None:
            return []
        batch = KindProblems(kind, [(m.fit.params, m.fit.effect, m.fit.x[0]) for m in compared], fixed)
        sets, assemble = batch.prediction([(c, m.fit.x[:1]) for c, m in enumerate(compared)])
        parts.append((text, groups, freqs, kind, len(jobs), len(jobs) + len(sets), assemble))
        jobs += sets
    # every plan's predictions of the models in one request (one launch per plan and structure)
    got = predict_sets(jobs)
    for text, groups, freqs, kind, a, b, assemble in parts:
        pred = {m.label: y[0] for m, y in zip(compared, assemble(got[a:b]))}
        s = sd[kind.coef]
        gains = {
            m.label: float(
                np.sum(
                    ((pred[best.label] - pred[m.label]).real / s[:, 0]) ** 2
                    + ((pred[best.label] - pred[m.label]).imag / s[:, 1]) ** 2
                )
                / 2.0
            )
            for m in rivals
        }
        plans.append((text, groups, freqs, kind, pred, gains))
    # a rival that no plan separates predicts the best model's data (an effect fitted at its
    # "off"): it is the same model for any measurement of this kind, not one to decide against
    distinct = [m.label for m in rivals if max(p[5][m.label] for p in plans) >= MIN_GAIN]
    out = []
    key = "heat_inputs_W" if problem.groups_are_heat_inputs else problem.group_name
    for text, groups, freqs, kind, pred, gains in plans:
        if not distinct:
            break
        worst = min(distinct, key=gains.get)
        out.append(
            {
                "description": text,
                key: [float(g) for g in groups],
                "frequencies_Hz": [float(x) for x in freqs],
                "separates": [best.label, worst],
                "expected_gain": gains[worst],
                "expected_gain_per_rival": gains,
                "_predictions": pred,
                "_sd": sd[kind.coef],
                "_rows": (kind.freq, kind.group, kind.coef),
            }
        )
    out.sort(key=lambda p: -p["expected_gain"])
    return out[:PLANS]
