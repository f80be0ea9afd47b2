"""The paper's §III illustration: a "remove" action and a "tap" action with a force.

Two small worlds:

* remove: a feature ``visible`` (False/True); "remove" makes a visible object invisible
  (97 % of the time), "look" changes nothing. Two well-separated outcomes: the plain
  network emulates ("which action made it vanish?") and imitates ("did remove work?").
* tap: a ball at ``position`` (m) is tapped with a force F uniform on [0, 20] N and rolls
  ``0.02 F + 0.0015 F^2`` m (rolling friction makes the mapping non-linear). Without a
  parameter site the network can only predict the average roll; with the parameter site
  (``param.force``) and its equidistant clusters (a mixture of Gaussians) it follows F.
  The prediction error of each variant is measured on fresh taps.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from effect_networks.experiments.harness.config import Result, check_int
from effect_networks.experiments.harness.registry import Experiment
from effect_networks.inference import fit, imitation_check, infer_action, predict
from effect_networks.models import Continuous, Discrete, EffectNetwork, Parameter

__all__ = [
    "TapAndRemoveConfig",
    "TapAndRemoveResult",
    "get_data",
    "roll",
    "run_tap_and_remove",
    "tap_network",
]

FORCE = (0.0, 20.0)  # N
MAX_BINS = 200  # force clusters


@dataclass(frozen=True)
class TapAndRemoveConfig:
    """Settings of :func:`run_tap_and_remove`; every field is checked on construction.

    Attributes
    ----------
    n : int
        Training rows (the test has a quarter, at least 50), >= 10.
    bins : int
        Force clusters, ``1..MAX_BINS``.
    seed : int
        Seeds both draws (>= 0).
    """

    n: int = 2000
    bins: int = 8
    seed: int = 0

    def __post_init__(self):
        check_int("n", self.n, 10)
        check_int("bins", self.bins, 1, MAX_BINS)
        check_int("seed", self.seed, 0)


def roll(force: np.ndarray) -> np.ndarray:
    """Distance rolled (m) for a tap of ``force`` (N): the hidden law the network learns."""
    return 0.02 * force + 0.0015 * force**2


def get_data(n: int, seed: int) -> dict[str, np.ndarray]:
    """``n`` random taps and removes: arrays of shape ``(n,)``, position in metres, force in N."""
    rng = np.random.default_rng(seed)
    visible = rng.random(n) < 0.7
    action = np.array(["look", "remove"])[rng.integers(0, 2, n)]
    gone = (action == "remove") & visible & (rng.random(n) < 0.97)
    position = rng.uniform(-1.0, 1.0, n)
    force = rng.uniform(*FORCE, n)
    rolled = position + roll(force) + rng.normal(0.0, 0.01, n)
    return {
        "visible": visible,
        "action": action,
        "visible_after": visible & ~gone,
        "position": position,
        "force": force,
        "rolled": rolled,
    }


def tap_network(bins: int | None) -> EffectNetwork:
    """The tap world with a force parameter cut into ``bins`` clusters, or without one."""
    params = (
        ()
        if bins is None
        else (Parameter("force", FORCE[0], FORCE[1], bins, ("tap",), "position"),)
    )
    return EffectNetwork((Continuous("position", 1),), ("tap",), params)


def tap_rows(d: dict[str, np.ndarray], with_force: bool) -> dict[str, object]:
    """Training rows of the tap network from :func:`get_data`'s taps."""
    rows = {
        "initial.position": d["position"][:, None],
        "action": ["tap"] * len(d["position"]),
        "end.position": d["rolled"][:, None],
    }
    if with_force:
        rows["param.force"] = d["force"][:, None]
    return rows


@dataclass
class TapAndRemoveResult(Result):
    """What :func:`run_tap_and_remove` measured.

    ``remove``: the best action for "visible, then not" and its probability, and the
    surprise of "vanished" and of "still there" after a remove. ``rms_m``: per tap
    variant, the RMS error of the predicted end position (m). ``test``: the test taps'
    ``force``, ``position``, ``rolled`` and each variant's predicted end position
    (``predicted``), for the figure.
    """

    experiment_name: ClassVar[str] = "tap_and_remove"

    n_train: int
    remove: dict
    rms_m: dict[str, float]
    test: dict

    def to_markdown(self) -> str:
        """The experiment's report, in Markdown (:meth:`~experiments.harness.config.Result.to_markdown`)."""
        r = self.remove
        lines = [
            f"# Tap and remove ({self.n_train} training rows)",
            "",
            f"- remove: object vanished -> best action {r['best_action']!r} "
            f"(p = {r['best_probability']:.3f}); surprise of 'vanished' after remove "
            f"{r['surprise_vanished']:.3f}, of 'still there' {r['surprise_still_there']:.3f}",
            "",
            "| tap network | RMS prediction error (m) |",
            "|---|---:|",
            *(f"| {label} | {rms:.4f} |" for label, rms in self.rms_m.items()),
            "",
        ]
        return "\n".join(lines)

    def figures(self, out: Path) -> list[Path]:
        """Draw the taps, ``tap_and_remove.png``, into the folder ``out``; its path."""
        return [plot_taps(self, out / "tap_and_remove.png")]

    def summary_rows(self, results) -> list[str]:
        """The results table's row of the tap (:meth:`~experiments.harness.config.Result.summary_rows`)."""
        cells = "; ".join(f"{label} {rms:.4f} m" for label, rms in self.rms_m.items())
        return [f"| §III tap: RMS prediction of the end position | qualitative | {cells} | |"]


def run_tap_and_remove(config: TapAndRemoveConfig) -> TapAndRemoveResult:
    """Fit both worlds' networks; emulate and imitate remove, predict taps three ways."""
    train = get_data(config.n, config.seed)
    test = get_data(max(config.n // 4, 50), config.seed + 1)

    remove = EffectNetwork((Discrete("visible", (False, True)),), ("look", "remove"))
    rows = {
        "initial.visible": train["visible"],
        "action": train["action"],
        "end.visible": train["visible_after"],
    }
    remove_params = fit(remove, rows).params
    emulated = infer_action(
        remove, remove_params, {"initial.visible": [True], "end.visible": [False]}
    )
    check = imitation_check(
        remove,
        remove_params,
        {
            "initial.visible": [True, True],
            "action": ["remove", "remove"],
            "end.visible": [False, True],
        },
    )

    rms, predicted = {}, {}
    for label, bins in (
        ("no parameter site", None),
        ("parameter, 1 cluster", 1),
        (f"parameter, {config.bins} clusters", config.bins),
    ):
        net = tap_network(bins)
        params = fit(net, tap_rows(train, bins is not None)).params
        ev = tap_rows(test, bins is not None)
        del ev["end.position"]
        mean = predict(net, params, ev).continuous["position"].mean[:, 0].numpy()
        predicted[label] = mean.tolist()
        rms[label] = float(np.sqrt(np.mean((mean - test["rolled"]) ** 2)))
    return TapAndRemoveResult(
        n_train=config.n,
        remove={
            "best_action": emulated.best_names[0],
            "best_probability": float(emulated.probs[0].max()),
            "surprise_vanished": float(check.surprise[0]),
            "surprise_still_there": float(check.surprise[1]),
        },
        rms_m=rms,
        test={
            "force": test["force"].tolist(),
            "position": test["position"].tolist(),
            "rolled": test["rolled"].tolist(),
            "predicted": predicted,
        },
    )


def plot_taps(result: TapAndRemoveResult, path) -> Path:
    """Observed and predicted roll over the tap force; saved to ``path``."""
    from matplotlib.figure import Figure

    test = {k: np.asarray(v) for k, v in result.test.items() if k != "predicted"}
    fig = Figure(figsize=(6.5, 4.2))
    ax = fig.subplots()
    order = np.argsort(test["force"])
    ax.plot(
        test["force"][order],
        (test["rolled"] - test["position"])[order],
        ".",
        ms=3,
        color="0.6",
        label="observed roll",
    )
    for label, mean in result.test["predicted"].items():
        ax.plot(
            test["force"][order],
            (np.asarray(mean) - test["position"])[order],
            lw=1.8,
            label=f"predicted: {label}",
        )
    ax.set_xlabel("tap force F (N)")
    ax.set_ylabel("end position - initial position (m)")
    ax.set_title("Tap: predicting the effect with and without the force parameter")
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


EXPERIMENTS = (
    Experiment(
        TapAndRemoveConfig,
        run_tap_and_remove,
        TapAndRemoveResult,
        order=10,
        tiny={"n": 100, "bins": 2},
        quick={"n": 600},
        folder="tap_and_remove",
    ),
)
