"""Beyond the paper: learn the can network from a fraction of the throws (active exploration).

Table I's can network is fitted on every 0° throw of the can data set (every stable
configuration x every throwable field x its repeats). Here a learner chooses which
throws to make (:func:`inference.design.active.explore`) and the learning curve of Table I's
exact fraction against the number of throws used is measured for each strategy, beside
the network fitted on every throw.

* **Pool and oracle.** The pool is the 0° throwable throws
  :func:`experiments.cans.fit_can_network` fits on: one candidate per recorded throw,
  so each (configuration, field) pair is listed once per recorded repeat and can be played at most that often.
  Playing candidate ``i`` returns the end configuration and count that recorded throw
  reached. The oracle is fair: every recorded throw is an independent draw of the world
  (its own seeded aim jitter), the learner sees only the throws it asks for, and the
  full-data network is fitted on exactly the same throws, so the curves and the
  full-data figure share one source and no simulation noise between them.
* **Scoring on held-out replays.** Table I's cases
  (:func:`experiments.can_tossing.run.table_one_cases`, both protocols, from the full data
  set so that every curve point answers the same cases) get their best field from the learned network exactly as
  Table I does (:func:`experiments.cans.choose`, both tie-break rules). The field
  is scored on ``repeats`` fresh throws of (start, field) that no network was fitted on
  (the physics bound's replays, :mod:`experiments.physics_bounds`, seed
  ``BOUND_SEED``): the case's success is the fraction of replays that reach the desired
  count, its expectation over the aim jitter rather than one throw's luck. The simulator's
  own best field, chosen on half of the replays and scored on the other half, is the
  bound (:func:`experiments.physics_bounds.held_out_best`).
* **Fits.** Every curve point's network is fitted on the chosen throws twice: plainly
  (:func:`inference.fit`, scored with both tie-break rules) and with each row's prior
  pooled from the neighbouring fields' throws (:func:`inference.fit_pooled`, kernel
  width ``pool_sigma`` fields, ``pool_strength`` pseudo-throws; score ``pooled``). Either
  way the start and field priors are the pool's
  (:func:`inference.design.active.with_pool_prior`), not the learner's play
  frequencies, which would otherwise steer the choice towards often-played fields. The full data is fitted the same two ways, and the
  goal is measured against its best score. The fits are of :func:`scoring_network`, the
  can network with the end configuration parentless (its large table, which no score
  reads, is never fitted; the same answers, bit for bit, at a fraction of the cost); the compiled tables of each fit
  answer both protocols, one field per distinct (start, desired count). Each budget's
  evaluation time is in the result (``point_time_s``; goal under ``POINT_GOAL_S``).
* **Strategies.** ``eig`` (plain Dirichlet information gain with the fit's pseudo-count
  as prior), ``eig_shared`` (the same with a prior shared by a start configuration's
  fields, weight ``prior_strength``), ``uncertainty`` (predictive entropy) and
  ``random``; every gain is about ``sites`` (default ``end.count``, the site Table I's
  query reads).

The goal: within one point of the full data's exact fraction with at most 10 % of its
throws (the 0° throws Table I fits on).

Layers, each importing only those before it: :mod:`.settings` (settings and constants),
:mod:`.run` (the run and its result), :mod:`.report` (Markdown, figures, rows of the
results table), and this package's declaration (``EXPERIMENTS``).
"""

from effect_networks.experiments.active import report
from effect_networks.experiments.active.run import (
    ActiveResult,
    bound_by_repeats,
    can_pool,
    cases_seen,
    replay_counts,
    run_active,
    scoring_network,
    table_one_on_replays,
)
from effect_networks.experiments.active.settings import (
    LEARNERS,
    QUICK,
    SCORES,
    ActiveConfig,
)
from effect_networks.experiments.harness.registry import Experiment

__all__ = [
    "ActiveConfig",
    "ActiveResult",
    "EXPERIMENTS",
    "LEARNERS",
    "QUICK",
    "SCORES",
    "bound_by_repeats",
    "can_pool",
    "cases_seen",
    "replay_counts",
    "report",
    "run_active",
    "scoring_network",
    "table_one_on_replays",
]

EXPERIMENTS = (
    Experiment(
        ActiveConfig,
        run_active,
        ActiveResult,
        order=100,
        tiny={"scale": "tiny", "repeats": 2, "fractions": (0.3, 1.0), "batch_size": 20},
        quick=QUICK,
        markdown=report.markdown,
        figures=report.figures,
        summary_rows=report.summary_rows,
    ),
)
