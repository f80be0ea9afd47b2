"""Figures of the throw kinematics (:mod:`sim2d.analytic_throw`), saved as files.

matplotlib is imported inside each function (and only its object-oriented
``Figure``, no pyplot state), so importing this module costs nothing.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from effect_networks.sim2d.analytic_throw import (
    PITCH_LIMITS_DEG,
    SHOULDER,
    TARGET_AREA,
    TARGET_PLANE_X,
    YAW_LIMITS_DEG,
    reachable_hit_boundary,
    throw,
)
from effect_networks.sim2d.materials import GRAVITY

__all__ = ["plot_flight_paths", "plot_target_to_hit"]


def plot_target_to_hit(path: str | Path, *, grid: int = 15) -> Path:
    """Save a figure of a grid of targets and the hit points they produce.

    The plane x = 2 m is drawn as the robot sees it (its left, +y, on the left).
    Each target is joined to its hit; throws clamped by the joint limits are
    coloured. Also drawn: the target area, the region of targets the arm can aim at
    directly (the joint-limit cone on the plane) and the region of reachable hits.

    Parameters
    ----------
    path : str or Path
        Output file (PNG by its suffix); parent folders are created.
    grid : int
        Targets per side of the grid, >= 2.

    Returns
    -------
    Path
        The file written.
    """
    from matplotlib.figure import Figure

    if isinstance(grid, bool) or not isinstance(grid, int | np.integer) or grid < 2:
        raise ValueError(f"grid = {grid!r}: expected an integer >= 2 targets per side")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    ys = np.linspace(TARGET_AREA.y_min, TARGET_AREA.y_max, grid)
    zs = np.linspace(TARGET_AREA.z_min, TARGET_AREA.z_max, grid)
    targets = np.stack(np.meshgrid(ys, zs), axis=-1).reshape(-1, 2)
    result = throw(targets)
    clamped = result.clamped

    fig = Figure(figsize=(7.5, 8.5), layout="constrained")
    ax = fig.add_subplot()
    area = np.array(
        [
            [TARGET_AREA.y_min, TARGET_AREA.z_min],
            [TARGET_AREA.y_max, TARGET_AREA.z_min],
            [TARGET_AREA.y_max, TARGET_AREA.z_max],
            [TARGET_AREA.y_min, TARGET_AREA.z_max],
            [TARGET_AREA.y_min, TARGET_AREA.z_min],
        ]
    )
    ax.plot(area[:, 0], area[:, 1], color="black", lw=1.0, label="target area")
    cone = _aim_cone_on_plane()
    ax.plot(
        cone[:, 0],
        cone[:, 1],
        color="tab:blue",
        lw=1.0,
        ls="--",
        label="aimable directly (joint-limit cone)",
    )
    hits = reachable_hit_boundary(200)
    ax.fill(
        hits[:, 0], hits[:, 1], color="tab:green", alpha=0.12, lw=0, label="reachable hit points"
    )

    for mask, colour, name in (
        (~clamped, "tab:blue", "unclamped"),
        (clamped, "tab:red", "clamped"),
    ):
        t, h = targets[mask], result.hit[mask]
        segments = np.stack([t, h], axis=1)
        for segment in segments:
            ax.plot(segment[:, 0], segment[:, 1], color=colour, lw=0.7, alpha=0.7)
        ax.scatter(
            t[:, 0],
            t[:, 1],
            s=10,
            facecolors="none",
            edgecolors=colour,
            label=f"target, {name} ({mask.sum()})",
        )
        ax.scatter(h[:, 0], h[:, 1], s=8, color=colour, label=f"its hit, {name}")

    ax.plot(
        *SHOULDER[1:],
        marker="+",
        color="black",
        ms=12,
        ls="none",
        label="shoulder height, straight ahead",
    )
    ax.set_aspect("equal")
    ax.invert_xaxis()  # as seen by the robot: its left (+y) on the left
    ax.set_xlabel("y [m]  (robot's left  <-   ->  robot's right)")
    ax.set_ylabel("z [m]")
    ax.set_title(
        f"Target -> hit on the plane x = {TARGET_PLANE_X:g} m, seen from the robot\n"
        f"joint limits: yaw {YAW_LIMITS_DEG} deg, pitch {PITCH_LIMITS_DEG} deg; "
        f"{clamped.mean():.0%} of the grid clamped\n"
        "no aim correction for gravity: every ball lands below its aim line"
    )
    fig.legend(loc="outside lower center", ncols=3, fontsize=8)
    ax.grid(alpha=0.3)
    fig.savefig(path, dpi=120)
    return path


def plot_flight_paths(path: str | Path, targets: np.ndarray) -> Path:
    """Save top and side views of the hand's path and the ball's flight.

    Parameters
    ----------
    path : str or Path
        Output file (PNG by its suffix); parent folders are created.
    targets : (n, 2) float, metres
        Targets ``[y, z]`` inside the target area, a handful.

    Returns
    -------
    Path
        The file written.
    """
    from matplotlib.figure import Figure

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    result = throw(targets)

    fig = Figure(figsize=(10, 4.5), layout="constrained")
    top, side = fig.subplots(1, 2)
    t_plane = (TARGET_PLANE_X - result.release_position[:, 0]) / result.release_velocity[:, 0]
    for i in range(len(result.targets)):
        colour = "tab:red" if result.clamped[i] else "tab:blue"
        t = np.linspace(0.0, t_plane[i], 50)
        flight = result.release_position[i] + t[:, None] * result.release_velocity[i]
        flight[:, 2] -= 0.5 * GRAVITY * t**2
        hand = np.stack([SHOULDER, result.release_position[i]])
        aim = np.stack([SHOULDER, [TARGET_PLANE_X, *result.targets[i]]])
        for ax, k in ((top, 1), (side, 2)):
            ax.plot(aim[:, 0], aim[:, k], color=colour, lw=0.6, ls=":")
            ax.plot(hand[:, 0], hand[:, k], color="black", lw=2.0)
            ax.plot(flight[:, 0], flight[:, k], color=colour, lw=1.0)
            ax.plot(TARGET_PLANE_X, result.targets[i, k - 1], "o", mfc="none", color=colour)
            ax.plot(TARGET_PLANE_X, result.hit[i, k - 1], "o", color=colour)
    for ax, label, (low, high) in (
        (top, "y [m] (robot's left +)", (TARGET_AREA.y_min, TARGET_AREA.y_max)),
        (side, "z [m]", (TARGET_AREA.z_min, TARGET_AREA.z_max)),
    ):
        ax.plot([TARGET_PLANE_X, TARGET_PLANE_X], [low, high], color="black", lw=3, alpha=0.3)
        ax.set_xlabel("x [m]")
        ax.set_ylabel(label)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
    top.set_title("top view: aim (dotted), hand path (black), ball")
    side.set_title("side view: open = target, filled = hit; red = clamped")
    fig.savefig(path, dpi=120)
    return path


def _aim_cone_on_plane(points_per_edge: int = 100) -> np.ndarray:
    """Closed ``(m, 2)`` outline of the targets inside the joint-limit cone."""
    (yaw_lo, yaw_hi) = np.radians(YAW_LIMITS_DEG)
    (pitch_lo, pitch_hi) = np.radians(PITCH_LIMITS_DEG)
    s = np.linspace(0.0, 1.0, points_per_edge)
    yaw = np.concatenate(
        [
            yaw_lo + s * (yaw_hi - yaw_lo),
            np.full_like(s, yaw_hi),
            yaw_hi - s * (yaw_hi - yaw_lo),
            np.full_like(s, yaw_lo),
        ]
    )
    pitch = np.concatenate(
        [
            np.full_like(s, pitch_lo),
            pitch_lo + s * (pitch_hi - pitch_lo),
            np.full_like(s, pitch_hi),
            pitch_hi - s * (pitch_hi - pitch_lo),
        ]
    )
    distance = (TARGET_PLANE_X - SHOULDER[0]) / np.cos(yaw)
    return np.column_stack(
        [SHOULDER[1] + distance * np.sin(yaw), SHOULDER[2] + distance * np.tan(pitch)]
    )
