"""The design search with its generations committed in groups (``commit_seconds``): the
same trials and the same study as committing every generation."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from study_copies import improving_generations

from tawarp.design.samplers import BatchCmaEs, pareto_mask
from tawarp.design.search import SearchCrash, search
from tawarp.design.space import DesignSpace
from tawarp.design.storage import study_summary, trials_table
from tawarp.model.core import load_core

VARS = ["material=ceramic,rvc_foam", "stack.length=0.005:0.1", "heat_input=1:30"]
NAMES = ["material", "stack.length", "heat_input", "gradient", "T_max", "heat_leak"]


def _space():
    return DesignSpace(load_core("rvc_foam"), VARS)


def _table(study):
    ds = trials_table(study)
    order = np.lexsort((ds["index"].values, ds.generation.values))
    return {k: ds[k].values[order] for k in NAMES + ["generation", "index"]}


@pytest.mark.parametrize("objectives", [("gradient",), ("gradient", "heat_leak")])
def test_grouped_commits_store_the_same_study(tmp_path, objectives):
    """Everything committed once at the end (commit_seconds far above the run) gives the
    trials of committing each generation, every one in the store; the study's copies:
    one objective, the best of each generation that improves on the generations before;
    two, exactly the feasible front of all trials (copies that a later generation of the
    group dominates are not written)."""
    kw = dict(n_trials=96, batch=16, seed=5, T_limit=450.0)
    each = search(_space(), objectives, storage=str(tmp_path / "a.journal"), commit_seconds=0.0, **kw)
    grouped = search(_space(), objectives, storage=str(tmp_path / "b.journal"), commit_seconds=1e9, **kw)
    # every generation committed, each append in the store's thread while the next runs
    overlapped = search(_space(), objectives, storage=str(tmp_path / "c.journal"), commit_seconds=1e-9, **kw)
    a, b, c = _table(each.study), _table(grouped.study), _table(overlapped.study)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        np.testing.assert_array_equal(a[k], c[k], err_msg=k)
    assert study_summary(grouped.study)["trials"] == 96
    if len(objectives) == 1:
        assert grouped.study.best_trial.values == each.study.best_trial.values
        improving = improving_generations(trials_table(grouped.study))
        for res in (each, grouped):
            assert sorted(t.system_attrs["tawarp:generation"] for t in res.study.trials) == improving
    else:
        ds = trials_table(grouped.study)
        ok = (ds.constraint.values <= 0) & (ds.state.values == "COMPLETE")
        F = np.stack([-ds.gradient.values[ok], ds.heat_leak.values[ok]], axis=1)
        front = {tuple(f) for f in F[pareto_mask(F)]}
        assert {(-t.values[0], t.values[1]) for t in grouped.study.best_trials} == front
        assert len(grouped.study.trials) <= len(each.study.trials)


def test_an_interrupted_grouped_run_commits_what_it_evaluated_and_resumes(tmp_path):
    """A run stopped (an exception) after asking its 4th generation commits the three it
    evaluated when it closes; the resumed run completes the lineage as an uninterrupted
    one, each (generation, index) once."""
    journal = str(tmp_path / "s.journal")
    kw = dict(n_trials=96, batch=16, seed=2, commit_seconds=1e9)
    with pytest.raises(SearchCrash):
        search(_space(), storage=journal, _stop_after=4, **kw)
    from tawarp.design.storage import open_study

    assert study_summary(open_study(journal, "tawarp-design", ["gradient"]))["trials"] == 48
    res = search(_space(), storage=journal, **kw)
    ds = trials_table(res.study)
    assert ds.sizes["trial"] == 96 and len(set(zip(ds.generation.values.tolist(), ds["index"].values.tolist()))) == 96
    ref = _table(search(_space(), n_trials=96, batch=16, seed=2).study)
    got = _table(res.study)
    for k in ref:
        np.testing.assert_array_equal(got[k], ref[k], err_msg=k)


def test_a_large_front_is_copied_spread_along_it(tmp_path, monkeypatch):
    """Several objectives: a lineage front larger than FRONT_COPIES puts that many of its
    members in the study, the two ends of each objective among them, every one on the
    front of all trials (which the trial store holds whole)."""
    from tawarp.design import search as search_module

    monkeypatch.setattr(search_module, "FRONT_COPIES", 5)
    objectives = ("gradient", "heat_leak")
    res = search(
        _space(), objectives, n_trials=96, batch=16, seed=5, T_limit=450.0, storage=str(tmp_path / "s.journal")
    )
    ds = trials_table(res.study)
    ok = (ds.constraint.values <= 0) & (ds.state.values == "COMPLETE")
    F = np.stack([-ds.gradient.values[ok], ds.heat_leak.values[ok]], axis=1)
    front = F[pareto_mask(F)]
    assert len(front) > 5
    copied = np.array([(-t.values[0], t.values[1]) for t in res.study.trials])
    assert len(copied) == 5 and {tuple(f) for f in copied} <= {tuple(f) for f in front}
    for j in range(2):
        assert front[:, j].min() in copied[:, j] and front[:, j].max() in copied[:, j]
    assert len(res.best) == 5


def test_a_failed_overlapped_append_stops_the_search(tmp_path, monkeypatch):
    """An append to the trial store that fails in the store's thread (a full disk) is
    raised by the search at its next commit, and what was stored before stays."""
    from tawarp.design.storage import StoreWriter

    append, calls = StoreWriter.append, []

    def failing(self, *a, **k):
        calls.append(1)
        if len(calls) == 3:
            raise OSError(28, "trial store: no space left on device")
        return append(self, *a, **k)

    monkeypatch.setattr(StoreWriter, "append", failing)
    journal = str(tmp_path / "s.journal")
    with pytest.raises(OSError, match="no space left"):
        search(_space(), storage=journal, n_trials=96, batch=16, seed=2, commit_seconds=1e-9)
    from tawarp.design.storage import open_study

    assert study_summary(open_study(journal, "tawarp-design", ["gradient"]))["trials"] == 2 * 16


@pytest.mark.parametrize(
    "device",
    ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not wp.is_cuda_available(), reason="no CUDA device"))],
)
def test_launched_generations_are_the_generations_asked_and_told(monkeypatch, device):
    """CMA-ES's generations launched with their update and evaluation in one sequence (on
    a GPU one CUDA graph, replayed from the third generation on) store the trials that
    the sampler's ask and tell store with the evaluation between them, bit for bit, over
    40 generations with the temperature limit active."""
    from tawarp.model.forward import ForwardSettings

    kw = dict(n_trials=40 * 16, batch=16, seed=11, T_limit=420.0, settings=ForwardSettings(device=device))
    launched = _table(search(_space(), **kw).study)
    monkeypatch.delattr(BatchCmaEs, "launch_generation")
    asked = _table(search(_space(), **kw).study)
    for k in launched:
        np.testing.assert_array_equal(launched[k], asked[k], err_msg=k)
