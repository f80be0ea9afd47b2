"""reproduce.py passes the executor on to every step that simulates the can world."""

from tests.helpers import load_example

reproduce = load_example("reproduce")


def test_the_executor_reaches_every_simulating_step():
    args = reproduce.parse_args(["--quick", "--executor", "dask://scheduler:8786"])
    steps = dict(reproduce.steps(args))
    for name in ("can_tossing", "combined", "physics_bounds"):
        i = steps[name].index("--executor")
        assert steps[name][i + 1] == "dask://scheduler:8786", name
    assert all(
        "--executor" not in argv
        for argv in dict(reproduce.steps(reproduce.parse_args([]))).values()
    )


def test_only_refuses_unknown_steps(capsys):
    import pytest

    with pytest.raises(SystemExit):
        reproduce.parse_args(["--only", "can_tossing", "can_tosing"])
    assert "unknown step(s) ['can_tosing']" in capsys.readouterr().err
    assert reproduce.parse_args(["--only", "throwing"]).only == ["throwing"]
