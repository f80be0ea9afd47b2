"""Tests of recorded throws (sim2d/recording.py) and the pictures made of them."""

from tests.helpers import load_example


def test_example_runs_with_tiny_arguments(tmp_path):
    files = load_example("can_world").main(["--out", str(tmp_path), "--frame-interval", "0.25"])
    assert set(files) == {"pyramid", "throw", "gif"}
    for path in files.values():
        assert path.exists() and path.stat().st_size > 1000
