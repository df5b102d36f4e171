"""A team scenario: the world, the radio, the robots, the control node and timed tasks, from TOML.

A scenario file looks like this (every table is optional; `erni sim` without a file runs
`Scenario()`, the default team)::

    name = "poi-coverage"
    title = "Paper 000: PoI coverage by three robots"
    duration = 120.0                  # s; `erni sim` runs until Ctrl-C when absent
    seed = 1
    ros2 = true                       # the control node shows the team to ROS 2, as `erni sim --ros2`
                                      # does; or a [ros2] table of the ros2 plugin's settings

    world = "world-corridor.toml"     # a world file (relative to this file), or a [world] table
    [world]                           # the same keys as a world file: bounds, wall, circle, polygon
    bounds = [-10.0, -5.0, 10.0, 15.0]

    [radio]                           # sim.manet.RadioModel
    comm_range = 4.5                  # R (m): no link beyond
    lossless_range = 3.0              # no loss up to here (m)
    channel = "nftables"              # --netns: this model as nftables rules, or "ns3" (802.11a in ns-3)

    [robots]                          # how many and where, unless listed one by one in [[robot]]
    count = 3
    layout = "line"                   # line, grid, random (in `area`), circle
    origin = [0.0, 0.0]
    spacing = 1.5

    [[robot]]                         # explicit start poses win over the layout
    name = "robot1"
    x = 0.0
    y = 0.0
    heading = 90.0                    # degrees

    [control]                         # the control node (base station) is a network node too
    x = 0.0
    y = -1.0

    [[poi]]                           # points of interest (drawn, and used by experiments)
    name = "poi"
    x = 0.0
    y = 11.0

    [[task]]                          # sent through the control node once the team is up
    at = 0.0                          # s after the team is up
    to = "all"                        # a robot name, or "all"
    verb = "Deploy"
    preposition = "widep"
    params = { x = 0.0, y = 11.0, range = 4.5 }

    [[failure]]                       # a robot fails: its agent is killed and its robot stops
    at = 20.0
    robot = "robot2"

    [strategy]                        # settings the experiments read (paper parameters)
    distance = 5.0

Units: metres, seconds, degrees. Errors read `FILE: field.path: message`.
"""

from __future__ import annotations

import importlib.resources
import math
import random
from pathlib import Path
from typing import Any, Literal

from pydantic import ConfigDict, Field, ValidationError, field_validator, model_validator

from erni.blackboard.errors import ConfigError, TaskError, describe_validation, shown
from erni.blackboard.objects import FiniteAny, Model
from erni.blackboard.schemas import read_toml
from erni.blackboard.tasks import Task
from erni.sim.world import RobotStart, World, WorldError

NAME = r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,62}$"
MAX_AGENT_ROBOTS = 240  # one loopback address 127.0.1.N per robot agent


class ScenarioError(ConfigError):
    """A scenario that cannot be used; the message names the file, the field and the problem."""


class _Strict(Model):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RadioSpec(_Strict):
    """The radio model: delivery ratio 1 up to `lossless_range`, 0 from `comm_range` on."""

    comm_range: float = Field(10.0, gt=0, description="communication range R (m)")
    lossless_range: float = Field(6.0, ge=0, description="range without loss (m)")
    min_quality: float = Field(0.1, gt=0, le=1, description="weakest link used for routing")
    channel: Literal["nftables", "ns3"] = Field(
        "nftables", description="what carries the frames in the real-mesh tier (--netns): this model as "
        "nftables drop rules, or ns-3's 802.11a ad-hoc network delivering about 10 % at comm_range (--channel wins)")

    @model_validator(mode="after")
    def _ranges(self) -> RadioSpec:
        if self.lossless_range > self.comm_range:
            raise ValueError(f"lossless_range ({self.lossless_range} m) must not exceed "
                             f"comm_range ({self.comm_range} m)")
        return self


class RobotsSpec(_Strict):
    """How many robots and how they start, when they are not listed one by one."""

    count: int | None = Field(None, ge=1, le=1000,
                              description="number of robots (default: the [[robot]] entries, else 4)")
    model: Literal["pioneer3", "amigobot"] = "pioneer3"
    layout: Literal["line", "grid", "random", "circle"] = "line"
    origin: tuple[float, float] = (0.0, 0.0)
    spacing: float = Field(1.5, gt=0, description="distance between neighbours in line and grid (m)")
    area: float = Field(2.0, gt=0, description="side of the square of the random layout (m)")
    heading: float | Literal["random"] = Field(90.0, description="start heading (deg), or 'random'")


class ControlSpec(_Strict):
    """The control node's place in the radio model (it does not move)."""

    x: float = 0.0
    y: float = -1.5


class PoiSpec(_Strict):
    """A point of interest (m)."""

    name: str = Field("poi", pattern=NAME)
    x: float
    y: float


class TaskSpec(_Strict):
    """A task sent through the control node `at` seconds after the team is up."""

    at: float = Field(0.0, ge=0)
    to: str = Field("all", description="a robot name, or 'all'")
    verb: str
    preposition: str
    params: dict[str, FiniteAny] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _valid_task(self) -> TaskSpec:
        try:
            Task(verb=self.verb, preposition=self.preposition, params=self.params)
        except TaskError as err:
            raise ValueError(str(err)) from None
        return self


class FailureSpec(_Strict):
    """Robot `robot` fails `at` seconds after the team is up (its agent is killed)."""

    at: float = Field(ge=0)
    robot: str


class Scenario(_Strict):
    """A whole simulated team: world, radio, robots, control node, PoIs, tasks and failures."""

    name: str = Field("default", pattern=NAME)
    title: str = "Four robots in an open room"
    description: str = ""
    duration: float | None = Field(None, gt=0, description="run this long (s); none = until Ctrl-C")
    seed: int = 0
    world: World = Field(default_factory=lambda: World(name="room", bounds=(-8.0, -4.0, 8.0, 10.0)))
    radio: RadioSpec = Field(default_factory=RadioSpec)
    robots: RobotsSpec = Field(default_factory=RobotsSpec)
    robot: list[RobotStart] = Field(default_factory=list)
    control: ControlSpec = Field(default_factory=ControlSpec)
    poi: list[PoiSpec] = Field(default_factory=list)
    task: list[TaskSpec] = Field(default_factory=list)
    failure: list[FailureSpec] = Field(default_factory=list)
    strategy: dict[str, FiniteAny] = Field(default_factory=dict, description="experiment parameters")
    ros2: bool | dict[str, FiniteAny] = Field(False, description="the control node runs the ros2 plugin: true, "
                                              "or a table of its settings")

    @field_validator("ros2", mode="before")
    @classmethod
    def _ros2(cls, value: Any) -> Any:
        if not isinstance(value, (bool, dict)):
            raise ValueError(f"expected true, false or a table of the ros2 plugin's settings, got {shown(value)}")
        return value

    @field_validator("robot")
    @classmethod
    def _names(cls, robots: list[RobotStart]) -> list[RobotStart]:
        import re

        names = [r.name for r in robots]
        for i, name in enumerate(names):
            if name and not re.match(NAME, name):
                raise ValueError(f"robot[{i}].name {name!r}: expected letters, digits, '_', '.', '-'")
            if name == "control":
                raise ValueError("robot name 'control' is taken by the control node")
        dup = sorted({n for n in names if n and names.count(n) > 1})
        if dup:
            raise ValueError(f"duplicate robot name(s): {', '.join(dup)}")
        return robots

    @model_validator(mode="after")
    def _references(self) -> Scenario:
        names = set(self.robot_names())
        for i, t in enumerate(self.task):
            if t.to != "all" and t.to not in names:
                raise ValueError(f"task[{i}].to: unknown robot {t.to!r}; expected 'all' or one of "
                                 f"{', '.join(sorted(names))}")
        for i, f in enumerate(self.failure):
            if f.robot not in names:
                raise ValueError(f"failure[{i}].robot: unknown robot {f.robot!r}; expected one of "
                                 f"{', '.join(sorted(names))}")
        return self

    # --- derived ------------------------------------------------------------------------

    @property
    def count(self) -> int:
        """Number of robots: the listed ones, or `robots.count`."""
        if self.robots.count is not None:
            return self.robots.count
        return len(self.robot) or 4

    def robot_names(self) -> list[str]:
        """Agent names of the robots, in order."""
        return [s.name for s in self.starts()]

    def starts(self) -> list[RobotStart]:
        """Start pose of every robot: listed ones first, then the layout's."""
        out: list[RobotStart] = []
        rng = random.Random(self.seed)
        spec = self.robots
        n = self.count
        for i in range(n):
            if i < len(self.robot):
                r = self.robot[i]
                out.append(r if r.name else r.model_copy(update={"name": f"robot{i + 1}"}))
                continue
            ox, oy = spec.origin
            if spec.layout == "line":
                x, y = ox + (i - (n - 1) / 2) * spec.spacing, oy
            elif spec.layout == "grid":
                cols = max(1, math.ceil(math.sqrt(n)))
                x = ox + (i % cols - (cols - 1) / 2) * spec.spacing
                y = oy + (i // cols) * spec.spacing
            elif spec.layout == "circle":
                radius = spec.spacing / (2 * math.sin(math.pi / n)) if n > 1 else 0.0  # neighbours `spacing` apart
                a = 2 * math.pi * i / n
                x, y = ox + radius * math.cos(a), oy + radius * math.sin(a)
            else:
                half = spec.area / 2
                x, y = ox + rng.uniform(-half, half), oy + rng.uniform(-half, half)
            heading = rng.uniform(-180.0, 180.0) if spec.heading == "random" else float(spec.heading)
            out.append(RobotStart(name=f"robot{i + 1}", x=x, y=y, heading=heading))
        return out

    def ros2_settings(self) -> dict[str, Any] | None:
        """The settings the scenario gives the control node's ros2 plugin; None when it runs none."""
        if self.ros2 is False:
            return None
        return {} if self.ros2 is True else dict(self.ros2)

    def with_robots(self, count: int) -> Scenario:
        """Return this scenario with `count` robots (listed starts are kept as far as they go)."""
        if count < 1:
            raise ScenarioError(f"--robots: expected at least 1, got {count}")
        data = self.model_dump()
        data["robots"]["count"] = count
        data["robot"] = data["robot"][:count]
        names = {r["name"] or f"robot{i + 1}" for i, r in enumerate(data["robot"])}
        names |= {f"robot{i + 1}" for i in range(count)}
        data["task"] = [t for t in data["task"] if t["to"] == "all" or t["to"] in names]
        data["failure"] = [f for f in data["failure"] if f["robot"] in names]
        return Scenario.model_validate(data)


def _world_from(value: Any, base: Path | None) -> Any:
    """Resolve `world = "file.toml"` (relative to the scenario) into the world's table."""
    if not isinstance(value, str):
        return value
    path = Path(value)
    if not path.is_absolute() and base is not None:
        path = base / path
    try:
        return World.load(path).model_dump()
    except WorldError as err:
        raise ScenarioError(f"world: {err}") from None


def parse_scenario(data: dict[str, Any], source: str = "<scenario>", base: Path | None = None) -> Scenario:
    """Validate scenario data; raise ScenarioError with one `SOURCE: field: message` line per problem."""
    if "world" in data:
        try:
            data = {**data, "world": _world_from(data["world"], base)}
        except ScenarioError as err:
            raise ScenarioError(f"{source}: {err}") from None
    try:
        scenario = Scenario.model_validate(data)
    except ValidationError as err:
        raise ScenarioError(describe_validation(err, source, sep="\n")) from None
    check_ros2_settings(scenario.ros2_settings(), source)
    return scenario


def check_ros2_settings(settings: dict[str, Any] | None, source: str = "<scenario>") -> None:
    """Raise ScenarioError (`SOURCE: ros2.KEY: message`) when the ros2 plugin would refuse `settings`.
    Without the plugin's libraries nothing is checked here: running it says which extra to install."""
    if not settings:
        return
    try:
        from erni.plugins.ros2 import ROS2Settings
    except ImportError:
        return
    try:
        ROS2Settings.model_validate(settings)
    except ValidationError as err:
        raise ScenarioError(describe_validation(err, source, prefix="ros2", sep="\n")) from None


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML file (raises ScenarioError naming file and field)."""
    path = Path(path)
    data = read_toml(path, "scenario", ScenarioError)
    return parse_scenario(data, str(path), path.parent)


def examples_dir() -> Path | None:
    """The example scenarios, worlds and configs shipped inside the package (`erni/examples`),
    found through importlib.resources wherever the package is installed."""
    found = importlib.resources.files("erni").joinpath("examples")
    if isinstance(found, Path) and found.is_dir():
        return found
    import erni  # a checkout without symbolic links: the examples/ folder beside erni/

    return next((Path(p) / "examples" for p in erni.__path__ if (Path(p) / "examples").is_dir()), None)


def find_scenario(name: str) -> Path:
    """Return the file of scenario NAME (`examples/scenario-NAME.toml`), or a path given as is."""
    path = Path(name)
    if path.suffix == ".toml" or path.exists():
        return path
    ex = examples_dir()
    if ex is not None and (ex / f"scenario-{name}.toml").is_file():
        return ex / f"scenario-{name}.toml"
    known = sorted(p.stem.removeprefix("scenario-") for p in ex.glob("scenario-*.toml")) if ex else []
    raise ScenarioError(f"{name}: no such scenario; expected a TOML file or one of: "
                        f"{', '.join(known) or '(no examples/ directory found)'}")
