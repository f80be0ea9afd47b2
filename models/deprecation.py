"""Old names kept for one release: a module's ``__getattr__`` that answers an old name
with the object of its new name and a ``DeprecationWarning``."""

from __future__ import annotations

import sys
import warnings
from collections.abc import Callable, Mapping


def renamed(
    module: str,
    names: Mapping[str, str],
    why: str = "a kind's fitted numbers are named <kind>Params",
) -> Callable[[str], object]:
    """A ``__getattr__`` for ``module`` (its ``__name__``) that answers each old name of
    ``names`` (``{old: new}``) with the module's object named ``new``, warning (with
    ``why``, the reason for the new name) that the old name goes away in the next
    release."""

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
