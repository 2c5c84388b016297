"""librealsense's rosbag layout (file version 4), shared by the bag player and the bag writer: topic
names, the message types rosbags must be told about, and the stream model (intrinsics, distortion,
extrinsic to the reference stream) as the bag stores it."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from configs.lens import DISTORTION_MODELS  # noqa: F401 - the bag's model names, read by bag.py
from drivers.interfaces import Intrinsics

FILE_VERSION = 4
#: librealsense's default depth unit (1 mm); a recording states its own in the Depth_Units option.
DEPTH_UNIT_M = 0.001
IMAGE_TOPIC = re.compile(r"^/device_(\d+)/sensor_(\d+)/(Depth|Color)_(\d+)/image/data$")
DEPTH_STREAM = "/device_0/sensor_0/Depth_0"
COLOR_STREAM = "/device_0/sensor_1/Color_0"

STREAM_INFO_MSG = """uint32 fps
string encoding
bool is_recommended
"""



def typestore():
    """ROS1 Noetic types plus realsense_msgs/StreamInfo."""
    try:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    except ImportError as e:
        raise ImportError("reading or writing a .bag needs the 'rosbags' package (pip install rosbags)") from e
    store = get_typestore(Stores.ROS1_NOETIC)
    store.register(get_types_from_msg(STREAM_INFO_MSG, "realsense_msgs/msg/StreamInfo"))
    return store


@dataclass(frozen=True)
class StreamModel:
    """One image stream as the bag describes it: its intrinsics (with the librealsense distortion model
    and its five coefficients), and the extrinsic from the reference stream to this stream
    (``p_stream = R @ p_ref + t``, librealsense's rs2_extrinsics)."""

    intrinsics: Intrinsics
    R: np.ndarray | None = None  # (3, 3); None = identity
    t: np.ndarray | None = None  # (3,) metres; None = zero

    @property
    def model(self) -> str:
        return self.intrinsics.model

    @property
    def coeffs(self) -> tuple[float, ...]:
        return self.intrinsics.coeffs

    @property
    def distorted(self) -> bool:
        return self.intrinsics.distorted

    def from_reference(self) -> np.ndarray:
        """4x4 transform taking reference-stream coordinates to this stream's."""
        T = np.eye(4)
        if self.R is not None:
            T[:3, :3] = self.R
        if self.t is not None:
            T[:3, 3] = self.t
        return T


def quat_to_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """Unit quaternion (as librealsense's rot2quat writes it) to a rotation matrix."""
    from scipy.spatial.transform import Rotation

    q = np.array([x, y, z, w], dtype=np.float64)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"extrinsic rotation is not a quaternion: {q.tolist()}")
    return Rotation.from_quat(q / n).as_matrix()


def matrix_to_quat(R: np.ndarray) -> tuple[float, float, float, float]:
    """Rotation matrix to (x, y, z, w), for the writer."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    return float(x), float(y), float(z), float(w)
