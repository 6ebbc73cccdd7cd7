"""``_cache.cached``: the one cache helper (bounded, per device, safe under torch.func transforms and
torch.compile, thread-safe) and ``torch_frontend.clear_caches``; every cache of the package goes
through it."""

from __future__ import annotations

import ast
import threading

import pytest
import torch
from torch.func import grad, jvp, vmap

import torch_frontend as tf
from torch_frontend import _cache

from .conftest import REPO


def _wrapped(t: torch.Tensor) -> bool:
    return torch._C._functorch.is_functorch_wrapped_tensor(t)  # the test may look; the package does not


def test_bounded_lru_and_counters():
    calls = []

    @_cache.cached(2)
    def build(n, device):
        calls.append(n)
        return torch.arange(n, device=device)

    dev = torch.device("cpu")
    a = build(3, dev)
    assert build(3, dev) is a  # a hit returns the very tensor
    build(4, dev)
    build(3, dev)  # 3 is now the most recently used
    build(5, dev)  # evicts 4
    build(4, dev)
    assert calls == [3, 4, 5, 4]
    st = build.cache_stats()
    assert (st.hits, st.misses, st.size, st.maxsize) == (2, 4, 2, 2)
    build.cache_clear()
    assert build.cache_stats().size == 0
    with pytest.raises(ValueError, match="maxsize"):
        _cache.cached(0)


def test_clear_caches_drops_every_registered_cache():
    @_cache.cached(4)
    def build(n):
        return torch.zeros(n)

    build(2)
    tf.FeatureTracker(REPO / "configs" / "euroc.yaml").track(torch.zeros(1, 1, 480, 752, dtype=torch.uint8), [0.0])
    assert any(s.size for s in _cache.cache_stats().values())
    tf.clear_caches()
    assert all(s.size == 0 for s in _cache.cache_stats().values())
    assert build.cache_stats().size == 0


@pytest.mark.parametrize("transform", ["grad", "jvp", "vmap"])
def test_a_miss_under_a_transform_keeps_a_plain_tensor(transform):
    """Built first under grad / jvp, the entry is a plain tensor (built again in the builder thread),
    and later calls outside the transform reuse it."""

    @_cache.cached(4)
    def build(n):
        return torch.arange(n, dtype=torch.float64) * 0.5

    seen = {}

    def f(x):
        seen["inside"] = build(3)
        return (x * seen["inside"]).sum() if transform == "grad" else x * seen["inside"]

    x = torch.ones(3, dtype=torch.float64)
    if transform == "grad":
        g = grad(f)(x)
        assert torch.equal(g, torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64))
    elif transform == "jvp":
        _, t = jvp(f, (x,), (x,))
        assert torch.equal(t, torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64))
    else:
        vmap(f)(torch.ones(2, 3, dtype=torch.float64))
    kept = build(3)
    assert not _wrapped(kept) and kept is seen["inside"]
    assert build.cache_stats().rebuilt == (0 if transform == "vmap" else 1)


def test_builder_calling_a_builder_under_a_transform_does_not_deadlock():
    @_cache.cached(4)
    def inner(n):
        return torch.ones(n)

    @_cache.cached(4)
    def outer(n):
        return inner(n) * 2

    _, t = jvp(lambda x: x * outer(2), (torch.ones(2),), (torch.ones(2),))
    assert torch.equal(t, torch.full((2,), 2.0)) and not _wrapped(outer(2)) and not _wrapped(inner(2))


def test_threads_see_one_consistent_cache():
    @_cache.cached(8)
    def build(n):
        return torch.full((n,), float(n))

    out, errors = [], []

    def work(i):
        try:
            for k in range(200):
                n = 1 + (i + k) % 12
                assert torch.equal(build(n), torch.full((n,), float(n)))
            out.append(i)
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and sorted(out) == [0, 1, 2, 3]
    assert build.cache_stats().size <= 8


def test_first_step_under_jvp_leaves_no_wrapped_tensor_in_any_cache():
    """A differentiable tracker's very first step under torch.func.jvp (every cache empty): no cache
    keeps a transform's wrapper (before: CLAHE's geometry and RANSAC's pair indices did)."""
    from .conftest import load_gray, sample_frames

    tf.clear_caches()
    tr = tf.FeatureTracker(REPO / "configs" / "euroc.yaml", differentiable=True)
    frames = [torch.from_numpy(load_gray(p))[None, None].float() for p in sample_frames("cam0")[:3]]
    state = tr.initial_state()
    for k, x in enumerate(frames):
        def f(img, state=state, k=k):
            return tr.step(state, img, [0.05 * k])[1].uv

        jvp(f, (x,), (torch.ones_like(x),))
        state, _ = tr.step(state, x, [0.05 * k])
    held = [t for c in list(_cache._REGISTRY) for v in list(c.entries.values()) for t in _cache._tensors(v)]
    assert held and not any(_wrapped(t) for t in held)


def _cache_idioms(path):
    """``(line, what)`` of every cache idiom other than ``_cache.cached`` in a module."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr in ("lru_cache", "cache") and \
                isinstance(node.value, ast.Name) and node.value.id == "functools":
            found.append((node.lineno, f"functools.{node.attr}"))
        if isinstance(node, ast.Assign) and isinstance(node.value, (ast.Dict, ast.Call)) and \
                any(isinstance(t, ast.Name) and "CACHE" in t.id.upper() for t in node.targets):
            found.append((node.lineno, "a module-level cache dict"))
    return found


def test_every_cache_goes_through_the_helper():
    bad = [f"{p.relative_to(REPO)}:{line}: {what}" for p in sorted((REPO / "torch_frontend").rglob("*.py"))
           if p.name != "_cache.py" for line, what in _cache_idioms(p)]
    assert not bad, "caches outside torch_frontend._cache.cached:\n" + "\n".join(bad)
