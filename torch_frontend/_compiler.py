"""``torch.compile`` markers that do not import ``torch._dynamo`` when the package is imported.

``torch.compiler.disable`` and ``assume_constant_result`` import dynamo at decoration time, which
adds ~1.5 s to every process that imports a kernel (the CLI, each rank of a distributed job) for a
feature most runs never use. These two apply the same marks lazily:

* :func:`constant_result`: dynamo's ``assume_constant_result`` mark (an attribute on the function):
  a traced call is evaluated at trace time and baked into the graph as a constant;
* :func:`outside_graphs`: ``torch.compiler.disable`` built on the first call made while compiling
  (when dynamo is loaded anyway); eager calls go straight to the function.
"""

from __future__ import annotations

import functools

import torch

__all__ = ["constant_result", "outside_graphs"]


def constant_result(fn):
    """``torch.compiler.assume_constant_result(fn)`` without importing dynamo: the same mark."""
    fn._dynamo_marked_constant = True
    return fn


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
