"""Reproduce the paper's experiments end to end and write ``results/``.

Runs the script of every experiment in :func:`experiments.harness.registry.experiments` in
turn (each can also be run alone; ``--quick`` gives each its quick settings): the §III
illustration, the worlds' pictures, throwing (§IV-B) and beyond the paper its adaptive
clusters and active throw targets, can tossing (§IV-A, Table I), the combined system
(§IV-C, Tables II-IV), the physics' own bounds, and beyond the paper the combined system
on every goal the physics reaches (:mod:`experiments.all_goals`) and Table I learned from
a fraction of the throws by active exploration (:mod:`experiments.active`). The can data
set is generated once under ``--data-dir`` (resumable; default: the cache folder, see
docs/data.md) and reused. Each step runs as its own process and is measured; then
``run.json`` and ``summary.md`` are written, and a full-scale run of every step refreshes
the results table of docs/results.md (:mod:`experiments.harness.reproduce`).

    ./reproduce              # full scale
    ./reproduce --quick      # a first look in a few minutes
    ./reproduce --executor dask://scheduler:8786   # the simulations on a Dask cluster
"""

from effect_networks.experiments.harness.reproduce import main

if __name__ == "__main__":
    main(description=__doc__)
