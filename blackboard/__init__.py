"""The agent core: transactional blackboard, plugins, agent host and the task language."""

from erni.blackboard.agent import Agent
from erni.blackboard.blackboard import Blackboard, Subscription, Transaction
from erni.blackboard.errors import ConfigError, ErniError, PluginError, TaskError, TransactionError
from erni.blackboard.objects import BBObject, new_uid
from erni.blackboard.plugin import Plugin
from erni.blackboard.tasks import (
    AllocationResult,
    Link,
    Neighbor,
    NetInfo,
    Params,
    Pose,
    Position,
    Route,
    Task,
    TaskState,
    language_table,
    register_preposition,
    register_verb,
)

__all__ = [
    "Agent", "Blackboard", "Plugin", "Subscription", "Transaction",
    "AllocationResult", "BBObject", "ConfigError", "ErniError", "Link", "Neighbor", "NetInfo",
    "Params", "PluginError", "Pose", "Position", "Route", "Task", "TaskError", "TaskState",
    "TransactionError", "language_table", "new_uid", "register_preposition", "register_verb",
]
