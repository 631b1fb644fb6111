"""Random streams from a caller's seed, checked once for the whole package.

NumPy refuses a negative seed with "expected non-negative integer" and a fractional one
with a TypeError about a SeedSequence, neither naming what was wrong where: a public
function that takes a ``seed`` checks it here first (:func:`checked_seed`), so the error
names the function and the argument. A valid seed's stream is NumPy's own:
:func:`generator` is ``np.random.default_rng(seed)``.
"""

from __future__ import annotations

import numbers

import numpy as np


def checked_seed(seed, where: str, *, argument: str = "seed", integer: bool = False):
    """``seed`` unchanged when it is a non-negative integer (Python's or NumPy's) or, unless
    ``integer``, None (fresh entropy) or a ``np.random.Generator`` (used as it is), as
    ``np.random.default_rng`` takes them; ``integer=True`` where the seed enters arithmetic
    or a ``SeedSequence``. Anything else (a negative or fractional number, a bool, a string)
    raises ValueError "WHERE: ARGUMENT must be a non-negative integer, got SEED"."""
    if not integer and (seed is None or isinstance(seed, np.random.Generator)):
        return seed
    if isinstance(seed, numbers.Integral) and not isinstance(seed, bool) and seed >= 0:
        return seed
    raise ValueError(f"{where}: {argument} must be a non-negative integer, got {seed!r}")


def generator(seed, where: str, *, argument: str = "seed") -> np.random.Generator:
    """``np.random.default_rng(seed)`` once :func:`checked_seed` accepts ``seed`` (None
    and a Generator included); ``where`` names the function that took it."""
    return np.random.default_rng(checked_seed(seed, where, argument=argument))
