"""Every number of every ERNI model is finite: NaN and the infinities are refused wherever a model
is validated, from Python values and from JSON text alike (pydantic's JSON parser reads `NaN` and
`Infinity` unless the model says otherwise), in fixed float fields and in free-form ones
(a result's values, a watch event's data, a plugin's settings table).

The models are found, not listed: every pydantic model defined in the `erni` package. Each must
validate from a sample below or from nothing (its defaults), so a model added later is held to
the same rule, or this test asks for its sample.
"""

from __future__ import annotations

import importlib
import json
import math
import pkgutil
import typing
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import BaseModel, JsonValue, ValidationError

import erni
from erni.blackboard import ErniError, NetInfo, Pose, Task, TaskError
from erni.blackboard.objects import finite_inside

NON_FINITE = [math.nan, math.inf, -math.inf]


def _all_models() -> list[type[BaseModel]]:
    for info in pkgutil.walk_packages(erni.__path__, "erni."):
        if not info.name.endswith("__main__"):
            importlib.import_module(info.name)
    found: set[type[BaseModel]] = set()
    todo = list(BaseModel.__subclasses__())
    while todo:
        cls = todo.pop()
        todo.extend(cls.__subclasses__())
        if cls.__module__.startswith("erni.") and "[" not in cls.__name__:  # not a generic's parametrisation
            found.add(cls)
    return sorted(found, key=lambda c: (c.__module__, c.__qualname__))


MODELS = _all_models()

_GOOD_POSE = {"robot": "robot2", "x": 1.5, "y": -2.25, "theta": 0.5, "v": 0.25, "w": -0.125, "battery": 12.5,
              "sonar": [0.5, 1.25, 2.0], "stamp": 1000.5}
_RESULT = {"state": "running", "confidence": 0.75, "progress": 0.5, "values": {"distance": 1.5, "pose": [1.0, 2.0],
           "deep": {"a": [{"b": 0.5}]}}, "message": "on its way", "stamp": 1000.25}
_POSE_ROW = {"x": 1.5, "y": -2.25, "theta": 0.5, "v": 0.25, "w": -0.125, "battery": 12.5}
_TASK_ROW = {"uid": "u", "robot": "robot1", "verb": "BotMotion", "preposition": "forward", "text": "forward distance=1.5",
             "params": {"distance": 1.5}, "source": "control", "created": 1000.5, "state": "running", "progress": 0.5,
             "message": "", "values": {"d": 0.25}}
SAMPLES: dict[str, dict[str, Any]] = {
    "AgentConfig": {"agent": {"name": "a"}, "plugin": [{"class": "echo", "settings": {"delay": 0.5, "t": [1.5]}}]},
    "AgentSection": {"name": "a", "slow_plugin_seconds": 1.5, "retention": 60.5},
    "PluginSection": {"class": "echo", "settings": {"delay": 0.5, "nested": {"x": [0.5, {"y": 2.5}]}}},
    "Cancel": {"uid": "u"}, "StatusRemoved": {"uid": "u"}, "StatusResend": {"uid": "u"}, "TaskQuery": {"uid": "u"},
    "TaskRescind": {"uid": "u"}, "TaskUnknown": {"uid": "u"}, "_ByUid": {"uid": "u"},
    "Circle": {"center": [1.5, 2.5], "radius": 0.5},
    "Polygon": {"points": [[0.5, 0.5], [1.5, 0.5], [1.5, 1.5]]},
    "Wall": {"a": [0.5, 0.5], "b": [1.5, 2.5]},
    "FloorPlan": {"bounds": [-1.5, -1.5, 1.5, 1.5], "wall": [{"a": [0.5, 0.5], "b": [1.5, 2.5]}],
                  "circle": [{"center": [1.5, 2.5], "radius": 0.5}]},
    "Fresh": {"uid": "u", "base": 10.5, "stamp": 11.5},
    "Beacon": {"interval": 1.5},
    "Peer": {"name": "robot2", "last_heard": 1000.5},
    "PeerList": {"agent": "control", "peers": [{"name": "robot2", "last_heard": 1000.5}],
                 "down_after": {"robot2": 2.5}, "beacons": {"robot2": 0.75}},
    "ResultUpdate": {"uid": "u", "result": _RESULT},
    "WatchEvent": {"agent": "control", "op": "change", "type": "Pose", "data": dict(_GOOD_POSE)},
    "WatchRequest": {"lease": 10.5},
    "AllocationResult": _RESULT,
    "Link": {"a": "r1", "b": "r2", "quality": 0.5}, "Neighbor": {"name": "r2", "quality": 0.5, "recent": 0.25},
    "Route": {"destination": "r2", "cost": 1.5}, "Position": {"x": 1.5, "y": 2.5, "heading": 90.5},
    "NetInfo": {"node": "r1", "kind": "network_topology", "neighbors": [{"name": "r2", "quality": 0.5}],
                "links": [{"a": "r1", "b": "r2", "quality": 0.5}], "routes": [{"destination": "r2", "cost": 1.5}],
                "positions": {"r2": {"x": 1.5, "y": 2.5}}, "stamp": 1000.5},
    "Pose": _GOOD_POSE,
    "Task": {"verb": "BotMotion", "preposition": "goto", "params": {"x": 1.5, "y": 2.5, "speed": 0.25},
             "source": "control", "destination": "robot2", "result": _RESULT, "created": 1000.5},
    "BackwardParams": {"distance": 1.5}, "DistanceParams": {"distance": 1.5}, "ForwardParams": {"distance": 1.5},
    "GotoParams": {"x": 1.5, "y": 2.5}, "PatrolParams": {"xmin": 0.5, "ymin": 0.5, "xmax": 1.5, "ymax": 1.5},
    "RelayParams": {"source": "a", "destination": "b"}, "TeleportParams": {"x": 1.5, "y": 2.5},
    "TurnParams": {"angle": 90.5}, "WidepParams": {"x": 1.5, "y": 2.5},
    "World": {"bounds": [-5.5, -5.5, 5.5, 5.5], "robot": [{"name": "sim1", "x": 1.5, "y": 2.5, "heading": 90.5}]},
    "Territory": {"robot": "r1", "block": [0.5, 0.5, 1.5, 1.5], "claims": {"r2": 10.5}, "stamp": 1.5},
    "CancelTaskMsg": {"type": "cancel_task", "uid": "u"},
    "CommandMsg": {"type": "command", "robots": ["robot1"], "action": "goto", "params": {"x": 1.5, "y": 2.5}},
    "MicMsg": {"type": "mic", "on": True}, "PingMsg": {"type": "ping"},
    "SayMsg": {"type": "say", "text": "robot 1 stop"}, "SelectMsg": {"type": "select", "robots": ["robot1"]},
    "ReplaySettings": {"log": "run.jsonl", "speed": 1.5},
    "SensorAck": {"consumer": "c", "robot": "r1", "seq": 1, "seen": 1.5},
    "SensorReading": {"robot": "r1", "seq": 1, "obstacle": [1.5, 2.5], "temperature": 20.5},
    "SourceSettings": {"out": "c", "gap": 0.5},
    "MoveSpec": {"at": 1.5, "node": "n1", "x": 1.5, "y": 2.5}, "NodeSpec": {"name": "n1", "x": 1.5, "y": 2.5},
    "erni.sim.manet_scenario.Scenario": {"comm_range": 10.5, "lossless_range": 5.5,
                                         "nodes": [{"name": "n1", "x": 1.5, "y": 2.5}]},
    "erni.sim.scenario.Scenario": {"duration": 10.5},
    "FailureSpec": {"at": 1.5, "robot": "robot1"}, "PoiSpec": {"x": 1.5, "y": 2.5},
    "TaskSpec": {"at": 1.5, "verb": "BotMotion", "preposition": "goto", "params": {"x": 1.5, "y": 2.5}},
    "Received": {"task": "u", "sender": "control"},
    "Relayed": {"task": {"verb": "BotMotion", "preposition": "forward", "params": {"distance": 1.5},
                         "source": "control", "destination": "robot2"}, "role": "control"},
    "TransportSettings": {"key": "a-team-key-of-some-length", "beacon_period": 0.5, "ack_timeout": 0.25},
    "Hello": {"sender": "a", "inst": "0" * 32, "reply": ["127.0.0.1", 5000], "eph": "0" * 64, "nonce": "0" * 32},
    "Envelope": {"sender": "robot2", "id": "m1", "kind": "status", "type": "Pose", "body": dict(_GOOD_POSE)},
    "EnvelopeHead": {"sender": "robot2", "reply": ["127.0.0.1", 5000]},
    "EnvelopeItem": {"id": "m1", "kind": "status", "body": {"a": [1.5, {"b": 2.5}]}},
    # what the control node's server sends the page
    "PoseRow": dict(_POSE_ROW),
    "RobotRow": {"name": "robot1", "number": 1, "up": True, "state": "ok", "reasons": [], "pose": dict(_POSE_ROW),
                 "address": "127.0.0.1:5000", "task": ""},
    "LinkRow": {"a": "robot1", "b": "robot2", "quality": 0.75, "stale": False},
    "TaskRow": dict(_TASK_ROW),
    "Metrics": {"robots": 2, "up": 2, "links": 1, "mean_quality": 0.75, "components": 1, "articulation_points": [],
                "degree": 1.5, "network_known": True},
    "LogLine": {"t": 1000.5, "level": "info", "text": "hello"},
    "SpeechState": {"available": False, "error": "", "recogniser": ""},
    "Picture": {"agent": "control", "verb": "BotMotion", "actions": ["goto"], "strategies": [],
                "speech": {"available": False, "error": "", "recogniser": ""}, "listening": False,
                "robots": [], "links": [], "floorplan": None,
                "metrics": {"robots": 0, "up": 0, "links": 0, "mean_quality": 0.5, "components": 0,
                            "articulation_points": [], "degree": 0.5, "network_known": False},
                "tasks": [dict(_TASK_ROW)], "log": [{"t": 1000.5, "level": "info", "text": "hello"}]},
    "HelloMsg": {"client": "page1"},
    "ReplyMsg": {"text": "Roger", "heard": "", "channel": "page", "client": "page1", "accepted": True},
    "SelectOut": {"robots": ["robot1"]},
    "ErrorMsg": {"message": "bad"},
}


def _valid(cls: type[BaseModel]) -> BaseModel:
    """A valid object of `cls`: its sample, or its defaults."""
    data = SAMPLES.get(f"{cls.__module__}.{cls.__name__}", SAMPLES.get(cls.__name__, {}))
    try:
        return cls.model_validate(data)
    except (ValidationError, ErniError) as err:
        pytest.fail(f"{cls.__module__}.{cls.__qualname__}: give it a valid sample in SAMPLES ({err})")


def _leaves(data: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Paths to the floats of plain data (tables, lists)."""
    if isinstance(data, float):
        return [path]
    if isinstance(data, dict):
        return [p for k, v in data.items() for p in _leaves(v, (*path, k))]
    if isinstance(data, (list, tuple)):
        return [p for i, v in enumerate(data) for p in _leaves(v, (*path, i))]
    return []


def _replace(data: Any, path: tuple[Any, ...], value: Any) -> Any:
    if not path:
        return value
    if isinstance(data, dict):
        return {**data, path[0]: _replace(data[path[0]], path[1:], value)}
    items = list(data)
    items[path[0]] = _replace(items[path[0]], path[1:], value)
    return items


def _refused(call: Any) -> bool:
    try:
        call()
    except (ValidationError, ErniError, ValueError):
        return True
    return False


def test_every_model_of_erni_is_found_and_refuses_non_finite_numbers_by_its_config():
    assert len(MODELS) > 80 and Pose in MODELS and NetInfo in MODELS
    lax = [f"{c.__module__}.{c.__qualname__}" for c in MODELS if c.model_config.get("allow_inf_nan") is not False]
    assert not lax, f"models that take NaN or infinities: {lax}"


def _free_form(annotation: Any) -> bool:
    """Whether a field's type lets any value through unchecked: Any, object or JsonValue, not wrapped
    in the finite check."""
    if annotation in (Any, object) or annotation is JsonValue:
        return True
    if typing.get_origin(annotation) is typing.Annotated:
        base, *meta = typing.get_args(annotation)
        if any(getattr(m, "func", None) is finite_inside for m in meta):
            return False
        return _free_form(base)
    return any(_free_form(a) for a in typing.get_args(annotation) if a is not Ellipsis)


def test_every_free_form_field_checks_the_numbers_inside():
    loose = [f"{c.__module__}.{c.__qualname__}.{name}" for c in MODELS for name, f in c.model_fields.items()
             if _free_form(f.annotation) and not any(getattr(m, "func", None) is finite_inside for m in f.metadata)]
    assert not loose, f"free-form fields that let NaN through: {loose}"


@settings(max_examples=400, deadline=None)
@given(st.data())
def test_a_non_finite_number_anywhere_in_any_model_is_refused_from_python_and_from_json(data):
    cls = data.draw(st.sampled_from(MODELS), label="model")
    obj = _valid(cls)
    bad = data.draw(st.sampled_from(NON_FINITE), label="value")
    dumped = obj.model_dump(mode="python", by_alias=True)
    if _refused(lambda: cls.model_validate(dumped)):  # a default that counts as given (zenoh settings on udp)
        dumped = obj.model_dump(mode="python", by_alias=True, exclude_unset=True)
    leaves = _leaves(dumped)
    if leaves:  # from Python values
        assert not _refused(lambda: cls.model_validate(dumped)), f"{cls.__name__}: its own dump does not validate"
        path = data.draw(st.sampled_from(leaves), label="path")
        hostile = _replace(dumped, path, bad)
        assert _refused(lambda: cls.model_validate(hostile)), f"{cls.__name__} took {bad} at {path}"
    dumped = obj.model_dump(mode="json", by_alias=True, exclude_unset=True)
    leaves = _leaves(dumped)
    if leaves and not _refused(lambda: cls.model_validate_json(json.dumps(dumped))):  # a secret shows as ***
        path = data.draw(st.sampled_from(leaves), label="json path")
        text = json.dumps(_replace(dumped, path, bad))  # NaN, Infinity, -Infinity: what Python's json writes
        assert _refused(lambda: cls.model_validate_json(text)), f"{cls.__name__} took {text}"


def test_every_sample_has_a_float_to_spoil_or_the_model_has_none():
    """The test above only bites where a sample holds floats: a model with a float field whose sample
    (or defaults) holds none is a gap."""
    gaps = []
    for cls in MODELS:
        has_float = any("float" in repr(f.annotation) for f in cls.model_fields.values())
        if has_float and not _leaves(_valid(cls).model_dump(mode="python", by_alias=True)):
            gaps.append(cls.__name__)
    assert not gaps, f"models with a float field but no float in their sample: {gaps}"


@pytest.mark.parametrize("where", ["values", "data", "settings", "body"])
@given(path=st.lists(st.sampled_from(["a", "b", 0]), max_size=4), bad=st.sampled_from(NON_FINITE))
@settings(max_examples=60, deadline=None)
def test_free_form_tables_refuse_a_non_finite_number_at_any_depth(where, path, bad):
    value: Any = bad
    for key in reversed(path):
        value = [value] if key == 0 else {key: value}
    cls, data = {"values": ("AllocationResult", {"values": {"v": value}}),
                 "data": ("WatchEvent", {**SAMPLES["WatchEvent"], "data": {"v": value}}),
                 "settings": ("PluginSection", {"class": "echo", "settings": {"v": value}}),
                 "body": ("EnvelopeItem", {"id": "m", "kind": "k", "body": {"v": value}})}[where]
    model = next(c for c in MODELS if c.__name__ == cls)
    assert _refused(lambda: model.model_validate(data))
    assert _refused(lambda: model.model_validate_json(json.dumps(data)))


def test_pose_from_json_with_nan_and_infinity_is_refused_naming_the_fields():
    with pytest.raises(ValidationError) as err:
        Pose.model_validate_json('{"robot": "robot2", "x": NaN, "y": Infinity, "theta": -Infinity}')
    assert {e["loc"][0] for e in err.value.errors()} == {"x", "y", "theta"}
    with pytest.raises(ValidationError):
        Pose.model_validate_json('{"robot": "robot2", "x": 1e400}')  # too large for a float: infinity
    with pytest.raises(TaskError):
        Task.parse('{"verb": "BotMotion", "preposition": "goto", "params": {"x": 1, "y": 2}, '
                   '"result": {"values": {"left": NaN}}}')


@pytest.mark.parametrize("text, says", [
    ("[agent]\nname = 'r1'\nretention = nan\n", "agent.retention: Input should be a finite number"),
    ("[agent]\nname = 'r1'\n[[plugin]]\nclass = 'echo'\n[plugin.settings]\ndelay = inf\n",
     "plugin[0].settings.delay: expected a finite number, got inf"),
    ("[agent]\nname = 'r1'\n[[plugin]]\nclass = 'echo'\n[plugin.settings]\nverbs = ['BotMotion']\nx = {y = [1.0, -inf]}\n",
     "expected a finite number, got -inf (at y[1])"),
])
def test_a_config_file_with_nan_or_inf_is_refused_naming_the_field(tmp_path, text, says):
    """TOML writes `nan` and `inf` as floats: a config that holds one is refused by `erni agent --check`."""
    import subprocess
    import sys

    path = tmp_path / "robot.toml"
    path.write_text(text)
    out = subprocess.run([sys.executable, "-m", "erni", "agent", str(path), "--check"], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 2 and says in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_a_plugin_from_elsewhere_gets_its_settings_checked_for_finite_numbers_too():
    """A plugin whose Settings derive from pydantic's BaseModel (not ERNI's Model) still refuses NaN:
    the agent validates settings through a strict subclass of them."""
    from erni.blackboard import Agent, ConfigError, Plugin

    class Settings(BaseModel):
        gain: float = 1.0

    class Outside(Plugin[Settings]):
        pass

    agent = Agent("outside", workers=1)
    with pytest.raises(ConfigError, match="settings.gain: Input should be a finite number"):
        agent.add_plugin(Outside, settings={"gain": math.nan})
    with pytest.raises(ConfigError, match="unknown key 'gian'"):
        agent.add_plugin(Outside, settings={"gian": 1.0})
    assert agent.add_plugin(Outside, settings={"gain": 2.0}).settings.gain == 2.0
