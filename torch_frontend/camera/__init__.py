"""camodocal camera models (``liftProjective`` / ``spaceToPlane``) as batched, differentiable torch modules.

Models: ``PinholeCamera`` (``PINHOLE``), ``PinholeFullCamera`` (``PINHOLE_FULL``), ``MeiCamera``
(``MEI``), ``KannalaBrandtCamera`` (``KANNALA_BRANDT``), ``ScaramuzzaCamera`` (``scaramuzza``); all
derive from ``CameraModel`` (``lift``, ``project``, ``undistort``, ``params_dict``, ``from_params``).
``camera_from_config`` builds one from a camodocal/VINS YAML parsed by
``torch_frontend.opencv_yaml.read_opencv_yaml``. See ``base.py`` for the shared conventions.
``CameraBatch`` (``batch.py``) holds B per-stream cameras (any mix of models) with a leading stream
dimension, usable as a tracker's camera.
"""

from .base import CameraModel
from .batch import CameraBatch
from .factory import MODELS, camera_from_config
from .kannala_brandt import KannalaBrandtCamera
from .mei import MeiCamera
from .pinhole import PinholeCamera, PinholeFullCamera
from .scaramuzza import ScaramuzzaCamera

__all__ = [
    "CameraModel",
    "CameraBatch",
    "PinholeCamera",
    "PinholeFullCamera",
    "MeiCamera",
    "KannalaBrandtCamera",
    "ScaramuzzaCamera",
    "camera_from_config",
    "MODELS",
]
