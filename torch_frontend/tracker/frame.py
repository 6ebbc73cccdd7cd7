"""``FeatureFrame``: what one tracker step publishes for B streams, and its VINS message layouts."""

from __future__ import annotations

import dataclasses
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch


@dataclasses.dataclass
class FeatureFrame:
    """One processed time step of all B streams.

    Attributes:
        ids: (B, K) int64, -1 in empty slots.
        uv: (B, K, 2) float, distorted pixels (x, y).
        xy: (B, K, 2) float, normalised undistorted coordinates (x/z, y/z).
        velocity: (B, K, 2) float, normalised units per second (VINS's rule per mode).
        track_count: (B, K) int64.
        valid: (B, K) bool, the features VINS would publish (mono: ``track_cnt > 1`` on published
            frames; fusion: every tracked feature).
        present: (B, K) bool, every feature in the tracker's table after this step (including
            just-detected ones, which the debug image draws).
        published: (B,) bool, this step built a feature message (mono: PUB_THIS_FRAME; the very
            first one is not sent, see ``sent``).
        sent: (B,) bool, the message would be sent to the estimator (mono: not on the first
            published frame).
        restarted: (B,) bool, a restart was signalled (gap > 1 s or time went backwards).
        tracked: (B,) bool, the image was processed (mono skips first images and restarts).
        timestamps: (B,) float64 seconds.
        overflow: (B,) bool, a fixed budget of the capturable step (LK iterations, RANSAC
            hypotheses, corner candidates, greedy rounds) was too small for OpenCV's exact answer
            in this step, so the stream's results may differ from the default path. Always False
            on the default path (it has no budgets) and, by the sizes chosen, on every test sequence.
        right_uv, right_xy, right_velocity, right_valid: stereo (fusion) observations of the same
            slots in camera 1, or None.
    """

    ids: torch.Tensor
    uv: torch.Tensor
    xy: torch.Tensor
    velocity: torch.Tensor
    track_count: torch.Tensor
    valid: torch.Tensor
    present: torch.Tensor
    published: torch.Tensor
    sent: torch.Tensor
    restarted: torch.Tensor
    tracked: torch.Tensor
    timestamps: torch.Tensor
    overflow: Optional[torch.Tensor] = None
    prev_uv: Optional[torch.Tensor] = None
    prev_valid: Optional[torch.Tensor] = None
    right_uv: Optional[torch.Tensor] = None
    right_xy: Optional[torch.Tensor] = None
    right_velocity: Optional[torch.Tensor] = None
    right_valid: Optional[torch.Tensor] = None

    @property
    def batch_size(self) -> int:
        return int(self.ids.shape[0])

    def _rows(self, b: int, mask: torch.Tensor):
        sel = mask[b].nonzero().flatten()
        return sel

    def to_point_cloud(self, b: int = 0) -> Dict[str, np.ndarray]:
        """Stream ``b`` in the VINS-Mono ``sensor_msgs/PointCloud`` layout.

        Returns a dict with ``points`` (M, 3) float32 rows (x, y, 1), and the five channels as
        float32 arrays in VINS order: ``id``, ``u``, ``v``, ``vx``, ``vy`` (the id is float32 as
        in VINS: exact up to 2**24). Also ``stamp`` (seconds).
        """
        sel = self._rows(b, self.valid)
        xy = self.xy[b, sel].detach().cpu().double().numpy()
        uv = self.uv[b, sel].detach().cpu().double().numpy()
        vel = self.velocity[b, sel].detach().cpu().double().numpy()
        ids = self.ids[b, sel].cpu().numpy()
        pts = np.concatenate([xy, np.ones((len(sel), 1))], axis=1).astype(np.float32)
        return {
            "stamp": float(self.timestamps[b]),
            "points": pts,
            "id": ids.astype(np.float32),
            "u": uv[:, 0].astype(np.float32),
            "v": uv[:, 1].astype(np.float32),
            "vx": vel[:, 0].astype(np.float32),
            "vy": vel[:, 1].astype(np.float32),
        }

    def to_vins_fusion(self, b: int = 0) -> Dict[int, List[Tuple[int, np.ndarray]]]:
        """Stream ``b`` as VINS-Fusion's ``{id: [(camera_id, [x, y, z, u, v, vx, vy])]}`` (ordered by id;
        camera 0 first, camera 1 second where a right observation exists)."""
        out: Dict[int, List[Tuple[int, np.ndarray]]] = {}
        sel = self._rows(b, self.valid)
        ids = self.ids[b, sel].cpu().numpy()
        xy = self.xy[b, sel].detach().cpu().double().numpy()
        uv = self.uv[b, sel].detach().cpu().double().numpy()
        vel = self.velocity[b, sel].detach().cpu().double().numpy()
        right = None
        if self.right_valid is not None:
            rv = self.right_valid[b, sel].cpu().numpy()
            rxy = self.right_xy[b, sel].detach().cpu().double().numpy()
            ruv = self.right_uv[b, sel].detach().cpu().double().numpy()
            rvel = self.right_velocity[b, sel].detach().cpu().double().numpy()
            right = (rv, rxy, ruv, rvel)
        order = np.argsort(ids, kind="stable")
        for j in order:
            obs = [(0, np.array([xy[j, 0], xy[j, 1], 1.0, uv[j, 0], uv[j, 1], vel[j, 0], vel[j, 1]]))]
            if right is not None and right[0][j]:
                rxy, ruv, rvel = right[1][j], right[2][j], right[3][j]
                obs.append((1, np.array([rxy[0], rxy[1], 1.0, ruv[0], ruv[1], rvel[0], rvel[1]])))
            out[int(ids[j])] = obs
        return out


__all__ = ["FeatureFrame"]
