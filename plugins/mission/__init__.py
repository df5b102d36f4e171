"""MissionControl (paper 004, 4.1-4.2.3): two-tier tasking, network-aware behaviour, deployment strategies."""

from plugins.mission.plugin import MissionControl, MissionSettings
from plugins.mission.team import Territory

__all__ = ["MissionControl", "MissionSettings", "Territory"]
