"""Questions about sequences of states, read off a fitted network's tables.

* :mod:`~inference.sequences.states` -- :class:`StateSpace`: a network's states (one
  label per discrete feature with an initial and an end node) as indices, masks and
  distributions.
* :mod:`~inference.sequences.transition_tables` -- :func:`transitions`: ``P(next state |
  state, action)`` over a network's states, as :class:`Transitions`.
* :mod:`~inference.sequences.factored_steps` -- :func:`step_model`: the same step one
  table per site (:class:`StepModel`), at any number of features.
* :mod:`~inference.sequences.planner` -- :func:`~inference.sequences.planner.plan`: the policy that reaches a goal
  within a horizon with the highest probability (:class:`Plan`, in
  :mod:`~inference.sequences.plans`), by exact dynamic programming over the dense
  tables of :mod:`~inference.sequences.dynamic_programming` (:func:`exact_plan` on any
  ``P(s' | s, a)`` tensor, :func:`policy_value` for a fixed policy) or factor by factor
  over the features the goal depends on (:mod:`~inference.sequences.factored_planning`,
  with an approximate route and its :class:`Certificate` beyond a budget).
* :mod:`~inference.sequences.explanation` -- :func:`explain`: a demonstration (a
  sequence of observed states) read as the actions that produced it
  (:class:`Explanation`), summing at each time only the configurations of what it does
  not show (:mod:`~inference.sequences.hidden_steps`, the step tables;
  :mod:`~inference.sequences.hidden_paths`, the sums over paths;
  :mod:`~inference.sequences.dense_explanation`, the route over every state, kept as
  the tests' twin); :mod:`~inference.sequences.demonstration` holds the
  demonstrations' encoding and draws them from a network.
* :mod:`~inference.sequences.chaining` -- :func:`link_probabilities` and :func:`chain`:
  one network's continuous output read as another's actions (:class:`BoxPartition`,
  :class:`FunctionLink`, :class:`LinkProbabilities`), and the chained transitions a
  planner plans over.

The single-step questions they build on are :mod:`inference.queries`; the sums,
:mod:`inference.exact`.
"""

from effect_networks.inference.sequences.chaining import (
    BoxPartition,
    FunctionLink,
    LinkProbabilities,
    chain,
    link_probabilities,
)
from effect_networks.inference.sequences.explanation import Explanation, explain
from effect_networks.inference.sequences.factored_steps import StepFactor, StepModel, step_model
from effect_networks.inference.sequences.planner import RestsOnUnseen, plan
from effect_networks.inference.sequences.plans import Certificate, Plan
from effect_networks.inference.sequences.states import ProjectedSpace, StateSpace
from effect_networks.inference.sequences.transition_tables import Transitions, transitions

__all__ = [
    "BoxPartition",
    "Certificate",
    "Explanation",
    "FunctionLink",
    "LinkProbabilities",
    "Plan",
    "ProjectedSpace",
    "RestsOnUnseen",
    "StateSpace",
    "StepFactor",
    "StepModel",
    "Transitions",
    "chain",
    "explain",
    "link_probabilities",
    "plan",
    "step_model",
    "transitions",
]
