"""Package attributes loaded on first use (PEP 562), so that importing a package for its light
parts (a protocol's tables, the fault kinds) does not load numpy, scipy or numba."""

from __future__ import annotations

import importlib
import sys
from typing import Callable


def lazy_attributes(package: str, where: dict[str, str]) -> Callable[[str], object]:
    """A module ``__getattr__`` for ``package``: attribute ``name`` is imported from its submodule
    ``where[name]`` when first asked for, then kept in the package."""
    def __getattr__(name: str):
        if name not in where:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{where[name]}"), name)
        setattr(sys.modules[package], name, value)
        return value
    return __getattr__
