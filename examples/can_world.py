"""The can world at a glance: the pyramid and its fields, one throw before/after, a GIF.

Writes ``pyramid.png``, ``throw.png`` and ``throw.gif`` to ``--out`` and prints the
throw's outcome (:func:`experiments.pictures.draw_can_world`)::

    .venv/bin/python examples/can_world.py --field 15 --angle 0   # low, flat, at the near can
"""

from effect_networks.experiments.harness.cli import main

if __name__ == "__main__":
    main("can_world", __doc__)
