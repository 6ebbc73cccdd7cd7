"""The house plan: the layers of ``torch_frontend``, bottom to top (checked by
``tests/test_import_layers.py``, shown in the README's "Layout" table)."""

from __future__ import annotations

from typing import List, Tuple

PACKAGE = "torch_frontend"

# The layers, bottom to top. A module may import its own layer and the layers below it, never one
# above. Entries are modules or packages of torch_frontend (a package holds its submodules); "" is
# the package's own __init__ (the lazy facade over everything).
LAYERS: List[Tuple[str, Tuple[str, ...]]] = [
    # exceptions, the lazy-name helper, atomic file writes, compiler marks, the one cache helper, the
    # autodiff helpers: no torch_frontend imports
    ("base", ("errors", "_lazy", "_atomic", "_compiler", "_cache", "_autodiff")),
    # the OpenCV FileStorage reader (numpy + yaml), argument checks, rotations/quaternions,
    # polynomial roots (the cubic of Lambda Twist P3P)
    ("readers and maths", ("opencv_yaml", "_checks", "geometry", "polynomial")),
    # camodocal camera models; trajectory files, alignment and ATE
    ("models", ("camera", "trajectory")),
    # VINS config files and sensor.yaml (torch-free; builds cameras on demand); VINS configs from
    # Kalibr / camera_info calibration files
    ("config", ("config", "calibration")),
    # image-sequence readers and the MultiStream batcher
    ("datasets", ("io",)),
    # the image kernels of the front end, and the one room of their CPU tuning
    ("kernels", ("_tuning", "fused", "equalize", "pyramid", "corners", "masks", "lk", "ransac")),
    # the front end: one pure step over the feature table, and the FeatureTracker around it
    ("front end", ("tracker",)),
    # training through the front end: nn.Module wrappers, tracking losses, the soft status
    ("learning", ("learn",)),
    # the back end: place recognition, verification, the pose graph
    ("back end", ("loop",)),
    # the references: the OpenCV oracle pipeline and the synthetic test beds
    ("references", ("testing",)),
    # run outputs and drawing
    ("writers", ("outputs", "viz")),
    # many processes: sharding, the ranks' coordination, k-medians over ranks (torch.distributed)
    ("distributed", ("distributed",)),
    # what users run: the pipelines, the CLI, the package's lazy facade
    ("what users run", ("pipelines", "cli", "__main__", "")),
]
