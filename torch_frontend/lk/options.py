"""The settings of one LK pass, :class:`LKOptions`, checked and normalised once (``docs/lk.md``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Tuple

from ..errors import ConfigError

__all__ = ["LKOptions", "GRAD_MODES"]

GRAD_MODES = ("unrolled", "implicit")


def _compile_items(value: Any) -> Tuple[Tuple[str, Any], ...] | bool:
    """``LKOptions.compile_step`` normalised: False, or the ``torch.compile`` keywords as sorted
    ``(name, value)`` pairs (``dynamic=True`` unless given), so that the options stay hashable."""
    if value is True:
        value = {}
    elif not isinstance(value, Mapping):
        if not value:  # False, None
            return False
        try:
            value = dict(value)
        except (TypeError, ValueError):
            raise ConfigError(f"compile_step must be a bool or a mapping of torch.compile keywords, got {value!r}") \
                from None
    kw = {"dynamic": True, **value}
    if any(not isinstance(k, str) for k in kw):
        raise ConfigError(f"compile_step: torch.compile keywords must be names, got {sorted(kw, key=str)!r}")
    items = tuple(sorted(kw.items()))
    try:
        hash(items)
    except TypeError:
        raise ConfigError(f"compile_step: the torch.compile keywords must be hashable, got {value!r}") from None
    return items


@dataclass(frozen=True)
class LKOptions:
    """The parameters of one LK pass, checked and normalised once (as :func:`track_lk` takes them).

    Attributes:
        win_size: window ``(w, h)`` in pixels, each > 2 (an int is taken as ``(w, w)``).
        max_level: top pyramid level, >= 0 (capped by the pyramids and OpenCV's size rule).
        max_iters: iterations per level, clamped to ``[0, 100]`` as OpenCV.
        eps: stop when ``|delta| <= eps`` pixels, clamped to ``[0, 10]`` as OpenCV.
        min_eig_threshold: ``minEigThreshold``.
        fixed_point: OpenCV's 14-bit fixed-point interpolation (8-bit images).
        capturable: False (default): the eager path, tuned for the CPU: compacts to the
            still-moving points and stops when none is left (one host sync per iteration). True:
            the capturable path (a fixed number of masked iterations per level, all streams in one
            pass, no host sync, a kernel count independent of B and of the data; CUDA graphs,
            ``torch.compile``). The same results bit for bit.
        iter_budget: iterations run per level (None: ``max_iters``, exact), an int or a tuple per
            level (``iter_budget[l]`` for level ``l``, the last entry for the levels above). A
            smaller budget bounds the work of the capturable path (on both paths the same
            results); a lane still iterating when it ends may differ from OpenCV, which the
            ``overflow`` field of ``_track_lk_impl``'s :class:`LKResult` reports per stream.
        tail_share: the capturable path's split of a full budget (``iter_budget`` None): after
            ``lk.capturable._TAIL_FROM`` (8) iterations on every lane, the rest run on a sub-batch of
            ``1/tail_share`` of the lanes (at least 16), the running ones first, and from 12
            iterations on a quarter of those where that pays (``lk.capturable._split_plan``): the
            work of the masked no-ops of lanes that have stopped (on real frames all but a few) is
            not done. A lane still running without a seat stops there and raises ``overflow``
            (results differ from OpenCV's only there). Default 8; 1: every lane runs every iteration.
        grad_mode: ``"implicit"`` (default: implicit-function gradient of the level-0 solution)
            or ``"unrolled"`` (autograd through every iteration); the forward values are the same
            bit for bit.
        compile_step: the eager path's per-iteration kernel through ``torch.compile`` (True, or a
            mapping of ``torch.compile`` keywords with hashable values; ``dynamic=True`` unless
            given); normalised to False or the sorted keyword pairs. The same values; no effect on
            the capturable path (compile the whole call there).
        backend: ``"fused"``: the calls these options cover run the fused LK (one custom op,
            OpenCV's bits; ``fused/``); ``"tensor"`` (default): the tensor LK. A resolved backend
            (:func:`torch_frontend.fused.resolve_backend`): ``track_lk`` and ``FeatureTracker``
            resolve ``lk_backend`` once. The fused LK covers 8-bit fixed point, float32 points, no
            ``iter_budget``, windows >= 8 wide and no unrolled gradient; any other call runs the
            tensor LK.

    Raises:
        ConfigError: a window <= 2, a negative / non-int ``max_level`` or ``iter_budget``, an
            unknown ``grad_mode`` or ``backend``, ``compile_step`` keywords that are not hashable.
    """

    win_size: Tuple[int, int] = (21, 21)
    max_level: int = 3
    max_iters: int = 30
    eps: float = 0.01
    min_eig_threshold: float = 1e-4
    fixed_point: bool = True
    capturable: bool = False
    iter_budget: int | Tuple[int, ...] | None = None
    tail_share: int = 8
    grad_mode: str = "implicit"
    compile_step: Any = False
    backend: str = "tensor"

    def __post_init__(self):
        if self.grad_mode not in GRAD_MODES:
            raise ConfigError(f"grad_mode must be one of {GRAD_MODES}, got {self.grad_mode!r}")
        win = self.win_size
        win = (win, win) if isinstance(win, int) else (int(win[0]), int(win[1]))
        if win[0] <= 2 or win[1] <= 2:
            raise ConfigError(f"win_size must be > 2 in both axes, got {self.win_size!r}")
        if not isinstance(self.max_level, int) or self.max_level < 0:
            raise ConfigError(f"max_level must be an int >= 0, got {self.max_level!r}")
        fields = dict(win_size=win, max_iters=min(max(int(self.max_iters), 0), 100),
                      eps=min(max(float(self.eps), 0.0), 10.0), min_eig_threshold=float(self.min_eig_threshold),
                      fixed_point=bool(self.fixed_point), capturable=bool(self.capturable),
                      compile_step=_compile_items(self.compile_step))
        if self.backend not in ("fused", "tensor"):
            raise ConfigError(f"LKOptions.backend must be 'fused' or 'tensor' (resolved), got {self.backend!r}")
        if isinstance(self.tail_share, bool) or not isinstance(self.tail_share, int) or self.tail_share < 1:
            raise ConfigError(f"tail_share must be an int >= 1, got {self.tail_share!r}")
        b = self.iter_budget
        if b is not None:
            items = b if isinstance(b, (tuple, list)) else (b,)
            if not items or any(isinstance(x, bool) or not isinstance(x, int) or x < 0 for x in items):
                raise ConfigError(f"iter_budget must be None, an int >= 0 or a non-empty tuple of them, got {b!r}")
            fields["iter_budget"] = tuple(items) if isinstance(b, (tuple, list)) else b
        for name, value in fields.items():
            object.__setattr__(self, name, value)

    def budget_at(self, level: int) -> int:
        """Iterations run at ``level``: ``iter_budget`` capped by ``max_iters`` (``max_iters`` when None)."""
        b = self.iter_budget
        if b is None:
            return self.max_iters
        if isinstance(b, tuple):
            b = b[min(level, len(b) - 1)]
        return min(b, self.max_iters)

    @property
    def budget(self) -> int:
        """The largest per-level budget (``max_iters`` when ``iter_budget`` is None)."""
        b = self.iter_budget
        return max(self.budget_at(l) for l in range(len(b))) if isinstance(b, tuple) else self.budget_at(0)

    @property
    def inexact(self) -> bool:
        """Some level's budget is below ``max_iters`` (results may differ from OpenCV: overflow flag)."""
        b = self.iter_budget
        return b is not None and any(min(x, self.max_iters) < self.max_iters for x in (b if isinstance(b, tuple) else (b,)))
