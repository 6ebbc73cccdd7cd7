"""Vocabulary files: training one on images (``torch-frontend vocabulary train``) and loading one
in any of the formats VINS and DBoW2 write.

Convention:
    Descriptors are VINS's keyframe descriptors: FAST corners (``loop.fast``) and 256-bit BRIEF
    (``loop.brief``, ``(K, 4)`` int64 per image). A vocabulary file ending in ``.bin`` is VINS's
    binary layout (``brief_k10L6.bin``), anything else the package's ``.npz``
    (``Vocabulary.save``). The file is one output, written atomically (``_atomic.atomic_path``: a
    temporary beside it renamed over it): an interrupted write (SIGINT, SIGTERM from the CLI)
    leaves the previous file, and the next write of that file removes a killed writer's temporary.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Union

from ..errors import ConfigError, DataError
from .common import OptionError, pad_ragged, progress_bar, resolve_device

__all__ = ["VocabularyOptions", "load_vocabulary", "run_vocabulary_train", "vocabulary_images"]

PathLike = Union[str, Path]


@dataclass
class VocabularyOptions:
    """Options of :func:`run_vocabulary_train`.

    Attributes:
        k: branching factor of the vocabulary tree (>= 2; VINS: 10).
        L: depth levels (>= 1; VINS: 6), so at most ``k ** L`` words.
        fast_threshold: FAST intensity threshold (grey levels, 0-255; VINS: 20).
        max_images: use this many images evenly spaced over the sorted list (None: all).
        max_keypoints: keep the strongest FAST corners per image (None: all, as VINS).
        seed: seed of the k-medians++ initialisation (same seed, same vocabulary).
        device: where description and training run (``"cpu"``, ``"cuda"``, a ``torch.device``).
        progress: tqdm bar on stderr (None: only on a terminal); k-medians reports its levels on
            stdout only alongside a visible bar.
        chunk: images of one size described per batched call.
    """

    k: int = 10
    L: int = 6
    fast_threshold: int = 20
    max_images: Optional[int] = None
    max_keypoints: Optional[int] = None
    seed: int = 0
    device: Any = "cpu"
    progress: Optional[bool] = None
    chunk: int = 8

    def check(self) -> None:
        """Raise ``OptionError`` naming the first bad option."""
        if self.k < 2:
            raise OptionError("k", f"k must be >= 2, got {self.k}")
        if self.L < 1:
            raise OptionError("L", f"L must be >= 1, got {self.L}")
        for name in ("max_images", "max_keypoints", "chunk"):
            v = getattr(self, name)
            if v is not None and v < 1:
                raise OptionError(name, f"{name} must be >= 1, got {v}")


def vocabulary_images(inputs: Sequence[PathLike], max_images: Optional[int] = None) -> List[Path]:
    """The image files of ``inputs``: files as given, folders' images sorted by name; with
    ``max_images``, that many evenly spaced over the list.

    Raises:
        DataError: a missing path or a folder without images.
    """
    import numpy as np

    from ..io.frames import IMAGE_SUFFIXES

    files: List[Path] = []
    for raw in inputs:
        p = Path(raw)
        if p.is_dir():
            found = sorted(f for f in p.iterdir()
                           if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith("."))
            if not found:
                raise DataError(f"{p}: no images in folder (looked for {'/'.join(x[1:] for x in IMAGE_SUFFIXES)})")
            files += found
        elif p.is_file():
            files.append(p)
        else:
            raise DataError(f"{p}: no such image file or folder")
    if max_images is not None and max_images < len(files):
        files = [files[int(i)] for i in np.linspace(0, len(files) - 1, max_images).round().astype(int)]
    return files


def _check_out(out: Path) -> None:
    if out.is_dir():
        raise OptionError("out", f"out {out}: is a folder, expected a vocabulary file name")
    if not out.parent.is_dir():
        raise OptionError("out", f"out {out}: folder {out.parent} does not exist")


def _describe_images(files: List[Path], opt: VocabularyOptions, dev, bar, beat=None) -> List[Any]:
    """BRIEF descriptors of every image: per image a ``(K_i, 4)`` int64 tensor on ``dev`` (valid
    descriptors only); images of one size go through ``fast``/``brief`` ``opt.chunk`` at a time
    (every image's descriptors are its own: the chunks do not change them). ``beat``: called per
    chunk (a sharded run's heartbeat)."""
    import numpy as np
    import torch

    from ..io.frames import read_image
    from ..loop import brief, fast

    descs: List[torch.Tensor] = []

    def describe(batch: List[np.ndarray]) -> None:
        img = torch.from_numpy(np.stack(batch)).to(dev)  # (b, H, W) uint8
        pts, _, valid = fast(img, threshold=opt.fast_threshold, max_points=opt.max_keypoints)
        d = brief(img, pts, valid)
        for b in range(d.shape[0]):
            descs.append(d[b][valid[b]])
        if bar is not None:
            bar.update(len(batch))
        if beat is not None:
            beat()

    pending: List[np.ndarray] = []
    for f in files:
        im = read_image(f)
        if pending and (im.shape != pending[0].shape or len(pending) >= opt.chunk):
            describe(pending)
            pending = []
        pending.append(im)
    if pending:
        describe(pending)
    return descs


def run_vocabulary_train(images: Sequence[PathLike], out: PathLike, options: VocabularyOptions | None = None
                         ) -> Dict[str, Any]:
    """Train a BRIEF vocabulary (``loop.Vocabulary.train``, hierarchical k-medians) on the FAST +
    BRIEF descriptors of ``images`` (files and/or folders, see :func:`vocabulary_images`) and save
    it to the file ``out`` (``.bin``: VINS's layout, else ``.npz``).

    Returns:
        a summary dict: ``images``, ``descriptors``, ``words``, ``nodes``, ``k``, ``L``,
        ``seconds`` and ``describe_seconds`` (wall time, s), ``out``, ``device``.

    Raises:
        OptionError: bad options or ``out``; DataError: missing or unreadable images, no corner.
    """
    import torch

    from ..loop import Vocabulary

    opt = VocabularyOptions() if options is None else options
    opt.check()
    out = Path(out)
    _check_out(out)
    dev = resolve_device(opt.device)
    files = vocabulary_images(images, opt.max_images)
    with progress_bar(opt.progress, len(files), "describing", "image") as bar:
        t0 = time.perf_counter()
        descs = _describe_images(files, opt, dev, bar)
        # Vocabulary.train reports its levels on stdout: only alongside a visible progress bar
        verbose = bar is not None and not bar.disable
    n_desc = sum(int(d.shape[0]) for d in descs)
    if n_desc == 0:
        raise DataError(f"no FAST corners (threshold {opt.fast_threshold}) in any of the {len(files)} images")
    desc, valid = pad_ragged(descs, device=dev)
    t_desc = time.perf_counter() - t0
    gen = torch.Generator(device=dev).manual_seed(int(opt.seed))
    voc = Vocabulary.train(desc, valid, k=opt.k, L=opt.L, generator=gen, progress=verbose)
    if out.suffix.lower() == ".bin":
        voc.save_vins_bin(out)
    else:
        voc.save(out)
    seconds = time.perf_counter() - t0
    return {"images": len(descs), "descriptors": n_desc, "words": int(voc.num_words), "nodes": int(voc.num_nodes),
            "k": opt.k, "L": opt.L, "seconds": round(seconds, 3), "describe_seconds": round(t_desc, 3),
            "out": str(out), "device": str(dev)}


def load_vocabulary(path: PathLike):
    """A ``Vocabulary`` from the package's ``.npz`` (``Vocabulary.save``), VINS's binary
    ``brief_k10L6.bin`` or a DBoW2 YAML, told apart by their content.

    Raises:
        DataError: a missing file, or one in none of these formats (one line naming the file).
    """
    from ..loop.vocabulary import Vocabulary

    p = Path(path)
    if not p.is_file():
        raise DataError(f"{p}: vocabulary file not found" if not p.exists() else f"{p}: not a file (expected a vocabulary)")
    with open(p, "rb") as fh:
        head = fh.read(16)
    try:
        if head.startswith(b"PK"):  # a zip: numpy .npz
            return Vocabulary.load(p)
        if head.lstrip().startswith((b"%YAML", b"vocabulary")) or p.suffix.lower() in (".yml", ".yaml"):
            return Vocabulary.load_dbow2_yaml(p)
        return Vocabulary.load_vins_bin(p)
    except (ConfigError, DataError, ValueError, KeyError, OSError) as exc:
        detail = str(exc)
        if detail.startswith(str(p)):
            detail = detail[len(str(p)):].lstrip(": ")
        raise DataError(f"{p}: not a vocabulary in a known format (the package's .npz, VINS's brief_k10L6.bin "
                        f"or a DBoW2 YAML): {detail}") from None
