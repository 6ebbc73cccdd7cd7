"""CPU tuning in one room: the kernels' batching / blocking constants and CPU-only strategies.

Every kernel is written once, in its reference form. What is here changes speed and memory only,
never a value (each strategy has a test that it gives the very result of one pass; see
``tests/test_tuning.py``):

* :func:`for_device` picks a :class:`Strategy` by device type. On the CPU the image-sized passes
  are cut into cache-sized blocks / groups of streams (fresh multi-MB temporaries sit above
  glibc's mmap threshold and are page-faulted in on every call, and they fall out of the caches);
  on any other device a kernel runs the whole batch in one pass, with no grouping and no blocking.
* :func:`inplace_ok` chooses the fast form of a kernel step (in place, or fewer ops): the same
  operations in the same order as the reference (out-of-place, differentiable) form, so the values
  are bit-identical; it is taken when autograd does not need the tensors involved.
  :func:`reference_forms` makes every kernel take its reference form (for the tests that hold each
  fast form equal to it).

Each constant names the benchmark that chose it; all were measured on 752x480 EuRoC frames with 1
torch thread (``benchmarks/bench_image.py``, ``bench_lk.py``, ``bench_ransac.py`` and the tracker
A/B ``benchmarks/ab_tracker.py``). A new CPU strategy goes here: a field of :class:`Strategy` with
its CPU value and its one-pass value, and a test that both give the same result.
"""

from __future__ import annotations

import contextlib
import dataclasses
import threading
from dataclasses import dataclass
from typing import Dict, Iterator, List, Optional, Tuple

import torch

from ._autodiff import derivative_wanted

__all__ = ["Strategy", "CPU", "ONE_PASS", "CUDA", "STRATEGIES", "for_device", "inplace_ok", "reference_forms"]


@dataclass(frozen=True)
class Strategy:
    """How the kernels split their work on one kind of device. ``None``: one pass."""

    #: CLAHE (``equalize``): pixels per block of image rows for the histogram keys and the LUT blend
    clahe_block_pixels: Optional[int]
    #: ``build_pyramid``: batches of more than ``pyramid_batch_pixels`` pixels are built in groups of
    #: ``pyramid_group_pixels`` pixels of streams
    pyramid_group_pixels: Optional[int]
    pyramid_batch_pixels: Optional[int]
    #: corner responses and GFTT non-maximum suppression: pixels per group of streams
    corner_block_pixels: Optional[int]
    #: LK: streams are tracked in groups of at most ``lk_max_streams`` streams and ``lk_max_lanes``
    #: points (pyramids padded once for the whole batch)
    lk_max_lanes: Optional[int]
    lk_max_streams: Optional[int]
    #: a host check that can skip work is free (CPU) rather than a device synchronisation
    host_checks_free: bool
    #: GFTT greedy minimum-distance acceptance: candidates per rank chunk, the first chunk
    #: ``gftt_chunk``, each next one twice as large up to ``gftt_chunk_max``; memory ~ 20 B
    #: survivors² + 12 B chunk max_corners bytes
    gftt_chunk: int
    gftt_chunk_max: int
    #: RANSAC: minimal samples per problem in the first round; problems x samples x points per later
    #: round (~10 floats each: a memory budget); lanes above which only real cubic roots are scored
    ransac_first_round: int
    ransac_round_elems: int
    ransac_compact_elems: int
    #: ``build_pyramid`` of a uint8 image (OpenCV's rounded 8-bit levels): each level as one strided
    #: 5x5 ``conv2d`` with the rounding's ``+ 0.5`` as its bias (True) or as the separable 5-tap sums
    #: (False). Every partial sum is an exact multiple of 1/256 below 2^8 (16 significant bits), so
    #: both give the same bits in any summation order (TF32 inputs too: 8-bit levels and k / 256
    #: taps are exact in it). bench (pyramid of 752x480 frames, 1 thread): the CPU is faster
    #: separable (4.3 vs 5.3 ms at B = 1, 79 vs 156 ms at B = 16); on a device the conv form is 3
    #: kernels per level instead of ~12 and ~3x fewer bytes (roofline.py)
    pyramid_conv: bool
    #: capturable CLAHE of an image that is a multiple of the grid: one int32 key per pixel for the
    #: histograms and the LUT gather, mixed-dtype elementwise ops (``equalize._clahe_blocks``, True)
    #: or the per-cell form with its own histogram key (``_clahe_padded``, False): the same bits.
    #: bench (752x480, 1 thread): the CPU casts mixed-dtype operands with extra copies, 43 vs 8 ms
    #: per frame; on a device 23 kernels and 41 MB per frame instead of 40 and 65 (roofline.py)
    clahe_block_keys: bool
    #: RANSAC's 7-point Gram-Schmidt step ``R - (g / g0) r0`` as two elementwise passes (True) or
    #: one ``baddbmm`` of the outer product (False): the same product and difference per entry, so
    #: the same bits; the CPU is faster elementwise, a device saves a launch per step with baddbmm
    ransac_gs_elementwise: bool
    #: the pyramid and the LK of 8-bit frames: ``"fused"``, one custom op each (``fused/``: numba on
    #: the CPU, Triton on CUDA; OpenCV's bits), or ``"tensor"``, the tensor kernels (``pyramid``,
    #: ``lk/``). bench_lk.py (150 points, 752x480, 1 thread): the fused pyramid + LK 1.46 ms per frame
    #: against cv2's 1.86 and the tensor LK's ~24 ms; count_step.py: 2 ops for the pyramid and the LK
    #: of a capturable step instead of ~2,900. A call or a tracker overrides it (``lk_backend=``)
    lk_backend: str = "tensor"
    #: CLAHE of 8-bit frames: ``"fused"``, one custom op (``fused/clahe_op.py``: numba on the CPU, two
    #: Triton launches on CUDA; OpenCV's bits), or ``"tensor"``, ``equalize``'s tensor CLAHE (the same
    #: bits). bench_clahe.py (752x480, 1 thread): see benchmarks/results/clahe.json. A call or a tracker
    #: overrides it (``clahe_backend=``)
    clahe_backend: str = "tensor"
    #: F-RANSAC's scoring, counting, best model and iteration bound: ``"fused"``, one custom op per
    #: round (``fused/ransac_op.py``: numba on the CPU, Triton on CUDA; OpenCV's ``computeError`` bits),
    #: or ``"tensor"`` (``ransac/scoring.py`` and the scans of ``eager.py`` / ``capturable.py``).
    #: ``find_fundamental(backend=...)`` overrides it; ``fused.resolve_ransac_backend`` resolves it
    ransac_backend: str = "tensor"
    #: goodFeaturesToTrack of 8-bit frames (min eigenvalue, block 3): ``"fused"``, one custom op
    #: (``fused/corners_op.py``: numba on the CPU, Triton + the capturable selection on CUDA; the
    #: tensor path's bits, response only where the mask matters), or ``"tensor"`` (``corners/``).
    #: bench_corners.py: see benchmarks/results/corners.json. A tracker overrides it (``corner_backend=``)
    corner_backend: str = "tensor"
    #: mono step: CLAHE -> pyramid -> LK of one frame as one op (``fused/front_op.py``) that runs the three
    #: kernels back to back on ``front_group`` streams at a time (each stream's image and pyramid reused
    #: while in cache), or None: three stage ops over the whole batch. Needs the fused CLAHE and LK
    front_group: Optional[int] = None
    #: camodocal's PINHOLE lift in the tracker (``lift_normalised``): ``"fused"``, one custom op
    #: (``fused/lift_op.py``: numba on the CPU, one Triton launch on CUDA; the tensor path's bits), or
    #: ``"tensor"`` (``PinholeCamera._lift_impl``). Other camera models lift with the tensor path. A
    #: tracker overrides it (``lift_backend=``)
    lift_backend: str = "tensor"

    # ------------------------------------------------------------------ work splits
    def clahe_rows(self, rows: int, width: int) -> List[Tuple[int, int]]:
        """Row ranges ``[r0, r1)`` of a ``(rows, width)`` pixel array processed together."""
        if self.clahe_block_pixels is None:
            return [(0, rows)]
        step = max(1, self.clahe_block_pixels // max(width, 1))
        return [(r, min(r + step, rows)) for r in range(0, rows, step)]

    def pyramid_streams(self, B: int, H: int, W: int) -> Optional[int]:
        """Streams per group for ``build_pyramid``, or None for one pass."""
        if self.pyramid_group_pixels is None:
            return None
        per = max(1, self.pyramid_group_pixels // max(H * W, 1))
        if B > per and B * H * W > self.pyramid_batch_pixels:
            return per
        return None

    def corner_streams(self, B: int, H: int, W: int) -> Optional[int]:
        """Streams per group for the corner response / NMS passes, or None for one pass."""
        if self.corner_block_pixels is None:
            return None
        per = max(1, self.corner_block_pixels // max(H * W, 1))
        return per if B > per else None

    def lk_streams(self, B: int, N: int) -> Optional[int]:
        """Streams per group for the LK, or None for one pass."""
        if self.lk_max_lanes is None:
            return None
        per = max(1, min(self.lk_max_streams, self.lk_max_lanes // max(N, 1)))
        return per if B > per else None


CPU = Strategy(
    # bench_image.py (clahe row): blocks of 2^17 pixels keep the float temporaries in cache and below
    # glibc's mmap threshold; one block for the batch made B=8 ~2x slower per image than B=1
    clahe_block_pixels=1 << 17,
    # ab_tracker.py (commit fc73e7f), ms per image at B = 64: 2.9 in groups of
    # one frame (2^19 pixels) vs 4.4 whole; at B <= 16 the whole batch is as fast or faster (the
    # final concatenation costs a copy), hence grouping only above 2^24 pixels (~46 frames)
    pyramid_group_pixels=1 << 19,
    pyramid_batch_pixels=1 << 24,
    # bench_image.py (min_eigen_response, good_features_to_track rows): the response needs ~10
    # image-sized temporaries; for the whole batch at once B=8 cost ~20x B=1
    corner_block_pixels=1 << 19,
    # bench_lk.py (N = 1000 rows), 2 cores: B=8 x N=1000 in groups of 4 streams (4000 lanes) took
    # 2x longer than stream by stream: the (win+1)^2 x lanes windows and their indices stay cache
    # friendly up to ~1024 lanes; small N: at most 8 streams per group
    lk_max_lanes=1024,
    lk_max_streams=8,
    host_checks_free=True,
    # bench_image.py (good_features_to_track row): on EuRoC frames OpenCV's 150th corner is found at
    # rank ~1500-1900, i.e. ~5 chunks growing 128 -> 512
    gftt_chunk=128,
    gftt_chunk_max=512,
    # bench_ransac.py: with few outliers OpenCV stops within 32 samples (small problems are bound by
    # the number of torch ops per round); 2^20 lanes per round bounds the score tensors; above 2^16
    # lanes compacting to the real roots (argsort + gather + one sync) is cheaper than scoring all
    ransac_first_round=32,
    ransac_round_elems=1 << 20,
    ransac_compact_elems=1 << 16,
    # bench_ransac.py-style A/B (one process, 150 points): the elementwise update makes the
    # 7-point solver ~10 % faster at B = 1 and 8-21 % at B = 32 than baddbmm
    ransac_gs_elementwise=True,
    pyramid_conv=False,
    clahe_block_keys=False,
    lk_backend="fused",
    clahe_backend="fused",
    ransac_backend="fused",
    corner_backend="fused",
    # bench_grouping.py (benchmarks/results/cache_grouping.md), 1 thread: the three kernels 0.89-0.93x
    # stage order at B = 16-64 one stream at a time, 0.89-0.94 in groups of 2, 0.93-0.97 of 4, 0.91-1.00
    # of 8; ab_tracker.py, the whole step against front_group=None: 0.91-1.02 at B = 16, 0.92-1.01 at
    # B = 64 (noise of the same size); G = 2 alike, G = 4 0.93-0.95 behind G = 1
    front_group=1,
    lift_backend="fused",
)

# Any other device (CUDA, ...): one pass, no grouping, no blocking. The GFTT chunks and the RANSAC
# rounds are part of the algorithms' schedules (results do not depend on them) and memory budgets,
# kept as on the CPU until measured on a device.
ONE_PASS = Strategy(
    clahe_block_pixels=None,
    pyramid_group_pixels=None,
    pyramid_batch_pixels=None,
    corner_block_pixels=None,
    lk_max_lanes=None,
    lk_max_streams=None,
    host_checks_free=False,
    gftt_chunk=CPU.gftt_chunk,
    gftt_chunk_max=CPU.gftt_chunk_max,
    ransac_first_round=CPU.ransac_first_round,
    ransac_round_elems=CPU.ransac_round_elems,
    ransac_compact_elems=CPU.ransac_compact_elems,
    ransac_gs_elementwise=False,  # one launch per Gram-Schmidt step (7 per RANSAC call) fewer
    pyramid_conv=True,
    clahe_block_keys=True,
)

#: CUDA: one pass, and the fused kernels (Triton) for the pyramid, the LK, CLAHE, RANSAC's scoring and detection
CUDA = dataclasses.replace(ONE_PASS, lk_backend="fused", clahe_backend="fused", ransac_backend="fused",
                           corner_backend="fused", lift_backend="fused")

#: device type -> strategy; types not listed get :data:`ONE_PASS` (tests swap entries to check that
#: a strategy does not change results)
STRATEGIES: Dict[str, Strategy] = {"cpu": CPU, "cuda": CUDA}


def for_device(device) -> Strategy:
    """The :class:`Strategy` for ``device`` (a ``torch.device`` or a string such as ``"cuda:0"``)."""
    kind = device.type if isinstance(device, torch.device) else torch.device(device).type
    return STRATEGIES.get(kind, ONE_PASS)


# per thread: a test holding one thread in reference_forms() must not switch the kernels of other
# threads, and interleaved blocks in two threads must not leave the switch on when both have left
_REFERENCE_ONLY = threading.local()


def inplace_ok(*tensors: Optional[torch.Tensor]) -> bool:
    """True when a kernel may take its fast (in-place) form for these tensors: none of them
    carries a derivative (``requires_grad`` or a forward-mode tangent,
    :func:`~torch_frontend._autodiff.derivative_wanted`) and :func:`reference_forms` is not
    active. ``None`` entries are ignored.

    The fast form of every kernel step performs the reference form's operations in the same order
    (in place, or into a preallocated output), so both give bit-identical values."""
    if getattr(_REFERENCE_ONLY, "on", False):
        return False
    return not derivative_wanted(*tensors)


@contextlib.contextmanager
def reference_forms() -> Iterator[None]:
    """Within this block every kernel takes its reference (out-of-place, differentiable) form,
    also without gradients: the tests compare it with the fast forms bit for bit. The switch holds
    for the calling thread only (kernels running in other threads keep their fast forms)."""
    old = getattr(_REFERENCE_ONLY, "on", False)
    _REFERENCE_ONLY.on = True
    try:
        yield
    finally:
        _REFERENCE_ONLY.on = old
