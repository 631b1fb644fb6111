"""Where a benchmark writes its JSON (bench/_results.py)."""

import importlib.util
import json
from pathlib import Path


def _results():
    path = Path(__file__).resolve().parents[1] / "bench" / "_results.py"
    spec = importlib.util.spec_from_file_location("bench_results", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_an_existing_folder_as_out_takes_the_benchmarks_own_file_name(tmp_path):
    path = _results().write_result({"cases": 3}, "loop_study_x.json", str(tmp_path))
    assert path == tmp_path / "loop_study_x.json"
    assert json.loads(path.read_text()) == {"cases": 3}


def test_a_file_as_out_is_written_under_that_name(tmp_path):
    path = _results().write_result({"cases": 3}, "loop_study_x.json", str(tmp_path / "mine.json"))
    assert path == tmp_path / "mine.json"
    assert json.loads(path.read_text()) == {"cases": 3}
    assert not (tmp_path / "loop_study_x.json").exists()


def test_the_device_time_sums_each_kind_and_ranks_activities_by_their_time(monkeypatch):
    import warp as wp

    path = Path(__file__).resolve().parents[1] / "bench" / "loop.py"
    monkeypatch.syspath_prepend(str(path.parent))  # the script imports its folder's modules
    spec = importlib.util.spec_from_file_location("bench_loop", path)
    loop = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(loop)
    timed = [
        wp.TimingResult("cuda:0", "forward kernel heat", wp.TIMING_KERNEL, 3.0),
        wp.TimingResult("cuda:0", "memcpy DtoH", wp.TIMING_MEMCPY, 1.5),
        wp.TimingResult("cuda:0", "forward kernel heat", wp.TIMING_KERNEL, 5.0),
        wp.TimingResult("cuda:0", "forward kernel transfer", wp.TIMING_KERNEL, 2.0),
    ]
    got = loop.device_time(timed, cases=2, top=2)
    assert got["seconds"]["kernels"] == 0.010 and got["seconds"]["copies"] == 0.0015
    assert got["ms_per_case"]["kernels"] == 5.0 and got["ms_per_case"]["memsets"] == 0.0
    assert got["activities_per_case"] == 2.0
    assert got["by_name"] == [
        {"name": "forward kernel heat", "seconds": 0.008, "count": 2},
        {"name": "forward kernel transfer", "seconds": 0.002, "count": 1},
    ]


def test_sets_are_counted_once_whether_predicted_on_the_host_or_left_on_the_device(monkeypatch):
    # bench/loop.py's forward_sets: a fit on a GPU asks for its model values on the device
    # (predict_on_device), which for an elastic frame, or a kind without its own, forms them
    # with predict: every set counts once, and the kind's methods are its own again after
    import numpy as np
    from test_lockstep import mesh_kind

    from tawarp.measure import MeasurementKind, TMatrixKind

    path = Path(__file__).resolve().parents[1] / "bench" / "loop.py"
    monkeypatch.syspath_prepend(str(path.parent))
    spec = importlib.util.spec_from_file_location("bench_loop", path)
    loop = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(loop)
    kind = mesh_kind(0)

    def values(n):
        return {"stack.porosity": np.full(n, kind.core.get("stack.porosity"))}

    own = (TMatrixKind.__dict__["predict"], TMatrixKind.__dict__["predict_on_device"])
    with loop.counting_sets(TMatrixKind) as count:
        kind.predict(values(3), 3)
        kind.predict_on_device(values(2), 2)
        MeasurementKind.predict_on_device(kind, values(4), 4)  # the host's values copied there
    assert count["sets"] == 3 + 2 + 4 and count["columns"] > 0
    assert (TMatrixKind.__dict__["predict"], TMatrixKind.__dict__["predict_on_device"]) == own
