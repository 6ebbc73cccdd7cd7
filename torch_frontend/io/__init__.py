"""Readers: OpenCV FileStorage YAML, datasets (EuRoC/TUM-VI ASL folders, image folders, ROS bags)."""

from .._lazy import lazy_exports
from .euroc import EurocSequence, camera_from_sensor_yaml, config_from_sensor_yaml, euroc_config
from .folder import ImageFolderSequence
from .frames import DataError, Frame, Sequence, decode_image, read_image
from .fsyaml import read_opencv_yaml
from .rosbag import RosbagSequence, list_image_topics
from .sources import open_sequence

_TRAJECTORY = ("Trajectory", "read_trajectory", "write_tum", "write_vins_csv", "interpolate", "covered",
               "associate", "align_se3", "ate_rmse", "add_drift")

# MultiStream/Batch need torch; importing them lazily keeps ``torch_frontend.config`` (which imports
# ``io.fsyaml``, hence this package) free of a torch import
__getattr__, __dir__ = lazy_exports(
    __name__, {"MultiStream": "multistream", "Batch": "multistream", **{n: "trajectory" for n in _TRAJECTORY}})

__all__ = [*_TRAJECTORY,
    "read_opencv_yaml",
    "DataError",
    "Frame",
    "Sequence",
    "read_image",
    "decode_image",
    "EurocSequence",
    "ImageFolderSequence",
    "RosbagSequence",
    "list_image_topics",
    "camera_from_sensor_yaml",
    "config_from_sensor_yaml",
    "euroc_config",
    "MultiStream",
    "Batch",
    "open_sequence",
]
