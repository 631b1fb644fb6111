"""Failures that must end in a clear message or go on: a design worker whose sampler
degenerated, bad files and arguments (one line naming the file and what to do)."""

from __future__ import annotations

import numpy as np
import pytest

from tawarp.design import search as search_module
from tawarp.design.samplers import make_sampler
from tawarp.design.search import search
from tawarp.design.space import DesignSpace
from tawarp.design.storage import trials_table
from tawarp.model.core import load_core


def _space():
    return DesignSpace(load_core("rvc_foam"), ["heat_input=1:18", "stack.length=0.01:0.1"])


class _DegeneratedSampler:
    """CMA-ES as it failed before its restarts: generation 2 asked as NaN points (stored
    by the search), then ``cmaes``' tell refusing them."""

    def __init__(self, *args):
        self.inner = make_sampler(*args)

    @property
    def generation(self):
        return self.inner.generation

    def ask(self, n):
        X = self.inner.ask(n)
        return np.full_like(X, np.nan) if self.inner.generation == 2 else X

    def tell(self, X, F, violation):
        if not np.all(np.isfinite(X)):
            raise AssertionError("Abs of all param values must be less than 1e+32 to avoid overflow errors")
        self.inner.tell(X, F, violation)


def test_a_worker_whose_sampler_degenerated_resumes(tmp_path, monkeypatch):
    """A lineage holding a generation of NaN points (stored by a sampler that then failed)
    resumes with the seed and batch it was started with, to the trials asked; no point
    stored after it is NaN."""
    journal = str(tmp_path / "s.journal")
    with monkeypatch.context() as m:
        m.setattr(search_module, "make_sampler", lambda *a: _DegeneratedSampler(*a))
        with pytest.raises(AssertionError, match="1e\\+32"):
            search(_space(), n_trials=64, batch=8, storage=journal, seed=3)
    ds = trials_table(search(_space(), n_trials=64, batch=8, storage=journal, seed=3).study)
    assert sorted(ds.generation.values.tolist()) == [g for g in range(8) for _ in range(8)]
    nan = np.isnan(ds["heat_input"].values) | np.isnan(ds["stack.length"].values)
    assert set(ds.generation.values[nan].tolist()) == {2}
