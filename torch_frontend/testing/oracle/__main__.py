"""``python -m torch_frontend.testing.oracle [VINS-Mono config]``: the Mono oracle over the
package's EuRoC sample frames, one table row per frame (default config: the source checkout's
``configs/euroc.yaml``; ``configs/`` is not installed with the package)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2

from .._photo import PHOTO_DIR
from .mono import OracleMonoTracker
from .vins_config import cfg_from_vins_yaml


def main(argv: list) -> None:
    cam0 = sorted(PHOTO_DIR.glob("*.png"))
    # default: the source checkout's EuRoC config (configs/ is not installed with the package)
    cfg_path = Path(argv[0]) if argv else Path(__file__).resolve().parents[3] / "configs" / "euroc.yaml"
    cfg = cfg_from_vins_yaml(cfg_path)
    frames = [(int(p.stem) / 1e9, cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)) for p in cam0]
    tr = OracleMonoTracker(cfg)
    print("| frame | tracked | pub | sent | N | msg (cnt>1) | lk lost | F rej | mask pruned | new | ms |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for k, (t, img) in enumerate(frames):
        t0 = time.perf_counter()
        r = tr.process(img, t)
        ms = 1e3 * (time.perf_counter() - t0)
        print(f"| {k} | {int(r['tracked'])} | {int(r['pub_this_frame'])} | {int(r['sent'])} | {len(r['ids'])} "
              f"| {int(r['published_mask'].sum())} | {r['n_lk_lost']} | {r['n_f_rejected']} "
              f"| {r['n_mask_pruned']} | {r['n_new']} | {ms:.1f} |")


if __name__ == "__main__":
    main(sys.argv[1:])
