"""Intel RealSense D435 through Open3D's RealSense support (no pyrealsense2): the live camera
(`sensor.RealSenseCamera`), bag playback (`bag.RealSenseBag`), both ``RGBDCamera``s, and a .bag writer
(`bag_writer`) for fixtures and twin exports. Never imports planners/, cellctl/ or sim/."""

from drivers.realsense.bag import RealSenseBag, read_bag_index
from drivers.realsense.config import CameraConfigError, RealSenseConfig, load_realsense_config
from drivers.realsense.sensor import DeviceInfo, RealSenseCamera, check_devices, list_devices, open_camera

__all__ = ["CameraConfigError", "DeviceInfo", "RealSenseBag", "RealSenseCamera", "RealSenseConfig",
           "check_devices", "list_devices", "load_realsense_config", "open_camera", "read_bag_index"]
