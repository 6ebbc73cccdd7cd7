"""KITTI sequences: the odometry layout and the raw (``*_sync``) layout, one camera, no config file.

Convention:
    * **Odometry** (``dataset/sequences/NN``): ``image_0/`` .. ``image_3/`` (``000000.png``, ...),
      ``calib.txt`` (lines ``P0: ...`` .. ``P3: ...`` and ``Tr: ...``, 12 numbers each: the 3×4
      projection matrices of the rectified cameras, and velodyne-to-camera-0) and ``times.txt``
      (one time in seconds per image, line k for image k).
    * **Raw** (``2011_09_26/2011_09_26_drive_0001_sync``): ``image_00/data/*.png`` with
      ``image_00/timestamps.txt`` (``2011-09-26 13:02:25.964389445`` per line, read as UTC) and
      ``calib_cam_to_cam.txt`` in the drive folder or its parent (``P_rect_00: ...``,
      ``S_rect_00: W H``). The ``*_sync`` images are rectified, as the odometry ones.
    * Camera ``cam0`` .. ``cam3`` (``--camera``; default ``cam0``: the left grey camera) is
      ``image_<i>`` / ``image_0<i>`` with ``P<i>`` / ``P_rect_0<i>``: a ``PINHOLE`` camera with
      ``fx fy cx cy`` of the projection matrix and zero distortion, of the size of the first
      image (raw: ``S_rect_0<i>``). The colour cameras 2, 3 are made grey by the reader.
    * Body frame = camera 0 (KITTI has no IMU; its ground-truth poses are camera 0's):
      ``body_T_cam0`` of :func:`kitti_config` is camera ``i``'s pose in camera 0's frame,
      ``[I | -K⁻¹ P<i>[:, 3]]`` (identity for ``cam0``; ``cam1``: ``+baseline`` along x).
    * :func:`kitti_config` gives VINS-Mono's front-end settings (``config.EUROC_FRONTEND``: the
      defaults of its ``feature_tracker``), stated in ``TrackerConfig.origin``; a VINS config given
      for a KITTI input replaces them with its front-end keys (:func:`kitti_config`'s ``base``),
      the camera always being calib.txt's.
    * Stream name: the sequence folder's name (``00``; raw: ``2011_09_26_drive_0001_sync``), and
      the camera when not ``cam0`` (``00/cam1``).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Tuple, Union

import numpy as np

from ..config import EUROC_FRONTEND, TrackerConfig
from .frames import IMAGE_SUFFIXES, DataError, Sequence, _Item, read_image

PathLike = Union[str, Path]
CAMERAS = ("cam0", "cam1", "cam2", "cam3")
#: TrackerConfig fields a VINS config given for a KITTI input sets (when its file has the key)
FRONTEND_FIELDS = ("max_cnt", "min_dist", "freq", "F_threshold", "F_method", "show_track", "equalize",
                   "fisheye", "flow_back")
ORIGIN = "KITTI {calib} {P}; VINS-Mono front-end defaults"


@dataclasses.dataclass
class KittiLayout:
    """Where a KITTI sequence's files are (:func:`find_kitti`)."""

    root: Path
    kind: str  # "odometry" or "raw"
    camera: int
    image_dir: Path
    calib: Path
    times: Path


def _camera_index(camera: str) -> int:
    if camera not in CAMERAS:
        raise DataError(f"`camera`: expected one of {', '.join(CAMERAS)} for a KITTI sequence "
                        f"(image_0 .. image_3), got {camera!r}")
    return CAMERAS.index(camera)


def find_kitti(root: PathLike, camera: str = "cam0") -> KittiLayout:
    """The files of the KITTI sequence ``root`` (odometry ``sequences/NN`` or a raw ``*_sync``
    drive folder) for ``camera``, or ``DataError`` naming what is missing."""
    r = Path(root)
    if not r.exists():
        raise DataError(f"{r}: folder not found")
    if not r.is_dir():
        raise DataError(f"{r}: not a folder (expected a KITTI sequence folder, e.g. dataset/sequences/00)")
    i = _camera_index(camera)
    if (r / "calib.txt").is_file() or (r / f"image_{i}").is_dir():
        for need in (f"image_{i}", "calib.txt", "times.txt"):
            if not (r / need).exists():
                raise DataError(f"{r}: KITTI odometry sequence without {need} (expected image_{i}/, calib.txt "
                                f"and times.txt)")
        return KittiLayout(r, "odometry", i, r / f"image_{i}", r / "calib.txt", r / "times.txt")
    cam = r / f"image_0{i}"
    if cam.is_dir():
        calib = next((d / "calib_cam_to_cam.txt" for d in (r, r.parent) if (d / "calib_cam_to_cam.txt").is_file()),
                     None)
        if calib is None:
            raise DataError(f"{r}: KITTI raw drive without calib_cam_to_cam.txt (looked here and in {r.parent})")
        if not (cam / "timestamps.txt").is_file():
            raise DataError(f"{cam}: KITTI raw camera folder without timestamps.txt")
        return KittiLayout(r, "raw", i, cam / "data" if (cam / "data").is_dir() else cam, calib,
                           cam / "timestamps.txt")
    inside = sorted(d.name for d in r.iterdir() if d.is_dir() and ((d / "calib.txt").is_file()
                                                                     or (d / f"image_0{i}").is_dir()))
    hint = f"; it holds sequences: give one of them, e.g. {r / inside[0]}" if inside else ""
    raise DataError(f"{r}: not a KITTI sequence (no calib.txt with image_{i}/ (odometry: sequences/NN) nor "
                    f"image_0{i}/ (raw: a *_sync drive folder)){hint}")


def read_calib(path: PathLike) -> Dict[str, np.ndarray]:
    """``{key: values}`` of a KITTI calibration file (``key: v1 v2 ...`` lines; the date line of
    ``calib_cam_to_cam.txt`` and other non-numeric values are left out)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise DataError(f"{p}: cannot read: {exc.strerror or exc}") from None
    out: Dict[str, np.ndarray] = {}
    for line in text.splitlines():
        key, sep, rest = line.partition(":")
        if not sep:
            continue
        try:
            out[key.strip()] = np.asarray([float(x) for x in rest.split()], dtype=np.float64)
        except ValueError:
            continue
    return out


def projection(layout: KittiLayout) -> Tuple[np.ndarray, Optional[Tuple[int, int]], str]:
    """``(P (3, 4), (W, H) or None, key)`` of the layout's camera from its calibration file."""
    cal = read_calib(layout.calib)
    i = layout.camera
    key = f"P{i}" if layout.kind == "odometry" else f"P_rect_0{i}"
    P = cal.get(key)
    if P is None or P.size != 12:
        got = "missing" if P is None else f"{P.size} numbers"
        raise DataError(f"{layout.calib}: {key}: expected 12 numbers (the 3x4 projection matrix), got {got}")
    size = None
    if layout.kind == "raw":
        S = cal.get(f"S_rect_0{i}")
        if S is not None and S.size == 2:
            size = (int(round(S[0])), int(round(S[1])))
    P = P.reshape(3, 4)
    if not (np.isfinite(P).all() and P[0, 0] > 0 and P[1, 1] > 0):
        raise DataError(f"{layout.calib}: {key}: expected a projection matrix with fx, fy > 0, got {P.tolist()}")
    return P, size, key


def _read_times(layout: KittiLayout) -> List[int]:
    """Integer nanoseconds of every line of ``times.txt`` (seconds) / ``timestamps.txt`` (dates)."""
    p = layout.times
    try:
        lines = [s.strip() for s in p.read_text(encoding="utf-8", errors="replace").splitlines()]
    except OSError as exc:
        raise DataError(f"{p}: cannot read: {exc.strerror or exc}") from None
    out: List[int] = []
    for n, s in enumerate(lines, 1):
        if not s:
            continue
        try:
            if layout.kind == "odometry":
                out.append(int((Decimal(s) * 1_000_000_000).to_integral_value()))
            else:
                day, _, frac = s.partition(".")
                t = _dt.datetime.strptime(day, "%Y-%m-%d %H:%M:%S").replace(tzinfo=_dt.timezone.utc)
                out.append(int(t.timestamp()) * 1_000_000_000 + int((frac + "000000000")[:9] if frac else 0))
        except (InvalidOperation, ValueError):
            what = "a time in seconds" if layout.kind == "odometry" else "a date 'YYYY-MM-DD HH:MM:SS.fffffffff'"
            raise DataError(f"{p}:{n}: expected {what}, got {s[:60]!r}") from None
    return out


class KittiSequence(Sequence):
    """Frames of one camera of a KITTI odometry sequence or raw drive (module docstring).

    Args:
        root: ``dataset/sequences/NN`` or a raw ``*_sync`` drive folder.
        camera: ``"cam0"`` (default: left grey) .. ``"cam3"``.
        skip_bad: skip unreadable frames instead of raising.

    Raises:
        DataError: a missing folder or file, a malformed time, no images, or a times file whose
            line count is not the number of images.
    """

    kind = "kitti"

    def __init__(self, root: PathLike, camera: str = "cam0", skip_bad: bool = False):
        self.layout = find_kitti(root, camera)
        name = self.layout.root.resolve().name + ("" if camera == "cam0" else f"/{camera}")
        super().__init__(name, skip_bad)
        files = sorted(f for f in self.layout.image_dir.iterdir()
                       if f.suffix.lower() in IMAGE_SUFFIXES and not f.name.startswith("."))
        if not files:
            raise DataError(f"{self.layout.image_dir}: empty sequence (no images)")
        stamps = _read_times(self.layout)
        if len(stamps) != len(files):
            raise DataError(f"{self.layout.times}: {len(stamps)} times for {len(files)} images in "
                            f"{self.layout.image_dir} (line k is image k's time)")
        self.entries: List[Tuple[int, Path]] = list(zip(stamps, files))

    def __len__(self) -> int:
        return len(self.entries)

    def _items(self) -> Iterator[_Item]:
        for i, (stamp, path) in enumerate(self.entries):
            yield _Item(i, stamp, str(path), lambda p=path: read_image(p))

    @property
    def times(self) -> np.ndarray:
        """``(N,)`` float64 seconds of the frames (KITTI poses' line k is at ``times[k]``)."""
        from .multistream import ns_to_seconds

        return ns_to_seconds(np.asarray([s for s, _ in self.entries], dtype=np.int64))


def kitti_config(root: PathLike, camera: str = "cam0", base: Optional[TrackerConfig] = None) -> TrackerConfig:
    """The ``TrackerConfig`` of a KITTI sequence's camera (module docstring): ``PINHOLE`` from the
    projection matrix, zero distortion, the first image's size; VINS-Mono's front-end settings
    (``EUROC_FRONTEND``), or ``base``'s front-end keys (a config given for the input: those its
    file sets, every ``FRONTEND_FIELDS`` of one built in code) and its extrinsic keys.

    Raises:
        DataError: missing files, a bad projection matrix, an unreadable first image.
    """
    from ..camera import PinholeCamera

    layout = find_kitti(root, camera)
    P, size, key = projection(layout)
    if size is None:
        first = next((f for f in sorted(layout.image_dir.iterdir()) if f.suffix.lower() in IMAGE_SUFFIXES), None)
        if first is None:
            raise DataError(f"{layout.image_dir}: empty sequence (no images)")
        h, w = read_image(first).shape[:2]
        size = (int(w), int(h))
    fx, fy, cx, cy = float(P[0, 0]), float(P[1, 1]), float(P[0, 2]), float(P[1, 2])
    cam = PinholeCamera(0.0, 0.0, 0.0, 0.0, fx, fy, cx, cy, width=size[0], height=size[1],
                        camera_name=f"kitti_{layout.root.name}_{CAMERAS[layout.camera]}")
    # camera i's centre in camera 0's frame: P_i = K [I | t_i] with x_i = x_0 + t_i
    K = P[:, :3]
    T = np.eye(4)
    T[:3, 3] = -np.linalg.solve(K, P[:, 3])
    settings = dict(EUROC_FRONTEND)
    origin = ORIGIN.format(calib=layout.calib.name, P=key)
    raw: Dict = {}
    if base is not None:
        given = [f for f in FRONTEND_FIELDS if f in base.raw] if base.raw else list(FRONTEND_FIELDS)
        settings.update({f: getattr(base, f) for f in given})
        raw = {k: v for k, v in base.raw.items() if k in ("extrinsicRotation", "extrinsicTranslation")}
        if base.body_T_cam0 is not None:
            T = np.asarray(base.body_T_cam0, dtype=np.float64)
        origin = f"KITTI {layout.calib.name} {key}; front end of {base.path}" if given else origin
    return TrackerConfig(path=str(layout.calib), flavour="mono", image_width=size[0], image_height=size[1],
                         camera=cam, body_T_cam0=T, raw=raw, origin=origin, **settings)


__all__ = ["CAMERAS", "FRONTEND_FIELDS", "KittiLayout", "KittiSequence", "find_kitti", "kitti_config",
           "projection", "read_calib"]
