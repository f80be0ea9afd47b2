"""Fitting (maximum likelihood) and exact queries on effect networks."""

from inference.fitting.em import EMResult, fit_em
from inference.fitting.fit import ConvergenceWarning, FitResult, fit, fit_gradient, fit_statistics
from inference.fitting.pooling import fit_pooled, grid_kernel
from inference.fitting.statistics import Statistics, params_from_statistics
from inference.queries import (
    ActionPosterior,
    CompiledQueries,
    GaussianMixture,
    ImitationCheck,
    ParameterForEffect,
    ParameterPosterior,
    Prediction,
    compile,
    imitation_check,
    infer_action,
    infer_parameter,
    parameter_for_effect,
    predict,
)
from inference.queries.enumeration import Enumerated, enumerate_model
from inference.queries.simulate import simulate

__all__ = [
    "ActionPosterior",
    "CompiledQueries",
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
    "compile",
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
