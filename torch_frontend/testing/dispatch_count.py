"""Count what a piece of tensor code would launch and wait for on a GPU, on any device.

``with OpCounter() as c: fn()`` records every aten op dispatched inside the block with a
``TorchDispatchMode``. Deterministic (no timings), so tests can assert on it:

* ``c.kernels``: non-view, non-allocation ops (each is at least one kernel launch on CUDA);
* ``c.views``: view/alias ops (no launch, host dispatch time only);
* ``c.syncs``: ops that make the host wait for a CUDA device: ``.item()``/``int()``/``bool()`` of
  a tensor (``_local_scalar_dense``), ops whose output size or error check is read back
  (``nonzero``, ``masked_select``, ``unique``, ``bincount``, ``equal``, boolean-mask indexing,
  ``repeat_interleave`` without ``output_size``, linalg ops that check errors on the host), and
  ``Tensor.tolist()`` / ``Tensor.numpy()`` (watched while the counter is active);
* ``c.bytes_written``: bytes of the tensors the kernels write (outputs, ``out=`` and in-place
  targets), and ``c.largest``: the largest of them: the memory-traffic floor of the block (every
  written byte is read at least once more, or it was not needed) and a bound on its peak tensor.
  Bytes read are not counted (a gather's source is a view of the whole tensor; see
  ``../shared/tools/cuda_sim/roofline.py`` for the read side);
* ``c.peak_live``: the peak of the bytes held at once by the storages the block's ops made or
  wrote (kernel and allocation outputs, views of them), each freed at its last tensor reference
  as a GPU's caching allocator would reuse it (no pool rounding): the block's transient peak plus
  what it writes of the longer-lived state; ``c.live_site`` names the op where it was reached;
* ``c.uploads``: tensors made from host data inside the block (``torch.tensor(...)``,
  ``lift_fresh``): on CUDA each is a blocking host-to-device copy, i.e. a sync as well (counted
  in ``c.syncs`` too).

``c.sites`` maps ``(kind, "file:line function")`` to counts for the syncs (the innermost frame in
``torch_frontend``), so that a failing test names the line. The classification follows PyTorch's
CUDA kernels as of torch 2.x, as ``../shared/tools/cuda_sim`` does (which runs a whole tracker on a
simulated CUDA device); this counter needs no device and no set-up.

Convention: counts are per block; ``c.kernels`` of a tracker step is the launch count of one step
on the code path of the tensors' device (run it with ``capturable=True`` for the CUDA path).
"""

from __future__ import annotations

import collections
import sys
import weakref
from pathlib import Path
from typing import Dict, Tuple

import torch
from torch.utils._python_dispatch import TorchDispatchMode

__all__ = ["OpCounter"]

_VIEW_NAMES = frozenset({
    "view", "_unsafe_view", "slice", "select", "unsqueeze", "squeeze", "as_strided", "expand", "detach",
    "alias", "t", "transpose", "permute", "unbind", "split", "split_with_sizes", "narrow", "diagonal",
    "unfold", "view_as", "_reshape_alias", "unflatten", "chunk", "expand_as", "view_as_real",
    "view_as_complex", "movedim", "_conj", "_neg_view", "real", "imag",
})
_ALLOC_NAMES = frozenset({"empty", "empty_like", "new_empty", "empty_strided", "new_empty_strided",
                          "empty_permuted"})
# ops that read a size or an error flag back to the host on CUDA (count: syncs per call)
_SYNC_OPS = {"nonzero": 1, "argwhere": 1, "masked_select": 1, "unique": 1, "_unique": 1, "_unique2": 1,
             "unique_dim": 1, "unique_consecutive": 1, "unique_dim_consecutive": 1, "bincount": 2,
             "histc": 1, "equal": 1, "_linalg_check_errors": 1, "_linalg_eigh": 1, "_linalg_svd": 1,
             "linalg_lstsq": 1, "linalg_eig": 1, "linalg_eigvals": 1, "_local_scalar_dense": 1}
_INDEX_OPS = frozenset({"index", "index_put_", "index_put", "_index_put_impl_"})
_UPLOAD_OPS = frozenset({"lift_fresh", "lift_fresh_copy"})
_PKG = str(Path(__file__).resolve().parents[1])


def _site() -> str:
    """``file:line function`` of the innermost torch_frontend frame outside this file."""
    f = sys._getframe(2)
    here = __file__
    while f is not None:
        fn = f.f_code.co_filename
        if fn.startswith(_PKG) and fn != here:
            return f"{Path(fn).relative_to(_PKG)}:{f.f_lineno} {f.f_code.co_name}"
        f = f.f_back
    return "?"


def _bool_index(name: str, args) -> bool:
    if name not in _INDEX_OPS or len(args) < 2 or args[1] is None:
        return False
    idx = [i for i in args[1] if isinstance(i, torch.Tensor)]
    if not any(i.dtype in (torch.bool, torch.uint8) for i in idx):
        return False
    if name != "index" and len(idx) == 1 and len(args) > 2 and isinstance(args[2], torch.Tensor) \
            and args[2].numel() == 1 and not (len(args) > 3 and args[3]):
        return False  # x[mask] = scalar: CUDA takes the masked_fill path, no sync
    return True


class OpCounter(TorchDispatchMode):
    """Counts kernels, views, syncs and uploads of the ops run inside ``with`` (see the module)."""

    def __init__(self):
        super().__init__()
        self.kernels = 0
        self.views = 0
        self.allocs = 0
        self.syncs = 0
        self.uploads = 0
        self.bytes_written = 0
        self.largest = 0
        self.live_bytes = 0
        self.peak_live = 0
        self.live_site = ""
        self._live: Dict[int, list] = {}  # storage data_ptr -> [tensor references, nbytes]
        self.sites: Dict[Tuple[str, str], int] = collections.Counter()
        self.names: Dict[str, int] = collections.Counter()
        self._saved = None

    # Tensor.tolist / numpy do not dispatch an aten op on the CPU: watch them while counting
    def __enter__(self):
        counter = self
        tolist, numpy = torch.Tensor.tolist, torch.Tensor.numpy

        def _tolist(t, *a, **k):
            counter._sync("tolist")
            return tolist(t, *a, **k)

        def _numpy(t, *a, **k):
            counter._sync("numpy")
            return numpy(t, *a, **k)

        self._saved = (tolist, numpy)
        torch.Tensor.tolist, torch.Tensor.numpy = _tolist, _numpy
        return super().__enter__()

    def __exit__(self, *exc):
        torch.Tensor.tolist, torch.Tensor.numpy = self._saved
        return super().__exit__(*exc)

    def _sync(self, kind: str, n: int = 1) -> None:
        self.syncs += n
        self.sites[(kind, _site())] += n

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = func.overloadpacket.__name__
        self.names[name] += 1
        if name in _UPLOAD_OPS:
            self.uploads += 1
            self._sync("upload (torch.tensor from host data)")
        elif name in _VIEW_NAMES:
            self.views += 1
        elif name in _ALLOC_NAMES:
            self.allocs += 1
        else:
            self.kernels += 1
            n = _SYNC_OPS.get(name, 0)
            if n:
                self._sync(name, n)
            elif _bool_index(name, args):
                self._sync(f"{name} (boolean mask)")
            elif name == "repeat_interleave" and len(args) == 1 and kwargs.get("output_size") is None:
                self._sync("repeat_interleave (no output_size)")
            out = func(*args, **kwargs)
            for t in (out if isinstance(out, (tuple, list)) else (out,)):
                if isinstance(t, torch.Tensor):
                    nb = t.numel() * t.element_size()
                    self.bytes_written += nb
                    self.largest = max(self.largest, nb)
            self._track(out, name, new=True)
            return out
        out = func(*args, **kwargs)
        self._track(out, name, new=name in _ALLOC_NAMES)
        return out

    def _track(self, out, name: str, new: bool) -> None:
        """Live storages: a kernel's or an allocation's outputs (``new``) start one; a view of a
        tracked storage adds a reference. Each tensor reference drops at its finalisation."""
        for t in (out if isinstance(out, (tuple, list)) else (out,)):
            if not isinstance(t, torch.Tensor) or t.device.type == "meta":
                continue
            try:
                st = t.untyped_storage()
                ptr, nb = st.data_ptr(), st.nbytes()
            except (RuntimeError, NotImplementedError):  # no storage (a wrapper subclass)
                continue
            e = self._live.get(ptr)
            if e is None:
                if not new or nb == 0:
                    continue
                e = self._live[ptr] = [0, nb]
                self.live_bytes += nb
                if self.live_bytes > self.peak_live:
                    self.peak_live, self.live_site = self.live_bytes, f"{name} at {_site()}"
            e[0] += 1
            weakref.finalize(t, self._release, ptr)

    def _release(self, ptr: int) -> None:
        e = self._live.get(ptr)
        if e is not None:
            e[0] -= 1
            if e[0] <= 0:
                self.live_bytes -= e[1]
                del self._live[ptr]

    def summary(self) -> str:
        """One line of totals and the sync sites, for messages."""
        top = ", ".join(f"{k[1]} {k[0]} x{v}" for k, v in sorted(self.sites.items(), key=lambda kv: -kv[1])[:8])
        return f"kernels {self.kernels}, views {self.views}, syncs {self.syncs} ({top or 'none'})"
