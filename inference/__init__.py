"""Fitting (maximum likelihood) and exact queries on effect networks."""

from inference.enumeration import Enumerated, enumerate_model
from inference.fit import FitResult, fit, fit_gradient
from inference.queries import (
    ActionPosterior,
    GaussianMixture,
    ImitationCheck,
    ParameterPosterior,
    Prediction,
    imitation_check,
    infer_action,
    infer_parameter,
    predict,
)
from inference.simulate import simulate

__all__ = [
    "ActionPosterior",
    "Enumerated",
    "FitResult",
    "GaussianMixture",
    "ImitationCheck",
    "ParameterPosterior",
    "Prediction",
    "enumerate_model",
    "fit",
    "fit_gradient",
    "imitation_check",
    "infer_action",
    "infer_parameter",
    "predict",
    "simulate",
]
