"""`erni.testing`: an agent for the plugin under test, task helpers, a team on a mock network, a fake robot."""

from __future__ import annotations

import pytest

from erni import Plugin, Pose, Task, TaskState
from erni.testing import MockTeam, agent_with, fake_robot, post_task, run_task, wait_for_task


class Answer(Plugin):
    """Succeeds every BotMotion task with the preposition as its message."""

    def setup(self) -> None:
        self.tasks = self.subscribe(Task, where=lambda t: t.verb == "BotMotion")

    def execute(self) -> None:
        for task in self.tasks.added:
            self.change(task.with_result(TaskState.SUCCEEDED, message=task.preposition))


def test_an_agent_with_the_plugin_runs_a_task_to_its_end() -> None:
    with agent_with(Answer) as agent:
        done = run_task(agent, "BotMotion", "goto", x=1, y=2)
    assert done.state is TaskState.SUCCEEDED and done.result is not None and done.result.message == "goto"
    assert done.source == "robot1"


def test_a_task_that_does_not_end_is_named_with_its_state() -> None:
    with agent_with("echo", settings={"verbs": ["NetWatch"]}) as agent:
        task = post_task(agent, "BotMotion", "stop")
        with pytest.raises(AssertionError, match=rf"task {task.uid} not done within 0.2 s at robot1 \(pending"):
            wait_for_task(agent, task, timeout=0.2)


def test_agents_of_a_mock_team_task_each_other_through_the_real_transport() -> None:
    with MockTeam(seed=4, loss=0.2) as team:
        team.add("control", role="control")
        team.add("robot1").add_plugin(Answer)
        team.add("robot2").add_plugin(Answer)
        team.start()
        done = [run_task(team["control"], "BotMotion", "forward", destination=name, distance=1)
                for name in ("robot1", "robot2")]
        assert [t.state for t in done] == [TaskState.SUCCEEDED] * 2
        assert wait_for_task(team["robot2"], done[1]).source == "control"


def test_a_fake_robot_drives_where_it_is_told() -> None:
    with agent_with("motion", settings=fake_robot()) as agent:
        done = run_task(agent, "BotMotion", "forward", distance=0.5, timeout=10)
        assert done.state is TaskState.SUCCEEDED, done.result
        (pose,) = agent.query(Pose)
    assert pose.x == pytest.approx(0.5, abs=0.05)
