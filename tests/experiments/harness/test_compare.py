"""experiments.harness.compare: two results folders, timings and paths aside."""

import json
import math

import pytest
from effect_networks.experiments.harness.compare import compare_folders, main


def write(folder, name, value):
    path = folder / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(value))


def test_runs_that_differ_only_in_timings_and_paths_are_equal(tmp_path, capsys):
    before, after = tmp_path / "a", tmp_path / "b"
    write(before, "x.json", {"rate": 0.5, "fit_s": 1.0, "files": {"png": "/a/x.png"}, "n": [1, 2]})
    write(after, "x.json", {"rate": 0.5, "fit_s": 2.0, "files": {"png": "/b/x.png"}, "n": [1, 2]})
    write(before, "run.json", {"step_seconds": {"x": 3.0}, "commit": "abc", "scale": "full"})
    write(after, "run.json", {"step_seconds": {"x": 4.0}, "commit": "def", "scale": "full"})
    assert compare_folders(before, after) == []
    assert main([str(before), str(after)]) == 0
    assert "equal" in capsys.readouterr().out


def test_every_difference_is_named_by_its_path(tmp_path):
    before, after = tmp_path / "a", tmp_path / "b"
    write(before, "sub/x.json", {"rate": 0.5, "rows": [1, 2], "nan": math.nan, "old": 1})
    write(after, "sub/x.json", {"rate": 0.5000000000000001, "rows": [1], "nan": math.nan})
    write(before, "gone.json", {})
    write(after, "new.json", {})
    got = compare_folders(before, after)
    assert got == [
        "gone.json: only in before",
        "sub/x.json/old: only in before",
        "sub/x.json/rate: 0.5 vs 0.5000000000000001",
        "sub/x.json/rows: length 2 vs 1",
        "new.json: only in after",
    ]
    assert main([str(before), str(after)]) == 1


def test_a_missing_folder_is_a_usage_error(tmp_path):
    with pytest.raises(SystemExit) as stop:
        main([str(tmp_path / "none"), str(tmp_path)])
    assert stop.value.code == 2
