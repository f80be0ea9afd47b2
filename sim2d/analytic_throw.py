r"""Analytic throw kinematics of the humanoid robot (paper §IV-B, "throw"-experiment).

The robot stands at the origin facing +x (z up, y to the robot's left) and throws at
a target point on the vertical target plane x = 2 m. Top view and side view::

    top view                                 side view

    y                 plane x = 2            z                 plane x = 2
    ^                      |  y = +1         ^                      |  z = 2.4
    |                  . . * target          |                 aim  |
    |            . . `     |             1.4 S---R. . . . . . . . . * target
  0 +---+----. `-----------|---> x           |       ` - .          |  } drop
 -0.2 S---R`               |                 |      ball     ` - .  o hit
    |                      |  y = -1         |                      |  z = 0.4
    0   0.3                2                 +---+------------------|---> x
                                             0   0.3                2

    S: right shoulder, start of the hand's straight path.  R: release, x = 0.3 m.
    Seen from above the ball flies on the line S -> target; seen from the side it
    falls below that line after R.

- S, the right shoulder, at (0, -0.2, 1.4) m.
- The arm: upper arm and forearm, :data:`UPPER_ARM_LENGTH` = :data:`FOREARM_LENGTH`
  = 0.3 m (an adult human's proportions; chosen). Its hand position is written in the
  swivel-angle form common in humanoid arm inverse kinematics (Tolani, Goswami &
  Badler 2000): azimuth (yaw) and elevation (pitch) of the shoulder-to-hand axis, the
  elbow flexion, which sets the shoulder-to-hand distance, and the swivel of the
  elbow about that axis, which moves no hand and is held fixed.
- The throw is a push (as in a shot put): the ball starts held at the shoulder, elbow
  fully flexed, so the fixed start point is S, and the hand moves straight out along
  the shoulder-to-hand axis towards the target at the constant :data:`HAND_SPEED`
  (no acceleration phase is modelled). Along that straight line only the elbow
  moves, extending from fully flexed (the point skeleton folds to a distance 0) to
  108-120 deg of flexion at release, a shoulder-to-hand distance of 0.30-0.35 m; the
  line's direction *is* the shoulder's (yaw, pitch). The shoulder's joint limits :data:`YAW_LIMITS_DEG` and
  :data:`PITCH_LIMITS_DEG` are therefore exactly the limits on the throw direction:
  a target outside that cone is thrown at along the nearest direction inside it (yaw
  and pitch clipped separately), and the throw is *clamped*: 46 % of uniform targets.
  Because the cone's apex is the shoulder, the limits of a first trial (yaw -15..25 deg,
  pitch -20..12 deg) would clamp 57 % here; ours are a little wider.
- The ball is released where the hand crosses x = :data:`RELEASE_X` = 0.3 m (paper:
  "released 30cm in front of the robot") with the hand's velocity, and flies
  ballistically (no drag) to the plane x = :data:`TARGET_PLANE_X`. The hit point is
  where it crosses that plane.

Gravity is deliberately *not* compensated: the robot aims straight at the target, so
even an unclamped ball lands directly below its target, lower by
``g/2 * (1.7 m / v_x)**2`` (0.29 m straight ahead, up to 0.40 m at the limits).
Clamping and this drop make the target-to-hit mapping non-linear and leave about half
of the target area (50.5 %) out of reach of any hit; the parameter network learns to
correct for both (paper §IV-B, Fig. 4). :func:`exact_target_for_hit` inverts the
noise-free mapping in closed form, as a reference for what the network learns.

Optional release noise (:class:`ReleaseNoise`) perturbs the ball's direction and
speed at release, after the joint limits, with an explicit numpy ``Generator``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from effect_networks.sim2d.clock import simulation
from effect_networks.sim2d.materials import GRAVITY

__all__ = [
    "FOREARM_LENGTH",
    "HAND_SPEED",
    "PITCH_LIMITS_DEG",
    "RELEASE_X",
    "SHOULDER",
    "TARGET_AREA",
    "TARGET_PLANE_X",
    "UPPER_ARM_LENGTH",
    "YAW_LIMITS_DEG",
    "ReleaseNoise",
    "TargetArea",
    "ThrowResult",
    "exact_target_for_hit",
    "is_reachable_hit",
    "reachable_hit_boundary",
    "sample_targets",
    "throw",
]

# Gravity is the can world's (m/s², along -z): one constant for both worlds.

#: Right shoulder position (x, y, z) in metres.
SHOULDER = np.array([0.0, -0.2, 1.4])
SHOULDER.setflags(write=False)

#: Upper-arm and forearm lengths, metres (chosen: adult proportions). At release the
#: shoulder-to-hand distance is 0.30-0.35 m, well inside their reach of 0.6 m.
UPPER_ARM_LENGTH = 0.3
#: metres, the forearm as long as the upper arm
FOREARM_LENGTH = 0.3

#: x of the release point, metres (paper §IV-B: "released 30cm in front of the robot").
RELEASE_X = 0.3

#: x of the target plane, metres (paper §IV-B: "located 2m in front ... of the robot").
TARGET_PLANE_X = 2.0

#: Hand speed along its straight path, m/s: constant, so the ball leaves at this
#: speed. Chosen equal to the can experiment's 7 m/s throw (paper §IV-A); the ball
#: then needs about 0.25 s to the plane and drops 0.29-0.40 m below its aim.
HAND_SPEED = 7.0

#: Shoulder yaw (azimuth of the shoulder-to-hand axis about +z, positive to the
#: robot's left) limits, degrees. Chosen so that the limits bind on both sides of the
#: area (looser limits never bind); about 46 % of uniform targets
#: are clamped in yaw or pitch.
YAW_LIMITS_DEG = (-20.0, 25.0)

#: Shoulder pitch (elevation of the shoulder-to-hand axis, positive up) limits,
#: degrees: a push throw cannot be aimed steeply up or down. Chosen like the yaw limits.
PITCH_LIMITS_DEG = (-20.0, 15.0)


@dataclass(frozen=True)
class TargetArea:
    """Axis-aligned rectangle on the target plane, bounds in metres.

    Attributes
    ----------
    y_min, y_max : float
        Lateral bounds (y positive to the robot's left).
    z_min, z_max : float
        Height bounds.
    """

    y_min: float
    y_max: float
    z_min: float
    z_max: float

    @property
    def low(self) -> np.ndarray:
        """(2,) float: the lower corner ``[y_min, z_min]``."""
        return np.array([self.y_min, self.z_min])

    @property
    def high(self) -> np.ndarray:
        """(2,) float: the upper corner ``[y_max, z_max]``."""
        return np.array([self.y_max, self.z_max])

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Whether each ``(..., 2)`` point ``[y, z]`` lies in the area (bounds included)."""
        points = np.asarray(points, dtype=float)
        return np.all((points >= self.low) & (points <= self.high), axis=-1)


#: Target area on the plane x = 2 m: 2 m x 2 m (paper §IV-B), centred on the robot,
#: i.e. on its mid-line y = 0 laterally and on its shoulder height z = 1.4 m vertically.
TARGET_AREA = TargetArea(y_min=-1.0, y_max=1.0, z_min=0.4, z_max=2.4)


@dataclass(frozen=True)
class ReleaseNoise:
    """Random error of the ball's release, applied after the joint limits.

    Attributes
    ----------
    direction_std_deg : float
        Standard deviation, degrees, of independent Gaussian errors added to the
        release direction's yaw and to its pitch. Default 0.5 deg.
    speed_rel_std : float
        Standard deviation of the relative speed error: the release speed is
        multiplied by ``1 + N(0, speed_rel_std**2)``. Default 0.02.
    """

    direction_std_deg: float = 0.5
    speed_rel_std: float = 0.02

    def __post_init__(self) -> None:
        for name in ("direction_std_deg", "speed_rel_std"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"ReleaseNoise.{name} = {value!r}: expected a finite number >= 0")


@dataclass(frozen=True)
class ThrowResult:
    """Throws at ``n`` targets; every array's first axis is the throw.

    Attributes
    ----------
    targets : (n, 2) float, metres
        The aimed-at points ``[y, z]`` on the plane x = 2 m, as given.
    hit : (n, 2) float, metres
        Where the ball crosses the plane x = 2 m, ``[y, z]``.
    velocity_at_plane : (n, 3) float, m/s
        The ball's velocity ``(vx, vy, vz)`` as it crosses the plane.
    release_position : (n, 3) float, metres
        The hand (ball) position at release, x = 0.3 m.
    release_velocity : (n, 3) float, m/s
        The ball's velocity at release (hand velocity, plus release noise if any).
    arm_yaw_pitch : (n, 2) float, radians
        The shoulder's (yaw, pitch), i.e. the direction of the hand's straight path;
        always within the joint limits. Without noise it is also the ball's direction.
    clamped : (n,) bool
        True where the direction towards the target lay outside the joint limits.
    """

    targets: np.ndarray
    hit: np.ndarray
    velocity_at_plane: np.ndarray
    release_position: np.ndarray
    release_velocity: np.ndarray
    arm_yaw_pitch: np.ndarray
    clamped: np.ndarray


def sample_targets(n: int, rng: np.random.Generator | int) -> np.ndarray:
    """Draw ``n`` targets uniformly on :data:`TARGET_AREA`.

    Parameters
    ----------
    n : int
        Number of targets, >= 0.
    rng : numpy.random.Generator or int
        Generator, or a seed for ``numpy.random.default_rng``.

    Returns
    -------
    (n, 2) float, metres
        Points ``[y, z]`` on the plane x = 2 m.
    """
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
        raise ValueError(f"n = {n!r}: expected a non-negative integer number of targets")
    rng = _generator(rng)
    return rng.uniform(TARGET_AREA.low, TARGET_AREA.high, size=(int(n), 2))


@simulation
def throw(
    targets: np.ndarray,
    *,
    rng: np.random.Generator | int | None = None,
    noise: ReleaseNoise | None = None,
) -> ThrowResult:
    """Throw one ball at each target and return where it crosses the target plane.

    Parameters
    ----------
    targets : (n, 2) float, metres
        Aimed-at points ``[y, z]`` on the plane x = 2 m, inside :data:`TARGET_AREA`.
    rng : numpy.random.Generator or int, optional
        Source of the release noise (a Generator or a seed). Required when ``noise``
        is given; unused otherwise.
    noise : ReleaseNoise, optional
        Release noise; None (default) throws exactly.

    Returns
    -------
    ThrowResult
        Hit points, velocities at the plane, release states and the clamped flags.

    Raises
    ------
    ValueError
        If ``targets`` is not a finite ``(n, 2)`` array inside :data:`TARGET_AREA`,
        or ``noise`` is given without ``rng``.
    """
    targets = _check_targets(targets)
    n = targets.shape[0]

    # Straight line from the shoulder (the start point) towards the target.
    aim = np.column_stack([np.full(n, TARGET_PLANE_X - SHOULDER[0]), targets - SHOULDER[1:]])
    yaw = np.arctan2(aim[:, 1], aim[:, 0])
    pitch = np.arctan2(aim[:, 2], np.hypot(aim[:, 0], aim[:, 1]))
    arm_yaw = np.clip(yaw, *np.radians(YAW_LIMITS_DEG))
    arm_pitch = np.clip(pitch, *np.radians(PITCH_LIMITS_DEG))
    clamped = (arm_yaw != yaw) | (arm_pitch != pitch)

    hand_direction = _unit_vector(arm_yaw, arm_pitch)
    release_position = SHOULDER + hand_direction * (
        (RELEASE_X - SHOULDER[0]) / hand_direction[:, :1]
    )
    assert np.all(
        np.linalg.norm(release_position - SHOULDER, axis=1) <= UPPER_ARM_LENGTH + FOREARM_LENGTH
    ), "release point out of the arm's reach"

    if noise is None:
        release_velocity = HAND_SPEED * hand_direction
    else:
        if rng is None:
            raise ValueError(
                "rng = None with noise given: pass rng=np.random.default_rng(seed) or an "
                "int seed so that the release noise is reproducible"
            )
        rng = _generator(rng)
        direction_error = rng.normal(0.0, np.radians(noise.direction_std_deg), size=(n, 2))
        speed = HAND_SPEED * (1.0 + rng.normal(0.0, noise.speed_rel_std, size=n))
        release_velocity = speed[:, None] * _unit_vector(
            arm_yaw + direction_error[:, 0], arm_pitch + direction_error[:, 1]
        )

    hit, velocity_at_plane = _fly(release_position, release_velocity)

    return ThrowResult(
        targets=targets,
        hit=hit,
        velocity_at_plane=velocity_at_plane,
        release_position=release_position,
        release_velocity=release_velocity,
        arm_yaw_pitch=np.column_stack([arm_yaw, arm_pitch]),
        clamped=clamped,
    )


def reachable_hit_boundary(points_per_edge: int = 100) -> np.ndarray:
    """The boundary of the set of noise-free hit points, as a closed polygon.

    Every noise-free throw travels along a direction inside the joint-limit box
    (yaw, pitch); the hits form the image of that box, whose boundary is the image
    of the box's four edges. The hit region may extend beyond :data:`TARGET_AREA`
    (the gravity drop carries low throws below it).

    Parameters
    ----------
    points_per_edge : int
        Points along each edge of the box, >= 2.

    Returns
    -------
    (4 * points_per_edge, 2) float, metres
        Polygon vertices ``[y, z]``, counter-clockwise, not repeating the first.
    """
    if isinstance(points_per_edge, bool) or not isinstance(points_per_edge, int | np.integer):
        raise ValueError(f"points_per_edge = {points_per_edge!r}: expected an integer >= 2")
    if points_per_edge < 2:
        raise ValueError(f"points_per_edge = {points_per_edge!r}: expected an integer >= 2")
    (yaw_lo, yaw_hi), (pitch_lo, pitch_hi) = (
        np.radians(YAW_LIMITS_DEG),
        np.radians(PITCH_LIMITS_DEG),
    )
    s = np.linspace(0.0, 1.0, points_per_edge, endpoint=False)
    # Counter-clockwise in (y, z): yaw grows to +y, pitch to +z.
    yaw = np.concatenate(
        [
            yaw_hi - s * (yaw_hi - yaw_lo),
            np.full_like(s, yaw_lo),
            yaw_lo + s * (yaw_hi - yaw_lo),
            np.full_like(s, yaw_hi),
        ]
    )
    pitch = np.concatenate(
        [
            np.full_like(s, pitch_hi),
            pitch_hi - s * (pitch_hi - pitch_lo),
            np.full_like(s, pitch_lo),
            pitch_lo + s * (pitch_hi - pitch_lo),
        ]
    )
    return _hit_of_direction(yaw, pitch)


def exact_target_for_hit(hits: np.ndarray, *, tolerance: float = 1e-9) -> np.ndarray:
    """The target whose noise-free throw hits each point: the exact inverse, in closed form.

    A reference for the learned inverse, not part of it. The hand's straight path
    seen from above runs from the shoulder to the hit, so the yaw is that of the hit.
    Along that yaw the height at the plane, with ``u = tan(pitch)``, the horizontal
    shoulder-to-plane distance ``D`` and ``c = g/2 * t(pitch=0)**2``, is
    ``z = z_S + D*u - c*(1 + u**2)``: a quadratic in ``u``, increasing on the lower
    root's branch (which holds the whole pitch range). The target is the point the
    straight line hits, ``[y, z_S + D*u]``.

    Parameters
    ----------
    hits : (n, 2) float, metres
        Points ``[y, z]`` on the plane x = 2 m (anywhere; not limited to the area).
    tolerance : float
        Radians by which yaw and pitch may exceed the joint limits and still count
        as reachable (hits of clamped throws lie on the limits up to rounding).

    Returns
    -------
    (n, 2) float, metres
        Targets ``[y, z]``, inside :data:`TARGET_AREA`; NaN rows where no noise-free
        throw hits the point.
    """
    hits = np.array(hits, dtype=float)
    if hits.ndim != 2 or hits.shape[1] != 2 or not np.all(np.isfinite(hits)):
        raise ValueError(
            f"hits with shape {hits.shape}: expected a finite (n, 2) array of [y, z] in metres"
        )
    yaw = np.arctan2(hits[:, 0] - SHOULDER[1], TARGET_PLANE_X - SHOULDER[0])
    shoulder_to_plane = (TARGET_PLANE_X - SHOULDER[0]) / np.cos(yaw)
    c = 0.5 * GRAVITY * ((TARGET_PLANE_X - RELEASE_X) / (np.cos(yaw) * HAND_SPEED)) ** 2
    rise_plus_c = hits[:, 1] - SHOULDER[2] + c
    discriminant = shoulder_to_plane**2 - 4.0 * c * rise_plus_c
    with np.errstate(invalid="ignore"):
        # The lower root, written so that it does not cancel.
        tan_pitch = 2.0 * rise_plus_c / (shoulder_to_plane + np.sqrt(discriminant))
    pitch = np.arctan(tan_pitch)
    yaw_lo, yaw_hi = np.radians(YAW_LIMITS_DEG)
    pitch_lo, pitch_hi = np.radians(PITCH_LIMITS_DEG)
    reachable = (
        (discriminant >= 0)
        & (yaw >= yaw_lo - tolerance)
        & (yaw <= yaw_hi + tolerance)
        & (pitch >= pitch_lo - tolerance)
        & (pitch <= pitch_hi + tolerance)
    )
    targets = np.column_stack([hits[:, 0], SHOULDER[2] + shoulder_to_plane * tan_pitch])
    # Every direction inside the limits points into the area (checked in the tests);
    # clipping only removes rounding, so that the targets can be thrown at.
    assert np.all(
        np.abs(np.clip(targets[reachable], TARGET_AREA.low, TARGET_AREA.high) - targets[reachable])
        < 1e-6
    ), "limits reach outside the area"
    targets = np.clip(targets, TARGET_AREA.low, TARGET_AREA.high)
    targets[~reachable] = np.nan
    return targets


def is_reachable_hit(points: np.ndarray, *, tolerance: float = 1e-9) -> np.ndarray:
    """Whether a noise-free throw can hit each point ``[y, z]`` of the target plane.

    Parameters
    ----------
    points : (n, 2) float, metres
        Points ``[y, z]`` on the plane x = 2 m.
    tolerance : float
        As in :func:`exact_target_for_hit`.

    Returns
    -------
    (n,) bool
        True where :func:`exact_target_for_hit` finds a target.
    """
    return np.all(np.isfinite(exact_target_for_hit(points, tolerance=tolerance)), axis=1)


def _hit_of_direction(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """Noise-free hit ``(n, 2)`` of throws along arm directions inside the limits."""
    direction = _unit_vector(yaw, pitch)
    release = SHOULDER + direction * ((RELEASE_X - SHOULDER[0]) / direction[:, :1])
    hit, _ = _fly(release, HAND_SPEED * direction)
    return hit


def _fly(position: np.ndarray, velocity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ballistic flight from ``(n, 3)`` release states to the target plane.

    x moves uniformly, so the time to the plane is closed-form. Returns the hit
    ``(n, 2)`` ``[y, z]`` and the velocity ``(n, 3)`` there.
    """
    flight_time = (TARGET_PLANE_X - position[:, 0]) / velocity[:, 0]
    assert np.all(flight_time > 0), "ball does not fly towards the target plane"
    hit = np.column_stack(
        [
            position[:, 1] + velocity[:, 1] * flight_time,
            position[:, 2] + velocity[:, 2] * flight_time - 0.5 * GRAVITY * flight_time**2,
        ]
    )
    velocity_at_plane = velocity.copy()
    velocity_at_plane[:, 2] -= GRAVITY * flight_time
    return hit, velocity_at_plane


def _unit_vector(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """(n, 3) unit vectors with the given yaw (about +z) and pitch (elevation)."""
    return np.column_stack(
        [np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)]
    )


def _check_targets(targets: np.ndarray) -> np.ndarray:
    try:
        array = np.array(targets, dtype=float)
    except (TypeError, ValueError) as error:
        raise ValueError(
            f"targets = {targets!r}: expected an (n, 2) float array of [y, z] in metres"
        ) from error
    if array.ndim != 2 or array.shape[1] != 2:
        raise ValueError(
            f"targets with shape {array.shape}: expected (n, 2), one [y, z] row per "
            "throw; reshape a single target with np.reshape(target, (1, 2))"
        )
    bad = ~np.all(np.isfinite(array), axis=1)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"targets[{i}] = {array[i].tolist()}: expected finite numbers "
            f"({int(bad.sum())} row(s) hold NaN or inf)"
        )
    outside = ~TARGET_AREA.contains(array)
    if np.any(outside):
        i = int(np.flatnonzero(outside)[0])
        raise ValueError(
            f"targets[{i}] = {array[i].tolist()}: expected inside the target area "
            f"y in [{TARGET_AREA.y_min}, {TARGET_AREA.y_max}] m, "
            f"z in [{TARGET_AREA.z_min}, {TARGET_AREA.z_max}] m "
            f"({int(outside.sum())} row(s) outside); clip with "
            "np.clip(targets, TARGET_AREA.low, TARGET_AREA.high)"
        )
    return array


def _generator(rng: np.random.Generator | int | None) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if rng is None or isinstance(rng, bool) or not isinstance(rng, int | np.integer):
        raise ValueError(f"rng = {rng!r}: expected a numpy.random.Generator or an int seed")
    return np.random.default_rng(int(rng))
