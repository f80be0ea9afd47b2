"""Fitting an effect network to training rows by maximum likelihood.

The closed form for tables and Gaussians (:func:`fit`, on sufficient statistics that
merge by addition: :mod:`inference.fitting.sufficient_statistics`), Newton steps for softmax CPDs,
EM for adaptive clusters (:mod:`inference.fitting.em`) and for missing values
(:mod:`inference.fitting.missing`), the gradient route (:func:`fit_gradient`) and a shared prior over table rows
(:mod:`inference.fitting.pooling`). Every route checks its settings, training rows and
masks with the same rules (:mod:`inference.fitting.rows`), read one way
(:mod:`inference.fitting.reading`), and returns a
:class:`FitResult` (:mod:`inference.fitting.result`). Structure learning
(:func:`learn_structure`) chooses the end features' parents by a decomposable score
(:mod:`inference.fitting.structure`, the families' scores in :mod:`inference.fitting.family`).
"""

from effect_networks.inference.fitting.em import EMResult, fit_em
from effect_networks.inference.fitting.family import family_scores
from effect_networks.inference.fitting.maximum_likelihood import (
    ConvergenceWarning,
    FitResult,
    fit,
    fit_gradient,
    fit_statistics,
)
from effect_networks.inference.fitting.online import fit_update
from effect_networks.inference.fitting.pooling import fit_pooled, grid_kernel
from effect_networks.inference.fitting.priors import K2, BDeu, NormalInverseWishart
from effect_networks.inference.fitting.scores import (
    CrossValidation,
    LogLikelihood,
    aic,
    bic,
    cross_validate,
    log_likelihood,
    n_parameters,
)
from effect_networks.inference.fitting.selection import ClusterSelection, select_clusters
from effect_networks.inference.fitting.structure import learn_structure
from effect_networks.inference.fitting.sufficient_statistics import (
    Statistics,
    params_from_statistics,
)

__all__ = [
    "K2",
    "NormalInverseWishart",
    "BDeu",
    "ClusterSelection",
    "ConvergenceWarning",
    "CrossValidation",
    "EMResult",
    "FitResult",
    "LogLikelihood",
    "Statistics",
    "aic",
    "bic",
    "cross_validate",
    "family_scores",
    "fit",
    "fit_em",
    "fit_gradient",
    "fit_pooled",
    "fit_statistics",
    "fit_update",
    "grid_kernel",
    "learn_structure",
    "log_likelihood",
    "n_parameters",
    "params_from_statistics",
    "select_clusters",
]
