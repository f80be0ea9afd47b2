"""Effect networks as Pyro models: declarations, fitted parameters, the model function."""

from models.cpds import (
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
from models.deprecation import renamed
from models.evidence import Evidence, Partial
from models.frames import from_frame, to_frame
from models.interop import PgmpyNetwork, from_pgmpy, read_bif, to_pgmpy, write_bif
from models.model import effect_model
from models.params import NetworkParams, load, random_params, save

#: The containers' names before they were named for their kinds, for one release.
__getattr__ = renamed(
    __name__,
    {"Table": "TableParams", "Softmax": "SoftmaxParams", "LinearGaussian": "LinearGaussianParams"},
)

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
