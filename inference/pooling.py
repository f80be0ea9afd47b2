"""Deprecated import path: this module is now :mod:`inference.fitting.pooling`.

Every name is forwarded there with a ``DeprecationWarning``; the old path goes away in
the next release.
"""

import importlib
import warnings

_NEW = "inference.fitting.pooling"

warnings.warn(
    f"inference.pooling moved to {_NEW}; import it from there",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name: str):
    return getattr(importlib.import_module(_NEW), name)
