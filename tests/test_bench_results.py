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
