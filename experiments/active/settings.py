"""The active-exploration experiment's settings, learners, scores and goals.

The experiment is described in :mod:`experiments.active`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from effect_networks.experiments.cans import CanDataSettings
from effect_networks.experiments.harness.config import (
    ConfigError,
    check_choice,
    check_float,
    check_int,
)

__all__ = [
    "ActiveConfig",
    "GOAL_FRACTION",
    "GOAL_POINTS",
    "LEARNERS",
    "POINT_GOAL_S",
    "QUICK",
    "SCORES",
]

#: The strategies compared: ``{name: (inference.design.active strategy, shared prior?)}``.
LEARNERS = {
    "eig": ("eig", False),
    "eig_shared": ("eig", True),
    "uncertainty": ("uncertainty", False),
    "random": ("random", False),
}
#: How each curve point's network is fitted and its field chosen: the plain fit with the
#: ``aim`` or ``index`` tie-break (:data:`experiments.can_tossing.settings.RULES`), or the tables
#: pooled over neighbouring fields (:func:`inference.fit_pooled`) with the ``aim`` rule.
SCORES = ("aim", "index", "pooled")
GOAL_FRACTION = 0.10  # of the full data's throws
GOAL_POINTS = 0.01  # within one point of the full data's exact fraction
#: Goal of one budget point's Table I evaluation (fits and scores), CPU seconds.
POINT_GOAL_S = 1.0
#: The quick scale's settings (examples/active.py --quick).
QUICK = {"scale": "quick", "repeats": 8, "fractions": (0.05, 0.1, 0.2, 0.5), "batch_size": 20}


@dataclass(frozen=True)
class ActiveConfig(CanDataSettings):
    """Settings of :func:`experiments.active.run.run_active`; every field is checked on construction.

    The can data set's, and where the replays are simulated if they are not under ``data_dir`` yet:
    :class:`experiments.cans.CanDataSettings`.

    Attributes
    ----------
    repeats : int
        Held-out replays per (start, field), >= 2 (the physics bound's file at this
        count is reused).
    fractions : tuple of float
        Budgets, as fractions of the pool (the 0° throws), each in ``(0, 1]``; increasing.
    learners : tuple of str
        Keys of ``LEARNERS``.
    batch_size : int
        Throws chosen before they are played.
    prior_strength : float
        Weight of the shared prior of ``eig_shared`` (> 0).
    pool_sigma, pool_strength : float
        The ``pooled`` score's fit (:func:`inference.fit_pooled`): Gaussian weights between
        fields ``pool_sigma`` cells apart (> 0) and ``pool_strength`` pseudo-throws of the
        neighbouring fields' outcomes in each row's prior (> 0).
    sites : tuple of str
        End sites the gains are about: ``end.count``, ``end.config`` or both.
    seed, n_seeds : int
        The learners run with seeds ``seed .. seed + n_seeds - 1`` (ties, random
        choices); the curves are their means.
    checkpoint_dir : Path or None
        Where each learner's state is saved after every batch (and resumed from); None:
        not saved.
    workers : int
        Processes for the learners (each learner and seed one task, its choices and its
        curve's fits: :func:`experiments.harness.parallel.run_tasks`); 0: one per core. The results
        do not depend on it.
    progress : bool
        Progress bars.
    """

    repeats: int = 16
    fractions: tuple[float, ...] = (0.02, 0.05, 0.1, 0.2, 0.5)
    learners: tuple[str, ...] = tuple(LEARNERS)
    batch_size: int = 100
    prior_strength: float = 1.0
    pool_sigma: float = 0.7
    pool_strength: float = 0.5
    sites: tuple[str, ...] = ("end.count",)
    seed: int = 0
    n_seeds: int = 1
    checkpoint_dir: Path | None = None
    workers: int = 0
    progress: bool = True

    def __post_init__(self):
        super().__post_init__()
        check_int("repeats", self.repeats, 2)
        object.__setattr__(self, "fractions", tuple(self.fractions))
        if not self.fractions:
            raise ConfigError("fractions", "no budget given; expected at least one")
        for f in self.fractions:
            check_float("fractions", f, 0.0, 1.0, low_open=True)
        if list(self.fractions) != sorted(set(self.fractions)):
            raise ConfigError("fractions", f"{self.fractions} must increase strictly")
        object.__setattr__(self, "learners", tuple(self.learners))
        if not self.learners:
            raise ConfigError("learners", "no learner given; expected at least one")
        for name in self.learners:
            check_choice("learners", name, LEARNERS)
        check_int("batch_size", self.batch_size, 1)
        check_float("prior_strength", self.prior_strength, 0.0, 1e6, low_open=True)
        check_float("pool_sigma", self.pool_sigma, 0.0, 1e3, low_open=True)
        check_float("pool_strength", self.pool_strength, 0.0, 1e6, low_open=True)
        object.__setattr__(self, "sites", tuple(self.sites))
        if not self.sites:
            raise ConfigError("sites", "no site given; expected end.count and/or end.config")
        for s in self.sites:
            check_choice("sites", s, ("end.count", "end.config"))
        check_int("seed", self.seed, 0)
        check_int("n_seeds", self.n_seeds, 1)
        check_int("workers", self.workers, 0)
        if self.checkpoint_dir is not None:
            object.__setattr__(self, "checkpoint_dir", Path(self.checkpoint_dir))
