"""The adaptive-throw experiment's settings and goals.

The experiment is described in :mod:`experiments.adaptive_throw`.
"""

from __future__ import annotations

from dataclasses import dataclass

from effect_networks.experiments.harness.config import ConfigError, check_float, check_int

__all__ = [
    "CAUSES",
    "AdaptiveThrowConfig",
    "GOAL_FIT_S",
    "GOAL_NOISE_RATIO",
    "GOAL_RMS_M",
    "QUERIES",
    "QUICK",
    "ROWS_PER_CLUSTER",
    "STRATEGIES",
]

GOAL_RMS_M = 0.0001  # 0.01 cm on both axes, noise-free
GOAL_FIT_S = 2.0  # one core
GOAL_NOISE_RATIO = 1.05  # within 5 % of the noise's own scatter
ROWS_PER_CLUSTER = 30  # the active curves' grid rule
#: How the active curves choose targets: at random; by the expected information gain about
#: the clusters' regressions; by the expected reduction of the predictive variance summed
#: over the target area (ALC).
STRATEGIES = ("random", "information", "variance")
#: The two inverse queries every layout is scored with (see the module).
QUERIES = ("posterior", "effect")
#: What an inverse-model hit's re-throw error is put down to, in order of precedence
#: (:func:`experiments.adaptive_throw.aiming.error_causes`).
CAUSES = ("clipped", "clamped", "choice", "curvature")
#: A first look in seconds.
QUICK = {
    "n_train": 2_000,
    "n_test": 200,
    "bins": (2, 4),
    "noisy_bins": 4,
    "em_steps": (2, 5),
    "budgets": (120, 240, 480),
    "batch": 40,
    "pool": 400,
    "noise_repeats": 3,
}


@dataclass(frozen=True)
class AdaptiveThrowConfig:
    """Settings of :func:`experiments.adaptive_throw.run.run_adaptive_throw`; every field is checked on construction.

    Attributes
    ----------
    n_train, n_test : int
        Training throws and test hits (noise-free and, at ``noisy_bins``, noisy).
    seed : int
        Seeds targets, release noise and the active runs (>= 0).
    bins : tuple of int
        Grid sizes (clusters per axis, each 1..50) for both layouts, noise-free.
    noisy_bins : int
        Grid size (clusters per axis, 1..50) of the comparison with release noise. Noisy
        throws support fewer clusters than noise-free ones: 20 x 20 clusters fit the
        noise (about 72 throws each) and re-throw 1-3 % worse than 16 x 16 (measured).
    em_steps : tuple of int
        Checkpoints of each adaptive fit (increasing): its error and fit time are measured
        after this many EM steps each (fewer if EM settles first).
    tol : float
        EM stops when a step gains less mean per-row log-likelihood (> 0).
    pseudo_count : float
        Every fit's pseudo-count (>= 0; see :func:`inference.fit`). Default 0: the
        library's 0.01 pseudo-rows of the pooled statistics carry the whole area's spread,
        which against a cluster a few centimetres wide weighs like a couple of rows and
        tilts its regression towards the pooled one (measured in README). With thousands
        of noise-free throws no cluster needs them.
    neighbours : int
        Training throws per local quadratic fit of the reference (>= 6).
    budgets : tuple of int
        Throw counts at which the active and random curves are measured (increasing;
        the first is thrown at random targets by both).
    batch, pool : int
        Targets chosen per round, among ``pool`` random candidates (``batch <= pool``).
    active_seeds : int
        Curves per strategy (>= 1), each from its own seed; a seed's first budget of
        random targets is the same for every strategy.
    noise_repeats : int
        Re-throws per desired hit with release noise (>= 1): the noisy RMS and scatter
        average over them.
    workers : int
        Processes for the model work (the fits and queries of each grid size, the noisy
        comparison, the active curves: :func:`experiments.harness.parallel.run_tasks`); 0: one per
        core. The results do not depend on it.
    progress : bool
        Progress bars.
    """

    n_train: int = 29_000
    n_test: int = 1_000
    seed: int = 0
    bins: tuple[int, ...] = (4, 8, 12, 16, 20)
    noisy_bins: int = 16
    em_steps: tuple[int, ...] = (5, 20)
    tol: float = 1e-6
    pseudo_count: float = 0.0
    neighbours: int = 40
    budgets: tuple[int, ...] = (250, 500, 1_000, 2_000, 4_000)
    batch: int = 50
    pool: int = 2_000
    active_seeds: int = 3
    noise_repeats: int = 10
    workers: int = 0
    progress: bool = True

    def __post_init__(self):
        check_int("n_train", self.n_train, 50)
        check_int("n_test", self.n_test, 1)
        check_int("seed", self.seed, 0)
        check_float("tol", self.tol, 0.0, 1.0, low_open=True)
        check_float("pseudo_count", self.pseudo_count, 0.0, 1e6)
        check_int("neighbours", self.neighbours, 6)
        if self.neighbours > self.n_train:
            raise ConfigError("neighbours", f"{self.neighbours} exceeds n_train={self.n_train}")
        check_int("batch", self.batch, 1)
        check_int("pool", self.pool, self.batch)
        check_int("active_seeds", self.active_seeds, 1)
        check_int("noise_repeats", self.noise_repeats, 1)
        check_int("workers", self.workers, 0)
        for name in ("bins", "budgets", "em_steps"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
            if not getattr(self, name):
                raise ConfigError(name, "empty; expected at least one value")
        for k in self.bins:
            check_int("bins", k, 1, 50)
        check_int("noisy_bins", self.noisy_bins, 1, 50)
        for b in self.budgets:
            check_int("budgets", b, 10)
        for steps in self.em_steps:
            check_int("em_steps", steps, 1)
        for name in ("budgets", "em_steps"):
            v = getattr(self, name)
            if any(b >= c for b, c in zip(v, v[1:], strict=False)):
                raise ConfigError(name, f"{v} must increase")
