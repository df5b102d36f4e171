"""Blackboard objects: frozen pydantic models with a stable `uid`; `Model`, the base of every ERNI
model, whose numbers are finite."""

from __future__ import annotations

import math
import uuid
from typing import Annotated, Any, ClassVar, Self, cast

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, JsonValue

from erni.blackboard.errors import UsageError


class Model(BaseModel):
    """Base of every pydantic model of ERNI: every number is finite.

    NaN and the infinities are refused in every float field, whether the value comes as a Python
    float or as JSON text (pydantic's JSON parser reads `NaN` and `Infinity` unless told not to),
    in a TOML file (`nan`, `inf`) or on the wire. A free-form field (`AllocationResult.values`, a
    watch event's data, a plugin's settings table) takes `FiniteJson` or `FiniteAny`, which check
    every number inside. A subclass's own `model_config` adds to this one.
    """

    model_config = ConfigDict(allow_inf_nan=False)


def finite_inside(value: Any) -> Any:
    """Return `value` (JSON-like data: tables, lists, numbers, text) if every float in it is finite;
    raise UsageError naming the first one that is not and where it sits (`expected a finite number,
    got nan (at speed[0])`). Walks without recursion, so depth costs no stack."""
    stack: list[tuple[str, Any]] = [("", value)]
    while stack:
        where, item = stack.pop()
        if isinstance(item, float):
            if not math.isfinite(item):
                raise UsageError(f"expected a finite number, got {item}" + (f" (at {where})" if where else ""))
        elif isinstance(item, dict):
            stack.extend((f"{where}.{k}" if where else str(k), v) for k, v in item.items())
        elif isinstance(item, (list, tuple)):
            stack.extend((f"{where}[{i}]", v) for i, v in enumerate(item))
    return value


FiniteJson = Annotated[JsonValue, AfterValidator(finite_inside)]
"""Any JSON value whose numbers are all finite."""

FiniteAny = Annotated[Any, AfterValidator(finite_inside)]
"""Any value (a TOML table's: dates too) whose floats, however deep in tables and lists, are all finite."""


def new_uid() -> str:
    """Return a fresh, globally unique object id."""
    return uuid.uuid4().hex[:16]


class BBObject(Model):
    """Base of everything published on a blackboard.

    Objects are immutable: a change is published as a new version with the same `uid`
    (`obj.evolve(field=value)`), so a plugin's view can never be altered under its feet.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    durable: ClassVar[bool] = False
    """True for objects the agent's journal keeps across a crash (tasks, mission state)."""

    uid: str = Field(default_factory=new_uid)

    def evolve(self, **changes: Any) -> Self:
        """Return a validated copy of this object with `changes` applied (same uid).

        The changes are validated, and the object's own validators run again; the fields it keeps
        are taken as they are (frozen models and values validated when this object was made), not
        dumped and validated anew: a control node evolves a task for every result a robot sends."""
        data = dict(self.__dict__)
        data.update(changes)
        return type(self).model_validate(data)

    @classmethod
    def trusted(cls, values: dict[str, Any], given: set[str]) -> Self:
        """An object of `values` already checked as its validation checks them (every field, in the
        model's order; `given`: the fields its sender gave), made without validating again: a codec's
        hot path (every robot's Pose). Through pydantic's own `model_construct`, never its slots."""
        # cast: the pydantic plugin types model_construct as the class it is declared on, not Self
        return cast(Self, cls.model_construct(_fields_set=given, **values))


def only_stamp_differs(old: BaseModel, new: BaseModel) -> bool:
    """Whether `new` is `old` but for its `stamp` field (compared field by field: stops at the first
    difference, and rows shared by both are not compared again)."""
    a, b = old.__dict__, new.__dict__
    return type(old) is type(new) and a.keys() == b.keys() and all(a[k] == b[k] for k in a if k != "stamp")
