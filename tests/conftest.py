"""Shared fixtures: devices, dtypes and data locations.

Tests read real data from the repo's own copies (``torch_frontend/data``, ``tests/data``). Some also
read ``../shared/data`` (beside the repo in CI) and skip, saying so, when it is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "torch_frontend" / "data" / "euroc_mini"
TEST_DATA = REPO / "tests" / "data"
# ../shared (real data and tools beside the repo; TORCH_FRONTEND_SHARED=DIR: elsewhere, or a missing
# folder to run as a fresh clone does)
SHARED = Path(os.environ.get("TORCH_FRONTEND_SHARED") or REPO.parent / "shared")
SHARED_DATA = SHARED / "data"

# One thread for torch and OpenCV in the tests: the suite runs on 2-core machines (CI), where the
# kernels' many small ops slow down by orders of magnitude when threads compete for the cores.
torch.set_num_threads(1)
try:
    import cv2 as _cv2

    _cv2.setNumThreads(1)
except ImportError:  # pragma: no cover
    pass

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
DTYPES = [torch.float32, torch.float64]


def shared_data_or_skip(*parts: str) -> Path:
    """Path under ``../shared/data``; skips the test with a clear reason when it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"../shared/data not found beside the repo (looked for {p}; TORCH_FRONTEND_SHARED=DIR points "
                    f"elsewhere); this test needs it")
    return p


def sample_frames(camera: str = "cam0"):
    """Sorted paths of the repo's sample EuRoC frames for ``camera``."""
    return sorted((SAMPLE / "mav0" / camera / "data").glob("*.png"))


def load_gray(path):
    """(H, W) uint8 numpy array of a grey image."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img is not None, f"cannot read {path}"
    return img


@pytest.fixture(scope="module")
def single_thread():
    """One intra-op thread for a module of many small ops: on a busy 2-core runner OpenMP spin-waits
    made such tests up to 10x slower. Use with ``pytestmark = pytest.mark.usefixtures("single_thread")``."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def ros_skip(why: str):
    """Skip a test that needs ROS 1, saying what is missing; a failure instead under
    ``TORCH_FRONTEND_REQUIRE_ROS=1`` (``make test-all``, CI: ``.ci/run`` installs ROS 1)."""
    import os

    if os.environ.get("TORCH_FRONTEND_REQUIRE_ROS") == "1":
        pytest.fail(f"ROS 1 required (TORCH_FRONTEND_REQUIRE_ROS=1) but missing: {why}")
    pytest.skip(f"ROS 1 missing: {why}")


@pytest.fixture(scope="module")
def ros_master():
    """A private ``roscore`` on a free port for a module (``tests._ros.roscore``): yields the
    environment for the node and the driver (``ROS_MASTER_URI``, ``ROS_HOSTNAME=127.0.0.1``, a
    temporary ``ROS_HOME``), or skips saying what is missing (:func:`ros_skip`)."""
    from . import _ros

    why = _ros.ros_missing()
    if why is not None:
        ros_skip(why)
    with _ros.roscore() as env:
        yield env


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)


@pytest.fixture(params=DTYPES, ids=["f32", "f64"])
def dtype(request):
    return request.param
