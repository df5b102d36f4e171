"""net-sim scenarios: nodes, radio parameters and timed moves, loaded from TOML."""

from __future__ import annotations

from pathlib import Path

from pydantic import ConfigDict, Field, ValidationError, model_validator

from erni.blackboard.errors import describe_validation
from erni.blackboard.objects import Model
from erni.blackboard.schemas import read_toml
from erni.sim.manet import ManetNetwork, RadioModel
from erni.sim.scenario import ScenarioError


class _Strict(Model):
    model_config = ConfigDict(extra="forbid", frozen=True)


class NodeSpec(_Strict):
    """One node of the scenario: its name, initial position (m) and optionally its own write community."""

    name: str = Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    x: float
    y: float
    heading: float = 0.0
    write_community: str | None = Field(None, min_length=1, description="this node's write community "
                                        "(default: the scenario's)")


class MoveSpec(_Strict):
    """At `at` seconds after start, node `node` jumps to (x, y)."""

    at: float = Field(ge=0)
    node: str
    x: float
    y: float


class Scenario(_Strict):
    """A simulated MANET: radio parameters, nodes, optional moves and SNMP serving options."""

    comm_range: float = Field(gt=0, description="communication range R (m)")
    lossless_range: float = Field(ge=0, description="range without loss (m)")
    min_quality: float = Field(0.1, gt=0, le=1, description="symmetric-link threshold")
    gps: bool = Field(False, description="moves also update the positions the network knows")
    host: str = "127.0.0.1"
    base_port: int = Field(1161, ge=0, le=65535, description="node i serves base_port + i - 1; 0 = any")
    read_community: str = Field("public", min_length=1, description="SNMP community that reads")
    write_community: str | None = Field(None, min_length=1, description="SNMP community that reads and "
                                        "SETs a node's position; none: the network is read-only")
    nodes: list[NodeSpec] = Field(min_length=1)
    moves: list[MoveSpec] = Field(default_factory=list)

    @model_validator(mode="after")
    def _consistent(self) -> Scenario:
        if self.lossless_range > self.comm_range:
            raise ValueError(f"lossless_range ({self.lossless_range} m) must not exceed "
                             f"comm_range ({self.comm_range} m)")
        names = [n.name for n in self.nodes]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"duplicate node name(s): {', '.join(dup)}")
        for m in self.moves:
            if m.node not in names:
                raise ValueError(f"move at {m.at} s: unknown node {m.node!r}; expected one of "
                                 f"{', '.join(names)}")
        for n in self.nodes:
            if (n.write_community or self.write_community) == self.read_community:
                raise ValueError(f"node {n.name!r}: the write community must differ from the read "
                                 f"community {self.read_community!r}")
        if self.base_port and self.base_port + len(self.nodes) - 1 > 65535:
            raise ValueError(f"base_port {self.base_port} + {len(self.nodes)} nodes exceeds 65535")
        return self

    def build(self) -> ManetNetwork:
        """Return a network with the scenario's radio and nodes at their initial positions."""
        net = ManetNetwork(RadioModel(self.comm_range, self.lossless_range, self.min_quality),
                           gps=self.gps)
        for n in self.nodes:
            net.add_node(n.name, n.x, n.y, n.heading)
        return net

    def write_communities(self) -> dict[str, str | None]:
        """Each node's write community (None: the node accepts no SET)."""
        return {n.name: n.write_community or self.write_community for n in self.nodes}

    def ports(self) -> dict[str, int]:
        """UDP port of each node (0 everywhere when base_port is 0: the OS picks)."""
        return {n.name: (self.base_port + i if self.base_port else 0)
                for i, n in enumerate(self.nodes)}


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario TOML file (raises ScenarioError with one clear line)."""
    path = Path(path)
    data = read_toml(path, "scenario", ScenarioError)
    try:
        return Scenario.model_validate(data)
    except ValidationError as err:
        raise ScenarioError(describe_validation(err, str(path))) from None
