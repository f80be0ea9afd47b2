"""The paper's throwing experiment (§IV-B): learn where to aim to hit a point, and re-throw.

The throw network's inverse query answers "where to aim to hit this point"; the robot
throws there and the new hit's RMS error against the desired one is reported per axis,
without and with release noise (:mod:`experiments.throwing`). Writes ``throwing.json``,
``throwing.md`` and ``throwing_errors.png`` to ``--out``::

    .venv/bin/python examples/throwing.py [--n-train 29000] [--n-test 1000] [--seed 0]
    .venv/bin/python examples/throwing.py --quick          # small sizes, seconds
"""

from effect_networks.experiments.harness.cli import main

if __name__ == "__main__":
    main("throwing", __doc__)
