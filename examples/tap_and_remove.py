"""The paper's §III illustration: a "remove" action and a "tap" action with a force.

"remove" is emulated and imitated with a plain network; "tap" is predicted without a
parameter site, with one cluster and with ``--bins`` force clusters
(:mod:`experiments.tap_and_remove`). Writes ``tap_and_remove.json``, ``.md`` and
``.png`` to ``--out``::

    .venv/bin/python examples/tap_and_remove.py --n 2000 --out results/tap_and_remove
"""

from effect_networks.experiments.harness.cli import main

if __name__ == "__main__":
    main("tap_and_remove", __doc__)
