"""Throws into the can pyramid read back as the fields they were thrown at.

Demonstrations of a few throws each, seen as configurations, read by the can network as
fields and thrown again (:mod:`experiments.can_demonstration`). Writes
``can_demonstration.json``, ``.md`` and ``.png`` to ``--out``::

    .venv/bin/python examples/can_demonstration.py --quick --out results/demonstration
"""

from effect_networks.experiments.harness.cli import main

if __name__ == "__main__":
    main("can_demonstration", __doc__)
