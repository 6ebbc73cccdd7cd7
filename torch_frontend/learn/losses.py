"""Tracking losses for training through the tracker: masked, NaN-safe, against ground-truth
positions, per-point or dense flow, or a homography.

Convention:
    ``tracked (B, N, 2)`` float pixels ``(x, y)`` in the second image, pixel centres at integer
    coordinates (the tracker's and OpenCV's convention). ``valid (B, N)`` bool, or float weights in
    ``[0, 1]`` (e.g. :func:`~torch_frontend.learn.soft_status`). A point enters the loss only where
    its weight is > 0 *and* every number it needs (tracked, start, target) is finite.

NaN safety: every per-point quantity is computed on ``torch.where(use, x, 0)``, never multiplied
by a mask afterwards: ``0 * NaN`` is NaN in the value and in the gradient, and a padded slot may
hold anything. A masked point therefore contributes exactly 0 to the value and 0 to every
gradient; with no point left the mean is 0 (not 0 / 0).
"""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F

from .._checks import check_shape

Tensor = torch.Tensor

#: the per-point penalties of :func:`tracking_loss`, by name
LOSSES = ("epe", "l1", "l2", "huber", "charbonnier")
REDUCTIONS = ("mean", "sum", "none")
#: homogeneous coordinates with |w| below this map to infinity: such a point is masked out
HOMOGRAPHY_MIN_W = 1e-9


def _finite_rows(x: Tensor) -> Tensor:
    """``(B, N)`` True where every coordinate of ``x (B, N, d)`` is finite."""
    return torch.isfinite(x).all(-1)


def homography_targets(start: Tensor, homography: Tensor) -> tuple[Tensor, Tensor]:
    """Where ``homography (B, 3, 3)`` (start image -> tracked image, pixels) maps ``start (B, N, 2)``:
    ``(target (B, N, 2), ok (B, N))``; ``ok`` is False where ``|w| < HOMOGRAPHY_MIN_W`` or a value is
    not finite (the target there is 0)."""
    check_shape(start, ("B", "N", 2), "start")
    check_shape(homography, (start.shape[0], 3, 3), "homography")
    Hm = homography.to(start.dtype)
    ok = _finite_rows(start)
    s = torch.where(ok.unsqueeze(-1), start, torch.zeros_like(start))
    q = s @ Hm[:, :2, :2].transpose(1, 2) + Hm[:, None, :2, 2]  # (B, N, 2): the first two rows of H [x y 1]
    w = s @ Hm[:, 2, :2].unsqueeze(-1) + Hm[:, None, 2:, 2]  # (B, N, 1)
    ok = ok & (w[..., 0].abs() >= HOMOGRAPHY_MIN_W)
    w = torch.where(ok.unsqueeze(-1), w, torch.ones_like(w))  # a safe divisor where masked
    target = q / w
    ok = ok & _finite_rows(target)
    return torch.where(ok.unsqueeze(-1), target, torch.zeros_like(target)), ok


def sample_flow(flow: Tensor, start: Tensor) -> tuple[Tensor, Tensor]:
    """A dense flow field ``flow (B, 2, H, W)`` (pixels, ``(dx, dy)`` channels) read bilinearly at
    ``start (B, N, 2)``: ``(flow at start (B, N, 2), ok (B, N))``; ``ok`` is False outside the image
    (pixel centres ``0 .. W - 1``) or where the field is not finite."""
    check_shape(start, ("B", "N", 2), "start")
    check_shape(flow, (start.shape[0], 2, None, None), "flow")
    H, W = flow.shape[-2:]
    ok = _finite_rows(start)
    s = torch.where(ok.unsqueeze(-1), start, torch.zeros_like(start))
    x, y = s[..., 0], s[..., 1]
    ok = ok & (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    # align_corners=True: -1 and +1 are the centres of the first and last pixels
    grid = torch.stack((2 * x / max(W - 1, 1) - 1, 2 * y / max(H - 1, 1) - 1), -1).unsqueeze(1)  # (B, 1, N, 2)
    f = F.grid_sample(flow.to(start.dtype), grid, mode="bilinear", padding_mode="border",
                      align_corners=True)[:, :, 0].transpose(1, 2)  # (B, N, 2)
    ok = ok & _finite_rows(f)
    return torch.where(ok.unsqueeze(-1), f, torch.zeros_like(f)), ok


def _penalty(d: Tensor, loss: str, delta: float) -> Tensor:
    """``(B, N)`` penalty of the residuals ``d (B, N, 2)`` (pixels; finite, 0 where masked)."""
    if loss == "l1":
        return d.abs().sum(-1)
    sq = (d * d).sum(-1)
    if loss == "l2":
        return sq
    if loss == "charbonnier":
        return torch.sqrt(sq + delta * delta) - delta
    # the Euclidean norm with a zero gradient (not NaN) at d = 0: sqrt is evaluated on a safe value
    pos = sq > 0
    e = torch.where(pos, torch.sqrt(torch.where(pos, sq, torch.ones_like(sq))), torch.zeros_like(sq))
    if loss == "epe":
        return e
    # huber on the end-point error: quadratic below delta, linear above (continuous slope)
    return torch.where(e <= delta, 0.5 * sq, delta * (e - 0.5 * delta))


def tracking_loss(tracked: Tensor, valid: Tensor, target: Optional[Tensor] = None, *, start: Optional[Tensor] = None,
                  flow: Optional[Tensor] = None, homography: Optional[Tensor] = None, loss: str = "epe",
                  delta: float = 1.0, reduction: str = "mean") -> Tensor:
    """The error of tracked points against the ground truth, masked and NaN-safe.

    The ground truth is exactly one of: ``target (B, N, 2)`` pixels; ``start`` + ``flow`` (per
    point ``(B, N, 2)`` or a dense field ``(B, 2, H, W)`` read bilinearly at ``start``); ``start`` +
    ``homography (B, 3, 3)`` (start image -> tracked image). ``start (B, N, 2)`` are the points in
    the first image (what the tracker tracked from).

    Args:
        tracked: ``(B, N, 2)`` float pixels, the tracker's output (e.g. ``frame.uv``).
        valid: ``(B, N)`` bool, or float weights (a soft status); weight 0 masks a point.
        loss: per point, of the residual ``d = tracked - target`` (pixels): ``"epe"`` ``|d|``
            (end-point error, the default; gradient 0 at ``d = 0``), ``"l1"`` ``|dx| + |dy|``,
            ``"l2"`` ``|d|^2``, ``"huber"`` (on ``|d|``, threshold ``delta`` px) or
            ``"charbonnier"`` ``sqrt(|d|^2 + delta^2) - delta``.
        reduction: ``"mean"`` (weighted mean over the used points; 0 when there is none),
            ``"sum"``, or ``"none"`` (``(B, N)``, 0 at masked points).

    Returns:
        A scalar (``(B, N)`` for ``reduction="none"``) in ``tracked``'s dtype.
    """
    check_shape(tracked, ("B", "N", 2), "tracked")
    B, N = tracked.shape[:2]
    check_shape(valid, (B, N), "valid")
    if loss not in LOSSES:
        raise ValueError(f"loss: expected one of {LOSSES}, got {loss!r}")
    if reduction not in REDUCTIONS:
        raise ValueError(f"reduction: expected one of {REDUCTIONS}, got {reduction!r}")
    if not delta > 0 and loss in ("huber", "charbonnier"):
        raise ValueError(f"delta: expected > 0 pixels for loss={loss!r}, got {delta}")
    given = [n for n, v in (("target", target), ("flow", flow), ("homography", homography)) if v is not None]
    if len(given) != 1:
        raise ValueError(f"tracking_loss: give exactly one of target, flow (with start), homography (with start); "
                         f"got {given or 'none'}")
    if target is None and start is None:
        raise ValueError(f"{given[0]}: needs start (B, N, 2), the points in the first image")
    if start is not None:
        check_shape(start, (B, N, 2), "start")
    if target is not None:
        check_shape(target, (B, N, 2), "target")
        ok = _finite_rows(target)
        gt = target.to(tracked.dtype)
    elif homography is not None:
        gt, ok = homography_targets(start.to(tracked.dtype), homography)
    else:
        if flow.dim() == 3:
            check_shape(flow, (B, N, 2), "flow")
            f, ok = flow.to(tracked.dtype), _finite_rows(flow) & _finite_rows(start)
        else:
            f, ok = sample_flow(flow, start.to(tracked.dtype))
        gt = start.to(tracked.dtype) + torch.where(ok.unsqueeze(-1), f, torch.zeros_like(f))
    w = valid.to(tracked.dtype)
    use = ok & (w > 0) & _finite_rows(tracked) & torch.isfinite(w)
    d = torch.where(use.unsqueeze(-1), tracked - torch.where(use.unsqueeze(-1), gt, torch.zeros_like(gt)),
                    torch.zeros_like(tracked))
    per = torch.where(use, _penalty(d, loss, float(delta)) * torch.where(use, w, torch.zeros_like(w)),
                      torch.zeros_like(w))
    if reduction == "none":
        return per
    if reduction == "sum":
        return per.sum()
    den = torch.where(use, w, torch.zeros_like(w)).sum()
    return per.sum() / den.clamp_min(torch.finfo(per.dtype).tiny)  # no point left: 0 / tiny = 0


__all__ = ["tracking_loss", "homography_targets", "sample_flow", "LOSSES"]
