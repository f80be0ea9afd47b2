"""Adaptive target clusters (EM) against the paper's grid, and active throw targets.

Beyond the paper's §IV-B (:mod:`experiments.adaptive_throw`): for each grid size the
grid layout and the EM-refined adaptive layout side by side (cluster count, fit time on
one torch thread, re-throw RMS) queried both as the paper does (the posterior) and with
the inverse model (``parameter_for_effect``), the largest also with release noise beside
the noise's own scatter and the exact inverse of the noise-free throw, a local-fit floor
of what the throws support, the best of the inverse model's candidates, what one best
plane per cell leaves of the map's curvature, and re-throw RMS against the number of
throws for actively chosen and random targets. Writes
``adaptive_throw.json``, ``adaptive_throw.md`` and ``adaptive_throw.png`` to ``--out``::

    .venv/bin/python examples/adaptive_throw.py [--n-train 29000] [--bins 4 8 12 16 20]
    .venv/bin/python examples/adaptive_throw.py --quick          # small sizes, seconds
"""

from effect_networks.experiments.harness.cli import main

if __name__ == "__main__":
    main("adaptive_throw", __doc__)
