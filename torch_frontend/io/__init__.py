"""Readers of image sequences: EuRoC/TUM-VI ASL folders, KITTI sequences, image folders, ROS bags, and the
``MultiStream`` batcher.

The OpenCV-YAML reader (``torch_frontend.opencv_yaml``), the ``sensor.yaml`` parser
(``torch_frontend.config``) and the trajectory files (``torch_frontend.trajectory``) live below
this package; their public names are also reachable here (``torch_frontend.io.read_opencv_yaml``,
``torch_frontend.io.add_drift``, ...), imported on first use.
"""

from .._lazy import lazy_exports
from .euroc import EurocSequence, euroc_config
from .feature_bag import FeatureBag, FeatureBagWriter, FeatureMessage, read_feature_bag
from .folder import ImageFolderSequence
from .frames import DataError, Frame, Sequence, decode_image, read_image
from .kitti import KittiSequence, kitti_config
from .rosbag import RosbagSequence, list_image_topics
from .sources import open_sequence

_TRAJECTORY = ("Trajectory", "read_trajectory", "write_tum", "write_vins_csv", "interpolate", "covered",
               "associate", "align_se3", "ate_rmse", "add_drift")

# A leading dot names a module of the parent package (importlib's relative form: ".trajectory"
# is torch_frontend.trajectory). MultiStream/Batch and the trajectories need torch: importing them
# lazily keeps ``import torch_frontend.io`` free of a torch import.
__getattr__, __dir__ = lazy_exports(__name__, {
    "MultiStream": "multistream",
    "Batch": "multistream",
    "read_opencv_yaml": ".opencv_yaml",
    "camera_from_sensor_yaml": ".config",
    "config_from_sensor_yaml": ".config",
    **{n: ".trajectory" for n in _TRAJECTORY},
})

__all__ = [*_TRAJECTORY,
    "read_opencv_yaml",
    "DataError",
    "Frame",
    "Sequence",
    "read_image",
    "decode_image",
    "EurocSequence",
    "ImageFolderSequence",
    "KittiSequence",
    "kitti_config",
    "RosbagSequence",
    "list_image_topics",
    "FeatureBag",
    "FeatureBagWriter",
    "FeatureMessage",
    "read_feature_bag",
    "camera_from_sensor_yaml",
    "config_from_sensor_yaml",
    "euroc_config",
    "MultiStream",
    "Batch",
    "open_sequence",
]
