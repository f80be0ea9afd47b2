"""Pictures of the can world: the pyramid with its fields, a throw before and after, a GIF.

matplotlib is imported inside the functions (sim2d itself needs only numpy and pymunk),
figures are built without pyplot (no global state) and saved to files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from effect_networks.sim2d import geometry as g
from effect_networks.sim2d import materials as m
from effect_networks.sim2d.field_throws import is_throwable, launch_state
from effect_networks.sim2d.geometry import mask_to_cans
from effect_networks.sim2d.recording import ThrowRecording

__all__ = ["animate_throw", "plot_pyramid", "plot_throw"]

_CAN_COLOUR = "#c0c8d0"
_GONE_COLOUR = "#e06050"
_BALL_COLOUR = "#3060c0"
_TABLE_COLOUR = "#8a6a48"
_VIEW_X = (g.ENTRY_X - 0.15, g.PYRAMID_X + g.PYRAMID_WIDTH + 0.8)
_VIEW_Z = (-0.08, g.PYRAMID_HEIGHT + 0.25)


def _figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _can_corners(x: float, z: float, angle: float) -> np.ndarray:
    half = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * [
        g.CAN_WIDTH / 2,
        g.CAN_HEIGHT / 2,
    ]
    c, s = np.cos(angle), np.sin(angle)
    return half @ np.array([[c, s], [-s, c]]) + [x, z]


def _setup_axes(ax, title: str) -> None:
    from matplotlib.patches import Rectangle

    ax.add_patch(
        Rectangle((_VIEW_X[0], -0.1), _VIEW_X[1] - _VIEW_X[0], 0.1, color=_TABLE_COLOUR, zorder=0)
    )
    ax.set_xlim(*_VIEW_X)
    ax.set_ylim(*_VIEW_Z)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m), away from the thrower")
    ax.set_ylabel("z (m)")
    ax.set_title(title, fontsize=10)


def _draw_cans(ax, poses: np.ndarray, colours, labels: bool = True) -> list:
    """Draw cans from ``(10, 3)`` poses (NaN rows skipped); returns the patches."""
    from matplotlib.patches import Polygon

    patches = []
    for i, (x, z, angle) in enumerate(poses):
        if np.isnan(x):
            continue
        patch = Polygon(_can_corners(x, z, angle), closed=True, fc=colours[i], ec="k", lw=0.8)
        ax.add_patch(patch)
        patches.append(patch)
        if labels:
            ax.text(
                x, z, str(i), ha="center", va="center", fontsize=9, fontweight="bold", zorder=8,
                bbox={"boxstyle": "circle,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.8},
            )  # fmt: skip
    return patches


def _standard_poses(config: int) -> np.ndarray:
    poses = np.full((g.N_CANS, 3), np.nan)
    for i in mask_to_cans(config):
        poses[i, :2] = g.can_positions()[i]
        poses[i, 2] = 0.0
    return poses


def _parabola(field: int, angle: int, n: int = 60) -> np.ndarray:
    """Nominal ball-centre path from the entry line to the field centre, ``(n, 2)``."""
    position, velocity = launch_state(field, angle)
    target = g.field_centres()[field]
    t = np.linspace(0.0, (target[0] - position[0]) / velocity[0], n)
    return np.stack(
        [position[0] + velocity[0] * t, position[1] + velocity[1] * t - 0.5 * m.GRAVITY * t**2],
        axis=1,
    )


def plot_pyramid(path, config: int = g.FULL_PYRAMID, *, example_field: int = 97) -> Path:
    """The pyramid, the 195 field centres and the three throwing angles.

    Field centres are dots, hollow where the flat (0 degree) throw is impossible; crosses
    mark fields unthrowable at every angle. The three nominal paths through
    ``example_field`` show the angles. Saved to ``path`` (any matplotlib format).
    """
    from matplotlib.patches import Rectangle

    fig = _figure(9, 6)
    ax = fig.add_subplot()
    _setup_axes(ax, f"can world: {g.n_cans(config)} cans, 15 x 13 fields, 3 angles")
    _draw_cans(ax, _standard_poses(config), [_CAN_COLOUR] * g.N_CANS)
    ax.add_patch(
        Rectangle(
            (g.PYRAMID_X, 0.0),
            g.PYRAMID_WIDTH,
            g.PYRAMID_HEIGHT,
            fill=False,
            ls="--",
            ec="grey",
            lw=0.8,
        )
    )
    centres = g.field_centres()
    throwable = np.array(
        [[is_throwable(f, a) for a in range(len(g.ANGLES))] for f in range(g.N_FIELDS)]
    )
    flat = throwable[:, 0]
    ax.scatter(*centres[flat].T, s=6, c="k", zorder=4, label="field centre")
    ax.scatter(
        *centres[~flat].T, s=8, facecolors="none", edgecolors="k", lw=0.6, zorder=4,
        label="field centre, not throwable flat",
    )  # fmt: skip
    never = ~throwable.any(axis=1)
    ax.scatter(
        *centres[never].T, s=20, marker="x", c="r", lw=0.8, zorder=4, label="never throwable"
    )
    for a, (name, colour) in enumerate(zip(g.ANGLE_NAMES, ["C2", "C1", "C4"], strict=True)):
        path_xz = _parabola(example_field, a)
        ax.plot(*path_xz.T, c=colour, lw=1.5, label=f'angle {a} "{name}" {g.ANGLES[a]} m/s')
        ax.add_patch(_ball_patch(path_xz[0], colour, alpha=0.35))
    ax.axvline(g.ENTRY_X, c="grey", lw=0.6, ls=":")
    ax.text(g.ENTRY_X, _VIEW_Z[1] - 0.03, " entry line", fontsize=8, color="grey")
    ax.legend(loc="upper right", fontsize=7)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)
    return path


def _ball_patch(xz, colour=_BALL_COLOUR, alpha: float = 1.0):
    from matplotlib.patches import Circle

    return Circle(tuple(xz), m.BALL_RADIUS, fc=colour, ec="k", lw=0.6, alpha=alpha, zorder=6)


def _legend(ax, *, path: bool = False) -> None:
    """The throw pictures' key: ball, cans thrown off, cans kept.

    And the ball's path and aimed field centre when ``path``.
    """
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [
        Line2D([], [], ls="", marker="o", ms=7, mfc=_BALL_COLOUR, mec="k", label="ball"),
        Patch(fc=_GONE_COLOUR, ec="k", label="cans thrown off"),
        Patch(fc=_CAN_COLOUR, ec="k", label="cans kept"),
    ]
    if path:
        handles += [
            Line2D([], [], c=_BALL_COLOUR, lw=1, ls="--", label="ball's path"),
            Line2D([], [], c="k", ls="", marker="+", ms=9, mew=1.5, label="aimed field centre"),
        ]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7)


def _describe(recording: ThrowRecording, field: int, angle: int) -> str:
    o = recording.outcome
    row, column = divmod(field, g.N_COLUMNS)
    gone = mask_to_cans(o.thrown_off)
    return (
        f"field {field} (row {row}, column {column}), angle {g.ANGLE_NAMES[angle]}: "
        f"{o.count_before} -> {o.count_after} cans, thrown off {list(gone)}"
        + (" (timed out)" if o.timed_out else "")
    )


def plot_throw(path, recording: ThrowRecording, field: int, angle: int) -> Path:
    """Before and after one throw: start scene with the ball's path, and the scene at rest.

    ``recording`` comes from :func:`sim2d.recording.record_throw` with the same field and angle.
    Cans thrown off are red in both panels; a legend names ball, cans thrown off and cans
    kept.
    """
    o = recording.outcome
    colours = [_GONE_COLOUR if o.thrown_off >> i & 1 else _CAN_COLOUR for i in range(g.N_CANS)]
    fig = _figure(12, 4.8)
    before, after = fig.subplots(1, 2, sharey=True)
    _setup_axes(before, "before")
    _draw_cans(before, recording.cans[0], colours)
    ball = recording.ball[~np.isnan(recording.ball[:, 0])]
    before.plot(*ball.T, c=_BALL_COLOUR, lw=1, ls="--")
    before.add_patch(_ball_patch(recording.ball[0]))
    before.plot(*g.field_centres()[field], "k+", ms=12, mew=1.5, zorder=7)
    _legend(before, path=True)
    _setup_axes(after, f"after {o.sim_time:.2f} s")
    _draw_cans(after, recording.cans[-1], colours)
    if not np.isnan(recording.ball[-1, 0]):
        after.add_patch(_ball_patch(recording.ball[-1]))
    _legend(after)
    fig.suptitle(_describe(recording, field, angle), fontsize=11)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path


def animate_throw(
    path, recording: ThrowRecording, field: int, angle: int, *, fps: int = 25
) -> Path:
    """An animated GIF of a recorded throw, with the legend of :func:`plot_throw`.

    One frame per recorded instant, ``fps`` frames a second.
    """
    from matplotlib.animation import PillowWriter

    o = recording.outcome
    colours = [_GONE_COLOUR if o.thrown_off >> i & 1 else _CAN_COLOUR for i in range(g.N_CANS)]
    fig = _figure(7, 4.2)
    ax = fig.add_subplot()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = PillowWriter(fps=fps)
    with writer.saving(fig, str(path), dpi=80):
        for k, t in enumerate(recording.times):
            ax.clear()
            _setup_axes(ax, f"t = {t:.2f} s   " + _describe(recording, field, angle))
            ax.title.set_fontsize(7)
            _draw_cans(ax, recording.cans[k], colours, labels=True)
            if not np.isnan(recording.ball[k, 0]):
                ax.add_patch(_ball_patch(recording.ball[k]))
            _legend(ax)
            writer.grab_frame()
    return path
