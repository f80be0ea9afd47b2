"""Deprecated home of the can-world scoring, which lives in :mod:`experiments.evaluation`.

This module re-exports that module's public names and warns on import; it is kept for
one release so that old imports keep working. It is the only module of ``inference/``
that imports from ``experiments/``, and nothing in the library imports it.
"""

import warnings

from experiments.evaluation import (
    ACCURACY_BINS,
    SURPRISE_LOG_TOLERANCE,
    accuracy_histogram,
    aim_pooled,
    aim_robust_best,
    roc_auc,
    roc_curve,
    tail_surprise,
)

__all__ = [
    "ACCURACY_BINS",
    "SURPRISE_LOG_TOLERANCE",
    "accuracy_histogram",
    "aim_pooled",
    "aim_robust_best",
    "roc_auc",
    "roc_curve",
    "tail_surprise",
]

warnings.warn(
    "inference.evaluation is deprecated and will be removed: import these names from "
    "experiments.evaluation instead",
    DeprecationWarning,
    stacklevel=2,
)
