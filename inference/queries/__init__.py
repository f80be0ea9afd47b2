"""Exact queries on a fitted effect network, batched over evidence rows.

One module per question, each with its traced answer (the Pyro model, enumerated) and, where one
exists, its compiled answer (tables read once off the same model) side by side.

* :mod:`~inference.queries.forward` -- :func:`predict` (the end state given the initial
  state and an action) and :func:`imitation_check` (how surprising an observed end state
  is under the executed action).
* :mod:`~inference.queries.action` -- :func:`infer_action`: the posterior over actions
  given a (partial) end state; compiled for all-discrete networks.
* :mod:`~inference.queries.parameter` -- :func:`infer_parameter`: the parameter
  posterior, which value an action used given its effect; compiled for a parameter whose
  continuous features no other parameter acts on.
* :mod:`~inference.queries.inverse` -- :func:`parameter_for_effect`: the inverse model,
  the value under which a desired effect is most likely.
* :mod:`~inference.queries.joint` -- :func:`predict_joint`: the joint of the discrete end
  features (not only each one's marginal).

Beside them: :mod:`~inference.queries.results` (the result types),
:mod:`~inference.queries.batching` (evidence checks and row handling),
:mod:`~inference.queries.implausibility`, :mod:`~inference.queries.surprise`,
:mod:`~inference.queries.sampling`; the sums they read are :mod:`inference.exact`'s.

Every query reports ``unseen``: the posterior probability that its answer rests on a
parent configuration no training row reached (answered from the pseudo-count prior alone),
and ``implausible``: a row whose observed end state the model gives almost no probability
(:mod:`inference.queries.implausibility`; threshold ``implausible_below``). Both warn; the
answer is still given.

The questions about sequences of states (transitions, plans, demonstrations, chained
networks) are :mod:`inference.sequences`; :func:`inference.compile` answers both kinds
from compiled tables (:mod:`inference.compiled`).

Evidence follows one convention (:mod:`models.evidence`): state labels for discrete
sites, numbers for continuous ones; a parameter row of NaN is unknown and integrated out
for that row. Empty evidence rows (``n = 0``) give empty results of the right shapes.
"""

from effect_networks.inference.queries.action import infer_action
from effect_networks.inference.queries.forward import imitation_check, predict
from effect_networks.inference.queries.inverse import parameter_for_effect
from effect_networks.inference.queries.joint import JointPrediction, predict_joint
from effect_networks.inference.queries.parameter import infer_parameter
from effect_networks.inference.queries.results import (
    ActionPosterior,
    GaussianMixture,
    ImitationCheck,
    ParameterForEffect,
    ParameterPosterior,
    Prediction,
)

__all__ = [
    "ActionPosterior",
    "GaussianMixture",
    "ImitationCheck",
    "JointPrediction",
    "ParameterForEffect",
    "ParameterPosterior",
    "Prediction",
    "imitation_check",
    "infer_action",
    "infer_parameter",
    "parameter_for_effect",
    "predict",
    "predict_joint",
]
