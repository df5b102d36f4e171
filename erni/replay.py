"""Recorded team logs: the file format, reading it back, and a plugin that replays it.

A log is JSON lines, or a rosbag2 MCAP bag written by `erni record --format mcap` (read by
`erni.bags`, which needs the ros2 extra: `rosbags`, `mcap`, PyYAML). The first line is a header
`{"erni_record": 1, "via": ..., "started": t}`;
every other line is one blackboard change seen by the recorded agent:
`{"t": seconds since start, "agent": ..., "op": "add"|"change"|"remove", "type": "Pose", "data": {...}}`.
Replaying publishes the same objects, in order and with the same spacing divided by the speed,
on a control node's blackboard, so its GUI and `erni watch` see them as they saw the live team.

A line is at most `MAX_LINE` bytes (1 MiB; a recorded change is a few hundred bytes, a team's
network a few kilobytes): a longer one is skipped without being held, and named, as is a line that
is not UTF-8, not JSON, not a valid object (a number that is not finite, an agent that is no name)
or nested deeper than 64 levels. The other lines replay. At most `MAX_PROBLEMS` such lines are
named one by one; the rest are counted.
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import Field, ValidationError

from erni.blackboard import BBObject, Plugin
from erni.blackboard.clock import SYSTEM, Clock
from erni.blackboard.errors import ErniError, describe_validation, shown
from erni.blackboard.objects import Model
from erni.blackboard.text import NAME_CHARS, is_name
from erni.transport.wire import TYPES, loads

FORMAT = 1
MCAP_MAGIC = b"\x89MCAP0\r\n"
MAX_SECONDS = 30 * 24 * 3600.0  # a recording longer than 30 days is a damaged or forged line, not a run
MAX_LINE = 1024 * 1024
"""The longest line of a JSON-lines log read (bytes, without its newline)."""
MAX_PROBLEMS = 1000
"""The most skipped lines named one by one; the rest are counted in one more line."""


class LogError(ErniError):
    """A log file cannot be replayed."""


@dataclass
class Event:
    """One recorded change."""

    t: float
    agent: str
    op: str
    obj: BBObject


def is_bag(path: Path) -> bool:
    """Whether `path` names a bag rather than a JSON-lines log: a `.mcap` name, a file that starts
    with MCAP's magic bytes, or a (rosbag2) directory."""
    if path.suffix.lower() == ".mcap" or path.is_dir():
        return True
    try:
        with path.open("rb") as f:
            return f.read(len(MCAP_MAGIC)) == MCAP_MAGIC
    except OSError:
        return False


def read_log(path: str | Path, robot: str | None = None) -> tuple[dict[str, Any], list[Event], list[str]]:
    """Return the header, the events, and one problem line per line (or bag message) that could not
    be read. `robot`: whose poses a single robot's own bag (Odometry on `/odom`) holds."""
    path = Path(path)
    if is_bag(path):
        try:
            from erni.bags import read_bag
        except ImportError as err:
            raise LogError(f"{path}: reading MCAP bags needs the ros2 extra (pip install 'erni[ros2]'): {err}") from None
        return read_bag(path, robot=robot)
    try:
        with path.open("rb") as f:
            return _read_lines(path, _lines(f))
    except OSError as err:
        raise LogError(f"{path}: cannot read: {err.strerror or err}") from None


def _lines(f: Any) -> Iterator[tuple[int, bytes | None]]:
    """(number, line) for each line of a file, None for a line longer than MAX_LINE (skipped, never held)."""
    number = 0
    while True:
        line = f.readline(MAX_LINE + 1)
        if not line:
            return
        number += 1
        if len(line) > MAX_LINE and not (len(line) == MAX_LINE + 1 and line.endswith(b"\n")):
            while line and not line.endswith(b"\n"):  # the rest of it, a block at a time
                line = f.readline(MAX_LINE)
            yield number, None
        else:
            yield number, line


def _read_lines(path: Path, lines: Iterator[tuple[int, bytes | None]]) -> tuple[dict[str, Any], list[Event], list[str]]:
    first = next(lines, None)
    if first is None:
        raise LogError(f"{path}: empty; expected a log written by `erni record`")
    try:
        header = loads(first[1].decode("utf-8")) if first[1] is not None else None
    except (ValueError, UnicodeDecodeError):
        header = None
    if not isinstance(header, dict) or header.get("erni_record") != FORMAT:
        raise LogError(f"{path}:1: not an ERNI record (expected a header line with \"erni_record\": {FORMAT})")
    events: list[Event] = []
    problems: list[str] = []
    skipped = 0
    for number, data in lines:
        try:
            if data is None:
                raise LogError(f"a line longer than {MAX_LINE} bytes; expected a recorded change")
            line = data.decode("utf-8")
            if not line.strip():
                continue
            events.append(_event_of(line))
        except (LogError, ValueError, KeyError, TypeError, RecursionError) as err:  # UnicodeDecodeError too
            if len(problems) < MAX_PROBLEMS:
                problems.append(f"{path}:{number}: {problem_of(err)}")
            else:
                skipped += 1
    if skipped:
        problems.append(f"{path}: {skipped} more lines skipped")
    events.sort(key=lambda e: e.t)
    return header, events, problems


def _event_of(line: str) -> Event:
    """One recorded change from its JSON line (LogError, or pydantic's or json's error, when it is none)."""
    raw = loads(line)
    if not isinstance(raw, dict):
        raise LogError(f"expected a JSON object, got {type(raw).__name__}")
    missing = [k for k in ("t", "agent", "op", "type", "data") if k not in raw]
    if missing:
        raise LogError(f"missing {', '.join(missing)}")
    t = raw["t"]
    if isinstance(t, bool) or not isinstance(t, (int, float)) or (
            isinstance(t, float) and not math.isfinite(t)) or t < 0:
        raise LogError(f"t: expected a finite number of seconds >= 0, got {shown(t)}")
    if t > MAX_SECONDS:  # replaying would wait that long for it
        raise LogError(f"t: expected seconds since the recording started, at most {MAX_SECONDS:.0f} "
                       f"(30 days), got {shown(t)}")
    if not is_name(raw["agent"]):
        raise LogError(f"agent {shown(raw['agent'])}: expected a name of {NAME_CHARS}")
    cls = TYPES.get(raw["type"]) if isinstance(raw["type"], str) else None
    if cls is None or not issubclass(cls, BBObject):
        raise LogError(f"unknown object type {shown(raw['type'])}")
    if raw["op"] not in ("add", "change", "remove"):
        raise LogError(f"unknown op {shown(raw['op'])}")
    return Event(float(t), raw["agent"], raw["op"], cls.model_validate(raw["data"]))


def problem_of(err: BaseException) -> str:
    """One line of at most 200 characters for why a recorded change was skipped: a model's validation
    error as its first field and problem (`data.x: Input should be a finite number (got nan)`)."""
    if isinstance(err, ValidationError):
        text = describe_validation(err, prefix="data")
    else:
        text = str(err) or type(err).__name__
    return text.splitlines()[0][:200]


class Recorder:
    """Append events to a log file as they arrive."""

    def __init__(self, path: str | Path, via: str, clock: Clock = SYSTEM):
        self.path = Path(path)
        self.clock = clock  # the recorder's: lines are stamped by it
        self.start = clock()
        self.count = 0
        try:
            self._f = self.path.open("w", encoding="utf-8")
        except OSError as err:
            raise LogError(f"{self.path}: cannot write: {err.strerror or err}") from None
        self._f.write(json.dumps({"erni_record": FORMAT, "via": via, "started": self.clock.wall()}) + "\n")

    def write(self, agent: str, op: str, type_name: str, data: dict[str, Any]) -> None:
        """Record one change, stamped with the time since the recording started."""
        line = {"t": round(self.clock() - self.start, 6), "agent": agent, "op": op,
                "type": type_name, "data": data}
        self._f.write(json.dumps(line, separators=(",", ":")) + "\n")
        self.count += 1

    def close(self) -> None:
        """Flush and close the file."""
        self._f.close()


class ReplaySettings(Model):
    """The `[plugin.settings]` of the replay plugin."""

    log: str = Field(description="log file or MCAP bag written by `erni record`")
    speed: float = Field(1.0, gt=0, le=1000, description="1 = recorded pace, 0.5 = slow motion")
    loop: bool = False
    robot: str | None = Field(None, description="the robot whose poses a single robot's own bag (Odometry on "
                              "/odom, no robot's namespace) holds")


class ReplayPlugin(Plugin[ReplaySettings]):
    """Publishes a recorded log on this agent's blackboard at the recorded pace × speed."""

    def setup(self) -> None:
        _, self.events, problems = read_log(self.settings.log, self.settings.robot)
        for line in problems:
            self.log.warning("skipped %s", line)
        self.speed = self.settings.speed
        self.position = 0
        self.paused = threading.Event()
        self.finished = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"erni-{self.agent_name}-replay", daemon=True)
        self._thread.start()

    def teardown(self) -> None:
        self._stop.set()
        self._thread.join(2)

    def pause(self, paused: bool = True) -> None:
        """Hold the replay (True) or go on (False)."""
        (self.paused.set if paused else self.paused.clear)()

    def _run(self) -> None:
        while not self._stop.is_set():
            clock, last_t = self.clock(), 0.0
            for index in range(len(self.events)):
                event = self.events[index]
                wait = (event.t - last_t) / self.speed
                deadline = clock + wait
                while not self._stop.is_set():
                    if self.paused.is_set():
                        held = self.clock()
                        self._stop.wait(0.05)
                        deadline += self.clock() - held
                        continue
                    left = deadline - self.clock()
                    if left <= 0:
                        break
                    self._stop.wait(min(left, 0.05))
                if self._stop.is_set():
                    return
                clock, last_t = self.clock(), event.t
                self._publish(event)
                self.position = index + 1
            self.finished.set()
            if not self.settings.loop:
                return
            with self.transaction():
                for obj in self.query(lambda o: type(o).__name__ in TYPES and not o.uid.startswith("peer:")):
                    self.remove(obj)

    def _publish(self, event: Event) -> None:
        try:
            with self.transaction():
                present = self.get(event.obj.uid) is not None
                if event.op == "remove":
                    if present:
                        self.remove(event.obj.uid)
                elif present:
                    self.change(event.obj, reports=["replayed"])
                else:
                    self.add(event.obj)
        except ErniError as err:
            self.log.warning("replay: %s", err)
