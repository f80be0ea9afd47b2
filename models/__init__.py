"""Effect networks as Pyro models: declarations, fitted parameters, the model function."""

from models.cpds import (
    CPD,
    KINDS,
    LinearGaussian,
    LinearGaussianCPD,
    ParameterMixture,
    Softmax,
    SoftmaxCPD,
    Table,
    TableCPD,
)
from models.declaration import (
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
from models.evidence import Evidence, Partial
from models.interop import PgmpyNetwork, from_pgmpy, read_bif, to_pgmpy, write_bif
from models.model import effect_model
from models.params import NetworkParams, load, random_params, save

__all__ = [
    "ACTION",
    "CPD",
    "KINDS",
    "LinearGaussianCPD",
    "ParameterMixture",
    "SoftmaxCPD",
    "TableCPD",
    "Continuous",
    "Discrete",
    "EffectNetwork",
    "Evidence",
    "LinearGaussian",
    "NetworkParams",
    "Parameter",
    "Partial",
    "PgmpyNetwork",
    "Softmax",
    "Table",
    "cluster_site",
    "effect_model",
    "end_site",
    "from_pgmpy",
    "initial_site",
    "load",
    "param_site",
    "read_bif",
    "random_params",
    "save",
    "to_pgmpy",
    "write_bif",
]
