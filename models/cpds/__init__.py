"""Conditional-distribution kinds: each one class that owns its behaviour.

=====================  ==================================  ===============================
kind (``name``)        site                                fitted numbers
=====================  ==================================  ===============================
``table``              discrete child, discrete parents    :class:`TableParams`
``softmax``            discrete child, continuous parents  :class:`SoftmaxParams`
``linear_gaussian``    continuous child                    :class:`LinearGaussianParams`
=====================  ==================================  ===============================

A kind (``TableCPD``, ...) is the structure of one site's distribution, as pgmpy's
``TabularCPD`` is; its fitted numbers are a separate typed container named for it
(``TableParams``, ...), as dynamax keeps ``ParamsCategoricalHMM`` apart from the model.

and :class:`ParameterMixture`, the cluster/value pair of an action parameter. A network
picks for each site the first kind of :data:`KINDS` that does not refuse it
(:meth:`CPD.refuses`), unless its declaration names another (``kinds=``). Adding a kind
to the toolkit is one module here plus its entry in :data:`KINDS`; a user's own kind is
a subclass of :class:`CPD` (or of a built-in kind) passed to the declaration.
"""

from effect_networks.models.cpds.base import CPD, concat_inputs, map_tensors
from effect_networks.models.cpds.linear_gaussian import (
    LinearGaussianCPD,
    LinearGaussianParams,
    Moments,
    NormalInverseWishart,
)
from effect_networks.models.cpds.mixture import ParameterMixture
from effect_networks.models.cpds.softmax import SoftmaxCPD, SoftmaxParams
from effect_networks.models.cpds.table import Counts, TableCPD, TableParams

#: The toolkit's kinds, in the order a site's default kind is chosen.
KINDS: tuple[type[CPD], ...] = (TableCPD, SoftmaxCPD, LinearGaussianCPD)


def default_kind(discrete: bool, width: int) -> type[CPD]:
    """The first kind of :data:`KINDS` that models such a site."""
    return next(k for k in KINDS if k.refuses(discrete, width) is None)


__all__ = [
    "CPD",
    "KINDS",
    "Counts",
    "LinearGaussianCPD",
    "LinearGaussianParams",
    "Moments",
    "NormalInverseWishart",
    "ParameterMixture",
    "SoftmaxCPD",
    "SoftmaxParams",
    "TableCPD",
    "TableParams",
    "concat_inputs",
    "default_kind",
    "map_tensors",
]
