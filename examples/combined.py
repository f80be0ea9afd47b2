"""The paper's combined system (§IV-C): the throw network aims, the can network plans.

Trains the throw network on the robot's throws and the can network on the can data set
(under ``--data-dir``, generated on first use), then plays the paper's three scenarios
(Tables II-IV) with the paper's round planner and with an exact planner
(:mod:`experiments.combined`). Writes ``combined.json`` and ``combined.md`` to ``--out``::

    .venv/bin/python examples/combined.py [--scale full|quick|tiny] [--noise]
        [--proposals can|combined] [--table-z 0.75] [--jitter 0.003]
"""

from effect_networks.experiments.harness.cli import main

if __name__ == "__main__":
    main("combined", __doc__)
