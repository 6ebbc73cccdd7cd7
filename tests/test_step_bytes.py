"""Memory-traffic bounds of the capturable mono step (issue 28): bytes written per stream per step
and the largest tensor, counted by ``torch_frontend.testing.dispatch_count.OpCounter`` on the
repo's EuRoC sample at B = 2 (752x480, VINS-Mono's euroc config).

The written bytes are the traffic's floor (each is read at least once more); the modelled totals
(reads too, on the CUDA path) are ``benchmarks/results/roofline.md``'s. Measured here before the
issue-28 work: 694 MB per stream per step on every step, largest tensor 34.3 MiB; after: 213 MB on
a track-only step, 372 MB on a publishing one, largest 13.7 MiB.
"""

from __future__ import annotations

import torch

import torch_frontend as tf
from torch_frontend.testing.dispatch_count import OpCounter

from .conftest import REPO, load_gray, sample_frames

B = 2
#: bounds per stream per step (MB) and on the largest tensor written (MiB), with ~15 % headroom
TRACK_ONLY_MB, PUBLISH_MB, MEAN_MB, LARGEST_MIB = 250, 430, 340, 16


def test_capturable_step_bytes_and_largest_tensor():
    paths = sample_frames("cam0")[:12]
    trk = tf.FeatureTracker(str(REPO / "configs" / "euroc.yaml"), num_streams=B, capturable=True)
    written = {True: [], False: []}
    largest = 0
    for k, p in enumerate(paths):
        img = torch.from_numpy(load_gray(p))[None, None].expand(B, 1, -1, -1).contiguous()
        t = torch.full((B,), int(p.stem) * 1e-9, dtype=torch.float64)
        with OpCounter() as c:
            frame = trk.track(img, t)
        if k >= 4:  # after the first publish and restart: the steady alternation
            written[bool(frame.published.any())].append(c.bytes_written / B / 1e6)
            largest = max(largest, c.largest)
    assert written[True] and written[False], "the sample publishes every other frame"
    track_only, publish = max(written[False]), max(written[True])
    mean = (sum(written[True]) + sum(written[False])) / (len(written[True]) + len(written[False]))
    assert track_only <= TRACK_ONLY_MB, written
    assert publish <= PUBLISH_MB, written
    assert mean <= MEAN_MB, written
    assert largest <= LARGEST_MIB * 2**20, largest / 2**20
    # the unpublished steps skip the publish-only stages: a clear gap (test_tracker_publish counts kernels)
    assert track_only < 0.7 * publish, written
