"""Demonstrations of a door world read back as the actions that produced them.

A written demonstration's per-step action posterior and most probable sequence, and how
often drawn demonstrations are read right (:mod:`experiments.demonstration`). Writes
``demonstration.json``, ``.md`` and ``.png`` to ``--out``::

    .venv/bin/python examples/demonstration.py --n-demos 1000 --out results/demonstration
"""

from effect_networks.experiments.harness.cli import main

if __name__ == "__main__":
    main("demonstration", __doc__)
