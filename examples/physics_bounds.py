"""What the physics allows: upper bounds on Table I (both protocols) and the combined scenarios.

No learning: the simulator's own best action, chosen on half of some fresh repeats and
scored on the other half (:mod:`experiments.physics_bounds`). The simulations are saved
under ``--data-dir`` as they finish and resumed when interrupted. Writes
``physics_bounds.json`` and ``physics_bounds.md`` to ``--out``::

    .venv/bin/python examples/physics_bounds.py [--scale full|quick|tiny]
        [--table-z 0.75 0.35 ...] [--executor process:N | dask-local:N | dask://HOST:PORT | ray]
"""

from effect_networks.experiments.harness.cli import main

if __name__ == "__main__":
    main("physics_bounds", __doc__)
