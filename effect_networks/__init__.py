"""effect-networks: a robot's actions stored as the feature changes they cause.

One installed package; its subpackages are the toolkit's rooms:

- :mod:`effect_networks.models`: declaring a network, its fitted parameters, the Pyro model;
- :mod:`effect_networks.inference`: fitting, the exact questions, planning, pictures;
- :mod:`effect_networks.sim2d`: the simulated can world and the robot's throw (no torch);
- :mod:`effect_networks.experiments`: the paper's experiments as a library.

The names a user reaches for first are on this face as well::

    import effect_networks as en

    net = en.EffectNetwork(features=..., actions=...)
    params = en.fit(net, rows).params
    route = en.plan(net, params, start, goal, horizon=3)

They are loaded when first used, so that ``import effect_networks.sim2d`` stays free of
torch and Pyro. ``from effect_networks import *`` brings every face name but
``compile`` (which would hide Python's built-in); ``en.compile`` is there.
"""

from __future__ import annotations

import importlib
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("effect-networks")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"

__doc__ = (__doc__ or "") + (
    f"\nThis is effect-networks {__version__}. Its documentation: README.md (set-up and the\n"
    "quick start) and the user guide in docs/ (docs/guide.md), built into a site with the\n"
    "reference by bin/build-docs; every function's own docstring (help(en.fit)).\n"
)

#: The subpackages, imported on first use as attributes (``en.inference``).
SUBPACKAGES = ("models", "inference", "sim2d", "experiments")
#: The faces whose names this face gives, in order: every name of their ``__all__``, and
#: the names they keep out of it (``NOT_STARRED``: ``compile``).
FACES = ("models", "inference")


def _face(sub: str):
    return importlib.import_module(f"{__name__}.{sub}")


def __getattr__(name: str):
    if name in SUBPACKAGES:
        return _face(name)
    if name == "__all__":  # what a star import brings: every face's __all__
        return sorted({n for sub in FACES for n in _face(sub).__all__}) + ["__version__"]
    if not name.startswith("_"):
        for sub in FACES:
            face = _face(sub)
            if name in face.__all__ or name in getattr(face, "NOT_STARRED", ()):
                value = getattr(face, name)
                globals()[name] = value  # looked up once
                return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *SUBPACKAGES, *__getattr__("__all__")})
