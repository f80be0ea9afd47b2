"""The compiled queries' building blocks, under their former path.

:class:`CompiledNetwork` and :func:`compile_discrete` live in
:mod:`inference.queries.action`; :func:`compile_parameter_query` and
:class:`CompiledJointParameterQuery` in :mod:`inference.queries.parameter`;
:class:`CompiledParameterQuery` in :mod:`inference.queries.parameter_tables`.
"""

from inference.queries.action import (
    ANSWERS_BUDGET,
    ANSWERS_CHUNK,
    CompiledNetwork,
    compile_discrete,
)
from inference.queries.parameter import CompiledJointParameterQuery, compile_parameter_query
from inference.queries.parameter_tables import CompiledParameterQuery

__all__ = [
    "ANSWERS_BUDGET",
    "ANSWERS_CHUNK",
    "CompiledJointParameterQuery",
    "CompiledNetwork",
    "CompiledParameterQuery",
    "compile_discrete",
    "compile_parameter_query",
]
