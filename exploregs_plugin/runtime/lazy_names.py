"""Names a package exports but imports on first use (PEP 562's module ``__getattr__``).

A package whose public names pull in heavy dependencies (pycolmap, the scene generators, the
whole training engine) lists them here instead of importing them at its top: ``--help`` and a
config then load without them, and ``from package import name`` still works.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any


def lazy_names(package: str, where: Mapping[str, str]) -> Callable[[str], Any]:
    """The ``__getattr__`` for ``package`` (its ``__name__``) that imports each name of ``where``
    from its module (relative to the package, ``".run"``) on first use and keeps it in the package."""

    def __getattr__(name: str) -> Any:
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(where[name], package), name)
        setattr(sys.modules[package], name, value)
        return value

    return __getattr__
