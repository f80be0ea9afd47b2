"""Fitting (maximum likelihood) and exact queries on effect networks."""

from inference.em import EMResult, fit_em
from inference.enumeration import Enumerated, enumerate_model
from inference.fit import ConvergenceWarning, FitResult, fit, fit_gradient, fit_statistics
from inference.pooling import fit_pooled, grid_kernel
from inference.queries import (
    ActionPosterior,
    GaussianMixture,
    ImitationCheck,
    ParameterForEffect,
    ParameterPosterior,
    Prediction,
    imitation_check,
    infer_action,
    infer_parameter,
    parameter_for_effect,
    predict,
)
from inference.simulate import simulate
from inference.statistics import Statistics, params_from_statistics

__all__ = [
    "ActionPosterior",
    "ConvergenceWarning",
    "EMResult",
    "Enumerated",
    "FitResult",
    "GaussianMixture",
    "ImitationCheck",
    "ParameterForEffect",
    "ParameterPosterior",
    "Statistics",
    "Prediction",
    "enumerate_model",
    "fit",
    "fit_em",
    "fit_gradient",
    "fit_pooled",
    "fit_statistics",
    "grid_kernel",
    "imitation_check",
    "infer_action",
    "infer_parameter",
    "parameter_for_effect",
    "params_from_statistics",
    "predict",
    "simulate",
]
