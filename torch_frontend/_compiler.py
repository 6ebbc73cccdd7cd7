"""``torch.compile`` marks that do not import ``torch._dynamo`` when the package is imported.

``torch.compiler.assume_constant_result`` imports dynamo when it is applied, which adds ~1.5 s to
every process that imports a kernel (the CLI, each rank of a distributed job) for a feature most
runs never use. :func:`constant_result` applies the same public mark later (a traced call of a
marked function is evaluated at trace time and baked into the graph as a constant): at once when
dynamo is loaded already, else in :func:`prepare_compile`, which every compile entry point of the
package (``FeatureTracker.compile``) calls before ``torch.compile``. ``assume_constant_result``
marks and returns the very function, so references taken earlier see the mark. (Cache misses while
compiling are kept out of graphs by ``_cache.cached`` itself.)
"""

from __future__ import annotations

import sys
import threading
from typing import Callable, List

import torch

__all__ = ["constant_result", "prepare_compile"]

_CONSTANT: List[Callable] = []  # functions waiting for their assume_constant_result mark
_LOCK = threading.Lock()


def _dynamo_loaded() -> bool:
    return "torch._dynamo" in sys.modules


def constant_result(fn):
    """``torch.compiler.assume_constant_result(fn)``, applied without importing dynamo now (see the
    module docstring). Returns ``fn`` itself."""
    if _dynamo_loaded():
        return torch.compiler.assume_constant_result(fn)
    with _LOCK:
        _CONSTANT.append(fn)
    return fn


def prepare_compile() -> None:
    """Apply the pending :func:`constant_result` marks (imports dynamo). Call before
    ``torch.compile`` of code that reaches marked functions; idempotent."""
    with _LOCK:
        pending = list(_CONSTANT)
        _CONSTANT.clear()
    for fn in pending:
        torch.compiler.assume_constant_result(fn)
