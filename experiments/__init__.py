"""The paper's experiments as a library: one module per experiment.

Each experiment is a function of a frozen, checked settings dataclass that returns a
result dataclass (``to_json``, ``from_json``/``load``, ``to_markdown``, ``figures``,
``summary_rows``, ``save``), and declares itself once (:mod:`.harness.registry`); the larger
ones keep their report beside them (``*_report``). The scripts in ``examples/`` call
:func:`.harness.cli.main`, which parses a command line into the settings, runs the experiment
and saves the result.

========================  ==============================================================
:mod:`.tap_and_remove`    §III: remove and tap, with and without a parameter site
:mod:`.throwing`          §IV-B: the throw network's inverse, re-thrown
:mod:`.can_tossing`       §IV-A: Table I under both protocols, emulation, imitation
:mod:`.combined`          §IV-C: both networks chained, Tables II-IV, both planners
:mod:`.physics_bounds`    the best any model could do, found by simulation
:mod:`.all_goals`         beyond the paper: every reachable goal, beside its bound
:mod:`.active`            beyond the paper: Table I from a fraction of the throws
:mod:`.pictures`          figures of the can world and of the robot's throw
:mod:`.cans`              the can data set at a scale and the can network on it
:mod:`.harness`           the harness: settings' checks, registry, command lines, summary
:mod:`.evaluation`        scoring: Table I's bins, ROC, aim-robust choice, aim pooling
========================  ==============================================================
"""
