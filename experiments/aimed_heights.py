"""The every-goal experiment's learned system: the robot aims at heights of the pyramid's face.

The throw network (:func:`train_robot`) turns a height on the near face into an aim; the can
network with aim heights as its actions (:func:`can_model`), fitted on the robot's own
experience, says what a hit at each height does; chained through the throw network's
predicted hit, they give the learned transition of aiming at a height
(:func:`learned_transition`). Used by :mod:`experiments.all_goals`.
"""

from __future__ import annotations

import numpy as np
import torch
from effect_networks.experiments.combined import Robot, hit_gaussians
from effect_networks.experiments.throwing import fit_throws, get_data
from effect_networks.inference import compile as compile_queries
from effect_networks.inference import fit, predict
from effect_networks.inference.sequences.chaining import BoxPartition, chain, link_probabilities
from effect_networks.models.can_pyramid import can_network, can_rows
from effect_networks.sim2d.analytic_throw import ReleaseNoise, throw
from effect_networks.sim2d.combined import CAN_BAND

__all__ = ["ROW_PRIOR", "can_model", "impact_angle", "learned_transition", "train_robot"]


def train_robot(n_throws: int, bins: int, seed: int, noise: ReleaseNoise | None) -> Robot:
    """The throw network fitted on ``n_throws`` random throws, as the robot that aims."""
    rng = np.random.default_rng(seed)
    targets, hits = get_data(n_throws, rng, noise)
    net, params, _ = fit_throws((bins, bins), targets, hits)
    return Robot(compile_queries(net, params), net, params, noise, rng)


#: Each (configuration, aim height) row's prior weight, in throws, spread evenly over the
#: configurations it may end in. The fit's default pseudo-count (0.01 per outcome) would
#: give each row about one pseudo-throw over some hundred configurations beside six real
#: throws: 15 % of every throw's probability on configurations it never reached, which
#: compounds over a plan's throws and held the predicted success about 9-18 points under the
#: measured one (the experiment's calibration table measures it).
ROW_PRIOR = 0.01


def can_model(states: list[int], heights: np.ndarray, outcomes: dict[int, np.ndarray]):
    """The can network with aim heights as actions, fitted on the robot's experience.

    Each row's tables carry a prior of ``ROW_PRIOR`` throws in all (a symmetric Dirichlet of
    ``ROW_PRIOR / len(states)`` per configuration). Returns ``P[s, b, s']``: the predicted next
    state for each state and height bin.
    """
    net = can_network(states, len(heights))
    starts, actions, ends = [], [], []
    for s, nxt in outcomes.items():
        starts.append(np.full(nxt.size, s))
        actions.append(np.repeat(np.arange(nxt.shape[0]), nxt.shape[1]))
        ends.append(nxt.reshape(-1))
    rows = can_rows(net, np.concatenate(starts), np.concatenate(actions), np.concatenate(ends))
    params = fit(net, rows, pseudo_count=ROW_PRIOR / len(states)).params
    n_a = len(heights)
    probs = torch.zeros(len(states), n_a, len(states), dtype=torch.float64)
    for i, s in enumerate(states):
        ev = {
            "initial.config": np.full(n_a, s),
            "initial.count": np.full(n_a, bin(s).count("1")),
            "action": list(net.actions),
        }
        probs[i] = predict(net, params, ev).discrete["config"].double()
    return probs


def learned_transition(
    can_probs: torch.Tensor,
    robot: Robot,
    heights: np.ndarray,
    table_z: float,
    boundary_sd: float = 0.0,
) -> tuple[torch.Tensor, np.ndarray]:
    """``T[s, a, s']`` of aiming at ``heights[a]``, and the robot's aims ``(A, 2)``.

    The networks chained (:func:`inference.sequences.chaining.chain`): the throw network's
    predicted hit (:func:`experiments.combined.hit_gaussians`, its height widened by the
    bins' boundary sd ``boundary_sd``, m) read as the height bin it falls in (each height
    owns the half step either side of it) within the can band; a hit beside the band or
    off the face changes nothing.
    """
    desired = np.stack([np.zeros_like(heights), heights + table_z], -1)
    aims = robot.aim(desired)
    half = np.diff(heights).mean() / 2 if len(heights) > 1 else 0.01
    edges = np.concatenate([heights - half, [heights[-1] + half]])
    across = np.tile([-CAN_BAND, CAN_BAND], (len(heights), 1))
    link = BoxPartition(
        np.stack([across[:, 0], edges[:-1]], -1),
        np.stack([across[:, 1], edges[1:]], -1),
        labels=range(len(heights)),
        actions=range(len(heights)),
    )
    hits = link_probabilities(link, hit_gaussians(robot, aims, table_z, boundary_sd))
    return chain(hits, can_probs), aims


def impact_angle(robot: Robot, heights: np.ndarray, table_z: float) -> float:
    """Mean descent angle (degrees, negative: downwards) of the robot's ball at the face."""
    aims = robot.aim(np.stack([np.zeros_like(heights), heights + table_z], -1))
    v = throw(aims).velocity_at_plane
    return float(np.degrees(np.arctan2(v[:, 2], v[:, 0])).mean())
