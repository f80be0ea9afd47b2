"""Beyond the paper: learn the can network from a fraction of the throws (active exploration).

A learner chooses which 0° throws of the can data set to make, by expected information
gain about the network's tables (or at random, or by uncertainty), and Table I is
measured on held-out replays at each budget beside the network fitted on every throw
(:mod:`experiments.active`), each network fitted plainly and pooled over neighbouring
fields (:func:`inference.fit_pooled`). Writes ``active.json``, ``active.md`` and ``active.png`` to
``--out``::

    .venv/bin/python examples/active.py                  # full scale
    .venv/bin/python examples/active.py --quick          # the quick data set, about a minute
"""

from effect_networks.experiments.harness.cli import main

if __name__ == "__main__":
    main("active", __doc__)
