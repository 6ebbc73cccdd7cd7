"""Memory bounds of the capturable mono step (issue 28): bytes written per stream per step, the
largest tensor and the peak of live memory, counted by
``torch_frontend.testing.dispatch_count.OpCounter`` on the repo's EuRoC sample at B = 2 (752x480,
VINS-Mono's euroc config).

The written bytes are the traffic's floor (each is read at least once more); the modelled totals
(reads too, on the CUDA path) are ``benchmarks/results/roofline.md``'s. Measured here before the
issue-28 work: 694 MB per stream per step on every step, largest tensor 34.3 MiB; after: 213 MB on
a track-only step, 372 MB on a publishing one, largest 13.7 MiB; then (LK's difference image
written channel by channel, detection's buffers dropped as they die, the stacked undistortion):
206 / 347.5 MB, and a peak of live memory of 14.0 MiB per stream on a track-only step, 17.7 on a
publishing one (from 20.0 and 30.0). Detection in exact-integer passes and int32 top-k keys
(the GFTT's response sums, NMS and keys): 302.3 MB on a publishing step. Then the LK by
convolution (no difference image, the template in ~18 ops) and the pyramid kept as it is when
every stream is tracked: 151.4 MB on a track-only step, 247.8 on a publishing one, 199.6 on
average, and a peak of live memory of 11.5 MiB per stream on a track-only step (17.7 publishing:
RANSAC's tests).
"""

from __future__ import annotations

import torch

import torch_frontend as tf
from torch_frontend.testing.dispatch_count import OpCounter

from .conftest import REPO, load_gray, sample_frames

B = 2
#: bounds per stream per step (MB) and on the largest tensor written (MiB), with ~15 % headroom
TRACK_ONLY_MB, PUBLISH_MB, MEAN_MB, LARGEST_MIB = 175, 285, 230, 16
#: bounds on the peak of live memory per stream (MiB): track-only and publishing steps, ~15 % headroom
TRACK_ONLY_PEAK_MIB, PUBLISH_PEAK_MIB = 13.2, 20.5


def test_capturable_step_bytes_and_largest_tensor():
    paths = sample_frames("cam0")[:12]
    trk = tf.FeatureTracker(str(REPO / "configs" / "euroc.yaml"), num_streams=B, capturable=True)
    written = {True: [], False: []}
    peak = {True: [], False: []}
    largest = 0
    for k, p in enumerate(paths):
        img = torch.from_numpy(load_gray(p))[None, None].expand(B, 1, -1, -1).contiguous()
        t = torch.full((B,), int(p.stem) * 1e-9, dtype=torch.float64)
        with OpCounter() as c:
            frame = trk.track(img, t)
        if k >= 4:  # after the first publish and restart: the steady alternation
            written[bool(frame.published.any())].append(c.bytes_written / B / 1e6)
            peak[bool(frame.published.any())].append((c.peak_live / B / 2**20, c.live_site))
            largest = max(largest, c.largest)
    assert written[True] and written[False], "the sample publishes every other frame"
    track_only, publish = max(written[False]), max(written[True])
    mean = (sum(written[True]) + sum(written[False])) / (len(written[True]) + len(written[False]))
    assert track_only <= TRACK_ONLY_MB, written
    assert publish <= PUBLISH_MB, written
    assert mean <= MEAN_MB, written
    assert largest <= LARGEST_MIB * 2**20, largest / 2**20
    assert max(peak[False])[0] <= TRACK_ONLY_PEAK_MIB, peak[False]
    assert max(peak[True])[0] <= PUBLISH_PEAK_MIB, peak[True]
    # the unpublished steps skip the publish-only stages: a clear gap (test_tracker_publish counts kernels)
    assert track_only < 0.7 * publish, written


def test_op_counter_peak_live_frees_at_the_last_reference():
    """``OpCounter.peak_live``: a storage counts from the op that makes it to its last tensor
    reference (a view keeps it), not longer: two buffers of 4 MB made one after the other, the
    first dropped before the second exists, peak at 4 MB; kept through a view, 8 MB."""
    n = 1 << 20  # float32: 4 MiB
    with OpCounter() as c:
        a = torch.ones(n)
        a += 1  # in place: the same storage
        del a
        b = torch.ones(n) * 2
    assert c.peak_live == 2 * 4 * n, c.peak_live  # ones, then its product (both alive at the mul)
    assert c.live_bytes == 4 * n  # b
    with OpCounter() as c:
        a = torch.ones(n)
        v = a[1:]
        del a
        b = torch.empty(n)
        b.fill_(v[0])
    assert c.peak_live == 2 * 4 * n and "fill_" not in c.live_site
    del v, b
    assert c.live_bytes == 0
