"""Blackboard objects: frozen pydantic models with a stable `uid`."""

from __future__ import annotations

import uuid
from typing import Any, ClassVar, Self

from pydantic import BaseModel, ConfigDict, Field


def new_uid() -> str:
    """Return a fresh, globally unique object id."""
    return uuid.uuid4().hex[:16]


class BBObject(BaseModel):
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


def only_stamp_differs(old: BaseModel, new: BaseModel) -> bool:
    """Whether `new` is `old` but for its `stamp` field (compared field by field: stops at the first
    difference, and rows shared by both are not compared again)."""
    a, b = old.__dict__, new.__dict__
    return type(old) is type(new) and a.keys() == b.keys() and all(a[k] == b[k] for k in a if k != "stamp")
