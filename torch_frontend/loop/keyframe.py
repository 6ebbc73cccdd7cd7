"""Keyframes of the VINS pose graph (spec §7.1–7.3, §7.11) and VINS's BRIEF matching (§7.6).

Convention:
    * Poses are body-to-world ``(R_w_i (3, 3), T_w_i (3,))`` float64, as VINS. ``origin_vio_*`` is
      the raw VIO pose at creation (never changed, same frame as ``point_3d``); ``vio_*`` is that pose
      moved into the pose-graph world of its sequence; ``T_w_i/R_w_i`` is the loop-corrected pose
      (the pose graph moves the last two).
    * Window points (tracked features with 3-D points, the query side of loop matching):
      ``point_3d (N, 3)`` float64 world points in the raw VIO frame, ``point_2d_uv (N, 2)`` float32
      pixels, ``point_2d_norm (N, 2)`` float64 normalized ``(x/z, y/z)``, ``point_id (N,)`` int64,
      ``window_brief (N, 4)`` int64 BRIEF at ``point_2d_uv``.
    * Keypoints (the database / candidate side): FAST (threshold 20, non-max suppression) on the
      **raw** keyframe image, ``keypoints (K, 2)`` float32 pixels in raster order,
      ``keypoints_norm (K, 2)`` float64 = ``lift(kp) / z`` with the camera model, ``brief (K, 4)``
      int64 BRIEF at the keypoints (``loop.features.brief``: Gaussian 9x9 sigma 2, VINS's sampling;
      bit ``i`` = bit ``i mod 64`` of word ``i div 64``).
    * ``loop_info (8,)`` float64: ``[t_x, t_y, t_z, q_w, q_x, q_y, q_z, yaw (degrees)]``.
    * ``match_brief`` is VINS's ``searchByBRIEFDes`` batched over B (current, candidate) pairs.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Dict, Optional, Tuple

import numpy as np
import torch

from .._checks import as_image_batch, check_shape, default_valid
from ..errors import DataError
from .features import brief as _brief
from .features import fast as _fast
from .features import hamming

__all__ = ["KeyFrame", "describe_keyframes", "keyframes_from_state", "keyframes_state", "match_brief"]

_F64 = torch.float64
Tensor = torch.Tensor


# ----------------------------------------------------------------------------------- describe
def _lift_norm(camera, uv: Tensor, valid: Tensor) -> Tensor:
    """``(..., 2)`` pixels -> ``(..., 2)`` float64 ``lift(uv) / z``; invalid lanes 0.

    Lifted in float64 (VINS lifts in double). Invalid lanes are zeroed with ``torch.where`` after
    the lift so that a model whose lift is undefined at padding positions cannot leak NaNs.
    """
    P = camera.lift(uv.to(_F64))
    n = P[..., :2] / P[..., 2:3]
    return torch.where(valid[..., None], n, torch.zeros_like(n))


def _describe_impl(img: Tensor, camera, pts_uv: Tensor, pts_valid: Tensor, fast_threshold: int,
                   pattern, max_keypoints: Optional[int]) -> Dict[str, Tensor]:
    kp, _, kp_valid = _fast(img, threshold=fast_threshold, nonmax=True, max_points=max_keypoints,
                            dtype=torch.float32)
    K = kp.shape[1]
    # One BRIEF call for both point sets: the 9x9 blur of each image is computed once. Window points
    # are cv::Point2f in VINS, so their sampling offsets are summed (and truncated) in float32.
    both = torch.cat([kp, pts_uv.to(torch.float32)], dim=1)
    both_valid = torch.cat([kp_valid, pts_valid], dim=1)
    desc = _brief(img, both, both_valid, pattern)
    return {
        "keypoints": kp,
        "keypoints_valid": kp_valid,
        "keypoints_norm": _lift_norm(camera, kp, kp_valid),
        "brief": desc[:, :K],
        "window_brief": desc[:, K:],
    }


def describe_keyframes(
    images: Tensor,
    camera,
    pts_uv: Tensor,
    pts_valid: Optional[Tensor] = None,
    fast_threshold: int = 20,
    pattern=None,
    max_keypoints: Optional[int] = None,
) -> Dict[str, Tensor]:
    """Describe B keyframes in one call: FAST + BRIEF at the corners, BRIEF at the window points.

    Convention:
        ``images``: ``(B, 1, H, W)`` or ``(B, H, W)`` uint8 raw keyframe images (float 0..255 is
        read as the 8-bit image it stands for). ``pts_uv``: ``(B, N, 2)`` float pixels ``(x, y)`` of
        the tracked features (summed in float32 for the BRIEF sampling, as VINS's ``cv::Point2f``),
        ``pts_valid``: ``(B, N)`` bool (default all True). FAST: threshold ``fast_threshold``,
        OpenCV's non-max suppression, raster order, padded to the largest count in the batch (or
        ``max_keypoints``, keeping the strongest). ``camera``: a ``torch_frontend.camera`` model
        (``lift``), used for ``keypoints_norm``. Speed: BRIEF's temporaries are ``(B, K + N, 256)``
        int64; on CPU one keyframe per call is ~2.4x faster than 16 per call (cache, no padding),
        on a GPU batch them all.

    Returns:
        dict of padded tensors: ``keypoints (B, K, 2)`` float32 pixels, ``keypoints_valid (B, K)``
        bool, ``keypoints_norm (B, K, 2)`` float64 ``lift(kp)/z`` (0 in padding), ``brief (B, K, 4)``
        int64, ``window_brief (B, N, 4)`` int64 (all-zero for invalid points).
    """
    img = as_image_batch(images, "images")
    check_shape(pts_uv, (img.shape[0], None, 2), "pts_uv")
    if not pts_uv.is_floating_point():
        raise TypeError(f"pts_uv: expected a floating point tensor, got {pts_uv.dtype}")
    valid = default_valid(pts_uv, pts_valid, "pts_valid")
    if max_keypoints is not None and int(max_keypoints) < 0:
        raise ValueError(f"max_keypoints: expected >= 0 or None, got {max_keypoints}")
    return _describe_impl(img, camera, pts_uv.to(img.device), valid.to(img.device), int(fast_threshold),
                          pattern, max_keypoints)


# --------------------------------------------------------------------------------------- match
def _match_impl(wd: Tensor, od: Tensor, wv: Tensor, ov: Tensor, accept: int, search: int
                ) -> Tuple[Tensor, Tensor, Tensor]:
    B, N, _ = wd.shape
    M = od.shape[1]
    dev = wd.device
    if M == 0 or N == 0:
        idx = torch.full((B, N), -1, dtype=torch.long, device=dev)
        return idx, torch.full((B, N), int(search), dtype=torch.long, device=dev), idx >= 0
    d = hamming(wd, od)  # (B, N, M) exact integers
    # candidates: valid old entries strictly below the search bound (VINS starts bestDist there)
    cand = (d < search) & ov[:, None, :]
    big = torch.iinfo(torch.long).max
    dm = torch.where(cand, d, torch.full_like(d, big))
    best = dm.amin(dim=-1)  # (B, N)
    # FIRST old index reaching the minimum (VINS updates only on a strictly smaller distance)
    ar = torch.arange(M, device=dev).expand_as(dm)
    first = torch.where(cand & (dm == best[..., None]), ar, torch.full_like(ar, M)).amin(dim=-1)
    found = cand.any(dim=-1) & wv
    matched = found & (best < accept)
    index = torch.where(matched, first, torch.full_like(first, -1))
    distance = torch.where(found, best, torch.full_like(best, int(search)))
    return index, distance, matched


def match_brief(
    window_desc: Tensor,
    old_desc: Tensor,
    window_valid: Optional[Tensor] = None,
    old_valid: Optional[Tensor] = None,
    accept: int = 80,
    search: int = 128,
) -> Tuple[Tensor, Tensor, Tensor]:
    """VINS's ``searchByBRIEFDes`` (spec §7.6 step 2), batched over B (current, old) pairs.

    Convention:
        For each window descriptor: among the valid old descriptors with Hamming distance
        ``< search``, the FIRST index with the smallest distance; accepted iff that distance is
        ``< accept``. No ratio test, no cross-check: one old descriptor may match several window
        descriptors. Invalid window or old entries never match.

    Args:
        window_desc: ``(B, N, 4)`` int64 packed BRIEF of the current keyframes' window points.
        old_desc: ``(B, M, 4)`` int64 packed BRIEF of the old keyframes' FAST corners.
        window_valid: optional ``(B, N)`` bool; old_valid: optional ``(B, M)`` bool.
        accept: acceptance bound (VINS 80). search: search bound (VINS 128).

    Returns:
        ``index (B, N)`` int64 old index of accepted matches, -1 otherwise;
        ``distance (B, N)`` int64 best distance found below ``search`` (``search`` when none, or
        for invalid window entries); ``matched (B, N)`` bool (``index >= 0``).
    """
    check_shape(window_desc, ("B", None, "W"), "window_desc")
    check_shape(old_desc, (window_desc.shape[0], None, window_desc.shape[2]), "old_desc")
    if window_desc.dtype != torch.int64 or old_desc.dtype != torch.int64:
        raise TypeError(f"window_desc, old_desc: expected int64 packed descriptors, got {window_desc.dtype} "
                        f"and {old_desc.dtype}")
    wv = default_valid(window_desc, window_valid, "window_valid").to(window_desc.device)
    ov = default_valid(old_desc, old_valid, "old_valid").to(window_desc.device)
    return _match_impl(window_desc, old_desc, wv, ov, int(accept), int(search))


# ------------------------------------------------------------------------------------ KeyFrame
def _as_f64(x, shape, name: str, where: str, device=None) -> Tensor:
    # straight onto ``device`` (None: a tensor stays where it is, an array goes to the CPU)
    t = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x, device=device)
    t = t.to(_F64)
    try:
        check_shape(t, shape, name)
    except ValueError as exc:
        raise DataError(f"keyframe at time {where}: {exc}") from None
    if not bool(torch.isfinite(t).all()):
        raise DataError(f"keyframe at time {where}: {name} has NaN or inf values")
    return t


@dataclass(eq=False)
class KeyFrame:
    """One keyframe of the pose graph (VINS ``KeyFrame``, spec §7.2).

    Convention: see the module docstring. Build with :meth:`create` (from an image, a VIO pose and
    the tracked features with 3-D points) or :meth:`loaded` (from a saved graph); the fields below
    are then consistent (aligned lengths, dtypes, one device).

    Attributes:
        time: seconds. sequence: VINS sequence (1, 2, ... live; 0 loaded).
        origin_vio_T ``(3,)``, origin_vio_R ``(3, 3)``: raw VIO body pose at creation, never changed.
        point_3d ``(N, 3)`` float64, point_2d_uv ``(N, 2)`` float32, point_2d_norm ``(N, 2)`` float64,
        point_id ``(N,)`` int64, window_brief ``(N, 4)`` int64.
        keypoints ``(K, 2)`` float32, keypoints_norm ``(K, 2)`` float64, brief ``(K, 4)`` int64.
        index: global index (-1 until the pose graph adds it).
        vio_T, vio_R, T_w_i, R_w_i: float64, initialised to the origin pose.
        has_loop, loop_index (-1), loop_info ``(8,)`` float64 ``[t (3), q wxyz (4), yaw deg]``.
        image: ``(H, W)`` uint8 or None (kept only with ``save_image``).
    """

    time: float
    sequence: int
    origin_vio_T: Tensor
    origin_vio_R: Tensor
    point_3d: Tensor
    point_2d_uv: Tensor
    point_2d_norm: Tensor
    point_id: Tensor
    window_brief: Tensor
    keypoints: Tensor
    keypoints_norm: Tensor
    brief: Tensor
    index: int = -1
    vio_T: Optional[Tensor] = None
    vio_R: Optional[Tensor] = None
    T_w_i: Optional[Tensor] = None
    R_w_i: Optional[Tensor] = None
    has_loop: bool = False
    loop_index: int = -1
    loop_info: Optional[Tensor] = None
    image: Optional[Tensor] = None

    def __post_init__(self) -> None:
        # Every pose starts as the origin pose (clones: the pose graph assigns/moves them separately).
        if self.vio_T is None:
            self.vio_T = self.origin_vio_T.clone()
        if self.vio_R is None:
            self.vio_R = self.origin_vio_R.clone()
        if self.T_w_i is None:
            self.T_w_i = self.vio_T.clone()
        if self.R_w_i is None:
            self.R_w_i = self.vio_R.clone()
        if self.loop_info is None:
            self.loop_info = torch.zeros(8, dtype=_F64, device=self.origin_vio_T.device)

    # -------------------------------------------------------------------------- properties
    @property
    def num_points(self) -> int:
        """N, the number of window points (tracked features with 3-D points)."""
        return int(self.point_3d.shape[0])

    @property
    def num_keypoints(self) -> int:
        """K, the number of FAST keypoints."""
        return int(self.keypoints.shape[0])

    @property
    def device(self) -> torch.device:
        """The device of the keyframe's tensors (that of ``origin_vio_T``)."""
        return self.origin_vio_T.device

    def to(self, device) -> KeyFrame:
        """Move every tensor field to ``device`` (in place; returns self). A no-op where they are."""
        device = torch.device(device)
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, torch.Tensor) and v.device != device:
                setattr(self, f.name, v.to(device))
        return self

    def update_vio_pose(self, T: Tensor, R: Tensor) -> None:
        """VINS ``updateVioPose``: set the vio pose and the corrected pose to ``(T, R)`` (moved to
        the keyframe's device)."""
        self.vio_T = torch.as_tensor(T, dtype=_F64, device=self.device).clone()
        self.vio_R = torch.as_tensor(R, dtype=_F64, device=self.device).clone()
        self.T_w_i, self.R_w_i = self.vio_T.clone(), self.vio_R.clone()

    def update_pose(self, T: Tensor, R: Tensor) -> None:
        """VINS ``updatePose``: set the corrected pose ``(T_w_i, R_w_i)`` (on the keyframe's device)."""
        self.T_w_i = torch.as_tensor(T, dtype=_F64, device=self.device).clone()
        self.R_w_i = torch.as_tensor(R, dtype=_F64, device=self.device).clone()

    # ------------------------------------------------------------------------ constructors
    @classmethod
    def create(
        cls,
        time: float,
        image,
        vio_T,
        vio_R,
        point_3d,
        point_2d_uv,
        point_id,
        camera,
        sequence: int = 1,
        point_2d_norm=None,
        fast_threshold: int = 20,
        pattern=None,
        save_image: bool = False,
    ) -> KeyFrame:
        """A new keyframe from the VIO (VINS's ``KeyFrame`` constructor, spec §7.1–7.3).

        Convention:
            ``image``: ``(H, W)`` uint8, the **raw** keyframe image (no CLAHE). ``vio_T (3,)``,
            ``vio_R (3, 3)``: raw VIO body-to-world pose. ``point_3d (N, 3)`` world points in the
            raw VIO frame, ``point_2d_uv (N, 2)`` pixels, ``point_id (N,)`` ids, optional
            ``point_2d_norm (N, 2)`` (default ``lift(uv) / z`` with ``camera``). Arrays may be
            tensors or numpy; they are stored as float64 (points, poses), float32 (pixels) and
            int64 (ids) on the image's device. FAST runs with ``fast_threshold`` and non-max
            suppression; BRIEF with ``pattern`` (default ``default_brief_pattern()``).

        Raises:
            DataError: naming the keyframe time and the problem: no points ("a keyframe needs
                tracked features with 3D points"), NaN/inf in a pose or the points, point arrays of
                different lengths, an image that is not a 2-D uint8 array.
        """
        where = f"{float(time):.6f}"
        img = torch.as_tensor(np.asarray(image) if not isinstance(image, torch.Tensor) else image)
        if img.dim() != 2 or img.dtype != torch.uint8:
            raise DataError(f"keyframe at time {where}: image must be a 2-D uint8 array (H, W), got "
                            f"{img.dtype} of shape {tuple(img.shape)}")
        dev = img.device
        uv = _as_f64(point_2d_uv, (None, 2), "point_2d_uv", where, dev).to(torch.float32)
        N = uv.shape[0]
        if N == 0:
            raise DataError(f"keyframe at time {where}: a keyframe needs tracked features with 3D points (got 0)")
        p3 = _as_f64(point_3d, (None, 3), "point_3d", where, dev)
        ids = torch.as_tensor(np.asarray(point_id) if not isinstance(point_id, torch.Tensor) else point_id, device=dev)
        if ids.dim() != 1:
            raise DataError(f"keyframe at time {where}: point_id: expected shape (N,), got {tuple(ids.shape)}")
        lens = {"point_3d": p3.shape[0], "point_2d_uv": N, "point_id": ids.shape[0]}
        if point_2d_norm is not None:
            norm = _as_f64(point_2d_norm, (None, 2), "point_2d_norm", where, dev)
            lens["point_2d_norm"] = norm.shape[0]
        if len(set(lens.values())) != 1:
            raise DataError(f"keyframe at time {where}: point arrays have different lengths {lens}")
        T = _as_f64(vio_T, (3,), "vio_T", where, dev)
        R = _as_f64(vio_R, (3, 3), "vio_R", where, dev)
        desc = _describe_impl(img[None, None], camera, uv[None], torch.ones(1, N, dtype=torch.bool, device=dev),
                              int(fast_threshold), pattern, None)
        if point_2d_norm is None:
            norm = _lift_norm(camera, uv, torch.ones(N, dtype=torch.bool, device=dev))
        return cls._assemble(time, sequence, T, R, p3, uv, norm, ids.to(torch.int64), desc, 0,
                             img if save_image else None)

    @classmethod
    def _assemble(cls, time, sequence, T, R, p3, uv, norm, ids, desc: Dict[str, Tensor], b: int,
                  image: Optional[Tensor]) -> KeyFrame:
        """Slice stream ``b`` of a ``describe_keyframes`` result into a keyframe (checked inputs)."""
        kv = desc["keypoints_valid"][b]
        return cls(
            time=float(time), sequence=int(sequence), origin_vio_T=T, origin_vio_R=R,
            point_3d=p3, point_2d_uv=uv.to(torch.float32), point_2d_norm=norm.to(_F64), point_id=ids,
            window_brief=desc["window_brief"][b, : p3.shape[0]].clone(),
            keypoints=desc["keypoints"][b][kv].clone(), keypoints_norm=desc["keypoints_norm"][b][kv].clone(),
            brief=desc["brief"][b][kv].clone(), image=image,
        )

    @classmethod
    def loaded(
        cls,
        index: int,
        time: float,
        T,
        R,
        keypoints,
        keypoints_norm,
        brief,
        loop_index: int = -1,
        loop_info=None,
    ) -> KeyFrame:
        """A keyframe read back from a saved graph (spec §7.11).

        Convention:
            ``sequence = 0``; the saved pose-graph pose ``(T (3,), R (3, 3))`` is the vio pose, the
            corrected pose and (unused upstream, defined here) the origin pose. No window points:
            ``point_*`` and ``window_brief`` have 0 rows. ``keypoints (K, 2)`` pixels,
            ``keypoints_norm (K, 2)``, ``brief (K, 4)`` int64; ``loop_info (8,)`` (zeros when None);
            ``has_loop = loop_index != -1``.

        Raises:
            DataError: NaN/inf in the pose or keypoints, or keypoint arrays of different lengths.
        """
        where = f"{float(time):.6f}"
        T = _as_f64(T, (3,), "T", where)
        R = _as_f64(R, (3, 3), "R", where)
        dev = T.device
        kp = _as_f64(keypoints, (None, 2), "keypoints", where, dev).to(torch.float32)
        kn = _as_f64(keypoints_norm, (None, 2), "keypoints_norm", where, dev)
        bd = torch.as_tensor(np.asarray(brief) if not isinstance(brief, torch.Tensor) else brief, device=dev)
        if bd.dim() != 2 or bd.dtype != torch.int64:
            raise DataError(f"keyframe at time {where}: brief: expected (K, W) int64, got {bd.dtype} "
                            f"of shape {tuple(bd.shape)}")
        lens = {"keypoints": kp.shape[0], "keypoints_norm": kn.shape[0], "brief": bd.shape[0]}
        if len(set(lens.values())) != 1:
            raise DataError(f"keyframe at time {where}: keypoint arrays have different lengths {lens}")
        info = (torch.zeros(8, dtype=_F64, device=dev) if loop_info is None
                else _as_f64(loop_info, (8,), "loop_info", where, dev))
        return cls(
            time=float(time), sequence=0, origin_vio_T=T, origin_vio_R=R,
            point_3d=torch.zeros(0, 3, dtype=_F64, device=dev),
            point_2d_uv=torch.zeros(0, 2, dtype=torch.float32, device=dev),
            point_2d_norm=torch.zeros(0, 2, dtype=_F64, device=dev),
            point_id=torch.zeros(0, dtype=torch.int64, device=dev),
            window_brief=torch.zeros(0, bd.shape[1], dtype=torch.int64, device=dev),
            keypoints=kp, keypoints_norm=kn, brief=bd, index=int(index),
            has_loop=int(loop_index) != -1, loop_index=int(loop_index), loop_info=info,
        )



# ------------------------------------------------------------------------------------ state
KEYFRAMES_STATE_VERSION = 1
#: fields a keyframe never changes once built, ragged: (name, its count per keyframe, dtype, trailing shape)
_RAGGED = (("point_3d", "n_points", _F64, (3,)), ("point_2d_uv", "n_points", torch.float32, (2,)),
           ("point_2d_norm", "n_points", _F64, (2,)), ("point_id", "n_points", torch.int64, ()),
           ("window_brief", "n_points", torch.int64, (4,)), ("keypoints", "n_keypoints", torch.float32, (2,)),
           ("keypoints_norm", "n_keypoints", _F64, (2,)), ("brief", "n_keypoints", torch.int64, (4,)))
#: fields the pose graph moves (and the origin pose, small), stacked: (name, shape per keyframe)
#: the keys of a ``keyframes_state`` that hold ``keyframes[since:]`` only (the append-only part)
KEYFRAME_STATIC_KEYS = ("start", "time", "sequence", *(r[0] for r in _RAGGED), "n_points", "n_keypoints", "images")
_POSES = (("origin_vio_T", (3,)), ("origin_vio_R", (3, 3)), ("vio_T", (3,)), ("vio_R", (3, 3)), ("T_w_i", (3,)),
          ("R_w_i", (3, 3)), ("loop_info", (8,)))


def keyframes_state(keyframes, since: int = 0) -> Dict[str, object]:
    """The state of a list of ``KeyFrame`` (every field, exactly) as CPU tensors, the part that
    never changes only for ``keyframes[since:]`` (an append-only chunk: a checkpoint writes a
    keyframe's points and descriptors once; :func:`keyframes_from_state` takes the chunks in
    order).

    Per keyframe of ``keyframes[since:]``: ``time (k,)`` float64, ``sequence (k,)`` int64, the
    point and keypoint arrays concatenated with ``n_points``/``n_keypoints (k,)``, ``images`` (a
    list: ``(H, W)`` uint8 or None). Per keyframe of all ``K``: ``index``/``loop_index (K,)``
    int64, ``has_loop (K,)`` bool and the poses stacked (``origin_vio_T (K, 3)``, ...,
    ``loop_info (K, 8)``)."""
    from .state import pack_ragged

    kfs = list(keyframes)
    new = kfs[since:]
    st: Dict[str, object] = {"kind": "KeyFrames", "version": KEYFRAMES_STATE_VERSION, "start": int(since),
                             "count": len(kfs), "time": torch.tensor([k.time for k in new], dtype=_F64),
                             "sequence": torch.tensor([int(k.sequence) for k in new], dtype=torch.int64)}
    for name, count, dtype, tail in _RAGGED:
        if name in ("window_brief", "brief") and new:
            tail = tuple(getattr(new[0], name).shape[1:])
        st[name], st[count] = pack_ragged([getattr(k, name) for k in new], torch.zeros(0, *tail, dtype=dtype))
    st["images"] = [None if k.image is None else k.image.detach().cpu() for k in new]
    for name in ("index", "loop_index"):
        st[name] = torch.tensor([int(getattr(k, name)) for k in kfs], dtype=torch.int64)
    st["has_loop"] = torch.tensor([bool(k.has_loop) for k in kfs], dtype=torch.bool)
    for name, shape in _POSES:
        st[name] = (torch.stack([getattr(k, name).detach().to(_F64).cpu() for k in kfs]) if kfs
                    else torch.zeros(0, *shape, dtype=_F64))
    return st


def keyframes_from_state(states, device=None):
    """The ``KeyFrame`` list of one :func:`keyframes_state` (``since=0``) or of its chunks in the
    order they were written (the last one gives the poses), on ``device`` (default CPU). Raises
    ``StateError`` for a state of another kind or version, or chunks that do not follow."""
    from .state import StateError, check_state, split_ragged

    chunks = list(states) if isinstance(states, (list, tuple)) else [states]
    if not chunks:
        return []
    dev = torch.device("cpu") if device is None else torch.device(device)
    static: Dict[str, list] = {name: [] for name in ("time", "sequence", "images", *(r[0] for r in _RAGGED))}
    for st in chunks:
        check_state(st, "KeyFrames", KEYFRAMES_STATE_VERSION, ("start", "count", "time", "index", "n_points"))
        if int(st["start"]) != len(static["time"]):
            raise StateError(f"KeyFrames state: a chunk starting at keyframe {int(st['start'])} does not follow "
                             f"the {len(static['time'])} keyframes before it (a chunk is missing)")
        static["time"] += st["time"].tolist()
        static["sequence"] += st["sequence"].tolist()
        static["images"] += list(st["images"])
        for name, count, _, _ in _RAGGED:
            static[name] += split_ragged(st[name], st[count], dev)
    last = chunks[-1]
    K = int(last["count"])
    if K != len(static["time"]):
        raise StateError(f"KeyFrames state: {K} keyframes, but the chunks hold {len(static['time'])}")
    poses = {name: last[name].to(dev) for name, _ in _POSES}
    index, loop_index, has_loop = last["index"].tolist(), last["loop_index"].tolist(), last["has_loop"].tolist()
    out = []
    for k in range(K):  # keyframes, not points
        img = static["images"][k]
        out.append(KeyFrame(time=float(static["time"][k]), sequence=int(static["sequence"][k]),
                            **{name: static[name][k] for name, _, _, _ in _RAGGED},
                            **{name: poses[name][k].clone() for name, _ in _POSES},
                            index=int(index[k]), has_loop=bool(has_loop[k]), loop_index=int(loop_index[k]),
                            image=None if img is None else img.to(dev)))
    return out
