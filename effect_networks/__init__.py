"""effect-networks: a robot's actions stored as the feature changes they cause.

One installed package; its subpackages are the toolkit's rooms:

- :mod:`effect_networks.models`: declaring a network, its fitted parameters, the Pyro model;
- :mod:`effect_networks.inference`: fitting, the exact questions, planning, pictures;
- :mod:`effect_networks.sim2d`: the simulated can world and the robot's throw (no torch);
- :mod:`effect_networks.experiments`: the paper's experiments as a library.

The names a user reaches for first are on this face as well::

    import effect_networks as en

    net = en.EffectNetwork(features=..., actions=...)
    params = en.fit(net, rows).params
    route = en.plan(net, params, start, goal, horizon=3)

They are loaded when first used, so that ``import effect_networks.sim2d`` stays free of
torch and Pyro. ``from effect_networks import *`` brings every face name but
``compile`` (which would hide Python's built-in); ``en.compile`` is there.
"""

from __future__ import annotations

import importlib
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("effect-networks")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"

#: The subpackages, imported on first use as attributes (``en.inference``).
SUBPACKAGES = ("models", "inference", "sim2d", "experiments")

#: Face name -> the subpackage whose face exports it: every name of
#: :mod:`effect_networks.models` and :mod:`effect_networks.inference` (a test checks).
_HOME = {
    **dict.fromkeys(
        (
            "ACTION",
            "CPD",
            "Continuous",
            "Discrete",
            "EffectNetwork",
            "Evidence",
            "KINDS",
            "LinearGaussianCPD",
            "LinearGaussianParams",
            "NetworkParams",
            "Parameter",
            "ParameterMixture",
            "Partial",
            "PgmpyNetwork",
            "SoftmaxCPD",
            "SoftmaxParams",
            "TableCPD",
            "TableParams",
            "cluster_site",
            "effect_model",
            "end_site",
            "from_frame",
            "from_pgmpy",
            "initial_site",
            "load",
            "param_site",
            "random_params",
            "read_bif",
            "save",
            "to_frame",
            "to_pgmpy",
            "write_bif",
        ),
        "models",
    ),
    **dict.fromkeys(
        (
            "ActionPosterior",
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
            "LinkProbabilities",
            "LogLikelihood",
            "OutsideTrainingData",
            "ParameterForEffect",
            "ParameterPosterior",
            "Plan",
            "Prediction",
            "StateSpace",
            "Transitions",
            "aic",
            "bic",
            "chain",
            "compile",
            "cross_validate",
            "explain",
            "explore",
            "fit",
            "fit_em",
            "fit_gradient",
            "fit_pooled",
            "fit_statistics",
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
            "transitions",
        ),
        "inference",
    ),
}

__all__ = sorted(name for name in _HOME if name != "compile") + ["__version__"]


def __getattr__(name: str):
    if name in SUBPACKAGES:
        return importlib.import_module(f"{__name__}.{name}")
    if name in _HOME:
        value = getattr(importlib.import_module(f"{__name__}.{_HOME[name]}"), name)
        globals()[name] = value  # looked up once
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_HOME, *SUBPACKAGES})
