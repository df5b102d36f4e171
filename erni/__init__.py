"""ERNI: teams of mobile robots cooperating over wireless ad-hoc networks.

Everything a plugin author needs is importable from here::

    from erni import Plugin, Task, TaskState, GotoParams

The parts: `erni.blackboard` (agent core and task language), `erni.transport` (messages between
agents), `erni.plugins` (motion, mobinet, mission, ui), `erni.strategies` (pure deployment
strategies), `erni.netgraph` (graph helpers), `erni.sim` (the simulator, never imported by an
agent's runtime), and the `erni` command line.
"""

import os as _os
from typing import TYPE_CHECKING

from erni._lazy import lazy_names as _lazy_names


def _find_the_source_folders() -> None:
    """In a checkout without symbolic links (a zip, Windows, `core.symlinks=false`) `erni/blackboard`
    is a small text file naming `../blackboard`: look for the design card's folders beside `erni/`
    then, as the links would. An installed copy holds the folders themselves and never gets here."""
    here = _os.path.dirname(_os.path.realpath(__file__))  # os.path, not pathlib: `import erni` stays light
    if _os.path.isdir(_os.path.join(here, "blackboard")):
        return
    root = _os.path.dirname(here)
    if not _os.path.isfile(_os.path.join(root, "blackboard", "__init__.py")):
        raise ImportError(f"erni: {_os.path.join(here, 'blackboard')} is not a folder and no blackboard/ package "
                          f"lies beside {here}; reinstall ERNI (pip install erni) or check out the whole repository")
    __path__.append(root)


_find_the_source_folders()

if TYPE_CHECKING:  # what a type checker and an IDE see; at run time each name is imported when first used
    from erni.blackboard.agent import Agent
    from erni.blackboard.blackboard import Predicate, Subscription, Transaction
    from erni.blackboard.errors import (
        ConfigError,
        ErniError,
        NetworkError,
        NotFoundError,
        PluginError,
        TaskError,
        TransactionError,
        UsageError,
        describe_validation,
    )
    from erni.blackboard.objects import BBObject, new_uid
    from erni.blackboard.plugin import NoSettings, Plugin
    from erni.blackboard.schemas import FloorPlan, Peer
    from erni.blackboard.tasks import (
        AllocationResult,
        AvoidParams,
        BackwardParams,
        CancelParams,
        ClearParams,
        DistanceParams,
        ForwardParams,
        GotoParams,
        Link,
        LinkQualityParams,
        Neighbor,
        NeighborListParams,
        NetInfo,
        NodePositionParams,
        NoParams,
        Params,
        PathCostParams,
        PatrolParams,
        Pose,
        Position,
        RandomWalkParams,
        RelayParams,
        Route,
        SayParams,
        SpreadParams,
        StopParams,
        Task,
        TaskState,
        TeleportParams,
        TopologyParams,
        TurnParams,
        VelocityParams,
        WatchParams,
        WidepParams,
        register_preposition,
        register_verb,
    )

# where each public name lives: `import erni` imports none of them (a command line that sends one
# stop starts in a fraction of a second); `erni.Task` or `from erni import Task` imports its module then
_HOMES = {
    "erni.blackboard.agent": ("Agent",),
    "erni.blackboard.blackboard": ("Predicate", "Subscription", "Transaction"),
    "erni.blackboard.errors": ("ConfigError", "ErniError", "NetworkError", "NotFoundError", "PluginError", "TaskError",
                               "TransactionError", "UsageError", "describe_validation"),
    "erni.blackboard.objects": ("BBObject", "new_uid"),
    "erni.blackboard.plugin": ("NoSettings", "Plugin"),
    "erni.blackboard.schemas": ("FloorPlan", "Peer"),
    "erni.blackboard.tasks": (
        "AllocationResult", "AvoidParams", "BackwardParams", "CancelParams", "ClearParams", "DistanceParams",
        "ForwardParams", "GotoParams", "Link", "LinkQualityParams", "Neighbor", "NeighborListParams", "NetInfo",
        "NodePositionParams", "NoParams", "Params", "PathCostParams", "PatrolParams", "Pose", "Position",
        "RandomWalkParams", "RelayParams", "Route", "SayParams", "SpreadParams", "StopParams", "Task", "TaskState",
        "TeleportParams", "TopologyParams", "TurnParams", "VelocityParams", "WatchParams", "WidepParams",
        "register_preposition", "register_verb"),
}

__version__ = "0.1.0"

__all__ = [
    # writing a plugin
    "Agent", "BBObject", "NoSettings", "Plugin", "Predicate", "Subscription", "Transaction", "new_uid",
    # the task language
    "AllocationResult", "Task", "TaskState", "Params", "register_preposition", "register_verb",
    "AvoidParams", "BackwardParams", "CancelParams", "ClearParams", "DistanceParams", "ForwardParams",
    "GotoParams", "LinkQualityParams", "NeighborListParams", "NoParams", "NodePositionParams", "PathCostParams",
    "PatrolParams", "RandomWalkParams", "RelayParams", "SayParams", "SpreadParams", "StopParams",
    "TeleportParams", "TopologyParams", "TurnParams", "VelocityParams", "WatchParams", "WidepParams",
    # published beside tasks
    "FloorPlan", "Link", "Neighbor", "NetInfo", "Peer", "Pose", "Position", "Route",
    # errors
    "ConfigError", "ErniError", "NetworkError", "NotFoundError", "PluginError", "TaskError",
    "TransactionError", "UsageError", "describe_validation",
]


__getattr__, __dir__ = _lazy_names(__name__, _HOMES, globals())
