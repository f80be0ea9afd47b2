"""The paper's can-tossing experiment (§IV-A): Table I, emulation and imitation.

The can network is fitted on the can data set's 0° throws (generated under ``--data-dir``
on first use, then reused) and judged by throwing again: Table I under both protocols
and both tie-breaks, emulation of demonstrated throws, and the imitation surprise's ROC
(:mod:`experiments.can_tossing`). Writes ``can_tossing.json``, ``can_tossing.md``,
``can_tossing_table1.png``, ``can_tossing_roc.png`` and ``can_tossing_bound_curve.png`` to
``--out``::

    .venv/bin/python examples/can_tossing.py --scale full
    .venv/bin/python examples/can_tossing.py --scale tiny --n-demos 30 --out /tmp/cans
"""

from effect_networks.experiments.harness.cli import main

if __name__ == "__main__":
    main("can_tossing", __doc__)
