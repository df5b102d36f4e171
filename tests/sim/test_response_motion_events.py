"""Paper 003, Table I: the behaviour stack cycles on the SIP that shows a commanded motion at
once, and the Pose of a reading that starts or stops motion is handed over at once. The clocks here
stand still or move by hand, so a SIP or a Pose held back by a rate would be held for good."""

from __future__ import annotations

import threading

from erni.blackboard import Task
from erni.blackboard.testing import wait_until
from erni.plugins.motion.driver import RobotState
from erni.plugins.motion.resource import RobotMotionResource
from erni.plugins.motion.robots import resolve_model


class Driver:
    """Stands in for the ARCOS driver: records the velocity asked, takes the SIPs it is given."""

    on_sip = None
    sip_interval = 0.01
    is_simulator = True
    last_error = ""

    def __init__(self) -> None:
        self.connected = True
        self.model = resolve_model("pioneer3")
        self.state: RobotState | None = sip(0, 0.0)
        self.asked = threading.Event()

    def vel(self, v: float) -> bool:
        if v:
            self.asked.set()
        return True

    def rvel(self, w: float) -> bool:
        return True

    def stop(self) -> bool:
        return True

    def open(self, wait: bool = True) -> None: ...
    def close(self) -> None: ...


def sip(seq: int, v: float) -> RobotState:
    return RobotState(x=0.0, y=0.0, theta=0.0, v=v, w=0.0, left=v, right=v, battery=12.5, stall_left=False,
                      stall_right=False, bumpers=0, motors_enabled=True, moving=v != 0.0, sonar={}, stamp=0.0,
                      seq=seq)


def wait(condition, timeout: float = 5.0) -> bool:
    """Whether `condition()` came true within `timeout` s."""
    try:
        wait_until(condition, timeout)
    except AssertionError:
        return bool(condition())
    return True


class Holding(threading.Event):
    """The stack thread's wake-up, counting the waits it goes into with a new SIP in hand: it looked at
    that SIP and holds it back for its rate (a cycle takes the SIP in hand: `_new_sip` is reset)."""

    def __init__(self, res: RobotMotionResource) -> None:
        super().__init__()
        self.res = res
        self.held = 0

    def wait(self, timeout: float | None = None) -> bool:
        if self.res._new_sip:
            self.held += 1
        return super().wait(timeout)


def test_the_stack_cycles_on_the_sip_after_a_task_though_its_rate_would_wait():
    driver = Driver()
    shown: list[float] = []
    res = RobotMotionResource(driver, lambda updates, state: state and shown.append(state.v),  # type: ignore[arg-type]
                              rate_hz=0.1, avoid_distance=0, clock=lambda: 0.0)
    holding = res._wake = Holding(res)
    res.start()
    try:
        res.submit(Task(verb="BotMotion", preposition="velocity", params={"v": 0.2}, source="test"))
        assert driver.asked.wait(5.0), "the task's cycle sent no velocity"
        assert wait(lambda: res._steering)
        cycles = res.cycles
        driver.state = sip(1, 0.2)
        res._sip(driver.state)  # a moment after the task's cycle (the clock stands still)
        # (the rate would hold it 10 s: a wait of its own, beside the frozen clock's)
        assert wait(lambda: res.cycles == cycles + 1, 3.0), "no stack cycle on the SIP after the task's"
        held = holding.held
        driver.state = sip(2, 0.2)  # a second SIP within the rate's period: no cycle for it
        res._sip(driver.state)
        assert wait(lambda: holding.held > held or res.cycles > cycles + 1), "the stack thread did not look at the SIP"
        assert res.cycles == cycles + 1
    finally:
        res.close()


class Counted(RobotMotionResource):
    """Counts the stack thread's rounds (a cycle while steering and its Pose, if any, handed over)."""

    rounds = 0

    def _publish_sip(self) -> None:
        super()._publish_sip()
        self.rounds += 1


def test_a_reading_that_starts_or_stops_motion_is_published_at_once_the_others_at_the_pose_rate():
    """Poses are due 100 s apart and the clock moves 20 ms a SIP: only a reading that changes what
    the blackboard says about motion may go before its time. From rest to 5 cm/s starts motion,
    20 cm/s only speeds up, 8 mm/s stands as a Stop judges it, and 0 after that stops nothing new."""
    driver = Driver()
    shown: list[float] = []
    now = [0.0]
    res = Counted(driver, lambda updates, state: state and shown.append(state.v),  # type: ignore[arg-type]
                  rate_hz=100, pose_rate_hz=0.01, avoid_distance=0, clock=lambda: now[0]).start()
    try:
        assert wait(lambda: shown == [0.0]), shown  # the first reading, before any Pose was due
        res.submit(Task(verb="BotMotion", preposition="velocity", params={"v": 0.2}, source="test"))
        assert driver.asked.wait(5.0), "the task's cycle sent no velocity"
        assert wait(lambda: res._steering)
        for seq, v in enumerate([0.05, 0.2, 0.008, 0.0], start=1):
            rounds = res.rounds
            driver.state = sip(seq, v)
            now[0] += 0.02
            res._sip(driver.state)
            assert wait(lambda r=rounds: res.rounds > r), f"no stack cycle on the SIP at {v} m/s"
    finally:
        res.close()
    assert shown == [0.0, 0.05, 0.008]
