"""Nav2's NavigateToPose action for the ros2 plugin: the goals it accepted, their statuses, feedback and results.

A goal is carried by ERNI tasks the plugin posts (a goto, then a turn to the goal's heading); the
navigator follows them on the blackboard and answers the action's services (send_goal, get_result,
cancel_goal) and publishes its topics (feedback, status) as rcl_action does. It keeps the goals'
state; the plugin gives it what it reads and writes through (`get`, `remove`, `send`, `wake_in`)
and the time.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from erni import ros2_messages as messages
from erni.blackboard.errors import UsageError
from erni.blackboard.objects import BBObject
from erni.blackboard.tasks import Pose, Task, TaskState
from erni.ros2_rmw import Request

# action_msgs/msg/GoalStatus
ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED = 1, 2, 3, 4, 5, 6
UNKNOWN_ERROR = 9000  # nav2_msgs/action/NavigateToPose_Result.UNKNOWN
KEEP_ENDED_GOALS = 100  # ended goals whose results are kept for get_result


@dataclass
class Goal:
    """A NavigateToPose goal: the goto (then the turn) that carries it, its status, who waits for its result."""

    goal_id: bytes
    robot: str
    stamp_ns: int
    x: float
    y: float
    started: float
    run: int  # the plugin's run that posted it (its tasks are on the blackboard from the next one)
    status: int = ACCEPTED
    goto: str | None = None
    turn: str | None = None  # None: not decided yet; "": no turn
    cancel: bool = False
    error: str = ""
    waiters: list[Request] = field(default_factory=list)
    feedback_at: float = -math.inf

    @property
    def ended(self) -> bool:
        return self.status in (SUCCEEDED, CANCELED, ABORTED)


class Navigator:
    """The NavigateToPose goals of the robots a ros2 plugin serves."""

    def __init__(self, *, get: Callable[[str], BBObject | None], remove: Callable[[BBObject], None],
                 send: Callable[[str, str, Any, int], None], wake_in: Callable[[float], Any],
                 topic: Callable[[str], str], frame: str, feedback_hz: float, log: Any) -> None:
        self.goals: dict[bytes, Goal] = {}
        self._get, self._remove, self._send, self._wake_in, self._topic = get, remove, send, wake_in, topic
        self.frame, self.feedback_hz, self.log = frame, feedback_hz, log

    def goal(self, goal_id: bytes | None) -> Goal | None:
        """The goal with this id (None for None or an id no goal has)."""
        return self.goals.get(goal_id) if goal_id is not None else None

    def send_goal(self, robot: str, request: Request, *, goal_heading: bool, now: float, now_ns: int, run: int
                  ) -> tuple[dict[str, float], float | None, bytes] | None:
        """A goal accepted (its goto's parameters, the heading to turn to, its id) or refused (None, answered)."""
        msg = messages.deserialize(request.payload, f"{messages.SEND_GOAL}_Request")
        goal_id = bytes(msg.goal_id.uuid)
        try:
            if goal_id in self.goals:
                raise UsageError("a goal with this id exists")
            params = messages.goto_params(msg.goal.pose)
        except ValueError as err:
            self.log.warning("ros2: navigate_to_pose goal for %s rejected: %s", robot, err)
            request.reply(messages.serialize(messages.make(f"{messages.SEND_GOAL}_Response", accepted=False,
                                                           stamp=messages.stamp(now_ns))))
            return None
        heading = messages.goal_heading(msg.goal.pose) if goal_heading else None
        self.goals[goal_id] = Goal(goal_id, robot, now_ns, params["x"], params["y"], now, run)
        request.reply(messages.serialize(messages.make(f"{messages.SEND_GOAL}_Response", accepted=True,
                                                       stamp=messages.stamp(now_ns))))
        self.publish_status(robot, now_ns)
        return params, heading, goal_id

    def get_result(self, request: Request) -> None:
        msg = messages.deserialize(request.payload, f"{messages.GET_RESULT}_Request")
        goal = self.goals.get(bytes(msg.goal_id.uuid))
        if goal is None:  # rcl_action answers an unknown goal at once, with status UNKNOWN
            request.reply(self._result(None))
        elif goal.ended:
            request.reply(self._result(goal))
        else:
            goal.waiters.append(request)

    @staticmethod
    def _result(goal: Goal | None) -> bytes:
        code = 0 if goal is None or goal.status == SUCCEEDED else UNKNOWN_ERROR
        result = messages.make(f"{messages.NAVIGATE_TO_POSE}_Result", error_code=code,
                               error_msg=goal.error if goal is not None else "")
        return messages.serialize(messages.make(f"{messages.GET_RESULT}_Response",
                                                status=goal.status if goal is not None else 0, result=result))

    def cancel_goal(self, robot: str, request: Request, now_ns: int) -> None:
        """rcl_action's rules: a zero goal id and a zero stamp cancel every goal, a zero id and a stamp every goal
        accepted at or before it, an id that goal (and those at or before a stamp given with it)."""
        msg = messages.deserialize(request.payload, f"{messages.CANCEL_GOAL}_Request")
        goal_id = bytes(msg.goal_info.goal_id.uuid)
        stamp_ns = msg.goal_info.stamp.sec * 1_000_000_000 + msg.goal_info.stamp.nanosec
        mine = [g for g in self.goals.values() if g.robot == robot]
        chosen = [g for g in mine if g.goal_id == goal_id or (not any(goal_id) and not stamp_ns)
                  or (stamp_ns and g.stamp_ns <= stamp_ns)]
        canceling = [g for g in chosen if not g.ended]
        for goal in canceling:
            goal.cancel, goal.status = True, CANCELING
            for uid in (goal.goto, goal.turn):
                task = self._get(uid) if uid else None
                if isinstance(task, Task) and not task.done:
                    self._remove(task)
        code = 0 if canceling else (3 if chosen else (2 if any(goal_id) else 0))  # NONE, GOAL_TERMINATED, UNKNOWN_GOAL_ID
        infos = [messages.make("action_msgs/msg/GoalInfo", goal_id=messages.uuid(g.goal_id),
                               stamp=messages.stamp(g.stamp_ns)) for g in canceling]
        request.reply(messages.serialize(messages.make(f"{messages.CANCEL_GOAL}_Response", return_code=code,
                                                       goals_canceling=infos)))
        if canceling:
            self.publish_status(robot, now_ns)

    def update(self, now: float, now_ns: int, run: int) -> None:
        """Each goal's status from its goto and turn; feedback while it runs; the result to those waiting."""
        changed: set[str] = set()
        for goal in self.goals.values():
            if goal.ended or goal.goto is None or goal.run == run:
                continue
            before = goal.status
            self._follow(goal)
            if goal.status != before:
                changed.add(goal.robot)
            if goal.status == EXECUTING and now - goal.feedback_at >= 1.0 / self.feedback_hz:
                goal.feedback_at = now
                self._publish_feedback(goal, now)
            if not goal.ended:
                self._wake_in(0.1)
        for robot in changed:
            self.publish_status(robot, now_ns)
        ended = [g.goal_id for g in self.goals.values() if g.ended]
        for goal_id in ended[:max(0, len(ended) - KEEP_ENDED_GOALS)]:
            del self.goals[goal_id]

    def _follow(self, goal: Goal) -> None:
        """A goal's status as its task says: the goto's, then (once it succeeded) the turn's."""
        goto = self._get(goal.goto) if goal.goto else None
        turn = self._get(goal.turn) if goal.turn else None
        if isinstance(goto, Task) and goto.state is TaskState.SUCCEEDED and goal.turn:
            current: Any = turn
        else:
            current = goto
        if not isinstance(current, Task):
            self.end(goal, CANCELED if goal.cancel else ABORTED, "the task was removed")
        elif current.state is TaskState.SUCCEEDED and (current is turn or goal.turn == ""):
            self.end(goal, SUCCEEDED, "")
        elif current.done:
            message = current.result.message if current.result else ""
            self.end(goal, CANCELED if goal.cancel else ABORTED, f"{current.preposition} "
                     f"{current.state.value}" + (f": {message}" if message else ""))
        elif not goal.cancel and current.state is TaskState.RUNNING:
            goal.status = EXECUTING

    def end(self, goal: Goal, status: int, error: str) -> None:
        """End a goal: its status, its error, and its result to those waiting for it."""
        goal.status, goal.error = status, error
        waiters, goal.waiters = goal.waiters, []
        for request in waiters:
            request.reply(self._result(goal))

    def _publish_feedback(self, goal: Goal, now: float) -> None:
        pose = self._get(f"pose:{goal.robot}")
        if not isinstance(pose, Pose):
            return
        stamp_ns = messages.stamp_ns_of(pose.stamp)
        current = messages.make(messages.POSE_STAMPED, header=messages.header(stamp_ns, self.frame),
                                pose=messages.ros_pose(pose.x, pose.y, pose.theta))
        feedback = messages.make(f"{messages.NAVIGATE_TO_POSE}_Feedback", current_pose=current,
                                 navigation_time=messages.duration(now - goal.started),
                                 distance_remaining=math.hypot(goal.x - pose.x, goal.y - pose.y))
        self._send(messages.FEEDBACK_MESSAGE, f"{self._topic(goal.robot)}/feedback",
                   messages.make(messages.FEEDBACK_MESSAGE, goal_id=messages.uuid(goal.goal_id), feedback=feedback),
                   stamp_ns)

    def publish_status(self, robot: str, stamp_ns: int) -> None:
        """A robot's goals and their statuses on its action's status topic."""
        statuses = [messages.make("action_msgs/msg/GoalStatus", status=g.status,
                                  goal_info=messages.make("action_msgs/msg/GoalInfo", goal_id=messages.uuid(g.goal_id),
                                                          stamp=messages.stamp(g.stamp_ns)))
                    for g in self.goals.values() if g.robot == robot]
        self._send(messages.GOAL_STATUS_ARRAY, f"{self._topic(robot)}/status",
                   messages.make(messages.GOAL_STATUS_ARRAY, status_list=statuses), stamp_ns)
