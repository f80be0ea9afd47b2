"""Can tossing (the paper's §IV-A): Table I, emulation and imitation with the can network.

The can network (Fig. 2: initial configuration and count, field, end configuration and
count) is fitted by maximum likelihood on the 0° throws of the can data set only
(:mod:`experiments.cans`), then judged by throwing again in the simulated world:

* **Table I.** For each case ``(start configuration, desired count)`` the best field
  given (configuration, count, desired count) is thrown at 0° with the data set's aim
  jitter and a fresh seed; desired minus achieved count is tallied in the paper's bins.
  Two protocols (:func:`table_one_cases`): ``counts``, one case per start and desired
  count some 0° training throw reached from it, plus the unchanged count; ``actions``,
  the paper's wording ("one action that leaves the setup unchanged and all actions that
  somehow change the number of cans"), one case per (start, field) whose first training
  throw changed the count, plus one unchanged case per start. Two ways to pick among
  fields tied in the exact posterior: ``index`` (the query's argmax, lowest index) and
  ``aim`` (the tied field whose neighbours also succeed under the model:
  :func:`experiments.evaluation.aim_robust_best`). All four are measured on the same
  seeds; the settings name the headline.
* **Emulation.** A demonstrated throw's observed end configuration is the evidence; the
  best field for it is thrown, and we count how often it reproduces the demonstrated end
  configuration (and count). The demonstrated field re-thrown with a fresh seed is the
  reference: how often the world reproduces its own effect.
* **Imitation.** Throws with a large aim error (``aim_error`` m per axis); a throw failed
  when its end configuration differs from the unperturbed intended throw's. The
  surprise of the observed end state under the intended field
  (:func:`inference.imitation_check`) should separate the two: ROC AUC. The network's
  table for one (configuration, field) rests on a few jittered throws and misses
  outcomes the field produces now and then; the pooled surprise scores the observed end
  configuration under the intended field's predictive averaged over an aim error of
  ``sigma`` fields (:func:`experiments.evaluation.aim_pooled`), ``sigma`` chosen on a
  separate validation draw of perturbed throws, as is the surprise's threshold (the
  largest true- minus false-positive rate there), whose rates on the scored throws are
  reported. The physics bound (:func:`.surprise.surprise_bound`): the same surprise
  computed from the simulator's own outcome frequencies per aim, over ``bound_repeats``
  replays of every field from every start (the physics bounds' Table I replays), which
  neither the scored throws nor their labels are part of. A few replays per aim estimate
  the world's outcome distribution roughly, so the bound is also measured as fresh
  replays of each scored throw's own aim grow to ``curve_repeats``
  (:func:`.surprise.bound_curve`), and a network fitted on the ``bound_repeats`` replays
  (:func:`experiments.cans.fit_on_replays`) shows how far ours moves towards it with
  more throws per aim than the data set has.

Every evaluation throw draws its aim jitter from ``SeedSequence([seed, purpose])``, never
from the data set's per-throw seeds.

Layers, each importing only those before it: :mod:`.settings` (settings and constants),
:mod:`.surprise` (the imitation surprise's scores and bound), :mod:`.run` (the run and its
result), :mod:`.report` (Markdown, figures, rows of the
results table), and this package's declaration (``EXPERIMENTS``).
"""

from effect_networks.experiments.can_tossing import report
from effect_networks.experiments.can_tossing.run import (
    CanTossingResult,
    emulation,
    imitation,
    play_table_one,
    run_can_tossing,
    summarise,
    table_one,
    table_one_cases,
)
from effect_networks.experiments.can_tossing.settings import (
    PROTOCOLS,
    RULES,
    CanTossingConfig,
)
from effect_networks.experiments.harness.registry import Experiment

__all__ = [
    "CanTossingConfig",
    "CanTossingResult",
    "EXPERIMENTS",
    "PROTOCOLS",
    "RULES",
    "emulation",
    "imitation",
    "play_table_one",
    "report",
    "run_can_tossing",
    "summarise",
    "table_one",
    "table_one_cases",
]

EXPERIMENTS = (
    Experiment(
        CanTossingConfig,
        run_can_tossing,
        CanTossingResult,
        order=60,
        tiny={"scale": "tiny", "n_demos": 2, "bound_repeats": 2, "curve_repeats": 2},
        quick={"scale": "quick", "n_demos": 100, "bound_repeats": 8, "curve_repeats": 32},
        markdown=report.markdown,
        figures=report.figures,
        summary_rows=report.summary_rows,
    ),
)
