"""One cache helper for every per-size constant of the package, and :func:`clear_caches`.

Kernels keep small tables that depend only on sizes, dtypes, devices and settings (index grids,
interpolation weights, OpenCV's RANSAC sample tables): built on the first call of a size, reused
by every later one, so that the per-frame path does no host work and no host-to-device copy. Every
such table is the result of a builder decorated with :func:`cached`:

* **bounded**: at most ``maxsize`` entries per builder, least recently used out first;
* **per device**: the device (and dtype) are arguments of the builder, hence part of the key;
  every entry of every builder is dropped by :func:`clear_caches` (``torch_frontend.clear_caches``),
  e.g. to give a GPU's memory back;
* **safe under torch.func transforms**: under ``grad`` / ``jvp`` / ``vmap`` even a factory function
  returns a tensor wrapped at the transform's level, which kept in a cache would outlive its
  transform (a later call fails with functorch's "escaped" error, or silently mixes levels). A
  result holding such a wrapper (a tensor without storage) is built again in the cache's own
  builder thread, where no transform of the caller is active (functorch's transform stack is per
  thread), and that plain result is kept and returned;
* **safe under torch.compile**: while dynamo traces, a call is a read-only look-up (no lock, no LRU
  update: a dict ``get`` that dynamo traces) and a miss is built outside the graph
  (``torch.compiler.disable``);
* **thread-safe**: look-ups and insertions hold the cache's lock; a builder runs without it, so two
  threads missing the same key may both build it (builders are pure: either result is the same).

A builder must be a pure function of hashable arguments (ints, floats, strings, tuples, dtypes,
devices) returning tensors, tuples / NamedTuples / lists / dicts of them, or host objects.
"""

from __future__ import annotations

import collections
import functools
import threading
import weakref
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable, Dict, List, NamedTuple, Optional

import torch

from ._autodiff import is_wrapper

__all__ = ["cached", "clear_caches", "cache_stats", "holds_plain_tensors"]

_MISSING = object()
# every cache made by `cached`, for clear_caches() (weak: a cache lives as long as its builder)
_REGISTRY: weakref.WeakSet[_Cache] = weakref.WeakSet()
_REGISTRY_LOCK = threading.Lock()


class CacheStats(NamedTuple):
    """A cache's counters: ``hits``, ``misses``, ``rebuilt`` (misses built again in the builder
    thread because the caller's result held a transform's wrapper), ``size``, ``maxsize``."""

    hits: int
    misses: int
    rebuilt: int
    size: int
    maxsize: int


def _tensors(value: Any):
    """The tensors inside a builder's result (tensors, tuples / lists / dicts, NamedTuples, and
    objects with a ``__dict__``, one level deep)."""
    if isinstance(value, torch.Tensor):
        yield value
    elif isinstance(value, (tuple, list)):
        for v in value:
            yield from _tensors(v)
    elif isinstance(value, dict):
        for v in value.values():
            yield from _tensors(v)
    elif hasattr(value, "__dict__") and not isinstance(value, type):
        for v in vars(value).values():
            if isinstance(v, (torch.Tensor, tuple, list, dict)):
                yield from _tensors(v)


def holds_plain_tensors(value: Any) -> bool:
    """Every tensor in ``value`` owns memory (none is a ``torch.func`` transform's wrapper, which
    must not outlive its transform): such a value may be kept across calls."""
    return not any(is_wrapper(t) for t in _tensors(value))


class _BuilderThread(threading.local):
    inside = False


_IN_BUILDER = _BuilderThread()
_EXECUTOR: Optional[ThreadPoolExecutor] = None
_EXECUTOR_LOCK = threading.Lock()


def _build_outside_transforms(fn: Callable, args: tuple) -> Any:
    """``fn(*args)`` in the builder thread (no ``torch.func`` transform of the caller is active
    there), on the caller's CUDA stream; the caller waits for it. A builder that calls another
    cached builder runs it inline (it is in the builder thread already)."""
    if _IN_BUILDER.inside:
        return fn(*args)
    global _EXECUTOR
    with _EXECUTOR_LOCK:
        if _EXECUTOR is None:
            _EXECUTOR = ThreadPoolExecutor(max_workers=1, thread_name_prefix="torch_frontend_cache")
    stream = torch.cuda.current_stream() if torch.cuda.is_available() and torch.cuda.is_initialized() else None

    def run():
        _IN_BUILDER.inside = True
        try:
            if stream is None:
                return fn(*args)
            with torch.cuda.stream(stream):
                return fn(*args)
        finally:
            _IN_BUILDER.inside = False

    return _EXECUTOR.submit(run).result()


class _Cache:
    """The cache of one builder (see :func:`cached`)."""

    def __init__(self, fn: Callable, maxsize: int):
        self.fn, self.maxsize = fn, int(maxsize)
        self.entries: collections.OrderedDict[tuple, Any] = collections.OrderedDict()
        self.lock = threading.Lock()
        self.hits = self.misses = self.rebuilt = 0
        self._build_outside = None

    def lookup(self, args: tuple) -> Any:
        if torch.compiler.is_compiling():
            # read only (dynamo traces a dict look-up); a miss is built outside the graph
            hit = self.entries.get(args, _MISSING)
            return self._miss_outside_graph(args) if hit is _MISSING else hit
        with self.lock:
            hit = self.entries.get(args, _MISSING)
            if hit is not _MISSING:
                self.entries.move_to_end(args)
                self.hits += 1
                return hit
            self.misses += 1
        value = self.fn(*args)
        if not holds_plain_tensors(value):  # built under a torch.func transform: build a plain one
            value = _build_outside_transforms(self.fn, args)
            self.rebuilt += 1
        with self.lock:
            value = self.entries.setdefault(args, value)  # another thread may have built it meanwhile
            self.entries.move_to_end(args)
            while len(self.entries) > self.maxsize:
                self.entries.popitem(last=False)
        return value

    def _miss_outside_graph(self, args: tuple) -> Any:
        # torch.compiler.disable imports dynamo: made on the first miss while compiling
        if self._build_outside is None:
            self._build_outside = torch.compiler.disable(self.lookup)
        return self._build_outside(args)

    def clear(self) -> None:
        with self.lock:
            self.entries.clear()

    def stats(self) -> CacheStats:
        with self.lock:
            return CacheStats(self.hits, self.misses, self.rebuilt, len(self.entries), self.maxsize)


def cached(maxsize: int) -> Callable[[Callable], Callable]:
    """Decorator: keep the results of a pure builder per argument tuple (positional, hashable), at
    most ``maxsize`` of them (LRU); see the module docstring for the rules. The decorated function
    has ``cache_clear()`` and ``cache_stats()`` (a :class:`CacheStats`)."""
    if int(maxsize) < 1:
        raise ValueError(f"maxsize: expected >= 1, got {maxsize}")

    def deco(fn: Callable) -> Callable:
        cache = _Cache(fn, maxsize)
        with _REGISTRY_LOCK:
            _REGISTRY.add(cache)

        @functools.wraps(fn)
        def get(*args):
            return cache.lookup(args)

        get.cache_clear = cache.clear
        get.cache_stats = cache.stats
        get._cache = cache  # keeps the cache alive with the function (the registry is weak)
        return get

    return deco


def clear_caches() -> None:
    """Drop every cached table of the package (all devices), e.g. to give a GPU's memory back or
    after changing devices; the next call of each kernel builds what it needs again. Objects that
    hold their own derived data (a :class:`~torch_frontend.Pyramid`'s padded levels, a tracker's
    state) are not touched."""
    with _REGISTRY_LOCK:
        caches = list(_REGISTRY)
    for c in caches:
        c.clear()


def cache_stats() -> Dict[str, CacheStats]:
    """``qualified builder name -> CacheStats`` of every cache (for tests and diagnostics)."""
    with _REGISTRY_LOCK:
        caches: List[_Cache] = list(_REGISTRY)
    return {f"{c.fn.__module__}.{c.fn.__qualname__}": c.stats() for c in caches}
