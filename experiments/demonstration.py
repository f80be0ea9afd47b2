"""Demonstrations read as action sequences (beyond the paper: programming by demonstration).

A door world: ``door`` (locked/shut/open), ``drawer`` (shut/open), ``switch`` (off/on);
actions press (flips the switch, 90 %), pull (opens a shut drawer, 90 %), turn (opens a
shut door, 85 %; a locked door stays locked) and wait (changes nothing). Training rows
come from these rules (:func:`door_rows`), one action at a time from random scenes; the
network, every initial feature and the action behind every end feature, is fitted on
them. Then :func:`inference.explain` reads

* one demonstration written out here (:data:`SHOWN`), partly observed, as the posterior
  over each step's action and the most probable sequence, drawn as a heat map; and
* ``n_demos`` demonstrations of ``steps`` steps drawn from the fitted network
  (:func:`~inference.sequences.demonstration.simulate_demonstrations`), with each discrete
  value hidden with probability ``hidden``: how often the most probable sequence
  (Viterbi) and the per-step posterior's argmax name the action that was drawn. Some
  steps cannot be told apart by any reader (pulling an open drawer looks like waiting):
  the share of steps whose drawn action changed nothing is reported beside.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from effect_networks.experiments.harness.config import Result, check_float, check_int
from effect_networks.experiments.harness.registry import Experiment
from effect_networks.inference import explain, fit
from effect_networks.inference.sequences.demonstration import simulate_demonstrations
from effect_networks.models import Discrete, EffectNetwork

__all__ = [
    "DemonstrationConfig",
    "DemonstrationResult",
    "door_network",
    "door_rows",
    "run_demonstration",
]

STATES = {"door": ("locked", "shut", "open"), "drawer": ("shut", "open"), "switch": ("off", "on")}
ACTIONS = ("press", "pull", "turn", "wait")

#: The demonstration drawn in the figure: the switch turned on, the door opened, the
#: drawer opened (the door not seen then), nothing seen to change, the switch turned off
#: (the drawer not seen).
SHOWN = (
    {"door": "shut", "drawer": "shut", "switch": "off"},
    {"door": "shut", "drawer": "shut", "switch": "on"},
    {"door": "open", "drawer": "shut", "switch": "on"},
    {"door": None, "drawer": "open", "switch": "on"},
    {"door": "open", "drawer": "open", "switch": "on"},
    {"door": "open", "drawer": None, "switch": "off"},
)


@dataclass(frozen=True)
class DemonstrationConfig:
    """Settings of :func:`run_demonstration`; every field is checked on construction.

    Attributes
    ----------
    n : int
        Training rows, >= 50.
    n_demos : int
        Demonstrations drawn and read back, >= 1.
    steps : int
        Steps per drawn demonstration, 1..20.
    hidden : float
        Share of the drawn demonstrations' discrete values hidden, in [0, 1).
    seed : int
        Seeds the training rows and the demonstrations (>= 0).
    """

    n: int = 3000
    n_demos: int = 1000
    steps: int = 5
    hidden: float = 0.3
    seed: int = 0

    def __post_init__(self):
        check_int("n", self.n, 50)
        check_int("n_demos", self.n_demos, 1)
        check_int("steps", self.steps, 1, 20)
        check_float("hidden", self.hidden, 0.0, 0.99)
        check_int("seed", self.seed, 0)


def door_network() -> EffectNetwork:
    """The door world's network: three discrete features, four actions."""
    return EffectNetwork(
        features=tuple(Discrete(name, states) for name, states in STATES.items()),
        actions=ACTIONS,
    )


def door_rows(n: int, seed: int) -> dict[str, np.ndarray]:
    """``n`` training rows by site (labels, ``(n,)`` each).

    Random scenes, a uniform action, the end state by the door world's rules.
    """
    rng = np.random.default_rng(seed)
    door = rng.choice(STATES["door"], n)
    drawer = rng.choice(STATES["drawer"], n)
    switch = rng.choice(STATES["switch"], n)
    action = rng.choice(ACTIONS, n)
    works = rng.random(n)
    flipped = (action == "press") & (works < 0.9)
    opened = (action == "turn") & (door == "shut") & (works < 0.85)
    pulled = (action == "pull") & (works < 0.9)
    return {
        "initial.door": door,
        "initial.drawer": drawer,
        "initial.switch": switch,
        "action": action,
        "end.door": np.where(opened, "open", door),
        "end.drawer": np.where(pulled, "open", drawer),
        "end.switch": np.where(flipped, np.where(switch == "on", "off", "on"), switch),
    }


@dataclass
class DemonstrationResult(Result):
    """What :func:`run_demonstration` found.

    ``shown``: the written demonstration (``states``, ``None`` where not observed), its
    per-step posterior ``probs`` (steps x actions), the most probable sequence
    ``best``, ``log_likelihood`` and ``implausible`` per step. ``drawn``: over the drawn
    demonstrations, the share of steps whose drawn action the most probable sequence
    names (``viterbi``; among the steps that changed something, ``viterbi_changed``),
    the per-step argmax names (``marginal``), the share of steps whose drawn action
    changed nothing (``idle``), the share flagged implausible, and
    the mean log-likelihood.
    """

    experiment_name: ClassVar[str] = "demonstration"

    n_train: int
    actions: list[str]
    shown: dict
    drawn: dict

    def to_markdown(self) -> str:
        """The experiment's report, in Markdown (:meth:`~experiments.harness.config.Result.to_markdown`)."""
        s, d = self.shown, self.drawn
        header = " | ".join(self.actions)
        lines = [
            f"# Demonstrations read as actions ({self.n_train} training rows)",
            "",
            f"Shown demonstration: most probable sequence {' -> '.join(s['best'])} "
            f"(log-likelihood {s['log_likelihood']:.3f})",
            "",
            f"| step | {header} | implausible |",
            "|---|" + "---:|" * len(self.actions) + "---|",
            *(
                f"| {t} -> {t + 1} | " + " | ".join(f"{p:.3f}" for p in row) + f" | {flag} |"
                for t, (row, flag) in enumerate(zip(s["probs"], s["implausible"], strict=True))
            ),
            "",
            f"Drawn: {d['n_demos']} demonstrations of {d['steps']} steps, {d['hidden']:.0%} "
            f"of the discrete values hidden: the most probable sequence names the drawn "
            f"action at {d['viterbi']:.1%} of the steps ({d['viterbi_changed']:.1%} of those "
            f"that changed something), the per-step argmax at {d['marginal']:.1%}; "
            f"{d['idle']:.1%} of the steps changed nothing; "
            f"{d['implausible']:.1%} flagged implausible; mean log-likelihood "
            f"{d['mean_log_likelihood']:.3f}.",
            "",
        ]
        return "\n".join(lines)

    def figures(self, out: Path) -> list[Path]:
        """Draw the shown demonstration, ``demonstration.png``, into ``out``; its path."""
        return [plot_shown(self, out / "demonstration.png")]

    def summary_rows(self, results) -> list[str]:
        """The results table's row of the demonstrations."""
        d = self.drawn
        return [
            f"| demonstrations read as actions (explain; beyond the paper) | — | most "
            f"probable sequence right at {d['viterbi_changed']:.1%} of the steps that "
            f"changed something ({d['viterbi']:.1%} of all; {d['hidden']:.0%} of the "
            "values hidden) | |"
        ]


def run_demonstration(config: DemonstrationConfig) -> DemonstrationResult:
    """Fit the door world; read the written demonstration and the drawn ones back."""
    net = door_network()
    params = fit(net, door_rows(config.n, config.seed)).params
    shown = explain(net, params, list(SHOWN))
    states, actions = simulate_demonstrations(
        net, params, config.n_demos, config.steps, seed=config.seed + 1
    )
    idle = np.ones(actions.shape, dtype=bool)
    for name in STATES:
        idle &= states[name][:, :-1] == states[name][:, 1:]
    rng = np.random.default_rng(config.seed + 2)
    seen = {
        name: np.where(rng.random(value.shape) < config.hidden, None, value)
        for name, value in states.items()
    }
    drawn = explain(net, params, seen)
    names = np.array(net.actions)
    right = np.array(drawn.best_names) == actions
    return DemonstrationResult(
        n_train=config.n,
        actions=list(net.actions),
        shown={
            "states": [dict(s) for s in SHOWN],
            "probs": drawn_list(shown.probs[0]),
            "best": list(shown.best_names[0]),
            "log_likelihood": float(shown.log_likelihood[0]),
            "implausible": shown.implausible[0].tolist(),
        },
        drawn={
            "n_demos": config.n_demos,
            "steps": config.steps,
            "hidden": config.hidden,
            "viterbi": float(right.mean()),
            "viterbi_changed": float(right[~idle].mean()) if (~idle).any() else 1.0,
            "marginal": float((names[drawn.probs.argmax(-1).numpy()] == actions).mean()),
            "idle": float(idle.mean()),
            "implausible": float(drawn.implausible.double().mean()),
            "mean_log_likelihood": float(drawn.log_likelihood.mean()),
        },
    )


def drawn_list(probs) -> list[list[float]]:
    """A posterior tensor as nested lists of floats (JSON)."""
    return [[float(p) for p in row] for row in probs]


def plot_shown(result: DemonstrationResult, path) -> Path:
    """The shown demonstration's per-step action posterior as a heat map; saved to ``path``."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.5, 3.6))
    ax = fig.subplots()
    probs = np.asarray(result.shown["probs"]).T  # (A, T)
    image = ax.imshow(probs, cmap="Blues", vmin=0.0, vmax=1.0, aspect="auto")
    best = [result.actions.index(a) for a in result.shown["best"]]
    ax.plot(range(len(best)), best, "o", color="C1")
    states = result.shown["states"]
    ax.set_xticks(
        range(len(best)),
        [_changed(states[t], states[t + 1]) for t in range(len(best))],
        fontsize=7,
    )
    ax.set_yticks(range(len(result.actions)), result.actions)
    ax.set_ylabel("P(action | demonstration)")
    ax.set_title("A door-world demonstration read as actions (dots: most probable)", fontsize=10)
    fig.colorbar(image, ax=ax)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


def _changed(before: dict, after: dict) -> str:
    """What a step shows changing (``?``: not observed at one end)."""
    parts = []
    for name in STATES:
        a, b = before.get(name), after.get(name)
        if a is None or b is None:
            parts.append(f"{name} ?")
        elif a != b:
            parts.append(f"{name} {a}→{b}")
    return "\n".join(parts) or "no change"


EXPERIMENTS = (
    Experiment(
        DemonstrationConfig,
        run_demonstration,
        DemonstrationResult,
        order=115,
        tiny={"n": 300, "n_demos": 50, "steps": 3},
        quick={"n": 1000, "n_demos": 300},
        folder="demonstration",
    ),
)
