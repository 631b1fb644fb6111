"""Shared design studies on a real PostgreSQL server: workers of the design
search (the ``tawarp design`` command, ``--storage postgresql+psycopg://...``) share one
study, one is killed with SIGKILL and resumed, and every trial is counted once; a
same-name worker is refused while the first lives.

The server is started by the tests (``pgserver``: PostgreSQL binaries from PyPI, in a
temporary folder, deleted at the end). Without it the module is skipped, except under CI
(the ``CI`` environment variable set), where a server that cannot start is a failure."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from urllib.parse import urlsplit, urlunsplit

import numpy as np
import pytest
from study_copies import improving_generations

from tawarp.design.search import search
from tawarp.design.space import DesignSpace
from tawarp.design.storage import StudyConflict, lineage, make_storage, trials_table
from tawarp.model.core import load_core

BATCH = 16
VARS = ["stack.length=0.004:0.1", "heat_input=1:9", "hot_hx.length=0.005:0.03"]  # test_design._space's variables
STUDY = "tawarp-design"
pytestmark = pytest.mark.filterwarnings("ignore:XDG_RUNTIME_DIR")  # pgserver's platformdirs, harmless


def _space():
    """The design space ``tawarp design rvc_foam --var VARS`` makes (a study is bound to it,
    the command's default fixed heat input of 9 W included)."""
    return DesignSpace(load_core("rvc_foam"), VARS, heat_input=9.0)


@pytest.fixture(scope="module")
def postgres(tmp_path_factory):
    """A PostgreSQL server of its own (pgserver), stopped and its data deleted at the end.
    Yields a function ``name -> SQLAlchemy URL`` of a new, empty database on it."""
    try:
        import pgserver
        import psycopg  # noqa: F401  (the driver of the URLs below)

        srv = pgserver.get_server(tmp_path_factory.mktemp("pgdata"), cleanup_mode="delete")
    except Exception as e:
        if os.environ.get("CI"):
            raise RuntimeError(
                f"CI: a PostgreSQL server must start for the shared-study tests "
                f"(pip install -e '.[test]' installs pgserver): {e!r}"
            ) from e
        pytest.skip(f"no PostgreSQL server: pgserver could not start one ({e!r}); pip install pgserver psycopg[binary]")
    base = urlsplit(srv.get_uri())  # postgresql://postgres:@/postgres?host=SOCKET_DIR

    def database(name: str) -> str:
        srv.psql(f"CREATE DATABASE {name};")
        # SQLAlchemy's default PostgreSQL driver is psycopg2; the installed one is psycopg 3
        return urlunsplit(base._replace(scheme="postgresql+psycopg", path="/" + name))

    yield database
    srv.cleanup()


_STARTED: list[subprocess.Popen] = []


@pytest.fixture(autouse=True)
def _no_worker_outlives_its_test():
    """A failing test leaves no worker running (some are asked for 10**6 trials)."""
    yield
    while _STARTED:
        p = _STARTED.pop()
        if p.poll() is None:
            p.kill()
            p.communicate()


def _design(url: str, worker: str, trials: int, out, seed: int = 0, store=None) -> subprocess.Popen:
    """``tawarp design`` over :func:`_space` as a process of its own, storing into ``url``
    (every trial into the trial store ``store`` when given)."""
    argv = [
        "design",
        "rvc_foam",
        *(a for v in VARS for a in ("--var", v)),
        "--trials",
        trials,
        "--batch",
        BATCH,
        "--storage",
        url,
        "--worker",
        worker,
        "--seed",
        seed,
        "--device",
        "cpu",
        "--quiet",
        "--no-plots",
        "-o",
        out,
        *(["--trial-store", store] if store else []),
    ]
    _STARTED.append(
        subprocess.Popen(
            [sys.executable, "-c", "import sys; from tawarp.cli import main; sys.exit(main())", *map(str, argv)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
    )
    return _STARTED[-1]


def _study(storage):
    """The design study, or None while no worker has created it."""
    import optuna

    try:
        return optuna.load_study(study_name=STUDY, storage=storage)
    except KeyError:
        return None


def _stored(storage, worker: str) -> int:
    study = _study(storage)
    return 0 if study is None else sum(len(g["index"]) for g in lineage(study, worker).values())


def _wait_until_stored(storage, worker: str, n: int, proc: subprocess.Popen, timeout: float = 60.0) -> None:
    t0 = time.monotonic()
    while _stored(storage, worker) < n:
        assert proc.poll() is None, f"worker {worker!r} ended before storing {n} trials:\n{proc.communicate()[0]}"
        assert time.monotonic() - t0 < timeout, f"worker {worker!r} stored < {n} trials in {timeout} s"
        time.sleep(0.05)


def _kill(proc: subprocess.Popen) -> None:
    """SIGKILL, then reap: a zombie still has its pid, and a claim lives while its pid does."""
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=30)
    assert proc.returncode == -signal.SIGKILL


def _check_counted_once(study, asked: dict[str, int]) -> None:
    """Every trial counted once (:func:`trials_table`: the study's trials, or its trial
    store's rows and their copies in the study): Optuna numbers 0..N-1; each worker's
    lineage holds generations 0..G-1 of members 0..BATCH-1, each (worker, generation,
    index) stored exactly once; COMPLETE = what the workers were asked for; nothing
    RUNNING."""
    trials = study.get_trials(deepcopy=False)
    assert sorted(t.number for t in trials) == list(range(len(trials)))
    assert {t.state.name for t in trials} == {"COMPLETE"}
    ds = trials_table(study)
    assert Counter(ds.state.values.tolist()) == {"COMPLETE": sum(asked.values())}
    keys = Counter(zip(ds.worker.values.tolist(), ds.generation.values.tolist(), ds["index"].values.tolist()))
    assert set(keys.values()) == {1}, [k for k, c in keys.items() if c > 1]
    assert set(keys) == {(w, g, j) for w, n in asked.items() for g in range(n // BATCH) for j in range(BATCH)}
    copies = Counter(
        (t.system_attrs["tawarp:worker"], t.system_attrs["tawarp:generation"])
        for t in trials
        if t.system_attrs.get("tawarp:copy")
    )
    if ds.attrs["store"]:  # one copy per generation that improved its lineage (one objective: its best)
        assert copies == {(w, g): 1 for w in asked for g in improving_generations(ds, w)}
    else:
        assert not copies


@pytest.mark.parametrize("with_store", [False, True], ids=["all-in-database", "trial-store"])
def test_two_workers_one_killed_and_resumed_count_every_trial_once(postgres, tmp_path, with_store):
    """Workers a and b search one study at once; b is killed (SIGKILL) after storing at
    least two generations, before it is done, and started again while a still runs. At
    the end every trial is counted once, and b's lineage is, point for point (rel 1e-12),
    the one an uninterrupted run of b stores: the sampler state is replayed from the
    stored generations, the members missing from the generation cut short are asked
    again (storing dominates a generation's time on PostgreSQL, one transaction per
    trial, so the kill mostly lands inside a generation). With a trial store (a folder
    both workers see) the store commits whole generations: the one cut short is asked
    again whole, and the study holds one copy of the best of each generation that improved
    on its lineage's generations before."""
    url = postgres("islands_store" if with_store else "islands")
    store = tmp_path / "trials" if with_store else None
    # with a trial store b stores a generation in a file append, not a transaction per
    # trial: 12 generations could all be stored between the poll that saw two and the kill
    # (a loaded machine), so b is asked for more there
    asked = {"a": 10 * BATCH, "b": (60 if with_store else 12) * BATCH}
    a = _design(url, "a", asked["a"], tmp_path / "a", seed=1, store=store)
    b = _design(url, "b", asked["b"], tmp_path / "b", seed=2, store=store)
    storage = make_storage(url)
    _wait_until_stored(storage, "b", 2 * BATCH, b)
    _kill(b)
    at_kill = _stored(storage, "b")
    assert 2 * BATCH <= at_kill < asked["b"], "b must be killed mid-run"
    b = _design(url, "b", asked["b"], tmp_path / "b", seed=2, store=store)
    for p in (a, b):
        out = p.communicate(timeout=180)[0]
        assert p.returncode == 0, out
    study = _study(storage)
    _check_counted_once(study, asked)
    # the resumed run evaluated exactly the members missing from the generation cut short
    assert json.loads((tmp_path / "b" / "design.json").read_text())["resumed_trials"] == -at_kill % BATCH
    ref = search(_space(), n_trials=asked["b"], batch=BATCH, worker="b", seed=2)  # in memory, never interrupted
    got, want = lineage(study, "b"), lineage(ref.study, "b")
    assert sorted(got) == sorted(want)
    for g in want:
        assert got[g]["index"].tolist() == want[g]["index"].tolist()
        for k in ["param:" + v.partition("=")[0] for v in VARS] + ["metric:gradient", "metric:T_max"]:
            np.testing.assert_allclose(got[g][k].astype(float), want[g][k].astype(float), rtol=1e-12, atol=0, err_msg=k)


def test_same_name_worker_is_refused_while_the_first_lives(postgres, tmp_path):
    """Two ``tawarp design --worker same`` start at once on one PostgreSQL study: the
    database orders their claims, the later is refused (exit 2, StudyConflict's message)
    while the earlier runs. The earlier is then killed (SIGKILL): its claim dies with its
    process, the name runs again and completes the lineage, every trial counted once."""
    url = postgres("race")
    procs = [_design(url, "same", 10**6, tmp_path / f"o{i}") for i in range(2)]
    t0 = time.monotonic()
    while all(p.poll() is None for p in procs):
        assert time.monotonic() - t0 < 60, "one of two same-name workers must be refused while the other runs"
        time.sleep(0.05)
    loser = next(p for p in procs if p.poll() is not None)
    winner = next(p for p in procs if p is not loser)
    out = loser.communicate(timeout=30)[0]
    assert loser.returncode == 2 and "is running in another live process" in out, out
    storage = make_storage(url)
    _wait_until_stored(storage, "same", BATCH, winner)
    with pytest.raises(StudyConflict, match="is running in another live process"):  # and from this process too
        search(_space(), n_trials=BATCH, batch=BATCH, storage=url, worker="same")
    _kill(winner)
    n = (_stored(storage, "same") // BATCH + 2) * BATCH
    res = search(_space(), n_trials=n, batch=BATCH, storage=url, worker="same")
    _check_counted_once(res.study, {"same": n})
