"""Motion benchmark: BotMotion task published -> first SIP showing wheel velocity, p50/p99.

The robot is `erni robot-sim` in a separate process, reached over TCP: the real byte path
(blackboard commit -> RobotMotionControl -> behaviour stack -> ARCOS VEL/RVEL -> simulated
firmware -> SIP -> driver). Beside it, in the same run, the floor: a bare ArcosDriver on a
second simulated robot sending VEL and waiting for the same SIP (no blackboard, no stack).
Both wait for the next SIP (on average half a period), so each row also shows the period;
commands are sent at a random phase of it. ratio = task path p50 / driver floor p50.

    python bench/bench_motion.py [--samples 40] [--periods 0.1,0.05,0.02] [--rate-hz 20]
"""

from __future__ import annotations

import argparse
import random
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from erni.blackboard import Agent, Pose, Task  # noqa: E402
from erni.blackboard.testing import wait_until  # noqa: E402
from erni.plugins.motion import ArcosDriver, RobotMotionControl  # noqa: E402


def start_sim(period: float) -> tuple[subprocess.Popen[str], list[str]]:
    """Run `erni robot-sim` with two robots on free ports; return the process and their URLs."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "erni", "robot-sim", "--port", "0", "--robots", "2",
         "--sip-period", str(period), "--log-level", "WARNING"],
        stdout=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[1])
    assert proc.stdout is not None
    urls = [proc.stdout.readline().split()[1] for _ in range(2)]
    return proc, urls


def moving_after(driver: ArcosDriver, t0: float, timeout: float = 3.0) -> float:
    """Return the arrival time of the first SIP after t0 whose wheels turn."""
    s = driver.wait_for(lambda s: s.stamp >= t0 and (s.left != 0 or s.right != 0), timeout)
    if s is None:
        raise RuntimeError("no SIP showed the wheels turning")
    return s.stamp


def still(driver: ArcosDriver) -> None:
    """Wait until the robot reports zero wheel velocity."""
    if driver.wait_for(lambda s: s.left == 0 and s.right == 0, 5.0) is None:
        raise RuntimeError("the robot did not stop")


def settle(period: float) -> None:
    """Sleep a random phase of the SIP period so samples do not lock onto the SIP clock."""
    time.sleep(0.03 + random.uniform(0, period))


def task_path(agent: Agent, driver: ArcosDriver, samples: int, period: float) -> list[float]:
    """Latency from the commit of a BotMotion velocity task to the first SIP showing motion."""
    out = []
    for _ in range(samples):
        still(driver)
        settle(period)
        task = Task(verb="BotMotion", preposition="velocity", params={"v": 0.2}, source="bench")
        t0 = time.monotonic()
        with agent.transaction() as tx:
            tx.add(task)
        out.append(moving_after(driver, t0) - t0)
        with agent.transaction() as tx:
            tx.remove(task.uid)
    return out


def driver_floor(driver: ArcosDriver, samples: int, period: float) -> list[float]:
    """Latency from a bare VEL command to the first SIP showing motion."""
    out = []
    for _ in range(samples):
        still(driver)
        settle(period)
        t0 = time.monotonic()
        driver.vel(0.2)
        out.append(moving_after(driver, t0) - t0)
        driver.stop()
    return out


def pct(values: list[float], q: float) -> float:
    """The q-quantile (0..1) of values, nearest rank."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(q * (len(ordered) - 1))))]


def main() -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=40)
    parser.add_argument("--periods", default="0.1,0.05,0.02", help="SIP periods to measure (s)")
    parser.add_argument("--rate-hz", type=float, default=20.0, help="behaviour stack rate")
    results.add_argument(parser)
    args = parser.parse_args()
    targets = []
    periods = [float(p) for p in args.periods.split(",")]
    print(f"motion benchmark: {args.samples} samples per row, behaviour stack at {args.rate_hz:g} Hz, "
          "robot-sim over TCP in another process")
    header = (f"{'SIP period':>10} | {'task p50':>8} {'p99':>7} | {'floor p50':>9} {'p99':>7} | "
              f"{'ratio':>5} | {'p50 / period':>12}")
    print(header)
    print("-" * len(header))
    for period in periods:
        proc, urls = start_sim(period)
        agent = Agent("bench", workers=2)
        agent.add_plugin(RobotMotionControl, name="motion", settings={
            "url": urls[0], "rate_hz": args.rate_hz, "pose_rate_hz": 10, "avoid_distance": 0})
        raw = ArcosDriver(urls[1], name="floor", sync_timeout=0.5)
        try:
            agent.start()
            wait_until(lambda agent=agent: agent.query(Pose), timeout=10)
            plugin = agent.plugin("motion")
            assert isinstance(plugin, RobotMotionControl)
            raw.open()
            driver_floor(raw, 3, period)  # warm-up
            task_path(agent, plugin.resource.driver, 3, period)
            floor = driver_floor(raw, args.samples, period)
            ours = task_path(agent, plugin.resource.driver, args.samples, period)
        finally:
            raw.close()
            agent.stop()
            proc.terminate()
            proc.wait(timeout=5)
        p50, p99 = statistics.median(ours), pct(ours, 0.99)
        f50, f99 = statistics.median(floor), pct(floor, 0.99)
        print(f"{period * 1000:>8.0f}ms | {p50 * 1000:>6.1f}ms {p99 * 1000:>5.1f}ms | {f50 * 1000:>7.1f}ms "
              f"{f99 * 1000:>5.1f}ms | {p50 / f50:>5.2f} | {p50 / period:>12.2f}")
        targets.append(results.target(
            f"task → wheels turning, SIP period {period * 1000:.0f} ms", "about the floor",
            f"a bare ArcosDriver sending VEL, {f50 * 1000:.1f} ms", f"{p50 / f50:.2f}x ({p50 * 1000:.1f} ms)", None))
    results.write("bench_motion", targets, path=args.results,
                  about="a BotMotion velocity task to the first SIP showing the wheels turning, through "
                  "`erni robot-sim` over TCP")
    return 0


if __name__ == "__main__":
    sys.exit(main())
