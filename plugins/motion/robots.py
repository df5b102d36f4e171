"""Robot models: the per-model ARCOS conversion factors and body geometry, chosen in config."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from erni.blackboard.errors import ConfigError

PIONEER3_SONAR = (90, 50, 30, 10, -10, -30, -50, -90, -90, -130, -150, -170, 170, 150, 130, 90)
AMIGOBOT_SONAR = (90, 41, 15, -15, -41, -90, -145, 145)


class RobotModel(BaseModel):
    """Conversion factors between ARCOS wire units and SI units, plus the body the behaviours need."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = "custom"
    dist_conv: float = Field(1.0, gt=0, description="mm per position unit (XPOS, YPOS, MOVE)")
    vel_conv: float = Field(1.0, gt=0, description="mm/s per velocity unit (LVEL, RVEL, VEL, SETV)")
    angle_conv: float = Field(0.001534, gt=0, description="rad per angle unit (THPOS, CONTROL)")
    range_conv: float = Field(1.0, gt=0, description="mm per sonar range unit")
    vel2_divisor: float = Field(20.0, gt=0, description="mm/s per VEL2 wheel unit")
    radius: float = Field(0.25, gt=0, description="body radius (m)")
    axle: float = Field(0.33, gt=0, description="wheel separation (m)")
    max_v: float = Field(1.2, gt=0, description="top speed the behaviours ask for (m/s)")
    max_rv: float = Field(180.0, gt=0, description="top turn rate the behaviours ask for (deg/s)")
    decel: float = Field(0.5, gt=0, description="deceleration the behaviours plan with (m/s^2)")
    rot_decel: float = Field(120.0, gt=0, description="rotational deceleration planned with (deg/s^2)")
    sonar_angles: tuple[float, ...] = Field(PIONEER3_SONAR, description="sonar bearings (deg, 0 = ahead)")


MODELS: dict[str, RobotModel] = {
    "pioneer3": RobotModel(name="pioneer3"),
    "amigobot": RobotModel(name="amigobot", dist_conv=0.5083, vel_conv=0.6154, radius=0.18, axle=0.28,
                           max_v=0.75, max_rv=100.0, sonar_angles=AMIGOBOT_SONAR),
}


def resolve_model(value: str | dict[str, Any] | RobotModel) -> RobotModel:
    """Return the model named `value`, or one built from a table (which may extend `base`)."""
    if isinstance(value, RobotModel):
        return value
    if isinstance(value, str):
        key = value.strip().lower().replace("-", "").replace(" ", "")
        aliases = {"p3": "pioneer3", "p3dx": "pioneer3", "p3at": "pioneer3", "amigo": "amigobot"}
        key = aliases.get(key, key)
        if key not in MODELS:
            raise ConfigError(f"model: unknown robot model {value!r}; expected one of "
                              f"{', '.join(MODELS)} or a table of conversion factors")
        return MODELS[key]
    if isinstance(value, dict):
        data = dict(value)
        base = data.pop("base", None)
        start = resolve_model(base).model_dump() if base else {}
        start.update(data)
        return RobotModel.model_validate(start)
    raise ConfigError(f"model: expected a model name or a table, got {value!r}")
