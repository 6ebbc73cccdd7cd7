"""Lazy public names for a package: each name is imported from its module on first use, so that
importing the package stays cheap (no torch import for the config and readers) and every module
can be used on its own."""

from __future__ import annotations

import importlib
import sys
from typing import Any, Callable, Dict, List, Tuple


def lazy_exports(package: str, exports: Dict[str, str]) -> Tuple[Callable[[str], Any], Callable[[], List[str]]]:
    """Module-level ``(__getattr__, __dir__)`` for ``package`` (its ``__name__``), given
    ``exports``: public name -> submodule (relative, without the dot) that defines it. A resolved
    name is stored in the package's namespace, so later lookups skip ``__getattr__``."""

    def __getattr__(name: str) -> Any:
        mod = exports.get(name)
        if mod is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f".{mod}", package), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> List[str]:
        return list(getattr(sys.modules[package], "__all__", sorted(exports)))

    return __getattr__, __dir__
