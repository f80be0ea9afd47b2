"""Physically possible configurations of the can pyramid, found by simulation.

A configuration (a subset of the ten cans, as a 10-bit mask; see :mod:`sim2d.geometry`) is
physically possible when, with its cans placed at their standard positions and
simulated for ``SETTLE_TIME`` = 5 s, no can's centre ever moves more than
``STABLE_TOLERANCE`` = 1 cm. All 2^10 subsets are simulated; none is
decided by a rule. Every subset in which each upper can has both supporters stands;
others can too, when the cans above pin a can that lost one supporter.

The simulation is the can world's (same step, solver, friction) with sleeping switched
off, so a slow creep is not mistaken for rest. A subset is rejected as soon as one can
has moved more than the tolerance, which makes the 1024 runs take seconds.

The result depends only on the physical constants, so it is cached on disk as JSON,
keyed by a hash of :func:`sim2d.materials.physical_constants` and the two constants here;
a cache that is damaged in any way (not JSON, or JSON of another shape) is recomputed
and rewritten, and a cache folder that cannot be written to is named in a warning.
The cache directory is ``$EFFECT_NETWORKS_CACHE`` if set, else
``~/.cache/effect-networks``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import warnings
from functools import lru_cache
from pathlib import Path

from effect_networks.sim2d import geometry, materials, world
from effect_networks.sim2d.chunks import write_text
from effect_networks.sim2d.clock import simulating, simulation
from effect_networks.sim2d.executors import open_executor

__all__ = [
    "SETTLE_TIME",
    "STABLE_TOLERANCE",
    "cache_dir",
    "check_config",
    "fully_supported",
    "is_stable",
    "settle_flags",
    "settles",
    "stable_configurations",
]

SETTLE_TIME = 5.0  # s
STABLE_TOLERANCE = 0.01  # m, the most a can of a standing configuration may move
_CHECK_EVERY = 10  # steps between displacement checks
_BATCH = 64  # masks per executor task


def cache_dir() -> Path:
    """Directory of the on-disk caches: ``$EFFECT_NETWORKS_CACHE`` or ~/.cache/effect-networks."""
    env = os.environ.get("EFFECT_NETWORKS_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "effect-networks"


def _cache_key() -> str:
    constants = dict(
        materials.physical_constants(), settle_time=SETTLE_TIME, stable_tolerance=STABLE_TOLERANCE
    )
    text = json.dumps(constants, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def fully_supported(mask: int) -> bool:
    """Whether every upper can of a configuration has both its supporters (a rule, for tests)."""
    for i in geometry.mask_to_cans(mask):
        below = geometry.SUPPORTERS[i]
        if below is not None and not all(mask >> j & 1 for j in below):
            return False
    return True


@simulation
def settles(mask: int, *, stepping: materials.Stepping = materials.STEPPING) -> bool:
    """Simulate one configuration for ``SETTLE_TIME``: whether no can moves more than 1 cm.

    Parameters
    ----------
    mask : int
        Any 10-bit configuration mask.
    stepping : sim2d.materials.Stepping
        The step and solver iterations (the cans start awake whatever it says).
    """
    mask = geometry.check_mask(mask)
    space = world.new_space(sleep_time=math.inf, iterations=stepping.solver_iterations)
    bodies = world.add_cans(space, mask)
    positions = geometry.can_positions()
    start = {i: tuple(positions[i]) for i in bodies}
    limit = STABLE_TOLERANCE**2
    dt = stepping.time_step
    for _ in range(round(SETTLE_TIME / dt) // _CHECK_EVERY):
        for _ in range(_CHECK_EVERY):
            space.step(dt)
        for i, body in bodies.items():
            dx = body.position.x - start[i][0]
            dz = body.position.y - start[i][1]
            if dx * dx + dz * dz > limit:
                return False
    return True


def settle_flags(masks) -> list[bool]:
    """:func:`settles` of each mask (one executor task)."""
    return [settles(mask) for mask in masks]


def _compute(executor=None) -> tuple[int, ...]:
    masks = list(range(1 << geometry.N_CANS))
    if executor is None:
        flags = settle_flags(masks)
    else:
        batches = [masks[i : i + _BATCH] for i in range(0, len(masks), _BATCH)]
        with contextlib.ExitStack() as stack:
            if isinstance(executor, str):
                executor = stack.enter_context(open_executor(executor))
            with simulating():  # the workers settle the configurations
                futures = [executor.submit(settle_flags, batch) for batch in batches]
                flags = [flag for future in futures for flag in future.result()]
    if len(flags) != len(masks) or not all(isinstance(f, bool) for f in flags):
        raise RuntimeError(
            f"the executor returned {len(flags)} results of types "
            f"{sorted({type(f).__name__ for f in flags})}; expected {len(masks)} bools"
        )
    return tuple(mask for mask, ok in zip(masks, flags, strict=True) if ok)


def stable_configurations(
    *, cache: bool = True, path: str | os.PathLike | None = None, executor=None
) -> tuple[int, ...]:
    """All physically possible configurations, sorted.

    Parameters
    ----------
    cache : bool
        Read the result from, and write it to, the on-disk cache. With False, simulate
        all 1024 subsets afresh (seconds) and leave the cache alone.
    path : path-like, optional
        Cache file to use instead of ``cache_dir() / "stable_configurations-<hash>.json"``.
    executor : str or object with ``submit``, optional
        Spreads the 1024 simulations in batches: a specification for
        :func:`sim2d.executors.open_executor`, or an open executor (only ``submit`` and
        the futures' ``result()`` are used). Default: this process.

    Returns
    -------
    tuple of int
        Sorted configuration masks; deterministic for fixed constants.
    """
    if not cache:
        return _compute(executor)
    file = (
        Path(path)
        if path is not None
        else cache_dir() / f"stable_configurations-{_cache_key()}.json"
    )
    cached = _read_cache(file)
    if cached is not None:
        return cached
    stable = _compute(executor)
    payload = {
        "key": _cache_key(),
        "constants": materials.physical_constants(),
        "settle_time": SETTLE_TIME,
        "stable_tolerance": STABLE_TOLERANCE,
        "n_stable": len(stable),
        "stable": list(stable),
    }
    # Written to a temporary file and renamed, so concurrent readers never see half a file.
    try:
        file.parent.mkdir(parents=True, exist_ok=True)
        write_text(file, json.dumps(payload, indent=1))
    except OSError as error:  # a read-only or full cache folder: the result stands
        warnings.warn(
            f"could not cache the stable configurations in {file} ({error.strerror or error}); "
            "they are simulated again next time",
            stacklevel=2,
        )
    return stable


def _read_cache(file: Path) -> tuple[int, ...] | None:
    """The configurations cached in ``file``; None if missing, of other constants, or damaged.

    Damaged in any way (unreadable, not JSON, JSON of another shape): recompute.
    """
    try:
        data = json.loads(file.read_text())
    except (OSError, ValueError, RecursionError):
        return None
    if not isinstance(data, dict) or data.get("key") != _cache_key():
        return None
    stable = data.get("stable")
    n = 1 << geometry.N_CANS
    if (
        not isinstance(stable, list)
        or not all(type(m) is int and 0 <= m < n for m in stable)
        or stable != sorted(set(stable))
        or data.get("n_stable") != len(stable)
    ):
        return None
    return tuple(stable)


@lru_cache(maxsize=1)
def _stable_set() -> frozenset[int]:
    return frozenset(stable_configurations())


def is_stable(mask: int) -> bool:
    """Whether a configuration is physically possible (uses the cached enumeration)."""
    return geometry.check_mask(mask) in _stable_set()


def check_config(config, name: str = "config") -> int:
    """``config`` as an int, refused unless it is a physically possible configuration."""
    mask = geometry.check_mask(config, name)
    if not is_stable(mask):
        raise ValueError(
            f"{name}={mask} (cans {geometry.mask_to_cans(mask)}) is not a physically possible "
            "configuration; expected one of sim2d.configurations.stable_configurations()"
        )
    return mask
