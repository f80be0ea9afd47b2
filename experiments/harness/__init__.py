"""What runs the experiments, none of them in particular.

=====================  ===============================================================
:mod:`.config`         checks of settings, and the results' base (JSON, report, files)
:mod:`.registry`       every experiment's declaration (``EXPERIMENTS`` in its module)
:mod:`.cli`            an experiment's command line, derived from its settings
:mod:`.parallel`       the experiments' tasks run in forked processes
:mod:`.steps`          a step's own measures (simulation time, peak memory)
:mod:`.summary`        the results table from the saved results, for README.md
:mod:`.compare`        two results folders compared, timings and paths aside
=====================  ===============================================================
"""
