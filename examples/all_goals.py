r"""Every goal the physics can reach: the combined system beside the physics bound.

For each table height, the robot throws at every height of the pyramid's face from every
state it can reach (its experience, and fresh repeats for the bound); the can network is
trained on that experience with aim heights as actions, the throw network on random
throws; the exact planner and the paper's round planner are played towards every stable
sub-configuration that the bound reaches within ``--horizon`` throws
(:mod:`experiments.all_goals`).

    python examples/all_goals.py [--quick] [--table-z 0.75 0.35] [--executor process:N]

Writes all_goals.json, all_goals.md and all_goals.png to ``--out``.
"""

from effect_networks.experiments.harness.cli import main

if __name__ == "__main__":
    main("all_goals", __doc__)
