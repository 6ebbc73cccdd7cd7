"""What every pipeline shares: the option error, the reader/run options, the device, the progress
bar and the ragged-to-padded conversion.

Importing this module imports neither torch nor tqdm (the CLI imports it to catch ``OptionError``).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterator, Optional, Sequence, Tuple, Union

if TYPE_CHECKING:  # pragma: no cover
    import torch

__all__ = ["InputOptions", "OptionError", "pad_ragged", "progress_bar", "resolve_device"]

#: widest progress bar (characters), and the terminal size assumed when a pty reports 0 x 0
MAX_BAR_COLUMNS = 120
FALLBACK_TERMINAL = (100, 20)


class OptionError(ValueError):
    """A bad pipeline option or argument. ``option`` is its name (a field of the options dataclass,
    or an argument of the pipeline function) and the message starts with that name, so that a
    front end can put its own spelling in its place (the CLI writes ``--max-frames`` for
    ``max_frames``)."""

    def __init__(self, option: str, message: str):
        if not message.startswith(option):
            message = f"{option}: {message}"
        super().__init__(message)
        self.option = option


@dataclass
class InputOptions:
    """How a pipeline reads its inputs and shows its progress (the fields ``TrackOptions`` and
    ``LoopOptions`` share).

    Attributes:
        device: where the tracker runs: ``"cpu"``, ``"cuda"``, ``"cuda:1"`` or a ``torch.device``.
        max_frames: at most this many frames per stream (None: all of them).
        camera: camera folder of ``euroc`` sources (``cam0``); also the camera of the
            ``sensor.yaml`` used when no config is given.
        fps: frame rate (Hz) of ``images`` sources whose file names are not timestamps (frame i is
            at i / fps s); None: times from the names.
        topic: image topic of ``bag`` sources; None: the config's ``image_topic``.
        skip_bad_frames: skip unreadable or corrupt frames (listed in the summary) instead of
            raising ``DataError``.
        progress: tqdm bars on stderr: True always, False never, None only on a terminal.
        workers: ``torch.utils.data.DataLoader`` worker processes that decode the frames ahead of
            the tracker (``pipelines.prefetch.FrameStream``); 0: decode in this process.
    """

    device: Union[str, torch.device] = "cpu"
    max_frames: Optional[int] = None
    camera: str = "cam0"
    fps: Optional[float] = None
    topic: Optional[str] = None
    skip_bad_frames: bool = False
    progress: Optional[bool] = None
    workers: int = 0

    def check(self) -> None:
        """Raise ``OptionError`` for a value no reader accepts."""
        if not isinstance(self.workers, int) or self.workers < 0:
            raise OptionError("workers", f"workers must be an integer >= 0, got {self.workers!r}")
        if self.max_frames is not None and self.max_frames < 1:
            raise OptionError("max_frames", f"max_frames must be >= 1, got {self.max_frames}")
        if self.fps is not None and not (self.fps > 0 and math.isfinite(self.fps)):
            # inf would put every frame at 0 s: the tracker would publish nothing
            raise OptionError("fps", f"fps must be a finite frame rate > 0 (Hz), got {self.fps}")


def resolve_device(device: Any, option: str = "device") -> torch.device:
    """``torch.device`` of ``device``; ``OptionError`` (named ``option``) when it is not a device,
    names CUDA on a machine without it, or is one this process cannot allocate on
    (``_checks.check_device``)."""
    import torch

    name = str(device)
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise OptionError(option, f"{option} {name}: CUDA is not available on this machine (use cpu)")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise OptionError(option, f"{option}: expected cpu or cuda, got {name!r}") from None
    from .._checks import check_device

    try:  # a device torch names but cannot use here (mps off a Mac, cuda:3 on a one-GPU machine)
        return check_device(dev, option)
    except ValueError as exc:
        raise OptionError(option, str(exc)) from None


@contextlib.contextmanager
def progress_bar(progress: Optional[bool], total: int, desc: str, unit: str) -> Iterator[Any]:
    """A tqdm bar on stderr for ``total`` ``unit``s (None when ``progress`` is False), closed on
    leaving the block. ``progress=None`` shows it only on a terminal."""
    if progress is False:
        yield None
        return
    import shutil
    import sys

    from tqdm import tqdm

    # a pty that reports a 0 x 0 size makes tqdm hide the bar: fall back to a usual size
    size = shutil.get_terminal_size(FALLBACK_TERMINAL)
    bar = tqdm(total=total, unit=unit, desc=desc, disable=None if progress is None else False, file=sys.stderr,
               ncols=min(MAX_BAR_COLUMNS, size.columns), nrows=size.lines, leave=False)
    try:
        yield bar
    finally:
        bar.close()


def pad_ragged(items: Sequence[torch.Tensor], *, min_length: int = 0, device: Any = None
               ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Stack ``B`` tensors of different lengths ``(N_b, ...)`` into one zero-padded
    ``(B, N, ...)`` tensor and its ``(B, N)`` bool ``valid`` mask, ``N = max(N_b, min_length)``.

    The padded tensor has the dtype and trailing shape of ``items[0]`` and lives on ``device``
    (default: ``items[0]``'s); ``items`` must not be empty.
    """
    import torch

    if not items:
        raise ValueError("pad_ragged: no tensors given")
    first = items[0]
    dev = first.device if device is None else device
    n = max(min_length, max(int(x.shape[0]) for x in items))
    out = torch.zeros((len(items), n, *first.shape[1:]), dtype=first.dtype, device=dev)
    valid = torch.zeros(len(items), n, dtype=torch.bool, device=dev)
    for i, x in enumerate(items):  # one copy per item (image or keyframe), not per element
        out[i, : x.shape[0]] = x
        valid[i, : x.shape[0]] = True
    return out, valid
