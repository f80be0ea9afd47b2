"""Can-world demonstrations read back as fields.

Beyond the paper: programming by demonstration with the can network.

The can network (Fig. 2: configuration and count before and after, the field) is fitted
on the 0° throws of the can data set (:mod:`experiments.cans`). A demonstrator then
throws a short sequence of balls into the simulated pyramid (sim2d), each at a field
drawn uniformly among the throwable ones, from the configuration the previous throw
left; what the robot sees is the sequence of configurations, not the fields.
:func:`inference.explain` reads it back as the posterior over each throw's field and
the most probable field sequence (Viterbi), with the actions' prior uniform over the
throwable fields.

What the demonstrator shows. The network can only read a throw from a configuration
it has seen thrown at (the data set's start configurations at this scale; at full scale
all of them): from any other configuration every field is equally likely to it. So a
demonstration starts from one of those, and each throw is kept only where it changed
the configuration into a configuration that the network knows; of up to ``tries`` drawn
fields, the first whose throw ends in a configuration the network was trained to throw
from is kept and the demonstration goes on; failing that, the first that changed the
configuration into a state of the network is kept and the demonstration ends there. It
also ends when the cans are gone or after ``steps`` throws. Keeping or redrawing a throw
depends only on its end configuration, which the robot sees, so the posterior over a
kept throw's field given its ends is that of a field drawn uniformly.

What the robot sees. The count at every time, the configuration at the start and at
the end, and each configuration in between with probability ``1 - hidden``; a hidden
configuration is latent (among the configurations of its count), carried from one
throw's end to the next throw's start.

Scores, per throw: the most probable sequence names the thrown field (``same_field``);
the field it names, thrown again from the true start with a fresh aim jitter, leaves the
demonstrated end configuration (``same_outcome``, as the emulation row of
:mod:`experiments.can_tossing` scores one throw: several fields give the same outcome);
and the reference, the thrown field thrown again with a fresh jitter (how often the
world repeats itself). Per demonstration: the whole sequence named, every throw's
outcome repeated.

The can data set is simulated where ``executor`` says; the demonstrations and the
throws again (some hundreds of throws) run in this process.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from effect_networks.experiments.cans import CanDataSettings, CanModel, can_dataset, fit_can_network
from effect_networks.experiments.harness.config import Result, check_float, check_int
from effect_networks.experiments.harness.registry import Experiment
from effect_networks.inference import explain
from effect_networks.models.can_pyramid import n_cans
from effect_networks.sim2d import field_throws, geometry
from effect_networks.sim2d.clock import simulation

__all__ = [
    "CanDemonstrationConfig",
    "CanDemonstrationResult",
    "play_demonstrations",
    "read_demonstrations",
    "run_can_demonstration",
]

ANGLE = 0  # the can network is fitted on, and the demonstrations thrown at, 0°
# Seed purposes: SeedSequence([seed, purpose]) for each kind of random draw.
DEMO, HIDE, REPLAY = 1, 2, 3
#: Starts drawn per demonstration asked for before :func:`play_demonstrations` gives up.
MAX_STARTS = 20


@dataclass(frozen=True)
class CanDemonstrationConfig(CanDataSettings):
    """Settings of :func:`run_can_demonstration`; every field is checked on construction.

    The can data set's: :class:`experiments.cans.CanDataSettings`.

    Attributes
    ----------
    n_demos : int
        Demonstrations thrown and read back, >= 1.
    steps : int
        Throws per demonstration at most, 1..10.
    hidden : float
        Share of the configurations between a demonstration's first and last that the
        robot does not see (it sees their count), in [0, 1].
    tries : int
        Fields drawn per throw before a demonstration ends, >= 1.
    seed : int
        Seeds the demonstrations, the hidden configurations and the throws again (>= 0).
    progress : bool
        Progress bars.
    """

    n_demos: int = 200
    steps: int = 4
    hidden: float = 0.3
    tries: int = 20
    seed: int = 0
    progress: bool = True

    def __post_init__(self):
        super().__post_init__()
        check_int("n_demos", self.n_demos, 1)
        check_int("steps", self.steps, 1, 10)
        check_float("hidden", self.hidden, 0.0, 1.0)
        check_int("tries", self.tries, 1)
        check_int("seed", self.seed, 0)


@simulation
def play_demonstrations(
    model: CanModel,
    trained: set[int],
    n: int,
    steps: int,
    tries: int,
    jitter: float,
    seed: int,
) -> list[tuple[list[int], list[int]]]:
    """``n`` demonstrations thrown in the simulated world.

    Per demonstration its configurations (masks, one more than throws) and its fields.

    Each starts from a configuration of ``trained`` (the configurations the network was
    fitted to throw from) with a can standing; each throw's field is drawn uniformly
    among the throwable ones and thrown with an aim jitter of ``jitter`` m; the module's
    notes say which throws are kept and when a demonstration ends. A start from which
    no drawn throw is kept is drawn again, up to ``MAX_STARTS * n`` starts in all
    (``ValueError`` beyond).
    """
    rng = np.random.default_rng(np.random.SeedSequence([seed, DEMO]))
    throwable = np.flatnonzero(model.throwable.numpy())
    known = set(model.states)
    starts = sorted(c for c in trained if c != 0)
    demos = []
    for _ in range(MAX_STARTS * n):
        if len(demos) == n:
            break
        configs, fields = [int(rng.choice(starts))], []
        while len(fields) < steps and configs[-1] != 0:
            start, fallback, kept = configs[-1], None, None
            for field in rng.choice(throwable, min(tries, len(throwable)), replace=False):
                end = field_throws.throw_at_field(
                    start, int(field), ANGLE, jitter=jitter, seed=int(rng.integers(1 << 32))
                ).end_config
                if end != start and end in trained:
                    kept = (int(field), end)
                    break
                if fallback is None and end != start and end in known:
                    fallback = (int(field), end)
            field, end = kept or fallback or (None, None)
            if field is None:
                break
            fields.append(field)
            configs.append(end)
            if kept is None:
                break
        if fields:
            demos.append((configs, fields))
    if len(demos) < n:
        raise ValueError(
            f"only {len(demos)} of {n} demonstrations after {MAX_STARTS * n} starts: no "
            f"throw of {tries} tries changed the configuration into one the network knows; "
            "raise tries"
        )
    return demos


def read_demonstrations(
    model: CanModel, configs: np.ndarray, seen: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Demonstrations of one length read back as fields with :func:`inference.explain`.

    ``configs`` ``(n, T + 1)`` masks; ``seen`` ``(n, T + 1)`` bool: where the robot sees
    the configuration (it always sees the count). The actions' prior is uniform over the
    fields the ball can reach at this angle; the state space is the network's
    configurations, each with its count. Returns the most probable field sequence
    ``(n, T)``, the per-throw posterior ``(n, T, 195)``, the log-likelihood ``(n,)`` and
    ``implausible`` ``(n, T)``.
    """
    configs = np.asarray(configs, dtype=np.int64)
    shown = np.where(seen, configs, None).astype(object)
    counts = n_cans(configs).astype(object)
    prior = (model.throwable.double() / model.throwable.sum()).tolist()
    space = [(c, int(n_cans(c))) for c in model.states]
    read = explain(
        model.net, model.params, {"config": shown, "count": counts}, prior=prior, state_space=space
    )
    return (
        read.best.numpy(),
        read.probs.numpy(),
        read.log_likelihood.numpy(),
        read.implausible.numpy(),
    )


@simulation
def throw_again(start: np.ndarray, fields: np.ndarray, jitter: float, seeds) -> np.ndarray:
    """``(n,)`` end configurations of the 0° throws ``(start[i], fields[i])`` with seeded jitter."""
    return np.array(
        [
            field_throws.throw_at_field(
                int(s), int(f), ANGLE, jitter=jitter, seed=int(k)
            ).end_config
            for s, f, k in zip(start, fields, seeds, strict=True)
        ],
        dtype=np.int64,
    )


@dataclass
class CanDemonstrationResult(Result):
    """What :func:`run_can_demonstration` found.

    ``throws``: over every thrown ball, the share whose field the most probable sequence
    names (``same_field``), whose named field thrown again repeats the demonstrated end
    configuration (``same_outcome``) and the same for the thrown field itself
    (``reference_same_outcome``), the share flagged implausible; the throws from a
    hidden configuration (``n_hidden_start``) and their ``same_outcome`` (None without
    any). ``sequences``: the
    shares of demonstrations whose whole field sequence is named, and whose every
    throw's outcome is repeated; the demonstrations' lengths (``lengths``: throws ->
    demonstrations). ``shown``: one demonstration (the first of the most throws) with
    its configurations, what was seen, the thrown and the read fields and its per-throw
    posterior over the fields (``probs``, throws x 195).
    """

    experiment_name: ClassVar[str] = "can_demonstration"

    scale: str
    n_states: int
    n_trained_starts: int
    n_demos: int
    hidden: float
    throws: dict
    sequences: dict
    lengths: dict
    shown: dict

    def to_markdown(self) -> str:
        """The experiment's report, in Markdown (:meth:`~experiments.harness.config.Result.to_markdown`)."""
        t, q, s = self.throws, self.sequences, self.shown
        lengths = ", ".join(
            f"{v} of {k} throw{'' if k == '1' else 's'}" for k, v in self.lengths.items()
        )
        steps = [
            f"| {i + 1} | {a} -> {b} | {'yes' if seen else 'no'} | {f} | {r} | {max(p):.3f} |"
            for i, (a, b, seen, f, r, p) in enumerate(
                zip(
                    s["configs"][:-1],
                    s["configs"][1:],
                    s["seen"][1:],
                    s["fields"],
                    s["read"],
                    s["probs"],
                    strict=True,
                )
            )
        ]
        return "\n".join(
            [
                f"# Can-world demonstrations read back as fields ({self.scale} scale)",
                "",
                f"The can network ({self.n_states} configurations, trained to throw from "
                f"{self.n_trained_starts}) reads {self.n_demos} demonstrations ({lengths}); "
                f"{self.hidden:.0%} of the configurations between a demonstration's first "
                "and last are hidden (their count seen).",
                "",
                f"- throws: the most probable sequence names the thrown field at "
                f"{t['same_field']:.1%} of {t['n']}; the field it names, thrown again, "
                f"repeats the demonstrated end configuration at {t['same_outcome']:.1%} "
                f"(the thrown field thrown again: {t['reference_same_outcome']:.1%}); "
                f"{t['implausible']:.1%} flagged implausible",
                f"- throws from a hidden configuration (its count seen): "
                f"{t['n_hidden_start']}, the read field repeats the outcome at "
                + (
                    "-"
                    if t["same_outcome_hidden_start"] is None
                    else f"{t['same_outcome_hidden_start']:.1%}"
                ),
                f"- demonstrations: the whole field sequence named at "
                f"{q['same_fields']:.1%}, every throw's outcome repeated at "
                f"{q['same_outcomes']:.1%} (thrown fields again: "
                f"{q['reference_same_outcomes']:.1%})",
                "",
                "Shown demonstration (configuration masks; read: the most probable "
                "sequence's field):",
                "",
                "| throw | configuration | end seen | thrown field | read field | "
                "largest posterior |",
                "|---:|---|---|---:|---:|---:|",
                *steps,
                "",
            ]
        )

    def figures(self, out: Path) -> list[Path]:
        """Draw the shown demonstration, ``can_demonstration.png``, into ``out``; its path."""
        return [plot_shown(self, Path(out) / "can_demonstration.png")]

    def summary_rows(self, results) -> list[str]:
        """The results table's row of the can-world demonstrations."""
        t = self.throws
        return [
            f"| can-world demonstrations read as fields (explain; beyond the paper) | — | "
            f"read field repeats the outcome at {t['same_outcome']:.1%} of the throws "
            f"(thrown field again: {t['reference_same_outcome']:.1%}); names the thrown "
            f"field at {t['same_field']:.1%} | |"
        ]


def run_can_demonstration(config: CanDemonstrationConfig) -> CanDemonstrationResult:
    """Fit the can network, throw demonstrations, read them back, throw the read fields."""
    data = can_dataset(
        config.data_dir, config.scale, progress=config.progress, executor=config.executor
    )
    model = fit_can_network(data, ANGLE)
    sel = (data.angle == ANGLE) & data.throwable
    trained = {int(c) for c in np.unique(data.start_config[sel])}
    jitter = float(data.metadata["jitter"])
    demos = play_demonstrations(
        model, trained, config.n_demos, config.steps, config.tries, jitter, config.seed
    )
    hide = np.random.default_rng(np.random.SeedSequence([config.seed, HIDE]))
    starts, ends, thrown, read, start_seen = [], [], [], [], []
    implausible, n_throws = [], []
    by_length: dict[int, list[int]] = {}
    for i, (_, fields) in enumerate(demos):
        by_length.setdefault(len(fields), []).append(i)
    seen_of, read_of, probs_of = {}, {}, {}
    for length, rows in sorted(by_length.items()):
        configs = np.array([demos[i][0] for i in rows])
        seen = hide.random(configs.shape) >= config.hidden
        seen[:, 0] = seen[:, -1] = True
        best, probs, _, flags = read_demonstrations(model, configs, seen)
        for j, i in enumerate(rows):
            seen_of[i], read_of[i], probs_of[i] = seen[j], best[j], probs[j]
        starts.append(configs[:, :-1].ravel())
        start_seen.append(seen[:, :-1].ravel())
        ends.append(configs[:, 1:].ravel())
        thrown.append(np.array([demos[i][1] for i in rows]).ravel())
        read.append(best.ravel())
        implausible.append(flags.ravel())
        n_throws += [length] * len(rows)
    starts, ends, thrown, read, start_seen = map(
        np.concatenate, (starts, ends, thrown, read, start_seen)
    )
    seeds = np.random.SeedSequence([config.seed, REPLAY]).generate_state(2 * len(starts))
    again = throw_again(starts, read, jitter, seeds[: len(starts)]) == ends
    reference = throw_again(starts, thrown, jitter, seeds[len(starts) :]) == ends
    per_demo = np.cumsum([0] + n_throws)

    def every(hit: np.ndarray) -> float:
        spans = zip(per_demo[:-1], per_demo[1:], strict=True)
        return float(np.mean([hit[a:b].all() for a, b in spans]))

    first = max(range(len(demos)), key=lambda i: (len(demos[i][1]), -i))
    configs, fields = demos[first]
    return CanDemonstrationResult(
        scale=config.scale,
        n_states=len(model.states),
        n_trained_starts=len(trained),
        n_demos=len(demos),
        hidden=config.hidden,
        throws={
            "n": int(len(starts)),
            "same_field": float(np.mean(read == thrown)),
            "same_outcome": float(again.mean()),
            "reference_same_outcome": float(reference.mean()),
            "implausible": float(np.concatenate(implausible).mean()),
            "n_hidden_start": int((~start_seen).sum()),
            "same_outcome_hidden_start": (
                float(again[~start_seen].mean()) if (~start_seen).any() else None
            ),
        },
        sequences={
            "same_fields": every(read == thrown),
            "same_outcomes": every(again),
            "reference_same_outcomes": every(reference),
        },
        lengths={str(k): len(v) for k, v in sorted(by_length.items())},
        shown={
            "configs": [int(c) for c in configs],
            "seen": [bool(v) for v in seen_of[first]],
            "fields": [int(f) for f in fields],
            "read": [int(f) for f in read_of[first]],
            "probs": [[float(p) for p in row] for row in probs_of[first]],
        },
    )


def plot_shown(result: CanDemonstrationResult, path) -> Path:
    """The shown demonstration, one panel per throw; saved to ``path``.

    The cans standing before it (a hidden configuration dashed), the posterior over the fields as a
    heat map on the field grid, the thrown field (x) and the read one (o).
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    s = result.shown
    n = len(s["fields"])
    fig = Figure(figsize=(2.6 * n + 0.8, 3.4))
    axes = np.atleast_1d(fig.subplots(1, n, sharey=True))
    x0, width = geometry.PYRAMID_X, geometry.PYRAMID_WIDTH
    extent = (x0, x0 + width, 0.0, geometry.PYRAMID_HEIGHT)
    centres = geometry.field_centres()
    top = max(max(row) for row in s["probs"])
    image = None
    for t, ax in enumerate(axes):
        grid = np.asarray(s["probs"][t]).reshape(geometry.N_ROWS, geometry.N_COLUMNS)
        image = ax.imshow(
            grid, origin="lower", extent=extent, cmap="Blues", vmin=0.0, vmax=top, zorder=1
        )
        positions = geometry.can_positions()
        for can in geometry.mask_to_cans(s["configs"][t]):
            cx, cz = positions[can]
            ax.add_patch(
                Rectangle(
                    (cx - geometry.CAN_WIDTH / 2, cz - geometry.CAN_HEIGHT / 2),
                    geometry.CAN_WIDTH,
                    geometry.CAN_HEIGHT,
                    facecolor="none",
                    edgecolor="0.3",
                    linestyle="-" if s["seen"][t] else "--",
                    zorder=2,
                )
            )
        ax.plot(*centres[s["fields"][t]], "x", color="C3", ms=9, mew=2, zorder=3)
        ax.plot(*centres[s["read"][t]], "o", mfc="none", color="C1", ms=10, mew=2, zorder=3)
        before, after = s["configs"][t], s["configs"][t + 1]
        ax.set_title(
            f"throw {t + 1}: {n_cans(before)} → {n_cans(after)} cans"
            + ("" if s["seen"][t] else "\n(start hidden)"),
            fontsize=9,
        )
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        ax.set_aspect("equal")
        ax.set_xlabel("x, m", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("z, m", fontsize=8)
    fig.suptitle(
        "A can-world demonstration read as fields (x thrown, o most probable sequence)",
        fontsize=10,
    )
    fig.colorbar(image, ax=list(axes), label="P(field | demonstration)", shrink=0.8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


EXPERIMENTS = (
    Experiment(
        CanDemonstrationConfig,
        run_can_demonstration,
        CanDemonstrationResult,
        order=116,
        tiny={"scale": "tiny", "n_demos": 8, "steps": 3, "tries": 5},
        quick={"scale": "quick", "n_demos": 200},
        folder="demonstration",
    ),
)
