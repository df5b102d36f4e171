"""The agent core: transactional blackboard, plugins, agent host and the task language."""

from erni.blackboard.agent import Agent
from erni.blackboard.blackboard import Blackboard, Predicate, Subscription, Transaction
from erni.blackboard.clock import Clock
from erni.blackboard.errors import (
    ConfigError,
    ErniError,
    NetworkError,
    NotFoundError,
    PluginError,
    TaskError,
    TransactionError,
    UsageError,
)
from erni.blackboard.objects import BBObject, new_uid
from erni.blackboard.peer import Peer
from erni.blackboard.plugin import NoSettings, Plugin
from erni.blackboard.tasks import (
    AllocationResult,
    Params,
    Task,
    TaskState,
    language_table,
    register_preposition,
    register_verb,
)
from erni.blackboard.world import Link, Neighbor, NetInfo, Pose, Position, Route

__all__ = [
    "Agent", "AllocationResult", "BBObject", "Blackboard", "Clock", "ConfigError", "ErniError", "Link", "Neighbor",
    "NetInfo", "NetworkError", "NoSettings", "NotFoundError", "Params", "Peer", "Plugin", "PluginError", "Pose",
    "Position", "Predicate", "Route", "Subscription", "Task", "TaskError", "TaskState", "Transaction",
    "TransactionError", "UsageError", "language_table", "new_uid", "register_preposition", "register_verb",
]
