"""Adaptive clusters and active throw targets on the throwing experiment.

Two questions beyond the paper's §IV-B, on the same throws (:mod:`experiments.throwing`:
uniform targets on the 2 m x 2 m area, their hits, re-throw RMS per axis ``y``, ``z``):

* **Layouts.** The paper's grid of target clusters (each cluster *is* its cell, fitted
  in closed form by :func:`inference.fit`) against adaptive clusters
  (``Parameter(layout="adaptive")``) refined from the same cells by
  expectation-maximisation over target and hit jointly (:func:`inference.fit_em`). For
  each grid size in ``bins``: cluster count, fit time and the noise-free re-throw RMS of
  both, each queried two ways (``QUERIES``): ``"posterior"``, the paper's inverse
  (:func:`inference.infer_parameter`: the best cluster's posterior mean of the target given
  the hit), and ``"effect"``, the inverse model (:func:`inference.parameter_for_effect`:
  the target under which the hit is most likely). At ``noisy_bins``, also trained and
  re-thrown with release noise, each desired hit re-thrown ``noise_repeats`` times, beside
  the noise's own scatter (the same throws about their noise-free hits) and beside the
  physics' bound: the noise-free throw inverted (:func:`local_inverse` on the noise-free
  training throws, within about 0.1 cm of exact at full scale), which no model of the noisy
  throws can beat by more than that. As a reference for
  the noise-free rows (the result's ``floor``), what a local fit makes of the training
  throws: per test hit,
  Newton's method on a local quadratic forward model fitted to the ``neighbours``
  training throws nearest the current aim (:func:`local_inverse`). Three measurements say
  where the inverse model's error comes from: per row, the best of its candidates (the
  cluster answer that the throw itself says misses least: the error a perfect choice
  would leave); per grid size, what the best linear pieces leave of the map's
  curvature (one least-squares plane per equidistant cell through the unclamped training
  throws, :func:`plane_residuals`); and per row, which hits carry its squared error (the
  worst 1 %'s share, and each cause's: an answer clipped into the area, an aim the arm
  clamps, a choice another cluster would have bettered, the piece's curvature;
  :func:`.aiming.error_tail`), with the headline row's largest errors.
* **Active throw targets.** Learning the grid network from few throws, each batch of
  targets chosen among a pool of random candidates by the expected information gain
  about the clusters' regressions (:func:`inference.design.active_gaussian.select_by_information`)
  or by the expected reduction of the predictive variance summed over the target area
  (:func:`inference.design.active_gaussian.select_by_variance`, ALC), on the grid that
  will be fitted at the next budget, against random targets; re-throw RMS against the
  number of throws, the mean of ``active_seeds`` seeds. The grid size follows the data:
  ``clamp(round(sqrt(n / 30)), 2, 16)`` clusters per axis for ``n`` throws (about 30
  throws per cluster), the same for every strategy; the same grid fitted on all the
  training throws is the curve's floor.

Timings are wall-clock seconds of the fit alone, in the calling process (the example
runs it on one torch thread).

Layers, each importing only those before it: :mod:`.settings` (settings and constants),
:mod:`.aiming` (the inverse model's aims, re-throws and their error's causes),
:mod:`.active_curves` (the active curves and the grid's floor), :mod:`.run` (the run and
its result), :mod:`.report` (Markdown, figures, rows of the
results table), and this package's declaration (``EXPERIMENTS``).
"""

from effect_networks.experiments.adaptive_throw import report
from effect_networks.experiments.adaptive_throw.run import (
    AdaptiveThrowResult,
    adaptive_throw_network,
    local_inverse,
    plane_residuals,
    run_adaptive_throw,
)
from effect_networks.experiments.adaptive_throw.settings import (
    QUERIES,
    QUICK,
    AdaptiveThrowConfig,
)
from effect_networks.experiments.harness.registry import Experiment

__all__ = [
    "AdaptiveThrowConfig",
    "AdaptiveThrowResult",
    "EXPERIMENTS",
    "QUERIES",
    "QUICK",
    "adaptive_throw_network",
    "local_inverse",
    "plane_residuals",
    "report",
    "run_adaptive_throw",
]

EXPERIMENTS = (
    Experiment(
        AdaptiveThrowConfig,
        run_adaptive_throw,
        AdaptiveThrowResult,
        order=50,
        tiny={
            "n_train": 300,
            "n_test": 20,
            "bins": (2,),
            "em_steps": (1, 2),
            "budgets": (40, 80),
            "batch": 20,
            "pool": 60,
        },
        quick=QUICK,
        markdown=report.markdown,
        figures=report.figures,
        summary_rows=report.summary_rows,
    ),
)
