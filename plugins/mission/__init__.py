"""MissionControl (paper 004, 4.1-4.2.3): two-tier tasking, network-aware behaviour, deployment strategies."""

from erni.plugins.mission.plugin import MissionControl, MissionSettings
from erni.plugins.mission.team import Territory

__all__ = ["MissionControl", "MissionSettings", "Territory"]
