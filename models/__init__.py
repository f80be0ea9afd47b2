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
from effect_networks.models.graphs import to_networkx
from effect_networks.models.interop import DroppedSites, PgmpyNetwork, from_pgmpy, to_pgmpy
from effect_networks.models.model import effect_model
from effect_networks.models.params import NetworkParams, load, random_params, save
from effect_networks.models.pgmpy_files import (
    read_bif,
    read_uai,
    read_xmlbif,
    write_bif,
    write_uai,
    write_xmlbif,
)
from effect_networks.models.portable import load_npz, save_npz

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
    "DroppedSites",
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
    "load_npz",
    "param_site",
    "read_bif",
    "read_uai",
    "read_xmlbif",
    "random_params",
    "save",
    "save_npz",
    "to_frame",
    "to_networkx",
    "to_pgmpy",
    "write_bif",
    "write_uai",
    "write_xmlbif",
]
