"""`erni console [--via HOST:PORT]`: task the team by typing commands in the speech grammar.

Each line is one utterance (`robot 3 go to 4 5`, `everyone stop`, `turn left 90 degrees`,
`robot 2 status`); the console answers like the speech front end ("Roger: robot 3, go to x 4,
y 5", "I don't know robot 9") and prints a line when each task it sent starts and when it ends,
also when it was stopped or superseded (obstacle avoidance is not superseded: it stays on until
turned off, and the console does not wait for it to end). "cancel that" withdraws the tasks of the
last command carried out; "set speed 0.2", "faster" and "slower" set the cruise speed of later
moves. A command that names no robot goes to the robots last named: at once, naming them ("Roger:
robot 3, clear your behaviours"), when they were named or answered about in the line just before;
older than that, the console asks ("Robot 3: clear your behaviours? ... type yes to confirm") and
sends nothing until "yes". A move longer than `--confirm-beyond` metres and a held velocity are
asked the same way. A stop never asks. Status questions are answered from the agent's
directory (link) and the poses and tasks it streams to the console (pose, battery, task).
On a terminal the lines are read at an `erni>` prompt (prompt_toolkit): an event line that
arrives while a line is typed is printed above the prompt, which is drawn again below it with the
line as it was; the lines typed are kept in `--history-file`, one per line. Lines from a pipe are
read to the end, then the console waits for the tasks it sent to finish (`--timeout`).
"""

from __future__ import annotations

import argparse
import math
import os
import queue
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

from erni.blackboard import Task
from erni.blackboard.schemas import Cancel, PeerList, ResultUpdate, WatchEvent, WatchRequest
from erni.blackboard.text import printable
from erni.commands._client import add_client_options, dumps, make_client, make_room_for_a_stream, stamp
from erni.commands._text import say, say_lines
from erni.transport.client import PeerListParts

WATCH_LEASE = 10.0
CONFIRM_BEYOND = 10.0  # m: a typed move longer than this is confirmed first (the GUI's typed box's default)
HISTORY_LENGTH = 1000  # lines kept in the history file

HELP = """examples:  robot 1 go to 2 3 | robots 1 and 2 turn right 90 degrees | go forward 2 feet
           everyone stop | cancel that | random walk | robot 2 status | where are you | how many robots
           set speed 0.2 | faster | slower | robot 1 go to robot 2 | avoid obstacles | stop avoiding obstacles
           attention | go to sleep | quit"""


def register(sub: Any) -> None:
    """Add the `console` sub-command."""
    p = sub.add_parser("console", help="type commands to the team in the speech grammar",
                       description="Type commands such as 'robot 3 go to 4 5' or 'everyone stop'; they go to the "
                       "robots through one agent\n(--via; else the control node of a running erni sim of this "
                       "user's, or one found by its beacons).\nA command that names no robot goes to the robots "
                       "named in the line before; named longer ago, the console\nasks first (type yes), as it "
                       "does before a move longer than --confirm-beyond. A stop never asks.\nExit 0, or 1 when a "
                       "piped command was refused or a task failed; 2 on bad arguments.",
                       epilog=HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--verb", choices=["RemoteBotMotion", "BotMotion"], default="RemoteBotMotion",
                   help="verb of the tasks (BotMotion for teams without MissionControl)")
    p.add_argument("--robot-names", default="robot{n}", help="agent name of robot n (default robot{n})")
    p.add_argument("--timeout", type=float, default=30.0,
                   help="after piped input ends, wait this long for the tasks to finish (s)")
    p.add_argument("--confirm-beyond", type=float, default=CONFIRM_BEYOND, metavar="METRES",
                   help="a move longer than this, or a held velocity, waits for a typed yes "
                   f"(default {CONFIRM_BEYOND:g}; 0: only a held velocity)")
    p.add_argument("--history-file", default=os.path.expanduser("~/.erni_console_history"),
                   help="the lines typed, kept for the next session (on a terminal only)")
    add_client_options(p)
    p.set_defaults(func=run)


class Console:
    """One operator's typed session: a Dialogue whose tasks travel through a Client."""

    def __init__(self, client: Any, addr: Any, dialogue: Any, out: TextIO, *, json_lines: bool = False) -> None:
        self.client, self.addr, self.dialogue, self.out = client, addr, dialogue, out
        self.json = json_lines
        self.peers: queue.Queue[PeerList] = queue.Queue()
        self.parts = PeerListParts()
        self.known: list[Any] = []  # the robots' Peer entries
        self.poses: dict[str, dict[str, Any]] = {}  # robot -> its last Pose (from the watch stream)
        self.doing: dict[str, tuple[float, str]] = {}  # robot -> (created, its running task in words)
        self.open: dict[str, Task] = {}  # uid -> task sent and not finished
        self.last: dict[str, str] = {}   # robot -> uid of its last motion task
        self.standing: set[str] = set()  # obstacle avoidance tasks: on until turned off
        self.running: set[str] = set()   # tasks whose start was printed
        self.failed = 0
        self.refused = 0
        self._lock = threading.Lock()
        self._out_lock = threading.Lock()
        self._stop = threading.Event()
        self._posed = threading.Event()  # the first Pose arrived through the watch
        self._waited = False
        self._thread = threading.Thread(target=self._receive, name="console-receive", daemon=True)

    def start(self) -> Console:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def robots(self) -> dict[str, Any]:
        """Ask the agent for its peers; return what the dialogue may tell of each robot (the last answer if slow)."""
        from erni.plugins.ui.dialogue import RobotView

        self.client.send(self.addr, "peers.request", None, reliable=True)
        try:
            reply = self.peers.get(timeout=2.0)
            self.known = [p for p in reply.peers if p.role == "robot"]
            control = [p.name for p in reply.peers if p.role == "control"]
            self.dialogue.control = control[0] if control else reply.agent
        except queue.Empty:
            self.print(f"(no peer list from {self.addr[0]}:{self.addr[1]}; using the last one)")
        if not self._waited:  # once: give the watch a moment to bring every robot's pose
            self._waited = True
            end = time.monotonic() + 3.0
            while time.monotonic() < end and self._posed.wait(0.1) is not None:
                with self._lock:
                    if all(p.name in self.poses for p in self.known):
                        break
        now = time.time()
        views = {}
        with self._lock:
            for peer in self.known:
                pose = self.poses.get(peer.name, {})
                views[peer.name] = RobotView(
                    peer.name, up=peer.up, x=pose.get("x"), y=pose.get("y"), theta=pose.get("theta"),
                    battery=pose.get("battery"), doing=self.doing.get(peer.name, (0.0, ""))[1],
                    silent=now - peer.last_heard if peer.last_heard else None)
        return views

    def say(self, line: str) -> None:
        """Answer one typed line and send its tasks."""
        with self._lock:
            running = list(self.open.values())
        reply = self.dialogue.hear(line, self.robots(), running)
        if reply.say is None:
            self.emit("(standing by: say 'attention')", {"heard": line, "ignored": True})
            return
        if not reply.accepted:
            self.refused += 1
        for uid in reply.withdraw:
            self._withdraw(uid, "cancelled by the operator" if reply.action == "cancel" else "re-sent at a new speed")
        # a RemoteBotMotion cancel (a stop) ends the robot's tasks there, and they report it
        remote_cancel = any(t.verb == "RemoteBotMotion" and t.preposition == "cancel" for t in reply.tasks)
        for task in reply.tasks:
            if reply.action not in ("teleport", "avoid_obstacles", "speed") and not remote_cancel:
                self._supersede(task.destination, reply.action)
            with self._lock:
                self.open[task.uid] = task
                if task.preposition == "avoid_obstacles" and getattr(task.params, "enabled", True):
                    self.standing.add(task.uid)  # stays on until turned off: never superseded, not waited for
                else:
                    self.last[task.destination or ""] = task.uid
            self.client.send(self.addr, "task.add", task)
        self.emit(reply.say, {"heard": line, "say": reply.say, "accepted": reply.accepted,
                              "targets": reply.targets, "tasks": [t.uid for t in reply.tasks]})

    def _supersede(self, robot: str | None, action: str) -> None:
        """Withdraw the robot's previous unfinished task from this console, and say it ended."""
        with self._lock:
            uid = self.last.pop(robot or "", None)
        if uid:
            self._withdraw(uid, f"superseded by {action}")

    def _withdraw(self, uid: str, why: str) -> None:
        """Cancel an unfinished task this console sent, and say it ended."""
        with self._lock:
            still = self.open.pop(uid, None)
            self.standing.discard(uid)
        if still:
            self.client.send(self.addr, "task.cancel", Cancel(uid=uid))
            self.emit(f"{stamp()} {still.destination}: {still.preposition} cancelled \u2014 {why}",
                      {"uid": uid, "agent": still.destination, "preposition": still.preposition,
                       "state": "cancelled", "message": why})

    def wait(self, timeout: float) -> None:
        """Wait until every task sent has finished, or `timeout` seconds (obstacle avoidance stays on)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if not set(self.open) - self.standing:
                    return
            time.sleep(0.05)
        with self._lock:
            left = [t for uid, t in self.open.items() if uid not in self.standing]
            for t in left:
                del self.open[t.uid]
        for task in left:
            self.print(f"{task.destination}: {task.preposition} not finished within {timeout:g} s; cancelling")
            self.client.send(self.addr, "task.cancel", Cancel(uid=task.uid))
            self.failed += 1
        time.sleep(0.2)

    def print(self, text: str) -> None:
        """Write whole lines: the receive thread's event lines and the replies never share a line (each
        one line, its control characters escaped, as `say` prints it)."""
        with self._out_lock:
            self.out.write(printable(text) + "\n")
            self.out.flush()

    def emit(self, text: str, data: dict[str, Any]) -> None:
        """Print a line of text, or with --json the same as one JSON object."""
        self.print(dumps(data) if self.json else text)

    def _receive(self) -> None:
        make_room_for_a_stream(self.client)
        renew = 0.0
        while not self._stop.is_set():
            if time.monotonic() >= renew:  # poses and tasks for status questions
                self.client.send(self.addr, "watch.request", WatchRequest(lease=WATCH_LEASE))
                renew = time.monotonic() + WATCH_LEASE / 2
            msg = self.client.receive(0.1)
            if msg is None:
                continue
            if msg.kind == "peers.reply" and isinstance(msg.body, PeerList):
                directory = self.parts.add(msg.body)  # a large directory comes in parts
                if directory is not None:
                    self.peers.put(directory)
            elif msg.kind == "task.result" and isinstance(msg.body, ResultUpdate):
                self._result(msg.body)
            elif msg.kind == "watch.event" and isinstance(msg.body, WatchEvent):
                self._watched(msg.body)

    def _watched(self, event: WatchEvent) -> None:
        d = event.data
        with self._lock:
            if event.type == "Pose" and event.op != "remove" and isinstance(d.get("robot"), str):
                self.poses[d["robot"]] = d
                self._posed.set()
            elif event.type == "Task" and isinstance(d.get("destination"), str):
                robot, state = d["destination"], (d.get("result") or {}).get("state", "pending")
                created = float(d.get("created") or 0.0)
                if event.op == "remove" or state in ("succeeded", "failed", "cancelled"):
                    if self.doing.get(robot, (0.0, ""))[0] <= created:
                        self.doing.pop(robot, None)
                elif d.get("preposition") == "avoid_obstacles":
                    pass  # on until turned off: not what the robot is doing
                elif created >= self.doing.get(robot, (0.0, ""))[0]:
                    self.doing[robot] = (created, f"busy: {d.get('preposition', '?')} ({state})")

    def _result(self, update: ResultUpdate) -> None:
        with self._lock:
            task = self.open.get(update.uid)
            if task is None:
                return
            if update.result.state.done:
                del self.open[update.uid]
        r = update.result
        if not r.state.done and r.state.value != "running":
            return
        if r.state.value == "running":
            if update.uid in self.running:
                return
            self.running.add(update.uid)
        if r.state.value == "failed":
            self.failed += 1
        message = f" \u2014 {r.message}" if r.message else ""
        self.emit(f"{stamp(r.stamp)} {task.destination}: {task.preposition} {r.state.value}{message}",
                  {"uid": task.uid, "agent": task.destination, "preposition": task.preposition,
                   **r.model_dump(mode="json")})


def _history(path: str) -> Any:
    """The console's line history in `path`: one line per command, as readline keeps it (the file of an
    earlier console reads as it was); the newest HISTORY_LENGTH lines are kept. Quietly none where the
    file cannot be read or written."""
    from prompt_toolkit.history import History

    class LineHistory(History):
        def load_history_strings(self) -> list[str]:
            try:
                lines = Path(path).read_text(encoding="utf-8", errors="replace").splitlines()
            except OSError:
                return []
            lines = [ln for ln in lines if ln.strip()]
            if len(lines) > 2 * HISTORY_LENGTH:  # trimmed now and then, not at every line
                lines = lines[-HISTORY_LENGTH:]
                self._write(lines)
            return list(reversed(lines[-HISTORY_LENGTH:]))  # newest first

        def store_string(self, string: str) -> None:
            try:
                Path(path).parent.mkdir(parents=True, exist_ok=True)
                with open(path, "a", encoding="utf-8") as f:
                    f.write(string.replace("\n", " ") + "\n")
            except OSError:
                pass

        def _write(self, lines: list[str]) -> None:
            try:
                Path(path).write_text("".join(f"{ln}\n" for ln in lines), encoding="utf-8")
            except OSError:
                pass

    return LineHistory()


def run(args: argparse.Namespace) -> int:
    """Read commands until EOF or `quit`."""
    from erni.plugins.ui.dialogue import Dialogue, Naming
    from erni.transport.client import ClientError

    if not math.isfinite(args.confirm_beyond) or args.confirm_beyond < 0:
        say(f"erni console: --confirm-beyond: expected a number of metres >= 0, got {args.confirm_beyond}",
            file=sys.stderr)
        return 2
    try:
        naming = Naming(args.robot_names)
        client = make_client(args)
    except ValueError as err:
        say(f"erni console: {err}", file=sys.stderr)
        return 2
    interactive = sys.stdin.isatty() and sys.stdout.isatty()
    with client:
        try:
            addr = client.find(None)
        except ClientError as err:
            say(f"erni console: {err}", file=sys.stderr)
            return 1
        # a command that names no robot acts at once only on the robots named in the exchange just before
        dialogue = Dialogue(naming, verb=args.verb, source=client.endpoint.name, listening=True,
                            confirm_remembered=True, confirm_beyond=args.confirm_beyond or math.inf)
        if interactive:
            _interactive(client, addr, dialogue, args)
            return 0
        console = Console(client, addr, dialogue, sys.stdout, json_lines=args.json).start()
        try:
            _read_lines(console, lambda: input(""), echo=not args.json)
            console.wait(args.timeout)
        except KeyboardInterrupt:
            say()
        finally:
            console.stop()
    return 1 if console.failed or console.refused else 0


def _interactive(client: Any, addr: Any, dialogue: Any, args: argparse.Namespace) -> None:
    """Read lines at a prompt on a terminal: event lines from the team are printed above the prompt, and
    the prompt with the line being typed is drawn again below them."""
    from prompt_toolkit import PromptSession
    from prompt_toolkit.patch_stdout import patch_stdout

    session: PromptSession[str] = PromptSession(history=_history(args.history_file))
    with patch_stdout():  # sys.stdout is a proxy that writes above the prompt from here on
        console = Console(client, addr, dialogue, sys.stdout, json_lines=args.json).start()
        try:
            say(f"erni console through {addr[0]}:{addr[1]}; tasks as {args.verb}")
            say_lines(HELP)
            _read_lines(console, lambda: session.prompt("erni> "), echo=False)
        except KeyboardInterrupt:
            say()
        finally:
            console.stop()


def _read_lines(console: Console, read: Callable[[], str], echo: bool) -> None:
    """Say each line `read` returns to the console until EOF or `quit` (`help` shows the help; `echo`: each
    line is printed before its answers)."""
    while True:
        try:
            line = read()
        except EOFError:
            break
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if line in ("quit", "exit"):
            break
        if line in ("help", "?"):
            say_lines(HELP)
            continue
        if echo:
            console.print(f"> {line}")
        console.say(line)
