"""A soft (or straight-through) tracking status: a differentiable confidence in ``[0, 1]`` for
the LK's discrete ``status``.

Convention:
    ``prev``, ``next``: ``(B, 1, H, W)`` images (uint8 or float grey levels 0..255) or their
    :class:`~torch_frontend.pyramid.Pyramid` (level 0 is used). ``pts (B, N, 2)`` pixels in ``prev``,
    ``tracked (B, N, 2)`` pixels in ``next`` (pixel centres at integer coordinates), ``status (B,
    N)`` bool (LK's; None: every point).

The confidence of a point is ``status * w_border * w_photo``:

* ``w_border = sigmoid(d / temperature)``, ``d`` the signed distance (px) of ``tracked`` to the edge
  of the region VINS's ``inBorder`` keeps (``border <= cvRound(x) < W - border``, i.e. ``x`` in
  ``[border - 0.5, W - border - 0.5)``): 0.5 on the edge, ~1 a few temperatures inside;
* ``w_photo = exp(-(r / sigma)^2)``, ``r`` the mean Charbonnier difference ``sqrt(e^2 + 1) - 1``
  (grey levels; smooth at ``e = 0``, unlike ``|e|``) between the ``win x win`` windows of ``prev``
  at ``pts`` and of ``next`` at ``tracked`` (bilinear): a track whose windows disagree is unlikely
  to be the same surface point.

LK's own discrete decisions (window outside the image, ``minEig`` below the threshold) enter only
as the factor ``status``: a point that LK lost has confidence 0 and no gradient.
``mode="straight_through"`` returns the hard status (0/1) as the value and the soft confidence's
gradient (``hard + soft - soft.detach()``), for losses that must count exactly the points VINS keeps.
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F

from .._cache import cached
from .._checks import as_image_batch, check_shape, default_valid
from ..pyramid import Pyramid

Tensor = torch.Tensor

MODES = ("soft", "straight_through")
#: default window side (px): VINS's LK window
STATUS_WIN = 21
#: default photometric scale (grey levels): well-tracked EuRoC / Middlebury windows differ by a
#: few grey levels after CLAHE, a wrong match by tens
PHOTO_SIGMA = 16.0
#: default softness of the border term (px)
BORDER_TEMPERATURE = 0.5


@cached(16)
def _window_offsets(win: int, dtype: torch.dtype, device) -> Tensor:
    """``(win * win, 2)`` offsets ``(dx, dy)`` of a window centred on its point, row-major."""
    r = torch.arange(win, dtype=dtype, device=device) - (win - 1) / 2.0
    dy, dx = torch.meshgrid(r, r, indexing="ij")
    return torch.stack((dx, dy), -1).reshape(-1, 2)


def _level0(img, name: str) -> Tensor:
    x = img.levels[0] if isinstance(img, Pyramid) else as_image_batch(torch.as_tensor(img), name)
    return x if x.is_floating_point() else x.to(torch.float32)


def sample_windows(img: Tensor, pts: Tensor, win: int) -> Tensor:
    """Bilinear ``win x win`` windows of ``img (B, 1, H, W)`` centred at ``pts (B, N, 2)`` pixels:
    ``(B, N, win * win)`` in ``pts``' dtype (samples beyond the edge repeat it: ``padding_mode="border"``)."""
    B, N = pts.shape[:2]
    H, W = img.shape[-2:]
    q = pts.unsqueeze(2) + _window_offsets(win, pts.dtype, pts.device)  # (B, N, win^2, 2)
    # align_corners=True: -1 / +1 are the centres of the first / last pixels (Python scales: no upload)
    grid = torch.stack((q[..., 0] * (2.0 / max(W - 1, 1)) - 1, q[..., 1] * (2.0 / max(H - 1, 1)) - 1), -1)
    return F.grid_sample(img.to(pts.dtype), grid, mode="bilinear", padding_mode="border",
                         align_corners=True)[:, 0]


def soft_status(prev, next, pts: Tensor, tracked: Tensor, status: Optional[Tensor] = None, *,
                win_size: int = STATUS_WIN, sigma: float = PHOTO_SIGMA, border: int = 1,
                temperature: float = BORDER_TEMPERATURE, mode: str = "soft") -> Tensor:
    """The differentiable confidence ``(B, N)`` of tracks ``pts -> tracked`` (module docstring).

    Args:
        prev, next: images or pyramids (level 0 is read).
        pts, tracked: ``(B, N, 2)`` float pixels in ``prev`` / ``next``.
        status: ``(B, N)`` bool (LK's status); None: all True.
        win_size: window side (px, odd or even).
        sigma: photometric scale (grey levels, > 0).
        border: VINS's ``inBorder`` margin (px, the tracker's ``border_size``).
        temperature: border softness (px, > 0).
        mode: ``"soft"`` (the confidence) or ``"straight_through"`` (the hard status as value, the
            confidence's gradient).

    Returns:
        ``(B, N)`` in ``tracked``'s dtype; 0 (and zero gradient) where ``status`` is False.
    """
    if mode not in MODES:
        raise ValueError(f"mode: expected one of {MODES}, got {mode!r}")
    if not (sigma > 0 and temperature > 0):
        raise ValueError(f"sigma and temperature must be > 0, got sigma={sigma}, temperature={temperature}")
    if int(win_size) < 1:
        raise ValueError(f"win_size: expected >= 1 pixels, got {win_size}")
    check_shape(pts, ("B", "N", 2), "pts")
    check_shape(tracked, tuple(pts.shape), "tracked")
    status = default_valid(pts, status, "status")
    P, Q = _level0(prev, "prev"), _level0(next, "next")
    for name, x in (("prev", P), ("next", Q)):
        if x.shape[0] != pts.shape[0]:
            raise ValueError(f"{name}: batch {x.shape[0]} does not match pts batch {pts.shape[0]}")
    if P.shape[-2:] != Q.shape[-2:]:
        raise ValueError(f"next: image size {tuple(Q.shape[-2:])} differs from prev's {tuple(P.shape[-2:])}")
    H, W = P.shape[-2:]
    # evaluated on safe values: a lost or padded lane may hold anything (NaN included)
    use = status & torch.isfinite(pts).all(-1) & torch.isfinite(tracked).all(-1)
    u = use.unsqueeze(-1)
    p = torch.where(u, pts, torch.zeros_like(pts)).to(tracked.dtype)
    t = torch.where(u, tracked, torch.zeros_like(tracked))
    lo = border - 0.5
    d = torch.minimum(torch.minimum(t[..., 0] - lo, (W - border - 0.5) - t[..., 0]),
                      torch.minimum(t[..., 1] - lo, (H - border - 0.5) - t[..., 1]))
    w_border = torch.sigmoid(d / temperature)
    e = sample_windows(Q, t, int(win_size)) - sample_windows(P, p, int(win_size))
    r = (torch.sqrt(e * e + 1.0) - 1.0).mean(-1)
    w_photo = torch.exp(-(r / sigma) ** 2)
    soft = torch.where(use, w_border * w_photo, torch.zeros_like(w_photo))
    if mode == "soft":
        return soft
    hard = status.to(soft.dtype)
    return hard + (soft - soft.detach())


__all__ = ["soft_status", "sample_windows", "MODES"]
