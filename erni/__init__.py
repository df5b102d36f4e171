"""ERNI: teams of mobile robots cooperating over wireless ad-hoc networks.

Everything a plugin author needs is importable from here::

    from erni import Plugin, Task, TaskState, GotoParams

The parts: `erni.blackboard` (agent core and task language), `erni.transport` (messages between
agents), `erni.plugins` (motion, mobinet, mission, ui), `erni.strategies` (pure deployment
strategies), `erni.netgraph` (graph helpers), `erni.sim` (the simulator, never imported by an
agent's runtime), and the `erni` command line.
"""

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
