"""ERNI: teams of mobile robots cooperating over wireless ad-hoc networks.

Everything a plugin author needs is importable from here::

    from erni import Plugin, Task, TaskState, GotoParams

The parts: `erni.blackboard` (agent core and task language), `erni.transport` (messages between
agents), `erni.plugins` (motion, mobinet, mission, ui), `erni.strategies` (pure deployment
strategies), `erni.netgraph` (graph helpers), `erni.sim` (the simulator, never imported by an
agent's runtime), and the `erni` command line.
"""

from pathlib import Path as _Path


def _find_the_source_folders() -> None:
    """In a checkout without symbolic links (a zip, Windows, `core.symlinks=false`) `erni/blackboard`
    is a small text file naming `../blackboard`: look for the design card's folders beside `erni/`
    then, as the links would. An installed copy holds the folders themselves and never gets here."""
    here = _Path(__file__).resolve().parent
    if (here / "blackboard").is_dir():
        return
    root = here.parent
    if not (root / "blackboard" / "__init__.py").is_file():
        raise ImportError(f"erni: {here / 'blackboard'} is not a folder and no blackboard/ package lies beside "
                          f"{here}; reinstall ERNI (pip install erni) or check out the whole repository")
    __path__.append(str(root))


_find_the_source_folders()

from erni.blackboard.agent import Agent  # noqa: E402
from erni.blackboard.blackboard import Predicate, Subscription, Transaction  # noqa: E402
from erni.blackboard.errors import (  # noqa: E402
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
from erni.blackboard.objects import BBObject, new_uid  # noqa: E402
from erni.blackboard.plugin import NoSettings, Plugin  # noqa: E402
from erni.blackboard.schemas import FloorPlan, Peer  # noqa: E402
from erni.blackboard.tasks import (  # noqa: E402
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
