"""The agent core: transactional blackboard, plugins, agent host and the task language."""

import importlib as _importlib
from typing import TYPE_CHECKING, Any

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
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}

__all__ = [
    "Agent", "AllocationResult", "BBObject", "Blackboard", "Clock", "ConfigError", "ErniError", "Link", "Neighbor",
    "NetInfo", "NetworkError", "NoSettings", "NotFoundError", "Params", "Peer", "Plugin", "PluginError", "Pose",
    "Position", "Predicate", "Route", "Subscription", "Task", "TaskError", "TaskState", "Transaction",
    "TransactionError", "UsageError", "language_table", "new_uid", "register_preposition", "register_verb",
]


def __getattr__(name: str) -> Any:
    """A name of `__all__`, imported from its module when first asked for; or a module of the package
    not imported yet (`erni.blackboard.agent`)."""
    module = _HOME_OF.get(name)
    if module is not None:
        value = getattr(_importlib.import_module(module), name)
        globals()[name] = value
        return value
    if not name.startswith("__"):
        try:
            return _importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as err:
            if err.name != f"{__name__}.{name}":
                raise
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_HOME_OF))
