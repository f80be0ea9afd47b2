"""The names of a network's Pyro sample sites, and what one site is.

A feature ``f`` has the sites ``initial.f`` (its state before the action) and ``end.f``
(after it); an action parameter ``p`` has ``param.p`` (its value) and ``cluster.p`` (its
cluster); the action is the one site ``action``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

#: The action's site: one discrete root, enumerated by queries.
ACTION = "action"

#: What a site stands for.
Role = Literal["initial", "action", "cluster", "param", "end"]


def initial_site(feature: str) -> str:
    """Site name of a feature's initial state.

    Parameters
    ----------
    feature : str
        A feature's name, as declared.

    Returns
    -------
    str
        ``"initial.{feature}"``: the key of its column in training rows and evidence.
    """
    return f"initial.{feature}"


def end_site(feature: str) -> str:
    """Site name of a feature's end state.

    Parameters
    ----------
    feature : str
        A feature's name, as declared.

    Returns
    -------
    str
        ``"end.{feature}"``: the key of its column in training rows and evidence.
    """
    return f"end.{feature}"


def param_site(parameter: str) -> str:
    """Site name of an action parameter's value.

    Parameters
    ----------
    parameter : str
        An action parameter's name, as declared.

    Returns
    -------
    str
        ``"param.{parameter}"``: the key of its column in training rows and evidence.
    """
    return f"param.{parameter}"


def cluster_site(parameter: str) -> str:
    """Site name of an action parameter's cluster.

    Parameters
    ----------
    parameter : str
        An action parameter's name, as declared.

    Returns
    -------
    str
        ``"cluster.{parameter}"``: the key of its column in training rows and evidence.
    """
    return f"cluster.{parameter}"


@dataclass(frozen=True)
class SiteSpec:
    """One Pyro sample site of a network: its name, type and size."""

    name: str
    discrete: bool
    size: int  # number of states (discrete) or dimension (continuous)
    role: Role
    feature: str | None = None
