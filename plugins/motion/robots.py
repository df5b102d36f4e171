"""Robot models: the published ARCOS parameters of the common MobileRobots bases, chosen by subtype.

An ARCOS robot names itself in its SYNC2 reply: name, class (`Pioneer`) and subtype
(`p3dx-sh`, `amigo`, `peoplebot-sh`, ...). The subtype decides how the wire units convert to SI
units (DistConvFactor, VelConvFactor, RangeConvFactor, DiffConvFactor, Vel2Divisor), the body
and where each sonar transducer sits. `MODELS` holds the values MobileRobots published for
each subtype (the robot parameter tables of the ARIA client library); the driver picks the
entry the robot names unless the configuration says otherwise, and says so when the two
disagree.

Commands are not converted: real firmware takes VEL in mm/s, MOVE in mm, HEAD in degrees
whatever the factors are. The factors apply only to what the robot reports (SIP positions,
wheel velocities, sonar ranges).

The planner's limits (`max_v`, `max_rv`, `accel`, `decel`, `rot_accel`, `rot_decel`) are the
speeds and accelerations the behaviours plan with; the driver sends them to the robot at
connect (SETV, SETRV, SETA, SETRA) so the robot brakes as the planner expects. Left unset they
are taken from the robot's own CONFIG reply.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from pydantic import ConfigDict, Field, ValidationError

from erni.blackboard.errors import ConfigError, describe_validation
from erni.blackboard.objects import Model

Transducer = tuple[float, float, float]
"""A sonar transducer: x (m, ahead), y (m, left) from the robot's centre, bearing (deg, 0 = ahead)."""

DEFAULT_LIMITS = {"max_v": 0.75, "max_rv": 100.0, "accel": 0.3, "decel": 0.3, "rot_accel": 100.0,
                  "rot_decel": 100.0}
"""ARCOS factory defaults (mm/s, deg/s, mm/s^2 and deg/s^2 in SI), used when neither the configuration
nor the robot's CONFIG reply gives a limit."""


class RobotModel(Model):
    """One robot model: wire conversion factors, body, sonar ring and the planner's limits."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field("custom", description="the table key, usually the SYNC2 subtype")
    robot_class: str = Field("Pioneer", description="class named in SYNC2")
    subclass: str = Field("", description="subtype named in SYNC2 (p3dx-sh, amigo, ...)")
    dist_conv: float = Field(1.0, gt=0, description="mm per position unit (SIP XPOS, YPOS)")
    vel_conv: float = Field(1.0, gt=0, description="mm/s per velocity unit (SIP LVEL, RVEL)")
    angle_conv: float = Field(0.001534, gt=0, description="rad per angle unit (THPOS, CONTROL)")
    range_conv: float = Field(1.0, gt=0, description="mm per sonar range unit")
    diff_conv: float = Field(0.0056, gt=0, description="rad/s per mm/s of wheel speed difference, halved")
    vel2_divisor: float = Field(20.0, gt=0, description="mm/s per VEL2 wheel unit")
    radius: float = Field(0.25, gt=0, description="body radius (m)")
    width: float = Field(0.425, gt=0, description="body width (m)")
    length: float = Field(0.511, gt=0, description="body length (m)")
    axle: float | None = Field(None, gt=0, description="wheel separation (m); default 2 / DiffConvFactor")
    top_v: float = Field(2.2, gt=0, description="the base's absolute top speed (m/s)")
    top_rv: float = Field(500.0, gt=0, description="the base's absolute top turn rate (deg/s)")
    has_move: bool = Field(True, description="the firmware has MOVE and HEAD position control")
    switch_baud: int = Field(38400, ge=0, description="serial rate to switch to with HOSTBAUD (0: stay at 9600)")
    sonar: tuple[Transducer | None, ...] = Field((), description="sonar transducers by number (None: not fitted)")
    max_v: float | None = Field(None, gt=0, description="top speed planned with and sent with SETV (m/s)")
    max_rv: float | None = Field(None, gt=0, description="top turn rate planned with and sent with SETRV (deg/s)")
    accel: float | None = Field(None, gt=0, description="acceleration sent with SETA (m/s^2)")
    decel: float | None = Field(None, gt=0, description="deceleration planned with, sent with SETA (m/s^2)")
    rot_accel: float | None = Field(None, gt=0, description="rotational acceleration sent with SETRA (deg/s^2)")
    rot_decel: float | None = Field(None, gt=0, description="rotational deceleration planned with (deg/s^2)")

    @property
    def track(self) -> float:
        """Wheel separation (m): the configured axle, else the one DiffConvFactor implies."""
        return self.axle if self.axle is not None else 2.0 / self.diff_conv / 1000.0

    @property
    def sonar_angles(self) -> tuple[float, ...]:
        """Bearing of each fitted transducer (deg), in sonar number order."""
        return tuple(t[2] for t in self.sonar if t is not None)

    def limit(self, name: str) -> float:
        """A planner limit, falling back on the ARCOS factory default when unset."""
        value = getattr(self, name)
        return float(value if value is not None else DEFAULT_LIMITS[name])

    def factors(self) -> dict[str, float]:
        """The conversion factors, for comparing two models."""
        return {k: getattr(self, k) for k in ("dist_conv", "vel_conv", "angle_conv", "range_conv", "diff_conv",
                                              "vel2_divisor")}


def _ring(*poses: tuple[int, int, int]) -> tuple[Transducer | None, ...]:
    """Transducer poses in mm and degrees as published; (0, 0, -180) marks a socket with none fitted."""
    return tuple(None if p == (0, 0, -180) else (p[0] / 1000.0, p[1] / 1000.0, float(p[2])) for p in poses)


P2_FRONT = ((69, 136, 90), (114, 119, 50), (148, 78, 30), (166, 27, 10), (166, -27, -10), (148, -78, -30),
            (114, -119, -50), (69, -136, -90))
P2_REAR = ((-157, -136, -90), (-203, -119, -130), (-237, -78, -150), (-255, -27, -170), (-255, 27, 170),
           (-237, 78, 150), (-203, 119, 130), (-157, 136, 90))
PB_MIDDLE = ((-20, 136, 90), (24, 119, 50), (58, 78, 30), (77, 27, 10), (77, -27, -10), (58, -78, -30),
             (24, -119, -50), (-20, -136, -90))
PB_TOP_REAR = ((-191, -136, -90), (-237, -119, -130), (-271, -78, -150), (-290, -27, -170), (-290, 27, 170),
               (-271, 78, 150), (-237, 119, 130), (-191, 136, 90))
AT_RING = ((147, 136, 90), (193, 119, 50), (227, 79, 30), (245, 27, 10), (245, -27, -10), (227, -79, -30),
           (193, -119, -50), (147, -136, -90), (-144, -136, -90), (-189, -119, -130), (-223, -79, -150),
           (-241, -27, -170), (-241, 27, 170), (-223, 79, 150), (-189, 119, 130), (-144, 136, 90))
AMIGO_RING = ((76, 100, 90), (125, 75, 41), (150, 30, 15), (150, -30, -15), (125, -75, -41), (76, -100, -90),
              (-140, -58, -145), (-140, 58, 145))
AMIGO_SH_RING = ((70, 100, 90), (125, 75, 41), (144, 30, 15), (144, -30, -15), (120, -75, -41), (70, -100, -90),
                 (-146, -58, -145), (-146, 58, 145))
PATROL_RING = ((83, 229, 90), (169, 202, 55), (232, 134, 30), (263, 46, 10), (263, -46, -10), (232, -134, -30),
               (169, -202, -55), (83, -229, -90), (-83, -229, -90), (-169, -202, -125), (-232, -134, -150),
               (-263, -46, -170), (-263, 46, 170), (-232, 134, 150), (-169, 202, 125), (-83, 229, 90))
POWERBOT_RING = ((152, 278, 90), (200, 267, 65), (241, 238, 45), (274, 200, 35), (300, 153, 25), (320, 96, 15),
                 (332, 33, 5), (0, 0, -180), (332, -33, -5), (320, -96, -15), (300, -153, -25), (274, -200, -35),
                 (241, -238, -45), (200, -267, -65), (152, -278, -90), (0, 0, -180), (-298, -278, -90),
                 (-347, -267, -115), (-388, -238, -135), (-420, -200, -145), (-447, -153, -155),
                 (-467, -96, -165), (-478, -33, -175), (0, 0, -180), (-478, 33, 175), (-467, 96, 165),
                 (-447, 153, 155), (-420, 200, 145), (-388, 238, 135), (-347, 267, 115), (-298, 278, 90),
                 (0, 0, -180))


def _model(subclass: str, **kw: Any) -> RobotModel:
    return RobotModel(name=subclass, subclass=subclass, **kw)


_DX = dict(radius=0.25, width=0.425, length=0.511, top_v=2.2, top_rv=500.0, diff_conv=0.0056)
_AT = dict(radius=0.5, width=0.505, length=0.626, top_v=1.2, top_rv=300.0, diff_conv=0.0034)
_AMIGO = dict(radius=0.18, width=0.279, length=0.33, top_v=1.0, top_rv=300.0, diff_conv=0.011)
_PEOPLE = dict(radius=0.34, width=0.425, length=0.513, diff_conv=0.006, top_v=2.2, top_rv=500.0)
_POWER = dict(radius=0.55, width=0.68, length=0.911, top_v=2.0, top_rv=360.0, diff_conv=0.00373)
_PATROL = dict(radius=0.25, width=0.425, length=0.51, top_v=2.2, top_rv=500.0, diff_conv=0.0056)

MODELS: dict[str, RobotModel] = {m.name: m for m in (
    # Pioneer 3 and 2 with SH (ARCOS) controllers: factors 1.0
    _model("p3dx-sh", sonar=_ring(*P2_FRONT, *P2_REAR), **_DX),
    _model("p3at-sh", sonar=_ring(*AT_RING), **_AT),
    _model("p3atiw-sh", sonar=_ring(*AT_RING), **{**_AT, "width": 0.49}),
    _model("peoplebot-sh", sonar=_ring(*P2_FRONT, *P2_REAR, *PB_MIDDLE, *PB_TOP_REAR), **_PEOPLE),
    _model("powerbot-sh", sonar=_ring(*POWERBOT_RING), **_POWER),
    _model("patrolbot-sh", sonar=_ring(*PATROL_RING), **_PATROL),
    _model("mt400", sonar=_ring(*PATROL_RING), **_PATROL),
    _model("researchPB", sonar=_ring(*PATROL_RING), **_PATROL),
    _model("amigo-sh", sonar=_ring(*AMIGO_SH_RING), **_AMIGO),
    # older controllers (Siemens C166, H8): position and velocity units are not millimetres
    _model("p3dx", dist_conv=0.485, sonar=_ring(*P2_FRONT, *P2_REAR), **_DX),
    _model("p3at", dist_conv=0.465, sonar=_ring(*AT_RING), **_AT),
    _model("p2dx", dist_conv=0.84, range_conv=0.268, sonar=_ring(*P2_FRONT, *P2_REAR), **_DX),
    _model("p2de", dist_conv=0.969, range_conv=0.268, sonar=_ring(*P2_FRONT, *P2_REAR), **_DX),
    _model("p2df", dist_conv=0.485, range_conv=0.268, sonar=_ring(*P2_FRONT, *P2_REAR), **{**_DX, "diff_conv": 0.006}),
    _model("p2d8", dist_conv=0.485, sonar=_ring(*P2_FRONT, *P2_REAR), **_DX),
    _model("p2d8+", dist_conv=0.485, sonar=_ring(*P2_FRONT, *P2_REAR), **_DX),
    _model("p2ce", dist_conv=0.826, range_conv=0.268, sonar=_ring(*P2_FRONT, *P2_REAR), **{**_DX, "diff_conv": 0.0057}),
    _model("p2at", dist_conv=1.32, range_conv=0.268, sonar=_ring(*AT_RING), **_AT),
    _model("p2at8", dist_conv=1.32, sonar=_ring(*AT_RING), **_AT),
    _model("p2at8+", dist_conv=0.465, sonar=_ring(*AT_RING), **_AT),
    _model("p2it", dist_conv=1.136, range_conv=0.268, sonar=_ring(*AT_RING), **{**_AT, "diff_conv": 0.0032}),
    _model("p2pb", dist_conv=0.424, range_conv=0.268, sonar=_ring(*P2_FRONT, *PB_MIDDLE, *P2_REAR),
           **{**_PEOPLE, "diff_conv": 0.0056}),
    _model("p2pp", dist_conv=0.485, range_conv=0.268, sonar=_ring(*P2_FRONT, *PB_MIDDLE, *P2_REAR), **_PEOPLE),
    _model("perfpb", dist_conv=0.485, sonar=_ring(*P2_FRONT, *PB_MIDDLE, *P2_REAR, *PB_TOP_REAR), **_PEOPLE),
    _model("perfpb+", dist_conv=0.485, sonar=_ring(*P2_FRONT, *PB_MIDDLE, *P2_REAR, *PB_TOP_REAR), **_PEOPLE),
    _model("powerbot", dist_conv=0.5813, sonar=_ring(*POWERBOT_RING[:31]), **_POWER),
    _model("amigo", dist_conv=0.5083, vel_conv=0.6154, sonar=_ring(*AMIGO_RING), **_AMIGO),
    # Seekur family: no sonar ring, no MOVE/HEAD
    _model("seekur", radius=0.833, width=1.27, length=1.41, top_v=2.2, top_rv=190.0, has_move=False),
    _model("seekurjr", radius=0.6, width=0.83, length=1.2, top_v=1.2, top_rv=80.0, has_move=False),
)}

ALIASES = {
    "pioneer3": "p3dx-sh", "p3": "p3dx-sh", "pioneer3dx": "p3dx-sh", "pioneer3at": "p3at-sh",
    "amigobot": "amigo", "amigobotsh": "amigo-sh", "peoplebot": "peoplebot-sh", "powerbot2": "powerbot-sh",
    "patrolbot": "patrolbot-sh", "researchpb": "researchPB",
}
"""Friendly names; the subtypes with laser or radio options (p3dx-sh-lms1xx, ...) use their base entry."""

_SUFFIXES = ("-lms1xx", "-lms500", "-lms200", "-tim3xx", "-tim5xx", "-uarcs", "-nolaser")


def lookup(name: str) -> RobotModel | None:
    """The table entry for a model name, alias or SYNC2 subtype (case and option suffixes ignored)."""
    key = name.strip()
    low = key.lower()
    for m in MODELS.values():
        if m.name.lower() == low:
            return m
    squashed = low.replace("-", "").replace(" ", "").replace("_", "")
    if squashed in ALIASES:
        return MODELS[ALIASES[squashed]]
    for suffix in _SUFFIXES:
        if low.endswith(suffix):
            return lookup(key[:-len(suffix)])
    for m in MODELS.values():  # "P3-DX-SH" and friends
        if m.name.lower().replace("-", "") == squashed:
            return m
    return None


def _unknown(value: str) -> ConfigError:
    return ConfigError(f"model: unknown robot model {value!r}; expected 'auto', a subtype such as "
                       f"{', '.join(list(MODELS)[:9])}, ... (or pioneer3, amigobot), or a table of factors")


@dataclass(frozen=True)
class ModelSpec:
    """What the configuration asks for: a base (a table entry, or `auto` = the robot's subtype) plus overrides."""

    base: str = "auto"
    overrides: Mapping[str, Any] = field(default_factory=dict)
    model: RobotModel | None = None  # a model given whole: used as it is

    @property
    def auto(self) -> bool:
        """The base is the model the robot names in SYNC2."""
        return self.model is None and self.base == "auto"

    def resolve(self, subtype: str | None = None) -> tuple[RobotModel, list[str]]:
        """The model for a robot naming `subtype` (None: not connected yet), and any warnings to log."""
        warnings: list[str] = []
        reported = lookup(subtype) if subtype else None
        if self.model is not None:
            base = self.model
        elif self.auto:
            if reported is not None:
                base = reported
            else:
                base = MODELS["p3dx-sh"]
                if subtype:
                    warnings.append(f"the robot's subtype {subtype!r} is not in the model table: using the ARCOS "
                                    f"defaults (all conversion factors 1.0); set model = {{ base = ..., "
                                    f"dist_conv = ... }} if its odometry is off")
        else:
            found = lookup(self.base)
            if found is None:
                raise _unknown(self.base)
            base = found
        model = _build(base, self.overrides)
        if reported is not None:
            ours, theirs = model.factors(), reported.factors()
            differ = [f"{k} {ours[k]:g} (robot's subtype: {theirs[k]:g})" for k in ours if ours[k] != theirs[k]]
            if differ:
                warnings.append(f"configured model {model.name!r} disagrees with the robot, which reports subtype "
                                f"{subtype!r}: {', '.join(differ)}; using the configured values (set "
                                f"model = 'auto' to follow the robot)")
        return model, warnings


def _build(base: RobotModel, overrides: Mapping[str, Any]) -> RobotModel:
    if not overrides:
        return base
    data = base.model_dump()
    data.update(overrides)
    if "name" not in overrides:
        data["name"] = f"{base.name}+custom"
    try:
        return RobotModel.model_validate(data)
    except ValidationError as err:
        raise ConfigError(f"model: {describe_validation(err)}") from None


def model_spec(value: str | Mapping[str, Any] | RobotModel | ModelSpec) -> ModelSpec:
    """Parse the `model` setting: 'auto', a name, or a table (`base` plus any RobotModel field)."""
    if isinstance(value, ModelSpec):
        return value
    if isinstance(value, RobotModel):
        return ModelSpec(base=value.name, model=value)
    if isinstance(value, str):
        name = value.strip()
        if name.lower() != "auto" and lookup(name) is None:
            raise _unknown(value)
        return ModelSpec(base="auto" if name.lower() == "auto" else name)
    if isinstance(value, Mapping):
        data = dict(value)
        base = str(data.pop("base", "auto")).strip()
        spec = ModelSpec(base="auto" if base.lower() == "auto" else base, overrides=data)
        spec.resolve()  # validates the base name and every override now, not at connect
        return spec
    raise ConfigError(f"model: expected 'auto', a model name or a table, got {value!r}")


def resolve_model(value: str | Mapping[str, Any] | RobotModel) -> RobotModel:
    """The model a setting names without asking the robot ('auto' gives the Pioneer 3 defaults)."""
    if isinstance(value, RobotModel):
        return value
    return model_spec(value).resolve()[0]
