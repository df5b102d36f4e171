"""The task language: typed parameters per preposition, clear refusals, results."""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st

from erni.blackboard import AllocationResult, NetInfo, Pose, Task, TaskError, TaskState
from erni.blackboard.tasks import PREPOSITIONS, VERBS, GotoParams, language_table


def test_every_preposition_of_table_2_exists():
    expected = {
        "NetWatch": {"node_position", "network_topology", "path_cost", "link_quality", "neighbor_list"},
        "BotMotion": {"randomwalk", "goto", "stop", "turn", "teleport", "clear", "velocity",
                      "avoid_obstacles", "forward", "backward", "say"},
        "RemoteBotMotion": {"randomwalk", "goto", "cancel", "teleport", "forward"},
        "Deploy": {"widep", "spread", "relay", "patrol"},
    }
    for verb, preps in expected.items():
        assert {p for (v, p) in PREPOSITIONS if v == verb} == preps
    assert set(VERBS) >= set(expected)


def test_params_are_typed_by_preposition():
    task = Task(verb="BotMotion", preposition="goto", params={"x": "1.5", "y": 2}, source="r1")
    assert isinstance(task.params, GotoParams)
    assert (task.params.x, task.params.y, task.params.speed) == (1.5, 2.0, 0.3)


@pytest.mark.parametrize("data, message", [
    ({"verb": "BotMotion", "preposition": "goto", "params": {"y": 1}}, "goto: missing 'x'"),
    ({"verb": "BotMotion", "preposition": "goto", "params": {}}, "goto: missing 'x'; goto: missing 'y'"),
    ({"verb": "BotMotion", "preposition": "fly"}, "BotMotion: unknown preposition 'fly'"),
    ({"verb": "Dance", "preposition": "goto"}, "unknown verb 'Dance'"),
    ({"verb": "BotMotion", "preposition": "forward", "params": {"distance": 1, "speed": -1}},
     "forward: speed: Input should be greater than 0"),
    ({"verb": "BotMotion", "preposition": "goto", "params": {"x": 1, "y": 1, "z": 1}},
     "goto: unknown key 'z'"),
    ({"verb": "BotMotion", "preposition": "turn", "params": {"angle": "left"}},
     "turn: angle: Input should be a valid number"),
    ({"verb": "BotMotion", "preposition": "goto", "params": "x=1"},
     "goto: params: expected a table of parameters"),
    ({"preposition": "goto"}, "goto: missing 'verb'"),
])
def test_invalid_tasks_are_refused_naming_the_field(data, message):
    with pytest.raises(TaskError) as info:
        Task(**data)
    assert str(info.value).startswith(message)
    with pytest.raises(TaskError) as info:
        Task.parse(json.dumps(data))
    assert message.split(";")[0] in str(info.value)


def test_preposition_spellings_normalize():
    for spelling in ("avoid obstacles", "Avoid-Obstacles", "avoid_obstacles"):
        assert Task(verb="BotMotion", preposition=spelling).preposition == "avoid_obstacles"


def test_json_round_trip_keeps_types():
    task = Task(verb="NetWatch", preposition="path_cost", params={"rate_hz": 2, "destination": "r3"},
                source="r1", destination="r2", parent="p1")
    task = task.with_result(TaskState.RUNNING, progress=0.25, values={"pose": {"x": 1.0}, "hops": 3})
    back = Task.parse(task.model_dump_json())
    assert back == task
    assert back.params.destination == "r3"
    assert back.result.values["hops"] == 3


def test_with_result_keeps_unspecified_fields_and_uid():
    task = Task(verb="BotMotion", preposition="stop")
    t1 = task.with_result(TaskState.RUNNING, progress=0.5, message="halfway")
    t2 = t1.with_result(progress=0.75)
    assert t2.uid == task.uid and t2.state is TaskState.RUNNING
    assert t2.result.message == "halfway" and t2.result.progress == 0.75
    assert not t2.done and t2.with_result(TaskState.FAILED).done


def test_result_bounds_are_checked():
    with pytest.raises(ValueError):
        AllocationResult(progress=1.5)
    with pytest.raises(ValueError):
        AllocationResult(confidence=-0.1)


def test_objects_are_frozen():
    pose = Pose(robot="r1", x=1.0)
    with pytest.raises(ValueError):
        pose.x = 2.0  # type: ignore[misc]
    assert pose.uid == "pose:r1" and pose.evolve(x=2.0).uid == "pose:r1"


def test_netinfo_carries_typed_network_state():
    info = NetInfo(node="r1", kind="neighbor_list",
                   neighbors=[{"name": "r2", "quality": 0.9}], articulation_points=["r1"])
    assert info.neighbors[0].quality == 0.9
    with pytest.raises(ValueError):
        NetInfo(node="r1", kind="neighbor_list", neighbors=[{"name": "r2", "quality": 2}])


def test_language_table_lists_every_preposition():
    table = language_table()
    for (verb, prep) in PREPOSITIONS:
        assert f"| {verb} | `{prep}` |" in table


@given(x=st.floats(allow_nan=False, allow_infinity=False, width=32),
       y=st.floats(allow_nan=False, allow_infinity=False, width=32),
       speed=st.floats(min_value=0.01, max_value=2.0))
def test_goto_round_trips_any_finite_target(x, y, speed):
    task = Task(verb="RemoteBotMotion", preposition="goto", params={"x": x, "y": y, "speed": speed})
    assert Task.parse(task.model_dump_json()).params == task.params


@given(st.dictionaries(st.text(max_size=5), st.one_of(st.integers(), st.text(max_size=5), st.none()),
                       max_size=4))
def test_random_params_either_validate_or_raise_task_error(params):
    try:
        Task(verb="BotMotion", preposition="goto", params=params)
    except TaskError as err:
        assert str(err).startswith("goto: ")


def test_the_reference_page_is_the_language():
    """The site's task-language page is generated from the registry, as `erni tasks` prints it."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / "docs" / "hooks.py"
    spec = importlib.util.spec_from_file_location("erni_docs_hooks", path)
    assert spec is not None and spec.loader is not None
    hooks = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hooks)
    page = hooks.expand((path.parent / "reference" / "tasks.md").read_text(encoding="utf-8"))
    assert language_table() in page, "the task-language page no longer shows what `erni tasks` prints"


@pytest.mark.parametrize("params, message", [
    ({"x": float("nan"), "y": 1}, "goto: x: expected a finite number, got nan"),
    ({"x": 1, "y": float("-inf")}, "goto: y: expected a finite number, got -inf"),
    ({"x": True, "y": 1}, "goto: x: expected a number, got True (a boolean)"),
    ({"x": "nan", "y": 1}, "goto: x: Input should be a finite number"),
    ({"x": 1, "y": 2, "timeout": False}, "goto: timeout: expected a number, got False (a boolean)"),
    ({"x": "z" * 100_000, "y": 1}, "goto: x: Input should be a valid number"),
])
def test_numbers_are_finite_and_never_booleans_and_long_values_are_cut(params, message):
    with pytest.raises(TaskError) as info:
        Task(verb="BotMotion", preposition="goto", params=params)
    text = str(info.value)
    assert text.startswith(message) and "\n" not in text and len(text) < 200, text
    for verb, prep in (("z" * 100_000, "goto"), ("BotMotion", "y" * 100_000)):
        with pytest.raises(TaskError) as info:
            Task(verb=verb, preposition=prep)
        assert len(str(info.value)) < 400


def test_results_refuse_non_finite_numbers():
    task = Task(verb="BotMotion", preposition="stop")
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="finite number"):
        task.with_result("running", progress=float("nan"))


def test_the_language_table_shows_every_default_as_a_value():
    """A default made by a factory is shown as the value it makes, written as on the command line."""
    table = language_table()
    assert "PydanticUndefined" not in table
    (say,) = [row for row in table.splitlines() if "| `say` |" in row]
    assert "`tones` = [[10, 72]]:" in say


def test_a_trusted_pose_is_the_pose_validation_makes():
    """`BBObject.trusted` (a codec's hot path) makes what `model_validate` makes of the same checked
    values: the same fields, the same fields given, frozen."""
    data = {"robot": "robot2", "x": 1.5, "y": -2.0, "theta": 0.5, "battery": 12.5, "sonar": [0.5, 1.0], "stamp": 1000.5}
    checked = Pose.model_validate(data)
    trusted = Pose.trusted(dict(checked.__dict__), set(checked.model_fields_set))
    assert trusted == checked and trusted.model_fields_set == checked.model_fields_set
    assert trusted.model_dump_json() == checked.model_dump_json()
    with pytest.raises(Exception, match="frozen"):
        trusted.x = 2.0
