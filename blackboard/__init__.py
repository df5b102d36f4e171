"""The agent core: transactional blackboard, plugins, agent host and the task language."""

from typing import TYPE_CHECKING

from erni._lazy import lazy_names as _lazy_names

if TYPE_CHECKING:  # at run time each name is imported when first used (see `__getattr__`)
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

# where each name lives: importing one module of the blackboard (`erni.blackboard.tasks`, as a
# command line sending a task does) imports this package first, and with it none of the others
_HOMES = {
    "erni.blackboard.agent": ("Agent",),
    "erni.blackboard.blackboard": ("Blackboard", "Predicate", "Subscription", "Transaction"),
    "erni.blackboard.clock": ("Clock",),
    "erni.blackboard.errors": ("ConfigError", "ErniError", "NetworkError", "NotFoundError", "PluginError", "TaskError",
                               "TransactionError", "UsageError"),
    "erni.blackboard.objects": ("BBObject", "new_uid"),
    "erni.blackboard.peer": ("Peer",),
    "erni.blackboard.plugin": ("NoSettings", "Plugin"),
    "erni.blackboard.tasks": ("AllocationResult", "Params", "Task", "TaskState", "language_table",
                              "register_preposition", "register_verb"),
    "erni.blackboard.world": ("Link", "Neighbor", "NetInfo", "Pose", "Position", "Route"),
}

__all__ = [
    "Agent", "AllocationResult", "BBObject", "Blackboard", "Clock", "ConfigError", "ErniError", "Link", "Neighbor",
    "NetInfo", "NetworkError", "NoSettings", "NotFoundError", "Params", "Peer", "Plugin", "PluginError", "Pose",
    "Position", "Predicate", "Route", "Subscription", "Task", "TaskError", "TaskState", "Transaction",
    "TransactionError", "UsageError", "language_table", "new_uid", "register_preposition", "register_verb",
]


__getattr__, __dir__ = _lazy_names(__name__, _HOMES, globals())
