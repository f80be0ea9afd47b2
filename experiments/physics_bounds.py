r"""What the physics allows: upper bounds on Table I and on the combined scenarios.

A learned model can at best pick the action that the simulator itself shows to work most
often. This measures that best, with no learning at all, so the experiments' figures can
be read against it:

* **Table I**, under both protocols of :func:`experiments.can_tossing.run.table_one_cases`.
  Every 0° field is thrown ``repeats`` more times from every start (the data set's
  jitter, fresh seeds; :func:`experiments.cans.replays`). For each case the
  field is chosen by its success on the first half of the repeats and scored on the
  second half (held out, so that luck in the choice does not count; :func:`held_out_best`).
* **Combined.** From every state its throws reach from the full pyramid, the robot
  throws at every reachable height of the pyramid's face (exact inverse kinematics,
  ``step`` apart) ``combined_repeats`` times with the data set's jitter
  (:func:`robot_throws`). The best policy over ``horizon`` throws is planned on half the
  repeats and scored on the other half, both ways round (:func:`cross_fitted_values`).

Both bounds' simulations are saved under ``data_dir`` as they finish and resumed when
interrupted.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import torch
from effect_networks.experiments.can_tossing.report import table_one_rows
from effect_networks.experiments.can_tossing.run import table_one_cases
from effect_networks.experiments.can_tossing.settings import ANGLE, PROTOCOLS
from effect_networks.experiments.cans import (
    BOUND_SEED,
    CanDataSettings,
    can_dataset,
    replays,
)
from effect_networks.experiments.combined import MAX_HORIZON, SCENARIOS
from effect_networks.experiments.harness.config import (
    ConfigError,
    Result,
    check_float,
    check_int,
)
from effect_networks.experiments.harness.registry import Experiment
from effect_networks.inference.sequences.dynamic_programming import exact_plan, policy_value
from effect_networks.sim2d import field_throws, geometry
from effect_networks.sim2d.analytic_throw import TARGET_AREA
from effect_networks.sim2d.combined import TABLE_TOP_Z, reachable_throws
from effect_networks.sim2d.configurations import stable_configurations
from effect_networks.sim2d.executors import open_executor

__all__ = [
    "PhysicsBoundsConfig",
    "PhysicsBoundsResult",
    "combined_bound",
    "cross_fitted_bound",
    "cross_fitted_values",
    "empirical_transition",
    "held_out_best",
    "robot_throws",
    "run_physics_bounds",
    "table_one_bound",
]


@dataclass(frozen=True)
class PhysicsBoundsConfig(CanDataSettings):
    """Settings of :func:`run_physics_bounds`; every field is checked on construction.

    The can data set's: :class:`experiments.cans.CanDataSettings`; the bounds' own simulations are
    saved beside it and run on the same executor.

    Attributes
    ----------
    repeats : int
        Table I: throws per (start, field), >= 2 (half choose, half score).
    table_z : tuple of float
        Combined: table heights above the robot's floor, m, each in
        ``[0, TARGET_AREA.z_max]``.
    step : float
        Combined: metres between the robot's throw heights, in ``(0, PYRAMID_HEIGHT]``.
    combined_repeats : int
        Combined: throws per (state, height), even (half plan, half score).
    horizon : int
        Combined: throws allowed, ``1..MAX_HORIZON``.
    progress : bool
        Progress bars.
    """

    repeats: int = 16
    table_z: tuple[float, ...] = (TABLE_TOP_Z,)
    step: float = 0.005
    combined_repeats: int = 24
    horizon: int = 6
    progress: bool = True

    def __post_init__(self):
        super().__post_init__()
        check_int("repeats", self.repeats, 2)
        object.__setattr__(self, "table_z", tuple(self.table_z))
        if not self.table_z:
            raise ConfigError("table_z", "no table height given; expected at least one")
        for z in self.table_z:
            check_float("table_z", z, 0.0, TARGET_AREA.z_max, unit="m")
        check_float("step", self.step, 0.0, geometry.PYRAMID_HEIGHT, low_open=True, unit="m")
        check_int("combined_repeats", self.combined_repeats, 2)
        if self.combined_repeats % 2:
            raise ConfigError(
                "combined_repeats", f"{self.combined_repeats} is odd; expected an even number"
            )
        check_int("horizon", self.horizon, 1, MAX_HORIZON)


def held_out_best(success: np.ndarray) -> np.ndarray:
    """Per case, the held-out rate of the action that succeeded most often on the first half.

    ``success (cases, actions, repeats)`` bool; the action chosen on the first half of the repeats
    (ties: the lowest index).
    """
    half = success.shape[-1] // 2
    chosen = success[..., :half].mean(-1).argmax(-1)
    held = success[..., half:].mean(-1)
    return np.take_along_axis(held, chosen[:, None], -1)[:, 0]


def table_one_bound(config: PhysicsBoundsConfig, executor=None) -> dict[str, dict]:
    """Table I's cases scored with the simulator's own best field, per protocol.

    Returns ``{protocol: {n_cases, repeats, exact_fraction_bound (held out),
    exact_fraction_in_sample, n_cases_never_reached}}`` for every protocol of
    :func:`experiments.can_tossing.run.table_one_cases`; both score the same throws.
    """
    progress = config.progress
    data = can_dataset(config.data_dir, config.scale, progress=progress, executor=executor)
    sims = replays(
        config.data_dir, config.scale, config.repeats, executor=executor, progress=progress
    )
    fields = np.flatnonzero([field_throws.is_throwable(f, ANGLE) for f in range(geometry.N_FIELDS)])
    counts = sims.count_after[:, fields]  # (configs, throwable fields, repeats)
    out = {}
    for protocol in PROTOCOLS:
        start, desired = table_one_cases(data, protocol)
        success = counts[[sims.row(s) for s in start]] == desired[:, None, None]
        out[protocol] = {
            "n_cases": int(len(start)),
            "repeats": config.repeats,
            "exact_fraction_bound": float(held_out_best(success).mean()),
            "exact_fraction_in_sample": float(success.mean(-1).max(-1).mean()),
            "n_cases_never_reached": int((~success.any((1, 2))).sum()),
        }
    return out


def robot_throws(
    data_dir,
    *,
    table_z: float,
    step: float,
    repeats: int,
    jitter: float,
    horizon: int,
    seed: int = BOUND_SEED,
    executor=None,
    progress: bool = True,
) -> dict[int, np.ndarray]:
    """The robot's exact throws at every face height from every state reachable from the pyramid.

    From the full pyramid within ``horizon - 1`` throws (:func:`sim2d.combined.reachable_throws`).

    Saved under ``data_dir`` in a folder named by the arguments, so every experiment that
    asks for the same throws (the combined bound here, :mod:`experiments.all_goals`)
    shares them; resumed when interrupted. ``{state: (heights, repeats) next states}``.
    """
    name = f"robot_throws_{table_z}_{step}_{jitter}_{repeats}_seed{seed}"
    return reachable_throws(
        Path(data_dir) / name, geometry.FULL_PYRAMID, depth=horizon, table_z=table_z,
        step=step, repeats=repeats, jitter=jitter, seed=seed, executor=executor,
        progress=progress,
    )  # fmt: skip


def empirical_transition(
    states: list[int], outcomes: dict[int, np.ndarray], cols: slice
) -> torch.Tensor:
    """``T[s, a, s']`` counted from the simulated outcomes' repeats ``cols``.

    A state without outcomes (never reached, or no cans) stays where it is.
    """
    index = {s: i for i, s in enumerate(states)}
    n_a = next(iter(outcomes.values())).shape[0]
    t = torch.zeros(len(states), n_a, len(states), dtype=torch.float64)
    for s in states:
        if s not in outcomes:
            t[index[s], :, index[s]] = 1.0
            continue
        nxt = outcomes[s][:, cols]
        for a in range(n_a):
            values, counts = np.unique(nxt[a], return_counts=True)
            t[index[s], a, [index[int(v)] for v in values]] = torch.as_tensor(
                counts / counts.sum(), dtype=torch.float64
            )
    return t


def cross_fitted_values(
    halves: tuple[torch.Tensor, torch.Tensor], goal: int, horizon: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(held_out, in_sample)``, each ``(horizon + 1, S)``.

    The best plan made on one half of the simulations scored on the other, both ways round and
    averaged; and the plans' own values on the halves they were made on, averaged.

    The held-out figure is low by the luck the plan's choice fitted in its half, the
    in-sample one high by the same luck; the true best lies between them.
    """
    held, in_sample = 0.0, 0.0
    for made, scored in ((0, 1), (1, 0)):
        plan = exact_plan(halves[made], goal, horizon)
        held = held + policy_value(halves[scored], plan.policy, goal, horizon) / 2
        in_sample = in_sample + plan.value / 2
    return held, in_sample


def cross_fitted_bound(
    halves: tuple[torch.Tensor, torch.Tensor], goal: int, start: int, horizon: int
) -> tuple[float, float]:
    """:func:`cross_fitted_values` from ``start`` with ``horizon`` actions left."""
    held, in_sample = cross_fitted_values(halves, goal, horizon)
    return float(held[horizon, start]), float(in_sample[horizon, start])


def combined_bound(
    config: PhysicsBoundsConfig, table_z: float, jitter: float, executor=None
) -> dict:
    """Per scenario: the best plan's success over the robot's exact throws.

    Held out (cross-fitted) and in sample, within ``horizon`` throws and in one throw.
    """
    outcomes = robot_throws(
        config.data_dir, table_z=table_z, step=config.step, repeats=config.combined_repeats,
        jitter=jitter, horizon=config.horizon, executor=executor, progress=config.progress,
    )  # fmt: skip
    states = sorted(stable_configurations())
    index = {s: i for i, s in enumerate(states)}
    half = config.combined_repeats // 2
    halves = (
        empirical_transition(states, outcomes, slice(None, half)),
        empirical_transition(states, outcomes, slice(half, None)),
    )
    full, horizon = index[geometry.FULL_PYRAMID], config.horizon
    out = {}
    for name, removed in SCENARIOS.items():
        goal = geometry.FULL_PYRAMID & ~geometry.cans_to_mask(removed)
        held, in_sample = cross_fitted_values(halves, index[goal], horizon)
        out[name] = {
            "success_bound": float(held[horizon, full]),
            "success_in_sample": float(in_sample[horizon, full]),
            "one_throw_bound": float(held[1, full]),
            "n_states": len(outcomes),
            "n_heights": int(next(iter(outcomes.values())).shape[0]),
        }
    return out


@dataclass
class PhysicsBoundsResult(Result):
    """What :func:`run_physics_bounds` measured (fractions in [0, 1]).

    ``table_one``: :func:`table_one_bound`'s, per protocol. ``combined``: per table height
    (``str(table_z)``) and scenario, :func:`combined_bound`'s.
    """

    experiment_name: ClassVar[str] = "physics_bounds"

    scale: str
    table_one: dict[str, dict]
    horizon: int
    jitter: float
    combined: dict[str, dict[str, dict]]
    seconds: float

    def to_markdown(self) -> str:
        """The experiment's report, in Markdown (:meth:`~experiments.harness.config.Result.to_markdown`)."""
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

    def summary_rows(self, results) -> list[str]:
        """Table I's bounds, when the can-tossing result is missing.

        The can-tossing result shows them beside its own figures; the combined bounds are the
        combined result's rows.
        """
        if "can_tossing" in results:
            return []
        return table_one_rows(None, self)


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


EXPERIMENTS = (
    Experiment(
        PhysicsBoundsConfig,
        run_physics_bounds,
        PhysicsBoundsResult,
        order=80,
        tiny={"scale": "tiny", "repeats": 2, "combined_repeats": 2, "step": 0.1},
        quick={"scale": "quick", "repeats": 8, "step": 0.01, "combined_repeats": 4},
    ),
)
