"""One compiled surface for the questions.

:func:`compile` returns a :class:`CompiledQueries` whose methods carry the traced queries' names,
arguments (less ``net`` and ``params``) and result types.

A method answers from tables read once off the model where they can answer the
evidence, and otherwise calls the traced query; each method's docstring says which. The
tables are built on first use and kept:

* ``infer_action``: the discrete factor tables
  (:class:`~inference.queries.action_tables.CompiledNetwork`) where every site is discrete;
* ``infer_parameter``: the compiled parameter posterior
  (:func:`~inference.queries.parameter.compile_parameter_query`) where no other parameter
  acts on the parameter's continuous features and the evidence is one it reads;
* ``predict``, ``imitation_check``, ``parameter_for_effect``: the traced queries;
* ``transitions`` and ``plan``: the model's tables traced once per context (the
  continuous initial features' values; :func:`~inference.sequences.transition_tables.model_tables`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch
from effect_networks.inference.queries.action import infer_action
from effect_networks.inference.queries.action_tables import compile_discrete as _compile_discrete
from effect_networks.inference.queries.forward import imitation_check, predict
from effect_networks.inference.queries.implausibility import IMPLAUSIBLE_BELOW
from effect_networks.inference.queries.inverse import parameter_for_effect
from effect_networks.inference.queries.parameter import (
    compile_parameter_query as _compile_parameter_query,
)
from effect_networks.inference.queries.parameter import infer_parameter, shared_features
from effect_networks.inference.queries.results import (
    ActionPosterior,
    ImitationCheck,
    ParameterForEffect,
    ParameterPosterior,
    Prediction,
)
from effect_networks.inference.queries.surprise import QUADRATURE_POINTS
from effect_networks.inference.sequences.factored_planning import EPISODES, MAX_RELEVANT_STATES
from effect_networks.inference.sequences.planner import Plan, dense_wanted, plan, plan_on
from effect_networks.inference.sequences.transition_tables import (
    Transitions,
    context_evidence,
    model_tables,
    transitions,
)
from effect_networks.models.declaration import EffectNetwork
from effect_networks.models.frames import as_data
from effect_networks.models.params import NetworkParams, check_params

if TYPE_CHECKING:  # annotations only
    from effect_networks.inference.queries.action_tables import CompiledNetwork
    from effect_networks.inference.queries.parameter import CompiledJointParameterQuery
    from effect_networks.inference.queries.parameter_tables import CompiledParameterQuery


def compile(net: EffectNetwork, params: NetworkParams) -> CompiledQueries:
    """The questions on ``net`` with fitted ``params``, from compiled tables where they can be.

    Answered from compiled tables where they can be (built on first use) and by the traced model
    otherwise; the same answers either way (tested equal).

    Parameters
    ----------
    net, params
        The network and its fitted parameters (checked to fit each other).

    Returns
    -------
    CompiledQueries
        The questions (``predict``, ``infer_action``, ...) on this network, as methods.
    """
    check_params(net, params)
    return CompiledQueries(net, params)


@dataclass(frozen=True, eq=False)
class CompiledQueries:
    """The questions on one fitted network; built by :func:`compile`.

    Each method has the free function's name, arguments (less ``net`` and ``params``)
    and result type. ``action_tables`` and :meth:`parameter_query` are the compiled
    building blocks the methods answer from (``None`` where there are none).
    """

    net: EffectNetwork
    params: NetworkParams = field(repr=False)
    _built: dict = field(default_factory=dict, init=False, repr=False)

    @property
    def action_tables(self) -> CompiledNetwork | None:
        """The discrete factor tables (built on first use); ``None`` where a site is continuous."""
        if "action" not in self._built:
            discrete = all(s.discrete for s in self.net.sites)
            self._built["action"] = _compile_discrete(self.net, self.params) if discrete else None
        return self._built["action"]

    def parameter_query(
        self, parameter: str
    ) -> CompiledParameterQuery | CompiledJointParameterQuery | None:
        """The compiled parameter posterior of ``parameter`` (built on first use).

        ``None`` where another parameter acts on one of its continuous features.
        """
        key = ("parameter", parameter)
        if key not in self._built:
            refused = shared_features(self.net, parameter)
            self._built[key] = (
                None if refused else _compile_parameter_query(self.net, self.params, parameter)
            )
        return self._built[key]

    def predict(
        self,
        evidence: Mapping[str, object],
        *,
        implausible_below: float = IMPLAUSIBLE_BELOW,
    ) -> Prediction:
        """:func:`inference.predict`, answered by the traced model (no tables yet)."""
        return predict(self.net, self.params, evidence, implausible_below=implausible_below)

    def imitation_check(
        self,
        evidence: Mapping[str, object],
        *,
        n_samples: int = QUADRATURE_POINTS,
        seed: int = 0,
        implausible_below: float = IMPLAUSIBLE_BELOW,
    ) -> ImitationCheck:
        """:func:`inference.imitation_check`, answered by the traced model (no tables yet)."""
        return imitation_check(
            self.net,
            self.params,
            evidence,
            n_samples=n_samples,
            seed=seed,
            implausible_below=implausible_below,
        )

    def parameter_for_effect(
        self, parameter: str, evidence: Mapping[str, object]
    ) -> ParameterForEffect:
        """:func:`inference.parameter_for_effect`, the inverse model, answered by the traced model.

        Its candidates are scored in closed form where it can.
        """
        return parameter_for_effect(self.net, self.params, parameter, evidence)

    def infer_action(
        self,
        evidence: Mapping[str, object],
        *,
        allowed: torch.Tensor | None = None,
        avoid_unseen: bool = True,
        implausible_below: float = IMPLAUSIBLE_BELOW,
    ) -> ActionPosterior:
        """:func:`inference.infer_action`, from the discrete factor tables where it can be.

        Answered from the tables where every site is discrete (any evidence, unknown initial states
        included; where the unknown sites are many and their joint splits, by elimination over the
        tables, row by row), by the traced model otherwise.
        """
        tables = self.action_tables
        if tables is None:
            return infer_action(
                self.net,
                self.params,
                evidence,
                allowed=allowed,
                avoid_unseen=avoid_unseen,
                implausible_below=implausible_below,
            )
        return tables.infer_action(
            evidence,
            allowed=allowed,
            avoid_unseen=avoid_unseen,
            implausible_below=implausible_below,
        )

    def infer_parameter(
        self,
        parameter: str,
        evidence: Mapping[str, object],
        *,
        mixture: bool = False,
        implausible_below: float = IMPLAUSIBLE_BELOW,
    ) -> ParameterPosterior:
        """:func:`inference.infer_parameter`, the parameter posterior, compiled where it can be.

        Answered from the compiled query where no other parameter acts on the parameter's continuous
        features and the evidence gives exactly what that query reads (an affected feature, the
        action, the features' discrete parents and continuous inputs, all initial states); by the
        traced model otherwise (an unknown initial state, an observed end feature the parameter does
        not act on, an invalid evidence).
        """
        query = self.parameter_query(parameter)
        evidence = as_data(self.net, evidence)  # a frame reaches the compiled query too
        if query is not None and isinstance(evidence, Mapping) and query.serves(set(evidence)):
            return query.infer_parameter(
                evidence, mixture=mixture, implausible_below=implausible_below
            )
        return infer_parameter(
            self.net,
            self.params,
            parameter,
            evidence,
            mixture=mixture,
            implausible_below=implausible_below,
        )

    def transitions(
        self,
        *,
        states=None,
        actions=None,
        parameter_values: str = "integrate",
        given: Mapping[str, object] | None = None,
        normalise: bool = False,
    ) -> Transitions:
        """:func:`inference.transitions`, read from the model's tables.

        Traced once per ``given`` (the continuous initial features' values) and kept.
        """
        key = ("tables", _context_key(self.net, given))
        if key not in self._built:
            self._built[key] = model_tables(self.net, self.params, given)
        return transitions(
            self.net,
            self.params,
            states=states,
            actions=actions,
            parameter_values=parameter_values,
            normalise=normalise,
            tables=self._built[key],
        )

    def plan(
        self,
        start,
        goal,
        horizon: int,
        allowed=None,
        *,
        states=None,
        parameter_values: str = "integrate",
        given: Mapping[str, object] | None = None,
        normalise: bool = False,
        avoid_unseen: bool = False,
        route: str = "auto",
        budget: int = MAX_RELEVANT_STATES,
        episodes: int = EPISODES,
        seed: int = 0,
    ) -> Plan:
        """:func:`inference.plan`: on :meth:`transitions` (the kept tables) on the dense route.

        The factored routes read the network's tables directly (:func:`inference.step_model`,
        no trace to keep), as :func:`inference.plan` chooses them.
        """
        if route == "factored" or (
            route == "auto" and not dense_wanted(self.net, states, normalise, allowed, start)
        ):
            return plan(
                self.net,
                self.params,
                start,
                goal,
                horizon,
                allowed,
                parameter_values=parameter_values,
                given=given,
                avoid_unseen=avoid_unseen,
                route="factored",
                budget=budget,
                episodes=episodes,
                seed=seed,
            )
        if route not in ("auto", "dense"):
            raise ValueError(f"route must be 'auto', 'dense' or 'factored', got {route!r}")
        model = self.transitions(
            states=states, parameter_values=parameter_values, given=given, normalise=normalise
        )
        return plan_on(model, start, goal, horizon, allowed, avoid_unseen=avoid_unseen)


def _context_key(net: EffectNetwork, given: Mapping[str, object] | None) -> tuple:
    """The continuous initial features' values, checked, as a hashable key."""
    return tuple(
        (site, tuple(value.reshape(-1).tolist()))
        for site, value in sorted(context_evidence(net, given).items())
    )
