"""ERNI in the ROS 2 world: the team's topics over rmw_zenoh (ROS 2 Jazzy), see docs/tutorials/ros2-foxglove.md.

`messages` converts ERNI's objects to ROS 2 messages (rosbags' Jazzy types and CDR), `rmw` speaks
rmw_zenoh's wire on a Zenoh session, `ROS2Plugin` puts both in an agent.
"""

from erni.plugins.ros2.plugin import ROS2Plugin, ROS2Settings

__all__ = ["ROS2Plugin", "ROS2Settings"]
