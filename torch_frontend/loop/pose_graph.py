"""VINS's pose graph: loop verification (``findConnection``), sequences, 4-/6-DoF optimisation,
odometry correction and persistence, with a synchronous optimiser.

Convention:
    * Poses are body-to-world ``(R_w_i (3, 3), T_w_i (3,))`` float64 (VINS). Each keyframe keeps
      its raw VIO pose (``origin_vio_*``, never changed), its VIO pose moved into the pose-graph
      world of its sequence (``vio_*``) and its loop-corrected pose (``T_w_i``, ``R_w_i``), spec §7.2.
    * ``mode="4dof"`` is VINS-Mono's ``pose_graph`` / Fusion's ``loop_fusion`` with an IMU
      (x, y, z, yaw; pitch and roll are observable and fixed); ``mode="6dof"`` is ``loop_fusion``
      without an IMU (§7.12): full-rotation drift, merge and ``RelativeRTError`` edges.
    * Keyframe ``index`` = global insertion order = the place-database entry id (§7.4).
    * The camera extrinsic ``(R_ic, t_ic)`` is camera-to-body (VINS's ``qic``, ``tic``).

Differences from VINS, on purpose:
    * ``optimize()`` runs synchronously right after each accepted loop (``auto_optimize=True``)
      instead of in a thread that polls every 2 s. VINS's thread would optimise once for several
      loops found within 2 s, starting from the same vio poses and using every queued loop; the
      synchronous port gives the same optimum for the same set of loop edges, only sooner, and
      new keyframes never need the "keyframes after ``cur_index``" drift update (§7.8.9), which is
      still applied for callers that add keyframes with ``auto_optimize=False``.
    * Drift, the merge shift and ``sequence_loop`` are kept per sequence, so keyframes of several
      sequences may arrive interleaved (several robots sharing one map). For sequences that
      arrive one after another (VINS) this is the same as VINS's single set of variables, which
      VINS resets when a new sequence starts (§7.7.1). ``yaw_drift`` is reported for the latest
      optimisation like VINS's.
    * Fast relocalisation (§7.10, Mono only, needs the estimator in the loop) is not modelled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from ..errors import DataError
from ..geometry import (
    R_to_quat,
    R_to_ypr,
    normalize_angle,
    quat_to_R,
    yaw_to_R,
    ypr_to_R,
)
from .database import PlaceDatabase
from .keyframe import KeyFrame, match_brief
from .vocabulary import Vocabulary

__all__ = ["LoopResult", "PoseGraph", "loop_results_from_state", "loop_results_state", "verify_loops"]

PathLike = Union[str, Path]
_F64 = torch.float64

# VINS's loop-acceptance constants (§7.6, also listed in §2)
MIN_LOOP_MATCHES = 25  # "count > 25" before and after PnP
MAX_LOOP_YAW = 30.0  # degrees
MAX_LOOP_T = 20.0  # metres
PNP_THRESHOLD = 10.0 / 460.0  # normalized reprojection error


@dataclass
class LoopResult:
    """One loop candidate and what verification made of it.

    ``reason``: ``"accepted"``, ``"few_matches"`` (≤ 25 BRIEF matches), ``"pnp_failed"``,
    ``"few_inliers"`` (≤ 25 PnP inliers), ``"yaw"`` (|relative yaw| ≥ 30°), ``"translation"``
    (‖relative t‖ ≥ 20). ``relative_t``/``relative_q``/``relative_yaw``: the current body pose in
    the old body frame (VINS's ``loop_info``), filled whenever PnP ran.
    """

    index: int
    old_index: int
    score: float
    accepted: bool
    reason: str
    num_matches: int
    num_inliers: int
    relative_t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    relative_q: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    relative_yaw: float = 0.0
    # matches for visualisation: current pixels (M, 2), old pixels (M, 2) of the PnP inliers
    cur_uv: Optional[np.ndarray] = None
    old_uv: Optional[np.ndarray] = None

    @property
    def loop_info(self) -> np.ndarray:
        return np.concatenate([self.relative_t, self.relative_q, [self.relative_yaw]])


LOOP_RESULTS_STATE_VERSION = 1


def loop_results_state(results: Sequence[LoopResult]) -> Dict[str, object]:
    """A list of :class:`LoopResult` as CPU tensors and lists (``loop.state``): per result the
    indices, counts, flags, score, reason and relative pose, and the inlier pixels concatenated
    with their counts (-1: none)."""
    from .state import pack_ragged

    rs = list(results)
    uv_n = torch.tensor([-1 if r.cur_uv is None else int(r.cur_uv.shape[0]) for r in rs], dtype=torch.int64)
    old_n = torch.tensor([-1 if r.old_uv is None else int(r.old_uv.shape[0]) for r in rs], dtype=torch.int64)
    empty = torch.zeros(0, 2, dtype=_F64)
    cur_uv, _ = pack_ragged([torch.from_numpy(np.asarray(r.cur_uv, dtype=np.float64)) for r in rs
                             if r.cur_uv is not None], empty)
    old_uv, _ = pack_ragged([torch.from_numpy(np.asarray(r.old_uv, dtype=np.float64)) for r in rs
                             if r.old_uv is not None], empty)
    ints = torch.tensor([[r.index, r.old_index, r.num_matches, r.num_inliers, int(r.accepted)] for r in rs],
                        dtype=torch.int64).reshape(-1, 5)
    return {"kind": "LoopResults", "version": LOOP_RESULTS_STATE_VERSION, "ints": ints,
            "score": torch.tensor([float(r.score) for r in rs], dtype=_F64), "reason": [r.reason for r in rs],
            "relative_t": torch.tensor(np.array([r.relative_t for r in rs], dtype=np.float64).reshape(-1, 3)),
            "relative_q": torch.tensor(np.array([r.relative_q for r in rs], dtype=np.float64).reshape(-1, 4)),
            "relative_yaw": torch.tensor([float(r.relative_yaw) for r in rs], dtype=_F64),
            "cur_uv": cur_uv, "cur_uv_n": uv_n, "old_uv": old_uv, "old_uv_n": old_n}


def loop_results_from_state(state: Dict[str, object]) -> List[LoopResult]:
    """The :class:`LoopResult` list of :func:`loop_results_state`."""
    from .state import check_state, split_ragged

    st = check_state(state, "LoopResults", LOOP_RESULTS_STATE_VERSION, ("ints", "score", "reason"))

    def ragged(name):
        n = st[f"{name}_n"]
        parts = iter(split_ragged(st[name], n[n >= 0]))
        return [None if int(k) < 0 else next(parts).numpy() for k in n.tolist()]

    cur, old = ragged("cur_uv"), ragged("old_uv")
    ints, score, yaw = st["ints"].tolist(), st["score"].tolist(), st["relative_yaw"].tolist()
    rt, rq = st["relative_t"].numpy(), st["relative_q"].numpy()
    return [LoopResult(int(i[0]), int(i[1]), float(score[k]), bool(i[4]), str(st["reason"][k]), int(i[2]), int(i[3]),
                       rt[k].copy(), rq[k].copy(), float(yaw[k]), cur[k], old[k]) for k, i in enumerate(ints)]


def _pad(rows: Sequence[torch.Tensor], width: int, fill=0):
    """Stack ragged ``(n_b, ...)`` tensors (one device) into ``(B, width, ...)`` plus a
    ``(B, width)`` mask, on their device."""
    dev = rows[0].device
    n = torch.tensor([r.shape[0] for r in rows], device=dev)
    out = torch.nn.utils.rnn.pad_sequence(list(rows), batch_first=True, padding_value=fill)
    if out.shape[1] < width:
        out = torch.cat([out, out.new_full((out.shape[0], width - out.shape[1], *out.shape[2:]), fill)], 1)
    valid = torch.arange(width, device=dev)[None, :] < n[:, None]
    return out, valid


def verify_loops(
    curs: Sequence[KeyFrame],
    olds: Sequence[KeyFrame],
    R_ic: torch.Tensor,
    t_ic: torch.Tensor,
    pnp_backend: str = "torch",
    generator: Optional[torch.Generator] = None,
    scores: Optional[Sequence[float]] = None,
) -> List[LoopResult]:
    """VINS ``findConnection`` (§7.6) for B (current, old) keyframe pairs at once.

    BRIEF matching of the current keyframe's window descriptors against the old keyframe's FAST
    descriptors (``match_brief``, batched over pairs), > 25 matches, PnP-RANSAC of the current
    keyframe's 3-D points (raw VIO world) against the old keyframe's normalized corners (one
    batched ``pnp_ransac`` call, initial guess = the current camera pose), > 25 inliers, then
    |relative yaw| < 30° and ‖relative t‖ < 20.

    Args:
        curs, olds: B keyframes each, all on one device (where the verification runs);
            ``curs`` need points and window descriptors.
        R_ic, t_ic: camera-to-body extrinsic, ``(3, 3)`` and ``(3,)`` (moved to that device).
        pnp_backend: ``"torch"`` (batched) or ``"opencv"`` (``cv2.solvePnPRansac`` as VINS).
        generator: RANSAC randomness (deterministic results).
        scores: place-recognition scores to carry into the results.
    Returns:
        B :class:`LoopResult` (``index``/``old_index`` from the keyframes).
    """
    from .pnp import pnp_ransac

    B = len(curs)
    if B != len(olds):
        raise ValueError(f"verify_loops: {B} current keyframes but {len(olds)} old ones")
    if B == 0:
        return []
    for c in curs:
        if c.point_3d.shape[0] == 0:
            raise DataError(f"verify_loops: keyframe {c.index} (time {c.time:.6f}) has no points to verify a loop with")
    scores = [0.0] * B if scores is None else list(scores)
    dev = curs[0].point_3d.device  # every keyframe and the extrinsic on the current keyframes' device
    R_ic = torch.as_tensor(R_ic, dtype=_F64, device=dev)
    t_ic = torch.as_tensor(t_ic, dtype=_F64, device=dev)
    n_cur = max(c.window_brief.shape[0] for c in curs)
    n_old = max(max(o.brief.shape[0] for o in olds), 1)
    wdesc, wvalid = _pad([c.window_brief for c in curs], n_cur)
    odesc, ovalid = _pad([o.brief if o.brief.shape[0] else torch.zeros(0, 4, dtype=torch.int64, device=dev)
                          for o in olds], n_old)
    midx, _, matched = match_brief(wdesc, odesc, wvalid, ovalid)
    n_match = matched.sum(1)
    n_match_h = n_match.cpu()  # the per-pair counts on the host once (not one copy per pair)

    p3, _ = _pad([c.point_3d.to(_F64) for c in curs], n_cur)
    onorm, _ = _pad([o.keypoints_norm.to(_F64) if o.keypoints_norm.shape[0]
                     else torch.zeros(0, 2, dtype=_F64, device=dev) for o in olds], n_old)
    pn = onorm.gather(1, midx.clamp_min(0)[..., None].expand(B, n_cur, 2))

    # initial guess = the current camera pose in its raw VIO world (§7.6)
    oR = torch.stack([c.origin_vio_R.to(_F64) for c in curs])
    oT = torch.stack([c.origin_vio_T.to(_F64) for c in curs])
    R_wc = oR @ R_ic
    T_wc = oT + oR @ t_ic
    init_R = R_wc.transpose(1, 2)
    init_t = -(init_R @ T_wc[..., None])[..., 0]

    run = n_match > MIN_LOOP_MATCHES
    results: List[Optional[LoopResult]] = [None] * B
    if bool(run.any()):
        sel = torch.nonzero(run).flatten()
        res = pnp_ransac(p3[sel], pn[sel], matched[sel], init_R[sel], init_t[sel],
                         threshold=PNP_THRESHOLD, iterations=100, confidence=0.99,
                         generator=generator, backend=pnp_backend)
        R_pnp, t_pnp = res.R.to(_F64), res.t.to(_F64)
        R_w_c_old = R_pnp.transpose(1, 2)
        T_w_c_old = -(R_w_c_old @ t_pnp[..., None])[..., 0]
        PnP_R_old = R_w_c_old @ R_ic.T
        PnP_T_old = T_w_c_old - PnP_R_old @ t_ic
        rel_t = (PnP_R_old.transpose(1, 2) @ (oT[sel] - PnP_T_old)[..., None])[..., 0]
        rel_R = PnP_R_old.transpose(1, 2) @ oR[sel]
        rel_q = R_to_quat(rel_R)
        rel_yaw = normalize_angle(R_to_ypr(oR[sel])[:, 0] - R_to_ypr(PnP_R_old)[:, 0])
        inl = res.inliers & matched[sel]
        n_inl = inl.sum(1)
        # the small per-pair results on the host once (one copy each, not one per pair and field)
        ok_h, n_inl_h, inl_h, midx_h = res.ok.cpu(), n_inl.cpu(), inl.cpu(), midx.cpu()
        rel_t_h, rel_q_h, rel_yaw_h = rel_t.cpu(), rel_q.cpu(), rel_yaw.cpu()
        for k, b in enumerate(sel.tolist()):  # B results, not points
            ok = bool(ok_h[k])
            ni = int(n_inl_h[k]) if ok else 0
            yaw_k, t_k = float(rel_yaw_h[k]), rel_t_h[k].numpy()
            if not ok:
                reason = "pnp_failed"
            elif ni <= MIN_LOOP_MATCHES:
                reason = "few_inliers"
            elif not abs(yaw_k) < MAX_LOOP_YAW:
                reason = "yaw"
            elif not float(np.linalg.norm(t_k)) < MAX_LOOP_T:
                reason = "translation"
            else:
                reason = "accepted"
            q_k = rel_q_h[k].numpy().copy()
            if not ok:  # no pose: report the identity, not the initial guess echoed back
                t_k, q_k, yaw_k = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]), 0.0
            m = inl_h[k]
            cur_uv = curs[b].point_2d_uv.cpu()[m[: curs[b].point_2d_uv.shape[0]]].double().numpy()
            old_uv = (olds[b].keypoints.cpu().double()[midx_h[b][m].clamp_min(0)].numpy()
                      if olds[b].keypoints.shape[0] else None)
            results[b] = LoopResult(curs[b].index, olds[b].index, float(scores[b]), reason == "accepted", reason,
                                    int(n_match_h[b]), ni, t_k.copy(), q_k, yaw_k, cur_uv, old_uv)
    for b in range(B):
        if results[b] is None:
            results[b] = LoopResult(curs[b].index, olds[b].index, float(scores[b]), False, "few_matches",
                                    int(n_match_h[b]), 0)
    return results  # type: ignore[return-value]


@dataclass
class _SeqState:
    """Per-sequence transforms (VINS keeps one set and resets it at a new sequence, §7.7.1)."""

    w_r_vio: torch.Tensor
    w_t_vio: torch.Tensor
    r_drift: torch.Tensor
    t_drift: torch.Tensor
    merged: bool = False  # VINS's sequence_loop[s]


def _identity_state(device) -> _SeqState:
    return _SeqState(torch.eye(3, dtype=_F64, device=device), torch.zeros(3, dtype=_F64, device=device),
                     torch.eye(3, dtype=_F64, device=device), torch.zeros(3, dtype=_F64, device=device))


class PoseGraph:
    """VINS-Mono ``pose_graph`` (``mode="4dof"``) / VINS-Fusion ``loop_fusion`` (``"6dof"``).

    Args:
        camera: the camera model (used to describe keyframes; kept for users).
        vocabulary: place-recognition vocabulary (``Vocabulary``); ``None`` disables loop
            detection (keyframes are still added, e.g. to be saved).
        mode: ``"4dof"`` (with IMU) or ``"6dof"`` (without).
        R_ic, t_ic: camera-to-body extrinsic (default identity / zero).
        pnp_backend: ``"torch"`` or ``"opencv"``.
        generator: RANSAC generator (default: seeded 0, deterministic).
        auto_optimize: optimise right after each accepted loop (see the module docstring).
        optimize_iters: VINS's Ceres ``max_num_iterations`` is 5.
        min_loop_gap: VINS queries only keyframes more than 50 indices older.
        device: where the graph's poses, drift and extrinsic live and its keyframes are verified
            and optimised (None: the device of ``R_ic`` when it is a tensor, else the CPU).
            ``add_keyframe`` and ``load`` move keyframes on another device onto it. The place
            database lives with the vocabulary.
    """

    def __init__(self, camera=None, vocabulary: Optional[Vocabulary] = None, mode: str = "4dof",
                 R_ic=None, t_ic=None, pnp_backend: str = "torch",
                 generator: Optional[torch.Generator] = None, auto_optimize: bool = True,
                 optimize_iters: int = 5, min_loop_gap: int = 50, save_images: bool = False, device=None):
        if mode not in ("4dof", "6dof"):
            raise ValueError(f"mode: expected '4dof' or '6dof', got {mode!r}")
        if pnp_backend not in ("torch", "opencv"):
            raise ValueError(f"pnp_backend: expected 'torch' or 'opencv', got {pnp_backend!r}")
        self.camera = camera
        self.vocabulary = vocabulary
        self.mode = mode
        if device is None:
            device = R_ic.device if isinstance(R_ic, torch.Tensor) else "cpu"
        self.device = dev = torch.device(device)
        self.R_ic = (torch.eye(3, dtype=_F64, device=dev) if R_ic is None
                     else torch.as_tensor(R_ic, dtype=_F64, device=dev).reshape(3, 3))
        self.t_ic = (torch.zeros(3, dtype=_F64, device=dev) if t_ic is None
                     else torch.as_tensor(t_ic, dtype=_F64, device=dev).reshape(3))
        self.pnp_backend = pnp_backend
        self.generator = torch.Generator().manual_seed(0) if generator is None else generator
        self.auto_optimize = auto_optimize
        self.optimize_iters = optimize_iters
        self.min_loop_gap = min_loop_gap
        self.save_images = save_images
        self.db = PlaceDatabase(vocabulary) if vocabulary is not None else None
        self.keyframes: List[KeyFrame] = []
        self.loops: List[LoopResult] = []  # every verified candidate, accepted or not
        self.scores: List[float] = []  # best place-recognition score per keyframe (0 when none)
        self.global_index = 0
        self.earliest_loop_index = -1
        self.yaw_drift = 0.0
        self.base_sequence = 1
        self._seq: Dict[int, _SeqState] = {}
        self._pending: List[int] = []  # accepted loops not yet optimised
        self.num_optimizations = 0
        self.optimize_seconds = 0.0

    # ------------------------------------------------------------------------------ state access
    def _state(self, sequence: int) -> _SeqState:
        if sequence not in self._seq:
            self._seq[sequence] = _identity_state(self.device)
        return self._seq[sequence]

    @property
    def r_drift(self) -> torch.Tensor:
        return self._latest_state().r_drift

    @property
    def t_drift(self) -> torch.Tensor:
        return self._latest_state().t_drift

    @property
    def w_r_vio(self) -> torch.Tensor:
        return self._latest_state().w_r_vio

    @property
    def w_t_vio(self) -> torch.Tensor:
        return self._latest_state().w_t_vio

    def _latest_state(self) -> _SeqState:
        seq = self.keyframes[-1].sequence if self.keyframes else 1
        return self._state(seq)

    def __len__(self) -> int:
        return len(self.keyframes)

    # ------------------------------------------------------------------------------ adding
    def _check_keyframe(self, kf: KeyFrame) -> None:
        if not isinstance(kf, KeyFrame):
            raise TypeError(f"add_keyframe: expected a KeyFrame, got {type(kf).__name__}")
        for name in ("origin_vio_T", "origin_vio_R"):
            v = getattr(kf, name)
            if not bool(torch.isfinite(v).all()):
                raise DataError(f"keyframe at time {kf.time:.6f}: {name} is not finite")
        if kf.sequence < 0:
            raise DataError(f"keyframe at time {kf.time:.6f}: sequence must be >= 0, got {kf.sequence}")
        if self.keyframes and kf.sequence == self.keyframes[-1].sequence and kf.time < self.keyframes[-1].time:
            raise DataError(f"keyframe at time {kf.time:.6f}: earlier than the previous keyframe of sequence "
                            f"{kf.sequence} ({self.keyframes[-1].time:.6f})")

    def _bow(self, kf: KeyFrame):
        K, dev = kf.brief.shape[0], kf.brief.device
        desc = kf.brief.reshape(1, K, 4) if K else torch.zeros(1, 1, 4, dtype=torch.int64, device=dev)
        valid = torch.full((1, max(K, 1)), K > 0, dtype=torch.bool, device=dev)
        return self.vocabulary.transform(desc, valid)

    def _detect(self, kf: KeyFrame) -> Tuple[int, float, float]:
        """VINS ``detectLoop`` (§7.5): ``(candidate or -1, its score, best score)``."""
        cand, score, best = self.db.detect_loop_many(self._bow(kf), [kf.index], [0], min_gap=self.min_loop_gap,
                                                     return_scores=True)
        return int(cand[0]), float(score[0]), float(best[0])

    def add_keyframe(self, kf: KeyFrame, detect_loop: bool = True) -> Optional[LoopResult]:
        """VINS ``addKeyFrame`` (§7.7): place it in its sequence's world, detect and verify a loop,
        merge sequences on their first loop, optimise (synchronously) and apply the drift.

        Returns:
            the :class:`LoopResult` of the verified candidate (accepted or not), or ``None`` when
            place recognition proposed none.
        """
        self._check_keyframe(kf)
        kf.to(self.device)  # the graph's keyframes share its device (a no-op when they do)
        st = self._state(kf.sequence)
        kf.vio_T = st.w_r_vio @ kf.origin_vio_T.to(_F64) + st.w_t_vio
        kf.vio_R = st.w_r_vio @ kf.origin_vio_R.to(_F64)
        kf.T_w_i, kf.R_w_i = kf.vio_T.clone(), kf.vio_R.clone()
        kf.index = self.global_index
        self.global_index += 1

        result = None
        loop_index, score, best = -1, 0.0, 0.0
        if self.db is not None:
            if detect_loop:
                loop_index, score, best = self._detect(kf)
            else:
                self.db.add(self._bow(kf))
        self.scores.append(best)
        if loop_index != -1:
            old = self.keyframes[loop_index]
            result = verify_loops([kf], [old], self.R_ic, self.t_ic, self.pnp_backend, self.generator, [score])[0]
            self.loops.append(result)
            if result.accepted:
                self._accept_loop(kf, old, result)
        # drift from the last optimisation (§7.7.5)
        st = self._state(kf.sequence)
        kf.T_w_i = st.r_drift @ kf.vio_T + st.t_drift
        kf.R_w_i = st.r_drift @ kf.vio_R
        if not self.save_images:
            kf.image = None
        self.keyframes.append(kf)
        if self._pending and self.auto_optimize:
            self.optimize()
        return result

    def _accept_loop(self, cur: KeyFrame, old: KeyFrame, res: LoopResult) -> None:
        cur.has_loop = True
        cur.loop_index = old.index
        cur.loop_info = torch.as_tensor(res.loop_info, dtype=_F64, device=self.device)
        self.earliest_loop_index = old.index if self.earliest_loop_index < 0 else min(self.earliest_loop_index, old.index)
        st = self._state(cur.sequence)
        if old.sequence != cur.sequence and not st.merged:
            # first loop of this sequence to another one: move the whole sequence (§7.7.4b-c)
            rel_t = torch.as_tensor(res.relative_t, dtype=_F64, device=self.device)
            rel_R = quat_to_R(torch.as_tensor(res.relative_q, dtype=_F64, device=self.device))
            w_P_cur = old.vio_R @ rel_t + old.vio_T
            w_R_cur = old.vio_R @ rel_R
            if self.mode == "4dof":
                shift_yaw = R_to_ypr(w_R_cur)[0] - R_to_ypr(cur.vio_R)[0]
                shift_r = yaw_to_R(shift_yaw)
            else:
                shift_r = w_R_cur @ cur.vio_R.T
            # VINS's quirk: the translation uses the full relative rotation, the rotation only yaw
            shift_t = w_P_cur - w_R_cur @ cur.vio_R.T @ cur.vio_T
            st.w_r_vio, st.w_t_vio = shift_r, shift_t
            for k in [*self.keyframes, cur]:
                if k.sequence == cur.sequence:
                    k.vio_T = shift_r @ k.vio_T + shift_t
                    k.vio_R = shift_r @ k.vio_R
                    k.T_w_i, k.R_w_i = k.vio_T.clone(), k.vio_R.clone()
            st.merged = True
        self._pending.append(cur.index)

    # ------------------------------------------------------------------------------ optimisation
    def optimize(self) -> bool:
        """One VINS ``optimize4DoF`` / ``optimize6DoF`` pass (§7.8) for the queued loops.

        Window: keyframes from the earliest loop target to the newest queued loop keyframe,
        initialised from their vio poses; the earliest loop target and loaded keyframes
        (sequence 0) are fixed. Writes the optimised poses back and updates the drift.
        Returns False when nothing was queued.
        """
        import time

        from . import optimize as opt

        if not self._pending:
            return False
        cur_index = self._pending[-1]
        self._pending.clear()
        first = self.earliest_loop_index
        t0 = time.perf_counter()
        win = [k for k in self.keyframes if first <= k.index <= cur_index]
        if not win:
            return False
        slot = {k.index: s for s, k in enumerate(win)}
        T = torch.stack([k.vio_T for k in win])
        R = torch.stack([k.vio_R for k in win])
        dev = self.device
        seq = torch.tensor([k.sequence for k in win], dtype=torch.int64, device=dev)
        fixed = torch.tensor([k.index == first or k.sequence == 0 for k in win], device=dev)
        si, sj = opt.sequential_edges(seq, 4)
        loops = [(slot[k.loop_index], s) for s, k in enumerate(win) if k.has_loop and k.loop_index in slot]
        li = torch.tensor([a for a, _ in loops], dtype=torch.int64, device=dev)
        lj = torch.tensor([b for _, b in loops], dtype=torch.int64, device=dev)
        info = (torch.stack([win[b].loop_info for _, b in loops]) if loops
                else torch.zeros(0, 8, dtype=_F64, device=dev))
        i = torch.cat([si, li])
        j = torch.cat([sj, lj])
        is_loop = torch.cat([torch.zeros(si.shape[0], dtype=torch.bool, device=dev),
                             torch.ones(li.shape[0], dtype=torch.bool, device=dev)])
        if self.mode == "4dof":
            ypr = R_to_ypr(R)
            t_meas_s, yaw_meas_s = opt.measurements_4dof(T, R, si, sj)
            t_meas = torch.cat([t_meas_s, info[:, :3]])
            yaw_meas = torch.cat([yaw_meas_s, info[:, 7]])
            t_opt, yaw_opt = opt.optimize_4dof(T, ypr[:, 0], ypr[:, 1], ypr[:, 2], i, j, t_meas, yaw_meas,
                                               is_loop, fixed, iters=self.optimize_iters)
            R_opt = ypr_to_R(torch.stack([yaw_opt, ypr[:, 1], ypr[:, 2]], -1))
        else:
            q = R_to_quat(R)
            t_meas_s, q_meas_s = opt.measurements_6dof(T, q, si, sj)
            t_meas = torch.cat([t_meas_s, info[:, :3]])
            q_meas = torch.cat([q_meas_s, info[:, 3:7]])
            t_opt, q_opt = opt.optimize_6dof(T, q, i, j, t_meas, q_meas, is_loop, fixed, iters=self.optimize_iters)
            R_opt = quat_to_R(q_opt)
        for s, k in enumerate(win):
            k.T_w_i = t_opt[s].detach().clone()
            k.R_w_i = R_opt[s].detach().clone()
        # drift from the newest optimised keyframe of each sequence in the window (§7.8.9)
        latest: Dict[int, KeyFrame] = {}
        for k in win:
            latest[k.sequence] = k
        for s_id, k in latest.items():
            if s_id == 0:
                continue
            st = self._state(s_id)
            if self.mode == "4dof":
                self.yaw_drift = float(R_to_ypr(k.R_w_i)[0] - R_to_ypr(k.vio_R)[0])
                st.r_drift = yaw_to_R(torch.tensor(self.yaw_drift, dtype=_F64, device=dev))
            else:
                st.r_drift = k.R_w_i @ k.vio_R.T
            st.t_drift = k.T_w_i - st.r_drift @ k.vio_T
        for k in self.keyframes:
            if k.index > cur_index and k.sequence != 0:
                st = self._state(k.sequence)
                k.T_w_i = st.r_drift @ k.vio_T + st.t_drift
                k.R_w_i = st.r_drift @ k.vio_R
        self.num_optimizations += 1
        self.optimize_seconds += time.perf_counter() - t0
        return True

    # ------------------------------------------------------------------------------ outputs
    def correct(self, T: torch.Tensor, R: torch.Tensor, sequence: Optional[int] = None):
        """Odometry correction (§7.9): a raw VIO body pose of ``sequence`` (default: the newest
        keyframe's) -> its loop-corrected pose. ``T (..., 3)``, ``R (..., 3, 3)`` float."""
        seq = (self.keyframes[-1].sequence if self.keyframes else 1) if sequence is None else sequence
        st = self._state(seq)
        T = torch.as_tensor(T, dtype=_F64, device=self.device)
        R = torch.as_tensor(R, dtype=_F64, device=self.device)
        rd = st.r_drift @ st.w_r_vio
        return (rd @ T[..., None])[..., 0] + st.r_drift @ st.w_t_vio + st.t_drift, rd @ R

    def poses(self, which: str = "corrected"):
        """``(time (N,) float64, T (N, 3), R (N, 3, 3))`` of every keyframe: ``"corrected"``
        (loop-corrected), ``"vio"`` (in the pose-graph world) or ``"origin"`` (raw VIO)."""
        dev = self.device
        if not self.keyframes:
            z = torch.zeros(0, dtype=_F64, device=dev)
            return z, torch.zeros(0, 3, dtype=_F64, device=dev), torch.zeros(0, 3, 3, dtype=_F64, device=dev)
        attr = {"corrected": ("T_w_i", "R_w_i"), "vio": ("vio_T", "vio_R"), "origin": ("origin_vio_T", "origin_vio_R")}
        if which not in attr:
            raise ValueError(f"which: expected one of {sorted(attr)}, got {which!r}")
        a, b = attr[which]
        t = torch.tensor([k.time for k in self.keyframes], dtype=_F64, device=dev)
        return t, torch.stack([getattr(k, a).to(_F64) for k in self.keyframes]), \
            torch.stack([getattr(k, b).to(_F64) for k in self.keyframes])

    def trajectory(self, which: str = "corrected"):
        """The keyframe poses as a :class:`torch_frontend.trajectory.Trajectory`."""
        from ..trajectory import Trajectory

        t, T, R = self.poses(which)
        return Trajectory(t, T, R_to_quat(R) if R.shape[0] else torch.zeros(0, 4, dtype=_F64, device=R.device))

    def csv_text(self) -> str:
        """``vins_result_loop.csv`` (§7.11): ``time·1e9`` with 0 decimals, then P.x P.y P.z Q.w
        Q.x Q.y Q.z with 5 decimals, each followed by a comma."""
        t, T, R = self.poses()
        q = R_to_quat(R) if R.shape[0] else R.new_zeros(0, 4)
        t, T, q = t.cpu(), T.cpu(), q.cpu()  # formatted on the host: one copy each, not one per value
        lines = []
        for k in range(t.shape[0]):
            vals = [f"{t[k].item() * 1e9:.0f}"] + [f"{v:.5f}" for v in (*T[k].tolist(), *q[k].tolist())]
            lines.append(",".join(vals) + ",\n")
        return "".join(lines)

    def write_csv(self, path: PathLike) -> Path:
        """Write ``vins_result_loop.csv`` atomically."""
        from .._atomic import write_text_atomic

        path = Path(path)
        write_text_atomic(path, self.csv_text())
        return path

    # ------------------------------------------------------------------------------ state
    STATE_VERSION = 1

    def _settings(self) -> Dict[str, object]:
        """What the graph was built with (a state is refused by a graph built otherwise)."""
        return {"mode": self.mode, "pnp_backend": self.pnp_backend, "auto_optimize": bool(self.auto_optimize),
                "optimize_iters": int(self.optimize_iters), "min_loop_gap": int(self.min_loop_gap),
                "save_images": bool(self.save_images), "R_ic": self.R_ic.cpu(), "t_ic": self.t_ic.cpu(),
                "words": None if self.vocabulary is None else int(self.vocabulary.num_words)}

    def state_dict(self, since: int = 0) -> Dict[str, object]:
        """Everything the graph needs to go on exactly as if it had never stopped, as CPU tensors
        and Python values (``loop.state``): the keyframes (every field; their points and
        descriptors only from keyframe ``since`` on: ``keyframe.keyframes_state``'s append-only
        chunks), the place database, every verified candidate, the scores, the counters, the
        per-sequence transforms, the queued loops, the RANSAC generator's state, and the settings
        it was built with. The camera and the vocabulary are not in it (the graph's constructor
        takes them)."""
        from .keyframe import keyframes_state

        seq = {int(s): {"w_r_vio": st.w_r_vio.cpu(), "w_t_vio": st.w_t_vio.cpu(), "r_drift": st.r_drift.cpu(),
                        "t_drift": st.t_drift.cpu(), "merged": bool(st.merged)} for s, st in self._seq.items()}
        return {"kind": "PoseGraph", "version": self.STATE_VERSION, "settings": self._settings(),
                "keyframes": keyframes_state(self.keyframes, since),
                "db": None if self.db is None else self.db.state_dict(),
                "loops": loop_results_state(self.loops),
                "scores": torch.tensor(self.scores, dtype=_F64),
                "global_index": int(self.global_index), "earliest_loop_index": int(self.earliest_loop_index),
                "yaw_drift": float(self.yaw_drift), "base_sequence": int(self.base_sequence), "sequences": seq,
                "pending": [int(i) for i in self._pending], "num_optimizations": int(self.num_optimizations),
                "optimize_seconds": float(self.optimize_seconds), "generator": self.generator.get_state()}

    def load_state_dict(self, state) -> None:
        """Restore one :meth:`state_dict` (``since=0``), or its chunks in the order they were
        written (the last one gives everything but the keyframes' points and descriptors), into
        this graph (built with the same settings and a vocabulary of the same size), onto its
        device. Raises ``StateError`` naming the first setting that differs, or for a state of
        another version; nothing changes then."""
        from .keyframe import keyframes_from_state
        from .state import check_same, check_state

        chunks = list(state) if isinstance(state, (list, tuple)) else [state]
        here = self._settings()
        for c in chunks:
            check_state(c, "PoseGraph", self.STATE_VERSION, ("settings", "keyframes", "loops", "generator"))
            for key, v in c["settings"].items():
                check_same("PoseGraph", key, v, here.get(key))
        st = chunks[-1]
        keyframes = keyframes_from_state([c["keyframes"] for c in chunks], self.device)
        loops = loop_results_from_state(st["loops"])
        if self.db is not None:
            db = PlaceDatabase(self.vocabulary)
            db.load_state_dict(st["db"])
            self.db = db
        self.keyframes, self.loops = keyframes, loops
        self.scores = [float(x) for x in st["scores"].tolist()]
        self.global_index, self.earliest_loop_index = int(st["global_index"]), int(st["earliest_loop_index"])
        self.yaw_drift, self.base_sequence = float(st["yaw_drift"]), int(st["base_sequence"])
        dev = self.device
        self._seq = {int(s): _SeqState(v["w_r_vio"].to(dev), v["w_t_vio"].to(dev), v["r_drift"].to(dev),
                                       v["t_drift"].to(dev), bool(v["merged"])) for s, v in st["sequences"].items()}
        self._pending = [int(i) for i in st["pending"]]
        self.num_optimizations, self.optimize_seconds = int(st["num_optimizations"]), float(st["optimize_seconds"])
        self.generator.set_state(st["generator"])

    # ------------------------------------------------------------------------------ persistence
    def save(self, directory: PathLike) -> Path:
        """Save in VINS's format (§7.11): ``pose_graph.txt``, ``<i>_keypoints.txt``,
        ``<i>_briefdes.dat`` (and ``<i>_image.png`` for kept images), plus the marker
        ``written-by-torch-frontend.json`` (the list of these files; VINS and :meth:`load` ignore it).

        Written into a temporary folder beside ``directory`` that replaces it as a whole, in one
        step, only when complete (``_atomic.StagedFolder``). Nothing the library did not write is
        ever deleted: ``directory`` is replaced only when it is absent, empty, an earlier save (its
        marker lists everything in it) or a folder saved before the marker existed (by this
        library or VINS) that holds only pose-graph files (``POSE_GRAPH_FILES``); anything else
        there, or a file at ``directory``, raises ``OutputFolderError`` (a ``DataError``) naming it
        and nothing is touched.

        Raises:
            DataError: the parent folder is missing; ``OutputFolderError`` as above.
        """
        from .._atomic import StagedFolder

        final = Path(directory)
        if not final.parent.exists():
            raise DataError(f"save: parent folder {final.parent} does not exist")
        with StagedFolder(final, "pose_graph", POSE_GRAPH_FILES) as stage:
            tmp = stage.path
            lines = []
            for k in self.keyframes:
                vq = R_to_quat(k.vio_R).tolist()
                pq = R_to_quat(k.R_w_i).tolist()
                info = k.loop_info.tolist()
                vals = [f" {k.index:d}", f"{k.time:f}"] + [f"{v:f}" for v in (*k.vio_T.tolist(), *k.T_w_i.tolist(), *vq, *pq)]
                vals += [f"{k.loop_index:d}"] + [f"{v:f}" for v in info] + [f"{k.keypoints.shape[0]:d}"]
                lines.append(" ".join(vals) + "\n")
                kp = k.keypoints.double().cpu().numpy()
                kn = k.keypoints_norm.double().cpu().numpy()
                (tmp / f"{k.index}_keypoints.txt").write_text(
                    "".join(f"{a:f} {b:f} {c:f} {d:f}\n" for (a, b), (c, d) in zip(kp, kn)))
                (tmp / f"{k.index}_briefdes.dat").write_text(_brief_to_text(k.brief))
                if k.image is not None:
                    import cv2

                    if not cv2.imwrite(str(tmp / f"{k.index}_image.png"), k.image.cpu().numpy()):
                        raise OSError(f"save: cannot write {final / f'{k.index}_image.png'}")
            (tmp / "pose_graph.txt").write_text("".join(lines))
        return final

    def load(self, directory: PathLike) -> int:
        """Load a graph saved by :meth:`save` or by VINS (§7.11): keyframes become sequence 0,
        fixed in optimisation, re-indexed after the current ones and added to the place database
        (no detection). Returns the number of keyframes loaded. Nothing changes on an error.
        The marker file of :meth:`save` is not needed: folders saved before it, or by VINS, load
        the same."""
        directory = Path(directory)
        rows = _read_pose_graph(directory)
        new: List[KeyFrame] = []
        base = self.global_index
        remap: Dict[int, int] = {}
        for r in rows:
            remap[r["index"]] = base + len(new)
            kp, kn, desc = _read_keypoints(directory, r["index"], r["count"])
            kf = KeyFrame.loaded(index=base + len(new), time=r["time"], T=r["T"], R=quat_to_R(r["q"]),
                                 keypoints=kp, keypoints_norm=kn, brief=desc,
                                 loop_index=r["loop_index"], loop_info=r["loop_info"])
            new.append(kf.to(self.device))
        for kf in new:
            if kf.loop_index >= 0:
                if kf.loop_index not in remap:
                    raise DataError(f"{directory / 'pose_graph.txt'}: keyframe {kf.index} loops to unknown index {kf.loop_index}")
                kf.loop_index = remap[kf.loop_index]
                kf.has_loop = True
        # all parsed: commit
        for kf in new:
            if self.db is not None:
                self.db.add(self._bow(kf))
            self.scores.append(0.0)
            self.keyframes.append(kf)
            if kf.loop_index >= 0:
                self.earliest_loop_index = kf.loop_index if self.earliest_loop_index < 0 else min(self.earliest_loop_index, kf.loop_index)
        self.global_index = base + len(new)
        self.base_sequence = 0
        return len(new)


# ---------------------------------------------------------------------------------- file formats
#: the files of a saved pose graph (``save``; VINS writes the same names): what a folder saved
#: before the marker existed may hold to be replaced (regular expressions, ``_atomic``)
POSE_GRAPH_FILES = (r"pose_graph\.txt", r"\d+_keypoints\.txt", r"\d+_briefdes\.dat", r"\d+_image\.png")


def _brief_to_text(desc: torch.Tensor) -> str:
    """boost ``dynamic_bitset`` text, most-significant bit first (char 0 = bit 255)."""
    if desc.shape[0] == 0:
        return ""
    d = desc.cpu().numpy().astype(np.int64).view(np.uint64)
    bits = ((d[:, :, None] >> np.arange(64, dtype=np.uint64)) & np.uint64(1)).astype(np.uint8)
    bits = bits.reshape(d.shape[0], -1)[:, ::-1]  # bit 255 first
    chars = (bits + ord("0")).astype(np.uint8)
    return "".join(row.tobytes().decode() + "\n" for row in chars)


def _text_to_brief(text: str, path: Path, count: int) -> torch.Tensor:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if len(lines) != count:
        raise DataError(f"{path}: expected {count} descriptors (pose_graph.txt), found {len(lines)}")
    if count == 0:
        return torch.zeros(0, 4, dtype=torch.int64)
    for n, ln in enumerate(lines, 1):
        if len(ln) != 256 or set(ln) - {"0", "1"}:
            raise DataError(f"{path}:{n}: expected 256 characters of 0/1, got {ln[:40]!r}")
    arr = np.frombuffer("".join(lines).encode(), dtype=np.uint8).reshape(count, 256) - ord("0")
    bits = arr[:, ::-1].reshape(count, 4, 64).astype(np.uint64)
    words = (bits << np.arange(64, dtype=np.uint64)).sum(-1, dtype=np.uint64)
    return torch.from_numpy(words.view(np.int64).copy())


def _read_pose_graph(directory: Path) -> List[dict]:
    path = directory / "pose_graph.txt"
    if not path.is_file():
        raise DataError(f"{path}: no saved pose graph here (pose_graph.txt missing)")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: unreadable ({e})") from None
    rows = []
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        f = line.split()
        if len(f) != 26:
            raise DataError(f"{path}:{n}: expected 26 fields (VINS pose_graph.txt), got {len(f)}")
        try:
            v = [float(x) for x in f]
        except ValueError:
            raise DataError(f"{path}:{n}: non-numeric field in {line.strip()[:60]!r}") from None
        if not all(math.isfinite(x) for x in v):
            raise DataError(f"{path}:{n}: non-finite value")
        q = torch.tensor(v[12:16], dtype=_F64)
        if abs(float(q.norm()) - 1.0) > 1e-3:
            raise DataError(f"{path}:{n}: PG quaternion is not unit (norm {float(q.norm()):.4f})")
        rows.append({"index": int(v[0]), "time": v[1], "T": torch.tensor(v[5:8], dtype=_F64), "q": q,
                     "loop_index": int(v[16]), "loop_info": torch.tensor(v[17:25], dtype=_F64), "count": int(v[25])})
    if not rows:
        raise DataError(f"{path}: empty pose graph")
    return rows


def _read_keypoints(directory: Path, index: int, count: int):
    kp_path = directory / f"{index}_keypoints.txt"
    de_path = directory / f"{index}_briefdes.dat"
    for p in (kp_path, de_path):
        if not p.is_file():
            raise DataError(f"{p}: missing (keyframe {index} of pose_graph.txt)")
    try:
        arr = np.loadtxt(kp_path, dtype=np.float64, ndmin=2)
    except ValueError as e:
        raise DataError(f"{kp_path}: unreadable keypoints ({e})") from None
    if count == 0:
        arr = np.zeros((0, 4))
    if arr.shape != (count, 4):
        raise DataError(f"{kp_path}: expected {count} rows of 4 numbers, got shape {arr.shape}")
    desc = _text_to_brief(de_path.read_text(), de_path, count)
    return (torch.from_numpy(arr[:, :2].astype(np.float32)), torch.from_numpy(arr[:, 2:].copy()), desc)
