"""The §III example runs with tiny arguments and shows what the paper says it shows."""

from tests.helpers import load_example


def test_tap_and_remove_runs(tmp_path):
    ex = load_example("tap_and_remove")
    rms = ex.main(ex.parse_args(["--n", "400", "--bins", "4", "--out", str(tmp_path)]))
    assert (tmp_path / "tap_and_remove.png").stat().st_size > 10_000
    no_param, one, many = rms.values()
    assert many < one < no_param  # the parameter site helps, and its clusters help more
