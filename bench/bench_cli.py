"""Command-line start benchmark: process start -> the first packet of `erni task` and `erni stop`.

A stop typed at a terminal is only as quick as the command that sends it starts. Each sample
launches a fresh process whose `--via` is a UDP socket this script listens on, and times from
just before the launch to the first datagram's arrival (the client's handshake: it proves a cli
identity of a team authority made for the run, as against `erni sim`), then kills the process.
Measured in the same run, the same way: `python -c pass` and `python -c "import erni"` (launch ->
exit), and a Python process that sends one datagram to the same socket (launch -> its arrival:
the floor of any Python command that sends). Every figure is the median over `--repeat`
samples; ratio = median / the `python -c pass` median. Beside each, the CPU time the process had
used by then (user + system, as the kernel counts it at its end): what a busy machine's waiting
does not add to, unlike the time.

    python bench/bench_cli.py [--repeat 15] [--beside COMMIT]

`--beside COMMIT` times that commit's `import erni` and `erni task` too, in the same rounds (its
tree taken out with `git archive` into a temporary directory and started there, so its own `erni`
package is the one imported): an earlier commit's figures beside this one's, on the same machine
at the same moments. Such a run is printed only: the results file (and the benchmarks page)
holds this commit's figures.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

GOAL = 0.3  # s: process start -> the first packet of a stop


def _cpu(proc: subprocess.Popen[bytes]) -> float:
    """Reap `proc`; return the CPU time (user + system, every thread) it used (s)."""
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return usage.ru_utime + usage.ru_stime


def to_exit(argv: list[str], cwd: Path, env: dict[str, str]) -> tuple[float, float]:
    """Launch -> exit, and the CPU time it took (s)."""
    t0 = time.monotonic()
    proc = subprocess.Popen(argv, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    cpu = _cpu(proc)
    wall = time.monotonic() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} exited {proc.returncode}")
    return wall, cpu


def to_first_packet(argv: list[str], cwd: Path, env: dict[str, str], sock: socket.socket) -> tuple[float, float]:
    """Launch -> the first datagram at `sock`, and the CPU time the process had used by then (s;
    it is killed at once, while it waits for an answer)."""
    sock.setblocking(False)
    while True:  # nothing left over from the previous sample
        try:
            sock.recv(65536)
        except BlockingIOError:
            break
    t0 = time.monotonic()
    proc = subprocess.Popen(argv, cwd=cwd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        sock.settimeout(20.0)
        try:
            sock.recv(65536)
        except TimeoutError:
            err = proc.stderr.read().decode(errors="replace") if proc.poll() is not None and proc.stderr else ""
            raise RuntimeError(f"no packet from {' '.join(argv)} within 20 s {err}") from None
        wall = time.monotonic() - t0
    finally:
        proc.kill()
    return wall, _cpu(proc)


def main() -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=15, help="samples of each command (default 15)")
    ap.add_argument("--beside", metavar="COMMIT", help="time this commit's `import erni` and `erni task` too")
    results.add_argument(ap)
    args = ap.parse_args()
    load = os.getloadavg()[0]  # the machine's business when the run began: the figures depend on it
    from erni.transport.identity import Authority

    with tempfile.TemporaryDirectory(prefix="erni-bench-cli-") as tmp, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        cli_pem = Authority.create(tmp, team="bench").issue("cli", "cli", Path(tmp) / "cli.pem")
        sock.bind(("127.0.0.1", 0))
        via = f"127.0.0.1:{sock.getsockname()[1]}"
        env = {**os.environ, "ERNI_IDENTITY": str(cli_pem)}
        env.pop("ERNI_TEAM_KEY", None)
        py = sys.executable
        task = ["-m", "erni", "task", "--via", via, "robot1", "RemoteBotMotion", "cancel"]
        # name -> (argv, where it starts)
        exits = {"python -c pass": ([py, "-c", "pass"], ROOT),
                 "python -c \"import erni\"": ([py, "-c", "import erni"], ROOT)}
        packets = {
            "python sending one datagram": ([py, "-c", "import socket; socket.socket(socket.AF_INET, socket."
                                             f"SOCK_DGRAM).sendto(b'x', ('127.0.0.1', {via.split(':')[1]}))"], ROOT),
            "erni task ROBOT RemoteBotMotion cancel": ([py, *task], ROOT),
            "erni stop ROBOT": ([py, "-m", "erni", "stop", "--via", via, "robot1"], ROOT),
            "erni stop (every robot)": ([py, "-m", "erni", "stop", "--via", via], ROOT),
        }
        if args.beside:
            old = Path(tmp) / "beside"
            old.mkdir()
            tree = subprocess.run(["git", "archive", args.beside], cwd=ROOT, capture_output=True, check=True).stdout
            subprocess.run(["tar", "-x", "-C", str(old)], input=tree, check=True)
            exits[f"python -c \"import erni\" at {args.beside}"] = ([py, "-c", "import erni"], old)
            packets[f"erni task ROBOT RemoteBotMotion cancel at {args.beside}"] = ([py, *task], old)
        samples: dict[str, list[tuple[float, float]]] = {name: [] for name in [*exits, *packets]}
        for k in range(args.repeat):  # interleaved: a busy moment of the machine falls on every command alike
            for name, (argv, cwd) in exits.items():
                samples[name].append(to_exit(argv, cwd, env))
            for name, (argv, cwd) in packets.items():
                samples[name].append(to_first_packet(argv, cwd, env, sock))
            print(f"  round {k + 1}/{args.repeat}", file=sys.stderr)
    floor = statistics.median(wall for wall, _ in samples["python -c pass"])
    print(f"{'command':<52} {'until':<13} {'min ms':>7} {'median':>7} {'max':>7} {'ratio':>6} {'CPU ms':>7}")
    targets = []
    for name, got in samples.items():
        xs = [wall for wall, _ in got]
        med, cpu = statistics.median(xs), statistics.median(c for _, c in got)
        until = "exit" if name in exits else "first packet"
        print(f"{name:<52} {until:<13} {min(xs) * 1000:7.0f} {med * 1000:7.0f} {max(xs) * 1000:7.0f} "
              f"{med / floor:6.1f} {cpu * 1000:7.0f}")
        erni_sends = name.startswith("erni ") and " at " not in name  # this commit's commands
        targets.append(results.target(
            f"`{name}`: launch → {until}", f"≤ {GOAL * 1000:.0f} ms" if erni_sends else "reported",
            f"`python -c pass`, {floor * 1000:.0f} ms",
            f"{med / floor:.1f}x ({med * 1000:.0f} ms; min {min(xs) * 1000:.0f}, max {max(xs) * 1000:.0f}; "
            f"CPU {cpu * 1000:.0f} ms)", med <= GOAL if erni_sends else None))
    if args.beside:
        print("results: not written (a run --beside another commit is printed only)")
        return 0
    results.write("bench_cli", targets, path=args.results,
                  about=f"a fresh process → its first packet (or its exit), median of {args.repeat}, beside "
                  f"`python -c pass` in the same run (load average {load:.1f} as it began)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
