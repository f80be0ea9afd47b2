"""The paper's experiments as a library: one module, or one package, per experiment.

Each experiment is a function of a frozen, checked settings dataclass that returns a
result dataclass (``to_json``, ``from_json``/``load``), and declares itself once
(:mod:`.harness.registry`): its settings, its run, its result and its report, which
:meth:`.harness.registry.Experiment.save` writes with the result. Each reads in layers:
settings and constants, the run and its result, the report, the declaration. A small
experiment is one module in that order (its result writes its own report); a large one
is a package of ``settings``, ``run`` and ``report`` modules
(:mod:`.active`, :mod:`.adaptive_throw`, :mod:`.can_tossing`), whose report is functions
of a result that the declaration names. The scripts in ``examples/`` call
:func:`.harness.cli.main`, which parses a command line into the settings, runs the
experiment and saves the result.

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
:mod:`.round_planner`     the paper's round planner over sets of objects
:mod:`.harness`           the harness: settings' checks, registry, command lines, summary
:mod:`.evaluation`        scoring: Table I's bins, ROC, aim-robust choice, aim pooling
========================  ==============================================================
"""
