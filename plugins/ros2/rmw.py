"""Moved to `erni.ros2_rmw` (a library the ROS 2 plugins, the motion plugin's ROS 2 base and the logs
share, not a plugin's part); this name stays for the imports that use it and is the same module."""

import sys

from erni import ros2_rmw as _moved
from erni.ros2_rmw import *  # noqa: F403

sys.modules[__name__] = _moved
