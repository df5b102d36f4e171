"""Moved to `erni.mcap_bounds` (a library the ROS 2 plugins, the motion plugin's ROS 2 base and the logs
share, not a plugin's part); this name stays for the imports that use it and is the same module."""

import sys

from erni import mcap_bounds as _moved
from erni.mcap_bounds import *  # noqa: F403

sys.modules[__name__] = _moved
