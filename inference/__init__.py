"""Fitting (maximum likelihood) and exact queries on effect networks.

The names the README and the guide teach.

Fitting (:mod:`inference.fitting`): :func:`fit`, :func:`fit_gradient`, :func:`fit_em`,
:func:`fit_pooled` (with :func:`grid_kernel`), :func:`fit_statistics` and
:func:`params_from_statistics`; :func:`simulate` draws rows in ``fit``'s format.
Scores (:mod:`inference.fitting.scores`): :func:`log_likelihood`, :func:`bic`,
:func:`aic`, :func:`cross_validate`, and :func:`select_clusters`, which chooses a
parameter's clusters by them; :func:`learn_structure` chooses the end features' parents
by a decomposable score (:mod:`inference.fitting.structure`).
Questions (:mod:`inference.queries`): :func:`predict`, :func:`imitation_check`,
:func:`infer_action`, :func:`infer_parameter` (the parameter posterior),
:func:`parameter_for_effect` (the inverse model), :func:`predict_joint` (the end
features' joint). Sequences (:mod:`inference.sequences`): :func:`transitions`
(``P(next state | state, action)`` over a network's states), :func:`plan` (the policy
that reaches a goal within a horizon), :func:`explain` (a demonstration read as the
actions that produced it); :func:`link_probabilities` and :func:`chain` read one
network's continuous output as another's actions. :func:`compile`
(:mod:`inference.compiled`): one object whose methods of the same names answer from
compiled tables where they can. The exact sums beneath them all: :mod:`inference.exact`.
Active exploration
(:mod:`inference.design`): :func:`explore`. Pictures of a network and its fitted
numbers (matplotlib, drawn into the caller's axes): the module :mod:`inference.plots`.

Lower-level names live in their modules (:mod:`inference.exact.enumeration`,
:mod:`inference.fitting.sufficient_statistics`, ...).
"""

from effect_networks.inference import plots as plots  # the module only: its names stay off the face
from effect_networks.inference.compiled import CompiledQueries
from effect_networks.inference.compiled import compile as compile  # on the face, not in __all__
from effect_networks.inference.design.active import explore
from effect_networks.inference.fitting.em import EMResult, fit_em
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
from effect_networks.inference.fitting.sufficient_statistics import params_from_statistics
from effect_networks.inference.queries import (
    ActionPosterior,
    GaussianMixture,
    ImitationCheck,
    JointPrediction,
    ParameterForEffect,
    ParameterPosterior,
    Prediction,
    imitation_check,
    infer_action,
    infer_parameter,
    parameter_for_effect,
    predict,
    predict_joint,
)
from effect_networks.inference.queries.implausibility import OutsideTrainingData
from effect_networks.inference.queries.sampling import simulate
from effect_networks.inference.sequences import (
    BoxPartition,
    Explanation,
    FunctionLink,
    LinkProbabilities,
    Plan,
    RestsOnUnseen,
    StateSpace,
    StepModel,
    Transitions,
    chain,
    explain,
    link_probabilities,
    plan,
    step_model,
    transitions,
)

#: On the face but left out of ``__all__``: ``from effect_networks.inference import *``
#: must not hide Python's built-in ``compile`` (``inference.compile`` is there).
NOT_STARRED = ("compile",)

__all__ = [
    "ActionPosterior",
    "BDeu",
    "BoxPartition",
    "ClusterSelection",
    "CompiledQueries",
    "ConvergenceWarning",
    "CrossValidation",
    "EMResult",
    "Explanation",
    "FitResult",
    "FunctionLink",
    "GaussianMixture",
    "ImitationCheck",
    "JointPrediction",
    "K2",
    "LinkProbabilities",
    "LogLikelihood",
    "NormalInverseWishart",
    "OutsideTrainingData",
    "ParameterForEffect",
    "ParameterPosterior",
    "Plan",
    "Prediction",
    "RestsOnUnseen",
    "StateSpace",
    "StepModel",
    "Transitions",
    "aic",
    "bic",
    "chain",
    "cross_validate",
    "explain",
    "explore",
    "fit",
    "fit_em",
    "fit_gradient",
    "fit_pooled",
    "fit_statistics",
    "fit_update",
    "grid_kernel",
    "imitation_check",
    "infer_action",
    "infer_parameter",
    "learn_structure",
    "link_probabilities",
    "log_likelihood",
    "n_parameters",
    "parameter_for_effect",
    "params_from_statistics",
    "plan",
    "predict",
    "predict_joint",
    "select_clusters",
    "simulate",
    "step_model",
    "transitions",
]
