"""Paper 003, Table I: the behaviour stack cycles on the SIP that shows a commanded motion at
once. The clock here stands still, so a SIP held back by the stack's rate would be held for good."""

from __future__ import annotations

import threading
import time

from erni.blackboard import Task
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
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.005)
    return condition()


def test_the_stack_cycles_on_the_sip_after_a_task_though_its_rate_would_wait():
    driver = Driver()
    shown: list[float] = []
    res = RobotMotionResource(driver, lambda updates, state: state and shown.append(state.v),  # type: ignore[arg-type]
                              rate_hz=0.1, avoid_distance=0, clock=lambda: 0.0).start()
    try:
        res.submit(Task(verb="BotMotion", preposition="velocity", params={"v": 0.2}, source="test"))
        assert driver.asked.wait(5.0), "the task's cycle sent no velocity"
        assert wait(lambda: res._steering)
        cycles = res.cycles
        driver.state = sip(1, 0.2)
        res._sip(driver.state)  # a moment after the task's cycle (the clock stands still)
        # (the rate would hold it 10 s: a wait of its own, beside the frozen clock's)
        assert wait(lambda: res.cycles == cycles + 1, 3.0), "no stack cycle on the SIP after the task's"
        driver.state = sip(2, 0.2)  # a second SIP within the rate's period: no cycle for it
        res._sip(driver.state)
        time.sleep(0.2)
        assert res.cycles == cycles + 1
    finally:
        res.close()
