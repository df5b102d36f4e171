"""Stop benchmark: each front end's stop -> every moving robot standing, on `erni sim`'s processes.

A team of four runs as `erni sim` starts it (RemoteBotMotion tier, real agent processes, the GUI).
Each round sets three robots moving as an operator does (a turn and a back-up typed on the page,
which the dialogue sends as BotMotion straight to the robot, a held velocity by `erni task`; or a
remote forward, a random walk and a remote goto), then stops the whole team from one front end:
"everybody stop" spoken by espeak-ng and streamed through the page's microphone path, the page's
Stop button, its typed line, `erni console`, `erni task ... RemoteBotMotion cancel` and `erni task
... BotMotion stop` (both of these start one `erni task` process per robot, and their time is
counted), and `erni stop` in either tier (one process for the whole team, its start counted). Latency: from the moment the command is complete (the last spoken word, the message
sent, the console taking the line, the `erni task` processes launched) until the robot stands for
good, as the control node sees its Pose (10 a second).

The floor, measured in the same run: a bare ArcosDriver on an `erni robot-sim` robot of the same
model, driving at 0.3 m/s, sends the ARCOS stop and waits for the first SIP that shows the wheels
standing (the robot's own braking and one SIP; no agent, no network).
ratio = front end's median / floor median.

    python bench/bench_stop.py [--rounds 3]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from erni.plugins.motion import ArcosDriver  # noqa: E402
from tests.sim import test_stop_matrix as matrix  # noqa: E402
from tests.sim.test_sim_cli import SimProcess  # noqa: E402


def floor(samples: int) -> list[float]:
    """A bare driver's stop: ARCOS stop sent -> first SIP with both wheels standing."""
    proc = subprocess.Popen([sys.executable, "-m", "erni", "robot-sim", "--port", "0", "--log-level", "WARNING"],
                            stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout is not None
    url = proc.stdout.readline().split()[1]
    out = []
    try:
        with ArcosDriver(url) as driver:
            for _ in range(samples):
                driver.vel(0.3)
                if driver.wait_for(lambda s: abs(s.v) > 0.28, 5.0) is None:
                    raise RuntimeError("the floor's robot did not reach 0.3 m/s")
                time.sleep(0.3)
                t0 = time.monotonic()
                driver.stop()
                s = driver.wait_for(lambda s, t0=t0: s.stamp >= t0 and s.left == 0 and s.right == 0, 5.0)
                if s is None:
                    raise RuntimeError("the floor's robot did not stop")
                out.append(s.stamp - t0)
                driver.vel(-0.3)  # and back, so it stays in the open
                driver.wait_for(lambda s: s.v < -0.28, 5.0)
                time.sleep(0.3)
                driver.stop()
                driver.wait_for(lambda s: s.left == 0 and s.right == 0, 5.0)
    finally:
        proc.terminate()
        proc.wait(10)
    return out


def main() -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=3, help="rounds per front end (each stops 3 moving robots)")
    results.add_argument(ap)
    args = ap.parse_args()
    targets = []
    base = floor(10)
    with tempfile.TemporaryDirectory(prefix="erni-bench-stop-") as tmp:
        run = Path(tmp) / "run"
        sim = SimProcess(run, "--robots", "4", "--control-port", "0", "--gui-listen", "127.0.0.1:0", headless=False)
        team = matrix.open_team(sim, run)
        try:
            lat: dict[str, list[float]] = {name: [] for name in matrix.FRONT_ENDS}
            for k in range(args.rounds):
                for name, front_end in matrix.FRONT_ENDS.items():
                    matrix.home(team)
                    typed, tasks = (matrix.TYPED_A, matrix.TASKS_A) if k % 2 == 0 else (matrix.TYPED_B, matrix.TASKS_B)
                    movers = matrix.start_motions(team, typed, tasks)
                    time.sleep(1.0)
                    sent = front_end(team, Path(tmp))
                    matrix.wait_for(lambda: all(team.watched.halted(r) for r in matrix.ROBOTS), 5,
                                    f"{name}: not every robot halted")
                    time.sleep(0.5)
                    lat[name] += [max(0.0, (team.watched.halted_since(r, sent) or sent) - sent) for r in movers]
                    print(f"  round {k + 1}/{args.rounds} {name}: {len(movers)} robots standing", file=sys.stderr)
        finally:
            team.close()
    fl = statistics.median(base)
    print(f"floor: bare ARCOS stop -> SIP standing, median {fl * 1000:.0f} ms (min {min(base) * 1000:.0f}, "
          f"max {max(base) * 1000:.0f}; {len(base)} stops)")
    print(f"{'front end':<22} {'median s':>9} {'p90 s':>7} {'max s':>7} {'n':>4} {'ratio':>7}")
    for name, xs in lat.items():
        xs.sort()
        med = statistics.median(xs)
        p90 = xs[min(len(xs) - 1, int(0.9 * len(xs)))]
        print(f"{name:<22} {med:9.2f} {p90:7.2f} {max(xs):7.2f} {len(xs):4d} {med / fl:7.1f}")
        cli = name.startswith("erni task") or name.startswith("task")
        targets.append(results.target(
            name, "reported" if cli else "within a braking time of the floor", f"bare ARCOS stop, {fl:.2f} s",
            f"{med / fl:.1f}x ({med:.2f} s)", None if cli else med <= fl + 0.5))
    results.write("bench_stop", targets, path=args.results,
                  about="each front end's stop → every moving robot of `erni sim` standing, beside a bare ARCOS stop")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
