"""Effect networks as Pyro models: declarations, fitted parameters, the model function."""

from effect_networks.models.cpds import (
    CPD,
    KINDS,
    LinearGaussianCPD,
    LinearGaussianParams,
    ParameterMixture,
    SoftmaxCPD,
    SoftmaxParams,
    TableCPD,
    TableParams,
)
from effect_networks.models.declaration import (
    ACTION,
    Continuous,
    Discrete,
    EffectNetwork,
    Parameter,
    cluster_site,
    end_site,
    initial_site,
    param_site,
)
from effect_networks.models.evidence import Evidence, Partial
from effect_networks.models.frames import from_frame, to_frame
from effect_networks.models.interop import PgmpyNetwork, from_pgmpy, read_bif, to_pgmpy, write_bif
from effect_networks.models.model import effect_model
from effect_networks.models.params import NetworkParams, load, random_params, save

__all__ = [
    "ACTION",
    "CPD",
    "KINDS",
    "LinearGaussianCPD",
    "LinearGaussianParams",
    "ParameterMixture",
    "SoftmaxCPD",
    "SoftmaxParams",
    "TableCPD",
    "TableParams",
    "Continuous",
    "Discrete",
    "EffectNetwork",
    "Evidence",
    "NetworkParams",
    "Parameter",
    "Partial",
    "PgmpyNetwork",
    "cluster_site",
    "effect_model",
    "end_site",
    "from_frame",
    "from_pgmpy",
    "initial_site",
    "load",
    "param_site",
    "read_bif",
    "random_params",
    "save",
    "to_frame",
    "to_pgmpy",
    "write_bif",
]
