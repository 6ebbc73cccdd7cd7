"""``torch.compile`` marks that do not import ``torch._dynamo`` when the package is imported.

``torch.compiler.disable`` and ``torch.compiler.assume_constant_result`` import dynamo when they
are applied, which adds ~1.5 s to every process that imports a kernel (the CLI, each rank of a
distributed job) for a feature most runs never use. These two apply the same public marks later:

* :func:`constant_result`: ``torch.compiler.assume_constant_result`` (a traced call is evaluated at
  trace time and baked into the graph as a constant). The mark is applied at once when dynamo is
  loaded already, else by :func:`prepare_compile`, which every compile entry point of the package
  (``FeatureTracker.compile``) calls before ``torch.compile``; ``assume_constant_result`` marks and
  returns the very function, so references taken earlier see the mark.
* :func:`outside_graphs`: ``torch.compiler.disable``, built on the first call made while compiling
  (when dynamo is loaded anyway); eager calls go straight to the function.
"""

from __future__ import annotations

import functools
import sys
import threading
from typing import Callable, List

import torch

__all__ = ["constant_result", "outside_graphs", "prepare_compile"]

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


def outside_graphs(fn):
    """``torch.compiler.disable(fn)``, made on the first call inside a ``torch.compile`` trace (cache
    builders: a cold cache under tracing runs eagerly instead of being traced)."""
    disabled = []

    @functools.wraps(fn)
    def call(*args, **kwargs):
        if torch.compiler.is_compiling():
            if not disabled:
                disabled.append(torch.compiler.disable(fn))
            return disabled[0](*args, **kwargs)
        return fn(*args, **kwargs)

    return call
