"""What every picture shares: the axes to draw on, a site's parents and its labels."""

from __future__ import annotations

from effect_networks.models.declaration import EffectNetwork


def new_axes(ax):
    """``ax``, or the axes of a new figure when it is ``None``."""
    if ax is None:
        import matplotlib.pyplot as plt

        _, ax = plt.subplots()
    return ax


def check_site(net: EffectNetwork, site: str) -> None:
    """Raise a ValueError naming ``site`` and the network's sites if it is not one."""
    if site not in {s.name for s in net.sites}:
        raise ValueError(
            f"site {site!r} does not exist in this network; its sites are "
            f"{[s.name for s in net.sites]}"
        )


def site_parents(net: EffectNetwork, site: str) -> tuple[str, ...]:
    """Every parent of ``site``: its discrete parents, then its continuous inputs.

    Parameters
    ----------
    net
        The network.
    site
        A site's name (``"end.visible"``, ...).

    Returns
    -------
    tuple of str
        The parents' site names.
    """
    cpd = net.cpd(site)
    return cpd.parents + cpd.inputs


def state_labels(net: EffectNetwork, site: str) -> tuple:
    """The labels of a discrete site's states.

    A feature's states, the action names, or a cluster's numbers ``0 .. C-1``.

    Parameters
    ----------
    net
        The network.
    site
        A discrete site's name.

    Returns
    -------
    tuple
        Its state labels, in order.
    """
    spec = net.site(site)
    if not spec.discrete:
        raise ValueError(f"site {site!r} is continuous; it has no state labels")
    if spec.role == "action":
        return net.actions
    if spec.role == "cluster":
        return tuple(range(spec.size))
    return net.feature(spec.feature).states
