"""Design search and its study storage (tawarp.design.search, tawarp.design.storage) and
the design command line, on the CPU."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from processes import reaped
from study_copies import improving_generations

from tawarp.design.samplers import nondominated_ranks
from tawarp.design.search import SearchCrash, search
from tawarp.design.space import DesignSpace
from tawarp.design.storage import StudyConflict, open_study, study_summary, trials_table
from tawarp.model.core import load_core

ROOT = Path(__file__).resolve().parents[1]
PAPER = ("ceramic", "mesh", "nicr_foam", "rvc_foam")


def known_optimum():
    """The optimum of the 2-D search (stack.length in [4, 100] mm, Q in [1, 9] W, rvc_foam core).

    The stack [x2, x3] has no source and an adiabatic cold end, so
    theta(x) = theta3 cosh(k (x - x2)) / cosh(k L), k = sqrt(2 h_s/(R lam_s)), and the heat
    it draws from the hot exchanger is F = G_s theta3 with G_s = lam_s S k tanh(k L). The
    rest of the heat model (hot exchanger with the source, buffer tube) is linear and does
    not depend on L: by superposition theta3 = a Q - b F, hence
    theta3 = a Q / (1 + b G_s(L)), and the gradient across the stack is

        g(L, Q) = a Q (1 - sech(k L)) / (L (1 + b G_s(L))).

    g is proportional to Q, so Q* = 9 W (T_max stays far below the limit); L* maximizes
    (1 - sech kL) / (L (1 + b G_s)): short stacks lose the temperature difference
    (1 - sech kL -> k^2 L^2 / 2), long ones divide it by L. a and b come from the exact
    solution at two lengths; the formula is checked at a third.
    """
    from scipy.optimize import minimize_scalar

    from tawarp.reference import heat_profile_exact, segment_conductivity

    core = load_core("rvc_foam")
    lam, h, R, S = segment_conductivity(core, 1), core.segments[1].h, core.radius, core.area
    k = np.sqrt(2 * h / (R * lam))
    G = lambda L: lam * S * k * np.tanh(k * L)  # noqa: E731

    def theta3(L):
        c = core.replace(**{"stack.length": L})
        return float(heat_profile_exact(c, 9.0).theta_in(1, c.positions()[2]))

    (c0, c1) = np.linalg.solve([[1, G(0.01)], [1, G(0.06)]], [1 / theta3(0.01), 1 / theta3(0.06)])
    a, b = 1 / (9.0 * c0), c1 / c0
    assert theta3(0.03) == pytest.approx(a * 9.0 / (1 + b * G(0.03)), rel=1e-10)
    g = lambda L: a * 9.0 / (1 + b * G(L)) * (1 - 1 / np.cosh(k * L)) / L  # noqa: E731
    r = minimize_scalar(lambda L: -g(L), bounds=(0.004, 0.1), method="bounded", options={"xatol": 1e-10})
    assert 0.005 < r.x < 0.09  # interior
    return core, r.x, g(r.x)


@pytest.mark.parametrize("engine", ["batched", "optuna"])
def test_search_finds_the_known_optimum(engine):
    core, L_star, g_star = known_optimum()
    space = DesignSpace(core, ["stack.length=0.004:0.1", "heat_input=1:9"])
    res = search(space, n_trials=640, batch=32, seed=0, engine=engine)
    best = res.best[0]
    assert best["params"]["stack.length"] == pytest.approx(L_star, rel=0.03)
    assert best["params"]["heat_input"] > 8.95
    assert best["values"]["gradient"] == pytest.approx(g_star, rel=2e-3)
    assert best["values"]["gradient"] <= g_star * (1 + 1e-9)
    t = res.timing
    assert t["evaluations"] == 640 and 0 < t["evaluation_share"] < 1 and 0 < t["sampler_share"] < 1


def test_multi_objective_front_is_feasible_and_nondominated():
    core = load_core("rvc_foam")
    space = DesignSpace(core, ["material=ceramic,rvc_foam", "stack.length=0.005:0.1", "heat_input=1:30"])
    res = search(space, ("gradient", "heat_leak"), n_trials=256, batch=32, seed=3, T_limit=450.0)
    front = res.best
    assert len(front) >= 5
    F = np.array([[-b["values"]["gradient"], b["values"]["heat_leak"]] for b in front])
    assert np.all(nondominated_ranks(F) == 0)
    assert all(b["metrics"]["T_max"] <= 450.0 for b in front)
    # the constraint was active: some trials were infeasible
    trials = res.study.get_trials()
    assert any(t.system_attrs["constraints"][0] > 0 for t in trials)


# -- persistence -----------------------------------------------------------------------------
_SCRIPT = """
import sys
from tawarp.model.core import load_core
from tawarp.design.space import DesignSpace
from tawarp.design.search import search
core = load_core("rvc_foam")
space = DesignSpace(core, ["stack.length=0.004:0.1", "heat_input=1:9", "hot_hx.length=0.005:0.03"])
kw = dict(n_trials=int(sys.argv[3]), batch=8, storage=sys.argv[1], worker=sys.argv[2], seed=int(sys.argv[4]))
if len(sys.argv) > 5:
    kw["_crash_after"] = int(sys.argv[5])
search(space, **kw)
"""


def _run(args, **kw):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen(
        [sys.executable, "-c", _SCRIPT, *map(str, args)],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        **kw,
    )


def _space():
    return DesignSpace(load_core("rvc_foam"), ["stack.length=0.004:0.1", "heat_input=1:9", "hot_hx.length=0.005:0.03"])


def _keys(ds) -> list[tuple]:
    return list(zip(ds.worker.values.tolist(), ds.generation.values.tolist(), ds["index"].values.tolist()))


def _same_rows(got, want, names) -> None:
    """Two trials tables hold the same trials (by worker, generation, index): the same
    points and metrics to 1e-12 relative."""
    kg, kw = _keys(got), _keys(want)
    assert len(set(kg)) == len(kg) and set(kg) == set(kw)
    og, ow = np.argsort([str(k) for k in kg]), np.argsort([str(k) for k in kw])
    for n in names:
        a, b = got[n].values[og], want[n].values[ow]
        if a.dtype.kind in "US":
            assert (a == b).all(), n
        else:
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=0, err_msg=n)


def _copies_are_the_generation_bests(study, ds) -> None:
    """One objective: the study holds exactly one copy per (worker, generation) that
    improved on the worker's generations before, its best feasible trial (a row of the
    table, values to the last bit)."""
    copies = study.get_trials()
    keys = [(t.system_attrs["tawarp:worker"], t.system_attrs["tawarp:generation"]) for t in copies]
    improving = {(w, g) for w in set(ds.worker.values.tolist()) for g in improving_generations(ds, w)}
    assert len(keys) == len(set(keys)) and set(keys) == improving
    for t in copies:
        sa = t.system_attrs
        gen = (ds.worker.values == sa["tawarp:worker"]) & (ds.generation.values == sa["tawarp:generation"])
        best = np.flatnonzero(gen)[
            np.argmax(np.where(ds.constraint.values[gen] <= 0, ds.gradient.values[gen], -np.inf))
        ]
        assert sa["tawarp:copy"] and int(ds["index"].values[best]) == sa["tawarp:index"]
        assert t.values[0] == ds.gradient.values[best] and int(ds.number.values[best]) == t.number


def test_resume_after_a_killed_run(tmp_path):
    """A process dies (os._exit) after asking its 2nd batch: the first is stored, the asked
    one is not; on resume the study becomes the one an uninterrupted run makes (the sampler
    state is replayed from the stored generations), nothing lost or duplicated."""
    journal = tmp_path / "study.journal"
    with reaped(_run([journal, "w0", 32, 5, 2])) as (p,):
        out, _ = p.communicate(timeout=120)
    assert p.returncode == 3, out
    st = study_summary(open_study(str(journal), "tawarp-design", ["gradient"]))
    # the copies come at a run's end: a killed run leaves them to its resume
    assert st["trials"] == 8 and st["states"] == {"COMPLETE": 8} and st["in_study"] == 0
    res = search(_space(), n_trials=32, batch=8, storage=str(journal), seed=5)
    assert res.resumed == 0
    ds = trials_table(res.study)
    assert ds.sizes["trial"] == 32 and set(ds.state.values) == {"COMPLETE"}
    assert sorted(ds.generation.values.tolist()) == sorted([g for g in range(4) for _ in range(8)])
    ref = search(_space(), n_trials=32, batch=8, seed=5)  # in memory: every trial in the study
    _same_rows(ds, trials_table(ref.study), ["stack.length", "heat_input", "hot_hx.length", "gradient", "T_max"])
    _copies_are_the_generation_bests(res.study, ds)
    # running it again adds nothing: the lineage is complete
    again = search(_space(), n_trials=32, batch=8, storage=str(journal), seed=5)
    assert trials_table(again.study).sizes["trial"] == 32 and again.resumed == 0
    assert len(again.study.trials) == len(res.study.trials)


def test_resume_in_process_optuna_engine(tmp_path):
    journal = str(tmp_path / "o.journal")
    with pytest.raises(SearchCrash):
        search(_space(), n_trials=32, batch=8, storage=journal, engine="optuna", _stop_after=2)
    res = search(_space(), n_trials=32, batch=8, storage=journal, engine="optuna")
    trials = res.study.get_trials()
    assert res.resumed == 8 and len(trials) == 32 and {t.state.name for t in trials} == {"COMPLETE"}
    assert len({t.number for t in trials}) == 32


@pytest.mark.parametrize("kind", ["sqlite", "journal"])
def test_two_processes_share_one_study(tmp_path, kind):
    url = f"sqlite:///{tmp_path / 'study.db'}" if kind == "sqlite" else str(tmp_path / "study.journal")
    with reaped(_run([url, "a", 48, 1]), _run([url, "b", 40, 2])) as procs:
        for p in procs:
            out, _ = p.communicate(timeout=180)
            assert p.returncode == 0, out
    study = open_study(url, "tawarp-design", ["gradient"])
    st = study_summary(study)
    assert st["trials"] == 48 + 40 and st["states"] == {"COMPLETE": 88} and st["unique"]
    assert st["workers"] == {"a": 48, "b": 40}
    # every trial of each worker is the one a lone run of that worker makes
    ds = trials_table(study)
    for w, n, seed in (("a", 48, 1), ("b", 40, 2)):
        ref = trials_table(search(_space(), n_trials=n, batch=8, worker=w, seed=seed).study)
        _same_rows(
            ds.isel(trial=ds.worker.values == w),
            ref,
            ["stack.length", "heat_input", "hot_hx.length", "gradient", "T_max"],
        )
    if kind == "journal":  # one trial-store file per worker run, the study holds a copy per improvement
        assert st["in_study"] == sum(len(improving_generations(ds, w)) for w in ("a", "b"))
        assert sorted(p.name.split("-")[0] for p in (tmp_path / "study.trials" / "tawarp-design").glob("*.h5")) == [
            "a",
            "b",
        ]
    else:
        assert st["in_study"] == 88 and st["store"] is None


# -- command line ----------------------------------------------------------------------------
def _cli(argv):
    import argparse

    from tawarp.cli.design import add_design_parser, add_rank_parser, add_sweep_parser

    parser = argparse.ArgumentParser(prog="tawarp")
    sub = parser.add_subparsers(dest="command", required=True)
    add_design_parser(sub)
    add_rank_parser(sub)
    add_sweep_parser(sub)
    args = parser.parse_args(argv)
    return args.func(args)


def test_cli_design_rank_sweep(tmp_path):
    import xarray as xr

    out = tmp_path / "d"
    assert (
        _cli(
            [
                "design",
                "rvc_foam",
                "--var",
                "stack.length=0.005:0.1",
                "--var",
                "Q=1:18",
                "--var",
                "material=ceramic,rvc_foam",
                "--trials",
                "64",
                "--batch",
                "16",
                "--device",
                "cpu",
                "--quiet",
                "-o",
                str(out),
            ]
        )
        == 0
    )
    rep = json.loads((out / "design.json").read_text())
    assert rep["summary"]["trials"] == 64 and rep["best"] and (out / "history.png").exists()
    assert (out / "best_profiles.png").exists() and (out / "study.journal").exists()
    assert rep["trial_store"] == str((out / "study.trials" / "tawarp-design").resolve())
    from tawarp.design.storage import open_study, trials_table

    copies = improving_generations(trials_table(open_study(str(out / "study.journal"), "tawarp-design", ["gradient"])))
    assert rep["summary"]["in_study"] == len(copies)
    assert (
        _cli(
            [
                "design",
                "rvc_foam",
                "--var",
                "stack.length=0.005:0.1",
                "--var",
                "Q=1:18",
                "--objectives",
                "gradient,acoustic_loss",
                "--freqs",
                "100,300",
                "--trials",
                "32",
                "--batch",
                "16",
                "--quiet",
                "-o",
                str(tmp_path / "mo"),
            ]
        )
        == 0
    )
    assert (tmp_path / "mo" / "pareto.png").exists()
    # the same output folder with other ranges: refused, design.json untouched
    with pytest.raises(StudyConflict, match="design space"):
        _cli(
            [
                "design",
                "rvc_foam",
                "--var",
                "stack.length=0.005:0.2",
                "--var",
                "Q=1:18",
                "--objectives",
                "gradient,acoustic_loss",
                "--freqs",
                "100,300",
                "--trials",
                "16",
                "--batch",
                "16",
                "--device",
                "cpu",
                "--quiet",
                "--no-plots",
                "-o",
                str(tmp_path / "mo"),
            ]
        )
    assert json.loads((tmp_path / "mo" / "design.json").read_text())["summary"]["trials"] == 32
    assert _cli(["rank", "--Q", "9,18", "--samples", "100", "--quiet", "-o", str(tmp_path / "rank.json")]) == 0
    rank = json.loads((tmp_path / "rank.json").read_text())
    assert {r["material"] for r in rank["ranking"]} == set(PAPER) and (tmp_path / "rank.png").exists()
    assert (
        _cli(
            [
                "sweep",
                "rvc_foam",
                "--var",
                "stack.length=0.01:0.08:4",
                "--var",
                "Q=1:18:3",
                "--quiet",
                "-o",
                str(tmp_path / "s.nc"),
            ]
        )
        == 0
    )
    ds = xr.open_dataset(tmp_path / "s.nc", engine="h5netcdf")
    assert ds.gradient.shape == (4, 3)
    ds.close()


def test_resume_a_generation_cut_short(tmp_path):
    """A process killed half-way through storing a generation (one append per trial): the
    missing members are asked again (the sampler is deterministic) and nothing is lost."""
    from optuna.trial import create_trial

    url = f"sqlite:///{tmp_path / 'cut.db'}"
    ref = search(_space(), n_trials=24, batch=8, seed=2)
    search(_space(), n_trials=8, batch=8, storage=url, seed=2)
    study = open_study(url, "tawarp-design", ["gradient"])
    # three members of generation 1, as a process that died would have left them
    gen1 = sorted(
        (t for t in ref.study.get_trials() if t.system_attrs["tawarp:generation"] == 1),
        key=lambda t: t.system_attrs["tawarp:index"],
    )[:3]
    study.add_trials(
        [
            create_trial(
                params=t.params,
                distributions=t.distributions,
                values=t.values,
                user_attrs=t.user_attrs,
                system_attrs=t.system_attrs,
            )
            for t in gen1
        ]
    )
    res = search(_space(), n_trials=24, batch=8, storage=url, seed=2)
    trials = res.study.get_trials()
    assert res.resumed == 5 and len(trials) == 24 and {t.state.name for t in trials} == {"COMPLETE"}
    key = lambda t: (t.system_attrs["tawarp:generation"], t.system_attrs["tawarp:index"])  # noqa: E731
    assert sorted(map(key, trials)) == sorted(map(key, ref.study.get_trials()))
    for a, b in zip(sorted(trials, key=key), sorted(ref.study.get_trials(), key=key)):
        assert a.params == pytest.approx(b.params, rel=1e-12)


# -- study integrity -------------------------------------------------------------------------------
def test_same_name_worker_is_refused_while_the_first_lives(tmp_path):
    """Two processes start the same worker on one journal at once (long runs): the storage
    orders their claims and the later one is refused while the earlier lives. Once the
    winner is interrupted (Ctrl-C), its claim ends: the name runs again and resumes the
    lineage, every (generation, index) stored once. (A claim also dies with its process:
    test_resume_after_a_killed_run.)"""
    import signal
    import time

    journal = tmp_path / "race.journal"

    def keys():
        k = _keys(trials_table(open_study(str(journal), "tawarp-design", ["gradient"])))
        return k, set(k)

    with reaped(*(_run([journal, "same", 10**6, 0]) for _ in range(2))) as procs:
        t0 = time.monotonic()
        while all(p.poll() is None for p in procs) and time.monotonic() - t0 < 120:
            time.sleep(0.05)
        done = [p for p in procs if p.poll() is not None]
        assert len(done) == 1, "one of the two must be refused while the other runs"
        winner = next(p for p in procs if p is not done[0])
        # let it store a generation first: SIGINT is handled between Python bytecodes, and a
        # winner still loading (or, in a fresh clone, compiling) its kernels would take that
        # long to see it
        t0 = time.monotonic()
        while winner.poll() is None and not keys()[0] and time.monotonic() - t0 < 300:
            time.sleep(0.1)
        winner.send_signal(signal.SIGINT)
        winner.communicate(timeout=60)
        out = done[0].communicate(timeout=60)[0]
    assert done[0].returncode != 0 and "StudyConflict" in out and "is running in another live process" in out, out

    trials, k = keys()
    assert len(trials) == len(k)
    n = (len(trials) // 8 + 2) * 8
    res = search(_space(), n_trials=n, batch=8, storage=str(journal), worker="same")
    trials, k = keys()
    assert len(trials) == len(k) == n and study_summary(res.study)["states"] == {"COMPLETE": n}
    assert res.study.directions[0].name == "MAXIMIZE"


def test_a_study_is_bound_to_its_design_space(tmp_path):
    journal = str(tmp_path / "s.journal")
    core = load_core("rvc_foam")
    search(DesignSpace(core, ["stack.length=0.004:0.1", "Q=1:9"]), n_trials=8, batch=8, storage=journal)
    with pytest.raises(StudyConflict, match=r"design space .*'high': 9\.0.*not .*'high': 18\.0"):
        search(DesignSpace(core, ["stack.length=0.004:0.1", "Q=1:18"]), n_trials=8, batch=8, storage=journal)
    assert study_summary(open_study(journal, "tawarp-design", ["gradient"]))["trials"] == 8


def test_workers_of_different_names_sample_different_points():
    """Default seed, two worker names: no design point is shared (each has its own stream);
    one name twice: the same points."""
    space = _space()
    a = search(space, n_trials=16, batch=8, worker="a").study.get_trials()
    b = search(space, n_trials=16, batch=8, worker="b").study.get_trials()
    a2 = search(space, n_trials=16, batch=8, worker="a").study.get_trials()
    pa = {tuple(sorted(t.params.items())) for t in a}
    pb = {tuple(sorted(t.params.items())) for t in b}
    assert len(pa) == 16 and not pa & pb
    assert pa == {tuple(sorted(t.params.items())) for t in a2}


def test_outputs_are_never_overwritten_by_their_companions(tmp_path):
    """sweep -o x.json would have replaced the netCDF with its JSON summary, rank -o x.png
    the ranking with its figure: both are refused, with a message, before any work."""
    (tmp_path / "out.json").write_text("{}")
    with pytest.raises(ValueError, match="give a .nc file name"):
        _cli(["sweep", "rvc_foam", "--var", "Q=1:18:3", "--quiet", "-o", str(tmp_path / "out.json")])
    with pytest.raises(ValueError, match="give a .json file name"):
        _cli(["rank", "--samples", "10", "--quiet", "-o", str(tmp_path / "rank.png")])
    assert (tmp_path / "out.json").read_text() == "{}" and not (tmp_path / "rank.png").exists()
    assert "COUNT" in _help("sweep")


def _help(command):
    import argparse

    from tawarp.cli.design import add_design_parser, add_rank_parser, add_sweep_parser

    parser = argparse.ArgumentParser(prog="tawarp")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (add_design_parser, add_rank_parser, add_sweep_parser):
        add(sub)
    return sub.choices[command].format_help()


def test_journal_file_is_optunas_format(tmp_path):
    """The search's journal backend writes Optuna's own journal format: a study stored
    through it (trials added concurrently with another writer) reads back identically
    through Optuna's JournalFileBackend, numbers consecutive."""
    import optuna
    from optuna.distributions import FloatDistribution
    from optuna.storages import JournalStorage
    from optuna.storages.journal import JournalFileBackend
    from optuna.trial import create_trial

    from tawarp.design.storage import add_evaluated, make_storage

    path = str(tmp_path / "b.journal")
    st = make_storage(path)
    study = open_study(st, "s", ["gradient"])
    d = {"x": FloatDistribution(0.0, 1.0)}
    add_evaluated(
        study,
        st,
        [{"x": 0.1 * j} for j in range(5)],
        d,
        np.arange(5.0)[:, None],
        [{"T_max": 300.0 + j} for j in range(5)],
        np.array([-1.0, 0, 1, 2, 3]),
        np.array([0, 0, 0, 1, 0], bool),
        [{"tawarp:index": j} for j in range(5)],
    )
    other = optuna.load_study(study_name="s", storage=JournalStorage(JournalFileBackend(path)))
    other.add_trial(create_trial(params={"x": 0.9}, distributions=d, value=9.0))
    add_evaluated(study, st, [{"x": 0.5}], d, np.array([[5.0]]), [{}], None, np.zeros(1, bool), [{}])
    trials = optuna.load_study(study_name="s", storage=JournalStorage(JournalFileBackend(path))).get_trials()
    assert [t.number for t in trials] == list(range(7))
    assert [t.state.name for t in trials] == ["COMPLETE"] * 3 + ["FAIL"] + ["COMPLETE"] * 3
    assert [t.value for t in trials] == [0.0, 1.0, 2.0, None, 4.0, 9.0, 5.0]
    assert trials[2].user_attrs == {"T_max": 302.0} and trials[2].system_attrs["constraints"] == [1.0]
    assert trials[4].system_attrs["tawarp:index"] == 4


def test_resume_with_another_seed_is_refused(tmp_path):
    """A lineage is the stream of its seed: resuming it with another seed or batch is
    refused, naming those the lineage was started with."""
    journal = str(tmp_path / "s.journal")
    search(_space(), n_trials=8, batch=8, storage=journal, seed=1)
    with pytest.raises(StudyConflict, match="was started with seed 1, batch 8, not seed 2, batch 8"):
        search(_space(), n_trials=16, batch=8, storage=journal, seed=2)
    with pytest.raises(StudyConflict, match="was started with seed 1, batch 8, not seed 1, batch 4"):
        search(_space(), n_trials=16, batch=4, storage=journal, seed=1)
    res = search(_space(), n_trials=16, batch=8, storage=journal, seed=1)
    assert study_summary(res.study)["trials"] == 16
