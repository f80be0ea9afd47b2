"""Old names kept for one release.

A module's ``__getattr__`` that answers an old name with the object of its new name
(:func:`renamed`) or a name from the module that holds it now (:func:`moved`), and a
``DeprecationWarning``.
"""

from __future__ import annotations

import importlib
import sys
import warnings
from collections.abc import Callable, Mapping


def renamed(
    module: str,
    names: Mapping[str, str],
    why: str = "a kind's fitted numbers are named <kind>Params",
) -> Callable[[str], object]:
    """A ``__getattr__`` for ``module`` that answers old names with their new objects.

    ``module`` is its ``__name__``. Each old name of ``names`` (``{old: new}``) is answered with the
    module's object named ``new``, warning (with ``why``, the reason for the new name) that the old
    name goes away in the next release.
    """

    def __getattr__(name: str) -> object:
        new = names.get(name)
        if new is None:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        warnings.warn(
            f"{module}.{name} is now {module}.{new} ({why}); the name {name} goes away in "
            "the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(sys.modules[module], new)

    return __getattr__


def moved(module: str, homes: Mapping[str, str], message: str) -> Callable[[str], object]:
    """A ``__getattr__`` for ``module`` that answers moved names from their new modules.

    ``module`` is its ``__name__``. Each name of ``homes`` (``{name: the module that holds it
    now}``) is answered from that module, warning with ``message`` formatted with ``name`` and
    ``home``.
    """

    def __getattr__(name: str) -> object:
        home = homes.get(name)
        if home is None:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        warnings.warn(message.format(name=name, home=home), DeprecationWarning, stacklevel=2)
        return getattr(importlib.import_module(home), name)

    return __getattr__
