"""Robot motion: BotMotion tasks performed by a behaviour stack on an ARCOS robot (Pioneer, AmigoBot)."""

from erni.plugins.motion.driver import ArcosDriver, LinkError, RobotInfo, RobotState
from erni.plugins.motion.plugin import MotionSettings, RobotMotionControl, pose_of
from erni.plugins.motion.resource import RobotMotionResource, TaskUpdate
from erni.plugins.motion.robots import MODELS, ModelSpec, RobotModel, lookup, model_spec, resolve_model

__all__ = [
    "ArcosDriver", "LinkError", "MODELS", "ModelSpec", "MotionSettings", "RobotInfo", "RobotModel",
    "RobotMotionControl", "RobotMotionResource", "RobotState", "TaskUpdate", "lookup", "model_spec", "pose_of",
    "resolve_model",
]
