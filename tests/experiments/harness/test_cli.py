"""experiments.harness.cli: a toy experiment's command line, derived from its settings: flags,
types, defaults, help, checks, --quick and the shared flags."""

from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import pytest
from effect_networks.experiments.harness import cli
from effect_networks.experiments.harness.config import Result, check_float, check_int
from effect_networks.experiments.harness.registry import Experiment


@dataclass(frozen=True)
class ToyConfig:
    """Settings of a toy.

    Attributes
    ----------
    n_balls : int
        Balls dropped (>= 1).
    heights : tuple of float
        Drop heights, m; ``(0, 2]`` each (50 % of them high).
    start, stop : int
        First and last ball
        to count.
    label : str or None
        A name for the run.
    noise : bool
        Throw with noise.
    progress : bool
        Progress bars.
    """

    n_balls: int = 10
    heights: tuple[float, ...] = (1.0, 1.5)
    start: int = 0
    stop: int = 9
    label: str | None = None
    noise: bool = False
    folder: Path = field(default=Path("toys"), metadata={"help": "Where ``toys`` go."})
    progress: bool = True

    def __post_init__(self):
        check_int("n_balls", self.n_balls, 1)
        object.__setattr__(self, "heights", tuple(self.heights))
        for h in self.heights:
            check_float("heights", h, 0.0, 2.0, low_open=True)


@dataclass
class ToyResult(Result):
    experiment_name: ClassVar[str] = "toy"

    n_balls: int
    heights: list

    def to_markdown(self) -> str:
        return f"{self.n_balls} balls\n"


def run_toy(config: ToyConfig) -> ToyResult:
    return ToyResult(config.n_balls, list(config.heights))


TOY = Experiment(ToyConfig, run_toy, ToyResult, order=1, tiny={"n_balls": 2}, quick={"n_balls": 5})


def test_help_comes_from_the_attributes_section_and_the_metadata():
    helps = cli.field_help(ToyConfig)
    assert helps["n_balls"] == "Balls dropped (>= 1)."
    assert helps["heights"] == "Drop heights, m; (0, 2] each (50 % of them high)."
    assert helps["start"] == helps["stop"] == "First and last ball to count."
    assert helps["folder"] == "Where toys go."
    usage = " ".join(cli.make_parser(TOY).format_help().split())
    assert "--n-balls N_BALLS" in usage and "(default: 10)" in usage
    assert "--heights HEIGHTS [HEIGHTS ...]" in usage and "(default: [1.0, 1.5])" in usage
    assert "--progress" not in usage and "--quiet" in usage
    assert "a first look: n_balls=5" in usage and "(50 % of them high)" in usage


def test_flags_are_typed_by_the_fields():
    config = cli.parse_args(
        TOY, ["--n-balls", "3", "--heights", "0.5", "2", "--label", "x", "--noise"]
    ).config
    assert config == ToyConfig(n_balls=3, heights=(0.5, 2.0), label="x", noise=True)
    assert cli.parse_args(TOY, ["--folder", "f"]).config.folder == "f"  # as given
    args = cli.parse_args(TOY, [])
    assert args.config == ToyConfig() and args.out == Path("results") and args.threads == 1


def test_quick_settings_yield_to_the_flags_given_and_quiet_silences():
    assert cli.parse_args(TOY, ["--quick"]).config.n_balls == 5
    assert cli.parse_args(TOY, ["--quick", "--n-balls", "7"]).config.n_balls == 7
    assert cli.parse_args(TOY, ["--quiet"]).config.progress is False


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--n-balls", "0"], "error: --n-balls: 0 is out of range; expected an integer >= 1"),
        (["--heights", "1", "3"], "error: --heights: 3.0 is out of range"),
        (["--n-balls", "1.5"], "argument --n-balls: invalid int value: '1.5'"),
        (["--threads", "0"], "error: --threads: 0 is out of range"),
    ],
)
def test_a_bad_value_is_a_usage_error_naming_the_flag(argv, words, capsys):
    with pytest.raises(SystemExit) as exited:
        cli.parse_args(TOY, argv)
    assert exited.value.code == 2 and words in capsys.readouterr().err


def test_main_runs_saves_and_prints(tmp_path, capsys):
    with pytest.raises(SystemExit) as exited:
        cli.main(TOY, argv=["--n-balls", "4", "--out", str(tmp_path)])
    assert exited.value.code == 0
    assert capsys.readouterr().out == "4 balls\n\n"
    assert ToyResult.load(tmp_path / "toy.json") == ToyResult(4, [1.0, 1.5])
    assert (tmp_path / "toy.md").read_text() == "4 balls\n"


def test_a_setting_without_a_flag_type_is_refused():
    @dataclass(frozen=True)
    class Odd:
        weights: dict = field(default_factory=dict)

    odd = Experiment(Odd, run_toy, ToyResult, order=1)
    with pytest.raises(TypeError, match="weights: a <class 'dict'> setting has no"):
        cli.make_parser(odd)
