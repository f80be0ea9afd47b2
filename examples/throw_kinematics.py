"""The throw kinematics of the paper's throwing experiment (§IV-B), in figures and numbers.

Writes ``target_to_hit.png`` (a grid of targets on the plane x = 2 m and the hits their
throws produce; throws clamped by the arm's joint limits in red) and
``flight_paths.png`` (top and side views of a few throws) to ``--out``, and prints the
clamped share of uniform targets, the share of the target area any throw can hit, the
time for ``--n`` throws and the scatter release noise adds
(:func:`experiments.pictures.draw_throw_kinematics`)::

    .venv/bin/python examples/throw_kinematics.py [--out results/throw] [--grid 15] [--n 30000]
"""

from effect_networks.experiments.harness.cli import main

if __name__ == "__main__":
    main("throw_kinematics", __doc__)
