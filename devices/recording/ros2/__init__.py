"""ROS 2 bags of a session's scenes (rosbag2 directory, MCAP storage, CDR messages; ADR 0020)."""

from cellcal.devices.recording.ros2.bag import BAG_VERSION, TOPICS, Ros2BagWriter
from cellcal.devices.recording.ros2.messages import Ros2Messages, typestore
from cellcal.devices.recording.ros2.static import launch_snippet, urdf_joint

__all__ = ["BAG_VERSION", "TOPICS", "Ros2BagWriter", "Ros2Messages", "launch_snippet", "typestore", "urdf_joint"]
