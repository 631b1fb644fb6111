"""What a one-objective design study holds beside its trial store (tests' helper)."""

import numpy as np


def improving_generations(ds, worker: str | None = None) -> list[int]:
    """The generations of a trials table (gradient, maximized; of ``worker`` alone where
    given) whose best feasible trial beats every generation before it: those whose best
    the study holds a copy of."""
    feasible = np.nan_to_num(ds.constraint.values.astype(float), nan=0.0) <= 0
    if worker is not None:
        feasible &= ds.worker.values == worker
    gens, gradient = ds.generation.values[feasible], ds.gradient.values[feasible]
    out, best = [], -np.inf
    for g in np.unique(gens):
        if gradient[gens == g].max() > best:
            out, best = out + [int(g)], gradient[gens == g].max()
    return out
