r"""What the physics allows: upper bounds on Table I and on the combined scenarios.

A learned model can at best pick the action that the simulator itself shows to work most
often. This measures that best, with no learning at all, so the experiments' figures can
be read against it:

* **Table I**, under both protocols of :func:`experiments.can_tossing.table_one_cases`.
  Every 0° field is thrown ``repeats`` more times from every start (the data set's
  jitter, fresh seeds; :func:`sim2d.can_dataset.generate_dataset`). For each case the
  field is chosen by its success on the first half of the repeats and scored on the
  second half (held out, so that luck in the choice does not count; :func:`held_out_best`).
* **Combined.** From every state between the full pyramid and each scenario's goal, the
  robot throws at every reachable height of the pyramid's face (exact inverse kinematics,
  ``step`` apart) ``combined_repeats`` times with the data set's jitter
  (:mod:`sim2d.combined`). The best policy over ``horizon`` throws is planned on half the
  repeats and scored on the other half (:func:`inference.planning.policy_value`).

Both bounds' simulations are saved under ``data_dir`` as they finish and resumed when
interrupted.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from experiments.can_tossing import ANGLE, PROTOCOLS, table_one_cases
from experiments.cans import SCALES, can_dataset, start_configurations
from experiments.combined import MAX_HORIZON, SCENARIOS
from experiments.config import (
    ConfigError,
    Result,
    check_choice,
    check_executor,
    check_float,
    check_int,
)
from inference.planning import exact_plan, policy_value
from sim2d import field_throws, geometry, materials
from sim2d.can_dataset import generate_dataset, load_dataset
from sim2d.chunks import locked, read_npz, run_chunks
from sim2d.combined import TABLE_TOP_Z, throws_from
from sim2d.configurations import stable_configurations
from sim2d.executors import open_executor
from sim2d.throw import TARGET_AREA

__all__ = [
    "PhysicsBoundsConfig",
    "PhysicsBoundsResult",
    "combined_bound",
    "combined_outcomes",
    "held_out_best",
    "run_physics_bounds",
    "table_one_bound",
]

BOUND_SEED = 1  # the training data set uses seed 0: these throws are fresh


@dataclass(frozen=True)
class PhysicsBoundsConfig:
    """Settings of :func:`run_physics_bounds`; every field is checked on construction.

    Attributes
    ----------
    scale, data_dir, executor
        The can data set (:func:`experiments.cans.can_dataset`); the bounds' own
        simulations are saved beside it and run on the same executor.
    repeats : int
        Table I: throws per (start, field), >= 2 (half choose, half score).
    table_z : tuple of float
        Combined: table heights above the robot's floor, m, each in
        ``[0, TARGET_AREA.z_max]``.
    step : float
        Combined: metres between the robot's throw heights, in ``(0, PYRAMID_HEIGHT]``.
    combined_repeats : int
        Combined: throws per (state, height), >= 2.
    horizon : int
        Combined: throws allowed, ``1..MAX_HORIZON``.
    progress : bool
        Progress bars.
    """

    scale: str = "full"
    data_dir: Path = Path("data")
    executor: str | None = None
    repeats: int = 16
    table_z: tuple[float, ...] = (TABLE_TOP_Z,)
    step: float = 0.002
    combined_repeats: int = 8
    horizon: int = 6
    progress: bool = True

    def __post_init__(self):
        check_choice("scale", self.scale, SCALES)
        object.__setattr__(self, "data_dir", Path(self.data_dir))
        check_executor("executor", self.executor)
        check_int("repeats", self.repeats, 2)
        object.__setattr__(self, "table_z", tuple(self.table_z))
        if not self.table_z:
            raise ConfigError("table_z", "no table height given; expected at least one")
        for z in self.table_z:
            check_float("table_z", z, 0.0, TARGET_AREA.z_max, unit="m")
        check_float("step", self.step, 0.0, geometry.PYRAMID_HEIGHT, low_open=True, unit="m")
        check_int("combined_repeats", self.combined_repeats, 2)
        check_int("horizon", self.horizon, 1, MAX_HORIZON)


def held_out_best(success: np.ndarray) -> np.ndarray:
    """``success (cases, actions, repeats)`` bool -> per case, the held-out rate of the action
    that succeeded most often on the first half of the repeats (ties: the lowest index)."""
    half = success.shape[-1] // 2
    chosen = success[..., :half].mean(-1).argmax(-1)
    held = success[..., half:].mean(-1)
    return np.take_along_axis(held, chosen[:, None], -1)[:, 0]


def table_one_bound(config: PhysicsBoundsConfig, executor=None) -> dict[str, dict]:
    """Table I's cases scored with the simulator's own best field, per protocol.

    Returns ``{protocol: {n_cases, repeats, exact_fraction_bound (held out),
    exact_fraction_in_sample, n_cases_never_reached}}`` for every protocol of
    :func:`experiments.can_tossing.table_one_cases`; both score the same throws.
    """
    progress = config.progress
    data = can_dataset(config.data_dir, config.scale, progress=progress, executor=executor)
    configs = [c for c in start_configurations(SCALES[config.scale]["n_configs"]) if c]
    path = generate_dataset(
        config.data_dir / f"can_bound_{config.scale}_{config.repeats}.npz",
        configs=configs,
        angles=(ANGLE,),
        repeats=config.repeats,
        seed=BOUND_SEED,
        executor=executor,
        progress=progress,
    )
    sims = load_dataset(path)
    fields = np.flatnonzero([field_throws.is_throwable(f, ANGLE) for f in range(geometry.N_FIELDS)])
    order = np.lexsort((sims.repeat, sims.field, sims.start_config))
    counts = sims.count_after[order].reshape(len(configs), geometry.N_FIELDS, config.repeats)
    counts = counts[:, fields]  # (configs, throwable fields, repeats)
    row = {c: i for i, c in enumerate(sorted(configs))}
    out = {}
    for protocol in PROTOCOLS:
        start, desired = table_one_cases(data, protocol)
        success = counts[[row[int(s)] for s in start]] == desired[:, None, None]
        out[protocol] = {
            "n_cases": int(len(start)),
            "repeats": config.repeats,
            "exact_fraction_bound": float(held_out_best(success).mean()),
            "exact_fraction_in_sample": float(success.mean(-1).max(-1).mean()),
            "n_cases_never_reached": int((~success.any((1, 2))).sum()),
        }
    return out


def combined_outcomes(
    config: PhysicsBoundsConfig, table_z: float, jitter: float, states, executor
) -> dict:
    """``{state: (heights, repeats) next states}``, saved per state under ``data_dir``
    (resumable; :func:`sim2d.chunks.run_chunks`)."""
    states = sorted(states)
    repeats, step = config.combined_repeats, config.step
    tasks = [(s, table_z, step, repeats, jitter, BOUND_SEED) for s in states]
    protocol = {
        "producer": "sim2d.combined.throws_from",
        "tasks": [list(t) for t in tasks],
        "constants": materials.physical_constants(),
    }
    folder = config.data_dir / f"combined_bound_{config.scale}_{table_z}_{step}_{repeats}.parts"
    with locked(folder):
        files = run_chunks(
            folder, protocol, throws_from, tasks, executor=executor,
            progress=config.progress, desc=f"combined bound (table {table_z} m)",
        )  # fmt: skip
        return {s: read_npz(f)["next_states"] for s, f in zip(states, files, strict=True)}


def combined_bound(
    config: PhysicsBoundsConfig, table_z: float, jitter: float, executor=None
) -> dict:
    """Per scenario: the best plan's held-out success, over the robot's exact throws."""
    stable = stable_configurations()
    goals = {
        name: geometry.FULL_PYRAMID & ~geometry.cans_to_mask(removed)
        for name, removed in SCENARIOS.items()
    }
    needed = {s for goal in goals.values() for s in stable if s & goal == goal}
    by_state = combined_outcomes(config, table_z, jitter, needed, executor)
    horizon = config.horizon
    out = {}
    for name, goal in goals.items():
        states = sorted(s for s in stable if s & goal == goal)
        outcomes = [by_state[s] for s in states]
        index = {s: i for i, s in enumerate(states)}
        half = config.combined_repeats // 2
        t = [torch.zeros(len(states), outcomes[0].shape[0], len(states), dtype=torch.float64)]
        t.append(t[0].clone())  # (planned on, scored on)
        for i, o in enumerate(outcomes):
            for part, cols in ((0, slice(None, half)), (1, slice(half, None))):
                for a, row in enumerate(o[:, cols]):
                    for nxt in row:  # a next state outside the goal's supersets is a failure
                        if nxt in index:
                            t[part][i, a, index[nxt]] += 1.0 / len(row)
        plan = exact_plan(t[0], index[goal], horizon)
        value = policy_value(t[1], plan.policy, index[goal], horizon)
        full = index[geometry.FULL_PYRAMID]
        out[name] = {
            "success_bound": float(value[horizon, full]),
            "success_in_sample": float(plan.value[horizon, full]),
            "one_throw_bound": float(value[1, full]),
            "n_states": len(states),
            "n_heights": int(outcomes[0].shape[0]),
        }
    return out


@dataclass
class PhysicsBoundsResult(Result):
    """What :func:`run_physics_bounds` measured (fractions in [0, 1]).

    ``table_one``: :func:`table_one_bound`'s, per protocol. ``combined``: per table height
    (``str(table_z)``) and scenario, :func:`combined_bound`'s.
    """

    scale: str
    table_one: dict[str, dict]
    horizon: int
    jitter: float
    combined: dict[str, dict[str, dict]]
    seconds: float

    def to_markdown(self) -> str:
        lines = [
            "**Table I, best field found by simulation** (jittered repeats per field, chosen "
            "on half, scored on the other half):",
            "",
            "| protocol | cases | repeats | exact, held out | exact, in sample | cases no "
            "repeat reached |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for protocol, t in self.table_one.items():
            lines.append(
                f"| {protocol} | {t['n_cases']} | {t['repeats']} | "
                f"{100 * t['exact_fraction_bound']:.2f} % | "
                f"{100 * t['exact_fraction_in_sample']:.2f} % | {t['n_cases_never_reached']} |"
            )
        lines += [
            "",
            "**Combined, best plan over the robot's exact throws** (held-out success within "
            f"{self.horizon} throws; in one throw):",
            "",
            "| table top (m) | " + " | ".join(SCENARIOS) + " |",
            "|---" * (len(SCENARIOS) + 1) + "|",
        ]
        for table_z, scen in self.combined.items():
            cells = [
                f"{100 * s['success_bound']:.1f} % ({100 * s['one_throw_bound']:.1f} %)"
                for s in scen.values()
            ]
            lines.append(f"| {table_z} | " + " | ".join(cells) + " |")
        return "\n".join(lines) + "\n"

    def save(self, out) -> list[Path]:
        """Write ``physics_bounds.json`` and ``physics_bounds.md`` to the folder ``out``."""
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        files = [out / "physics_bounds.json", out / "physics_bounds.md"]
        files[0].write_text(self.to_json())
        files[1].write_text(self.to_markdown())
        return files


def run_physics_bounds(config: PhysicsBoundsConfig) -> PhysicsBoundsResult:
    """Both bounds, simulated on ``config.executor`` (saved and resumed under ``data_dir``)."""
    started = time.perf_counter()
    with open_executor(config.executor) as executor:
        data = can_dataset(config.data_dir, config.scale, progress=False, executor=executor)
        jitter = float(data.metadata["jitter"])
        table_one = table_one_bound(config, executor)
        combined = {str(z): combined_bound(config, z, jitter, executor) for z in config.table_z}
    return PhysicsBoundsResult(
        scale=config.scale,
        table_one=table_one,
        horizon=config.horizon,
        jitter=jitter,
        combined=combined,
        seconds=time.perf_counter() - started,
    )
