"""UIPlugin: the control node's web GUI and speech front end, meeting the team on the blackboard.

The plugin watches robots' `Pose`, `NetInfo` and `transport.Peer` objects and the tasks
sent to robots, and hands a typed picture of the team (`protocol.Picture`) to its web server
(thread `ui-http`) at `rate_hz`. Commands from the page, typed utterances and recognised speech come
back through `later()` and become tasks for the robots (`RemoteBotMotion`, or `BotMotion`
with `verb = "BotMotion"`). Spoken feedback runs on thread `ui-voice`, recognition on
`ui-speech`; no I/O happens inside a transaction.
"""

from __future__ import annotations

import ipaddress
import math
import secrets
import sys
import threading
import time
from collections import deque
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field, SecretStr, field_validator

from erni import netgraph
from erni.blackboard import NetInfo, Plugin, Pose, Task
from erni.blackboard.objects import Model
from erni.blackboard.schemas import Peer, load_floorplan
from erni.blackboard.tasks import best_links
from erni.logs import mask_secrets
from erni.plugins.ui.dialogue import ROGER, Dialogue, Memory, Naming, Reply, RobotView, Sent, restate, tasks_for
from erni.plugins.ui.grammar import ATTENTION, STANDARD_ACTIONS, Refusal, strategies
from erni.plugins.ui.protocol import (
    CancelTaskMsg,
    CommandMsg,
    ErrorMsg,
    JsonDict,
    LinkRow,
    LogLevel,
    LogLine,
    Metrics,
    MicMsg,
    Picture,
    PoseRow,
    ReplyMsg,
    RobotRow,
    SayMsg,
    SelectMsg,
    SelectOut,
    SpeechState,
    TaskRow,
)
from erni.plugins.ui.server import WebServer
from erni.plugins.ui.speech import LOUD_ROOM, Listener, Microphone, SpeechError, choose_recognizer, wav_frames
from erni.plugins.ui.voice import Speaker
from erni.transport import parse_address

_LOOPBACK_NAMES = {"localhost", "ip6-localhost"}
_ENDED_LEVEL: dict[str, LogLevel] = {"succeeded": "info", "cancelled": "dim"}  # a task's end in the log; else error


def announce(url: str) -> None:
    """Print the GUI's URL; its token only to a terminal (output that goes to a file is a log)."""
    if sys.stdout.isatty():
        print(f"ERNI GUI: {url}", flush=True)
    else:
        print(f"ERNI GUI: {mask_secrets(url)} (the token is shown on a terminal only; or set the UI's token)",
              flush=True)


class UISettings(Model):
    """Settings of the UI plugin (the `[plugin.settings]` table)."""

    model_config = ConfigDict(extra="forbid")

    listen: str = Field("127.0.0.1:8080", description="HOST:PORT of the GUI (0 = any free port)")
    token: SecretStr | None = Field(None, description="access token of the page (printed in its URL); generated "
                                    "when not set, on localhost too")
    allowed_hosts: list[str] = Field(default_factory=list, description="extra host names the page may be "
                                     "opened by (a reverse proxy's, a DNS name of this host)")
    verb: Literal["RemoteBotMotion", "BotMotion"] = Field(
        "RemoteBotMotion", description="verb of the tasks sent to robots (BotMotion: teams without MissionControl)")
    robot_names: str = Field("robot{n}", description="agent name of robot n")
    low_battery: float = Field(11.5, ge=0, description="battery voltage below which a robot shows as low (V)")
    rate_hz: float = Field(10.0, gt=0, le=50, description="GUI updates per second")
    supersede: bool = Field(True, description="a new motion command cancels the robot's previous one "
                            "(obstacle avoidance stays on until turned off)")
    read_back: float = Field(5.0, ge=0, description="a spoken move longer than this (m) or off the floor plan, "
                             "a spoken command to several robots, a clear, a teleport or a deployment is read "
                             "back and carried out on 'yes'; 0 = never")
    read_back_numbers: bool = Field(True, description="a spoken motion command with a distance, angle or "
                                    "coordinate is read back and carried out on 'yes' (a recogniser mishears "
                                    "numbers without doubting them)")
    confirm_beyond: float = Field(10.0, ge=0, description="a typed move that would leave the floor plan, or "
                                  "a held velocity, is confirmed once before it is sent; so is one longer than "
                                  "this (m) where the floor plan cannot tell (none, or the robot's pose unknown); "
                                  "0 = no bound on distance")
    history: int = Field(60, ge=1, le=10000, description="finished tasks kept in the task list")
    speak: bool = Field(True, description="spoken feedback through espeak-ng on the control node")
    voice: str = Field("en-us", description="espeak-ng voice")
    wake: list[Annotated[str, Field(pattern=r"^[a-z]+( [a-z]+){0,3}$")]] = Field(
        default_factory=lambda: list(ATTENTION), min_length=1, max_length=8,
        description="phrases that wake the speech front end after 'go to sleep' (lower-case words)")
    recogniser: Literal["auto", "vosk", "pocketsphinx"] = Field(
        "auto", description="speech recogniser: auto = vosk when a vosk model is given, else pocketsphinx")
    vosk_model: str | None = Field(None, description="vosk model directory (default: VOSK_MODEL_PATH)")
    denoise: Literal["off", "auto", "webrtc", "speex", "rnnoise"] = Field(
        "auto", description="noise suppressor before the recogniser (PocketSphinx), for every microphone and WAV; "
        "auto: WebRTC's in a quiet room, RNNoise while the room is louder than loud_room (WebRTC alone without "
        "pyrnnoise); speex and rnnoise need speexdsp-ns and pyrnnoise installed")
    loud_room: float = Field(LOUD_ROOM, ge=-90.0, le=0.0, description="the room's own level (dBFS, between words) "
                             "above which denoise auto hears through RNNoise")
    vad: Literal["off", "silero", "webrtc"] = Field(
        "silero", description="voice-activity detector that ends utterances (off: the background's level does)")
    auto_gain: int = Field(0, ge=0, le=31, description="WebRTC's automatic gain target below full scale (dBFS); "
                           "0 = off")
    microphone: bool = Field(False, description="listen to the control node's own microphone (arecord)")
    microphone_device: str | None = Field(None, description="ALSA device of the local microphone")
    wav: str | None = Field(None, description="a WAV file of commands to recognise at start")
    floorplan: str | None = Field(None, description="walls and obstacles to draw: a world TOML file")
    netinfo_max_age: float = Field(10.0, ge=0, description="network info older than this is stale (s); 0 = never")

    @field_validator("listen")
    @classmethod
    def _check_listen(cls, v: str) -> str:
        parse_address(v)
        return v

    @field_validator("token")
    @classmethod
    def _check_token(cls, v: SecretStr | None) -> SecretStr | None:
        if v is not None and len(v.get_secret_value()) < 8:
            raise ValueError("expected at least 8 characters (or leave it out: one is generated)")
        return v

    @field_validator("floorplan")
    @classmethod
    def _check_floorplan(cls, v: str | None) -> str | None:
        if v is not None:
            load_floorplan(v)
        return v

    @field_validator("robot_names")
    @classmethod
    def _check_names(cls, v: str) -> str:
        Naming(v)
        return v


def is_loopback(host: str) -> bool:
    """True for localhost, 127.0.0.0/8 and ::1."""
    if host.lower() in _LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


class UIPlugin(Plugin[UISettings]):
    """The control node's GUI and speech front end."""


    def setup(self) -> None:
        s = self.settings
        me = self.agent_name
        self.naming = Naming(s.robot_names)
        memory = Memory()  # "cancel that" and cruise speeds: the same whether typed, spoken or clicked
        area = load_floorplan(s.floorplan).bounds if s.floorplan else None
        self.typed = Dialogue(self.naming, verb=s.verb, source=me, listening=True, control=me, memory=memory,
                              area=area, confirm_beyond=s.confirm_beyond or math.inf, clock=self.clock)
        self.spoken = Dialogue(self.naming, verb=s.verb, source=me, listening=False, control=me, memory=memory,
                               read_back=s.read_back or None, read_back_numbers=s.read_back_numbers, area=area,
                               echo=True, wake=tuple(s.wake), clock=self.clock)
        self.poses = self.subscribe(Pose)
        self.netinfo = self.subscribe(NetInfo)
        self.peers = self.subscribe(Peer)
        self.tasks = self.subscribe(Task, where=lambda t: t.destination not in (None, "", me))
        self.logs: deque[LogLine] = deque(maxlen=200)
        self.mic_clients: set[str] = set()
        self._ended: set[str] = set()
        self.retired: deque[TaskRow] = deque(maxlen=s.history)  # tasks cancelled before they ended
        self._retired_uids: set[str] = set()
        self._published: Picture | None = None
        self._lock = threading.Lock()
        self._dirty = True
        self._threads: list[Any] = []
        self._stopping = threading.Event()
        self.floorplan = load_floorplan(s.floorplan) if s.floorplan else None
        host, port = parse_address(s.listen)
        # always a token, on localhost too: any local program or web page could otherwise drive the robots
        token = s.token.get_secret_value() if s.token else secrets.token_urlsafe(16)
        self.speaker = Speaker(voice=s.voice).start() if s.speak else None
        self.listener: Listener | None = None
        self.speech_error = ""
        self.recogniser_name = ""
        self._start_speech(s)
        self.server = WebServer(host, port, token=token, on_message=self._from_page, on_audio=self._audio,
                                on_close=self._page_closed, rate_hz=s.rate_hz,
                                announce=announce,
                                allowed_hosts=tuple(s.allowed_hosts))
        self.server.publish(self.snapshot())
        try:
            self.server.start()
        except OSError:
            self.teardown()
            raise
        self.url = self.server.url
        self.log.info("GUI of %s at %s (token required)", me, self.url.split("?")[0])
        self._log("info", f"control node {me} serving the GUI; tasks go as {s.verb}")
        if self.speech_error:
            self._log("warn", self.speech_error)
        self.wake_every(1.0 / s.rate_hz)

    def _start_speech(self, s: UISettings) -> None:
        try:
            from erni.plugins.ui.frontend import FrontEnd

            front = FrontEnd(s.denoise, s.vad, s.auto_gain, loud=s.loud_room)
            if front.note:
                self.log.info("%s", front.note)
            load = choose_recognizer(s.recogniser, s.vosk_model, wake=tuple(s.wake), front=front)
        except SpeechError as err:
            self.speech_error = str(err)
            self.log.warning("speech recognition off: %s", err)
            return
        self.recogniser_name = "vosk" if getattr(load, "backend", "") == "vosk" else "pocketsphinx"
        self.listener = Listener(load, self._recognised,
                                 on_error=lambda why: self.later(lambda: self._speech_failed(why))).start()
        if s.microphone:
            try:
                mic = Microphone(lambda pcm: self._feed("local", pcm), s.microphone_device).start()
                self._threads.append(mic)
            except (SpeechError, OSError) as err:
                self.log.warning("local microphone off: %s", err)
        if s.wav:
            feeder = threading.Thread(target=self._play_wav, args=(s.wav,), name="ui-wav", daemon=True)
            feeder.start()
            self._threads.append(feeder)

    def _speech_failed(self, why: str) -> None:
        self.speech_error = why
        self.log.warning("speech recognition off: %s", why)
        self._log("warn", why)

    def teardown(self) -> None:
        """Stop the web server, the microphone, the recogniser and the voice; join their threads."""
        if hasattr(self, "_stopping"):
            self._stopping.set()
        for part in [getattr(self, "server", None), *getattr(self, "_threads", []),
                     getattr(self, "listener", None), getattr(self, "speaker", None)]:
            if isinstance(part, threading.Thread):
                part.join(timeout=10)
            elif part is not None:
                part.stop()

    # -- each run ---------------------------------------------------------------------------

    def execute(self) -> None:
        for peer in self.peers.added:
            if peer.role != "control":
                self._log("info" if peer.up else "warn", f"{peer.name} {'joined' if peer.up else 'is not heard'}")
        for peer in self.peers.changed:
            reports = self.peers.reports(peer)
            if "down" in reports:
                self._log("error", f"{peer.name}: link lost (not heard for {self.clock.wall() - peer.last_heard:.0f} s)")
            elif "up" in reports:
                self._log("info", f"{peer.name}: link back")
            elif "restarted" in reports:
                self._log("warn", f"{peer.name} restarted")
        for task in self.tasks.added + self.tasks.changed:
            if task.done:
                self._task_ended(task)
        for task in self.tasks.removed:
            if not task.done and task.uid not in self._retired_uids:
                # withdrawn before it ended (by the client that sent it through this node): keep its row
                self._keep_row(task, f"withdrawn by {task.source}")
                self._log("dim", f"{task.destination}: {task.preposition} cancelled \u2014 withdrawn by {task.source}")
            self._retired_uids.discard(task.uid)
        for sub in (self.poses, self.netinfo, self.peers, self.tasks):
            if sub.added or sub.changed or sub.removed:
                self._dirty = True
        self._forget_old_tasks()
        if self._dirty:
            self._dirty = False
            self._publish()

    def _publish(self) -> None:
        """Hand the page a new picture only when something it shows changed: an idle page does no work."""
        picture = self.snapshot()
        if picture != self._published:
            self._published = picture
            self.server.publish(picture)

    def _task_ended(self, task: Task) -> None:
        r = task.result
        if r is None:
            return
        if task.uid in self._ended:
            return
        self._ended.add(task.uid)
        level = _ENDED_LEVEL.get(r.state.value, "error")
        self._log(level, f"{task.destination}: {task.preposition} {r.state.value}"
                  + (f" — {r.message}" if r.message else ""))

    def _forget_old_tasks(self) -> None:
        mine = [t for t in self.tasks if t.done and t.source == self.agent_name]
        if len(mine) > self.settings.history:
            mine.sort(key=lambda t: t.created)
            for t in mine[: len(mine) - self.settings.history]:
                self.remove(t)
                self._ended.discard(t.uid)

    # -- the picture of the team ------------------------------------------------------------

    def robots(self) -> list[str]:
        """Agent names of the robots: those with a Pose, and peers that announce role robot."""
        names = {p.robot for p in self.poses}
        names |= {p.name for p in self.peers if p.role == "robot"}
        names.discard(self.agent_name)
        return sorted(names, key=lambda n: (self.naming.number(n) is None, self.naming.number(n) or 0, n))

    def _known(self) -> tuple[dict[str, Pose], dict[str, Peer], list[str], dict[str, Task]]:
        """Poses and peers by robot, the robots' names, and each robot's newest running task (obstacle
        avoidance stays on until turned off: it is not a task in hand)."""
        poses = {p.robot: p for p in self.poses}
        peers = {p.name: p for p in self.peers}
        running: dict[str, Task] = {}
        for t in sorted(self.tasks, key=lambda t: t.created):
            if not t.done and t.destination and t.preposition != "avoid_obstacles":
                running[t.destination] = t
        return poses, peers, self.robots(), running

    def picture(self) -> JsonDict:
        """Return what the page shows as JSON-ready data: `snapshot()` dumped as the page gets it."""
        return self.snapshot().model_dump(mode="json")

    def snapshot(self) -> Picture:
        """Return what the page shows: robots, links, metrics, tasks, log, settings."""
        s = self.settings
        poses, peers, names, running = self._known()
        robots: list[RobotRow] = []
        up_names: set[str] = set()
        for name in names:
            pose, peer = poses.get(name), peers.get(name)
            reasons = []
            if pose is not None:
                if pose.battery is not None and pose.battery < s.low_battery:
                    reasons.append(f"battery {pose.battery:.1f} V")
                if pose.stalled:
                    reasons.append("stalled")
                if not pose.motors_enabled:
                    reasons.append("motors off")
                if pose.bumpers:
                    reasons.append("bumper")
            up = peer.up if peer is not None else pose is not None
            if up:
                up_names.add(name)
            task = running.get(name)
            robots.append(RobotRow(
                name=name, number=number if (number := self.naming.number(name)) is not None else name[:2],
                up=up, state="lost" if not up else ("warn" if reasons else "ok"), reasons=reasons,
                pose=None if pose is None else PoseRow.of(pose.x, pose.y, pose.theta, pose.v, pose.w, pose.battery),
                address=peer.address if peer else "", task=short(task) if task else ""))
        links = self._links(set(names), up_names)
        rows = [_task_row(t) for t in self.tasks] + list(self.retired)
        rows.sort(key=lambda r: r.created, reverse=True)
        return Picture(
            agent=self.agent_name, verb=s.verb, actions=list(STANDARD_ACTIONS), strategies=strategies(),
            speech=SpeechState(available=self.listener is not None and not self.speech_error,
                               error=self.speech_error, recogniser=self.recogniser_name),
            listening=self.spoken.listening, robots=robots, links=links, floorplan=self.floorplan,
            metrics=_metrics(names, robots, links, network_known=any(True for _ in self.netinfo)),
            tasks=rows[: s.history + 20], log=list(self.logs))

    def views(self) -> dict[str, RobotView]:
        """What the dialogue may tell the operator about each robot: pose, task, battery, link."""
        poses, peers, names, running = self._known()
        best: dict[str, float] = {}
        for lk in self._links(set(names), set(names)):
            for end in (lk.a, lk.b):
                best[end] = max(best.get(end, 0.0), lk.quality)
        now = self.clock.wall()
        out = {}
        for name in names:
            pose, peer, task = poses.get(name), peers.get(name), running.get(name)
            doing = ""
            if task is not None:
                r = task.result
                progress = f" {r.progress:.0%}" if r is not None and r.progress else ""
                try:
                    what = restate(task.preposition, task.params.model_dump())
                except KeyError:
                    what = short(task)
                doing = f"busy: {what} ({task.state.value}{progress})"
            out[name] = RobotView(
                name, up=peer.up if peer is not None else pose is not None,
                x=pose.x if pose else None, y=pose.y if pose else None, theta=pose.theta if pose else None,
                battery=pose.battery if pose else None, doing=doing,
                silent=now - peer.last_heard if peer is not None and peer.last_heard else None,
                link=best.get(name))
        return out

    def _links(self, names: set[str], up: set[str]) -> list[LinkRow]:
        """Links between robots from their NetInfo, best quality first; `stale` when old or an end is lost."""
        best = best_links(self.netinfo, names, lambda end: end not in up, self.settings.netinfo_max_age, self.clock.wall())
        return [LinkRow(a=a, b=b, quality=round(q, 3), stale=stale) for (a, b), (q, stale) in sorted(best.items())]

    def _log(self, level: LogLevel, text: str) -> None:
        self.logs.append(LogLine(t=self.clock.wall(), level=level, text=text))
        self._dirty = True

    # -- from the page (server thread) ------------------------------------------------------

    def _from_page(self, client: str, msg: Any) -> None:
        if isinstance(msg, MicMsg):
            self._mic(client, msg.on)
        else:
            self.later(lambda: self._page_message(client, msg))

    def _page_closed(self, client: str) -> None:
        self._mic(client, False)

    def _mic(self, client: str, on: bool) -> None:
        if on and (self.listener is None or self.listener.error):
            why = self.listener.error if self.listener is not None else self.speech_error
            self.server.emit(ErrorMsg(message=f"speech recognition off: {why}"), client)
            return
        with self._lock:
            was = client in self.mic_clients
            (self.mic_clients.add if on else self.mic_clients.discard)(client)
        if was and not on and self.listener is not None:
            self.listener.end_utterance(client)

    def _audio(self, client: str, pcm: bytes) -> None:
        with self._lock:
            listening = client in self.mic_clients
        if listening:
            self._feed(client, pcm)

    def _feed(self, source: str, pcm: bytes) -> None:
        if self.listener is not None:
            self.listener.feed(source, pcm)

    def _play_wav(self, path: str) -> None:
        try:
            for frame in wav_frames(path):
                if self._stopping.is_set():
                    return
                self._feed("wav", frame)
                time.sleep(0.01)  # no faster than the recogniser needs: keep its queue short
        except SpeechError as err:
            self.log.warning("%s", err)
        if self.listener is not None:
            self.listener.end_utterance("wav")

    def _recognised(self, source: str, text: Any, unsure: bool = False, **evidence: Any) -> None:
        """A recognised utterance (a text, or an object with `text` and `unsure`); `unsure` asks again."""
        words = str(getattr(text, "text", text))
        doubt = bool(unsure or getattr(text, "unsure", False) or evidence.get("unsure", False))
        self.later(lambda: self._answer(self.spoken.hear(words, self.views(), self._unfinished(), unsure=doubt),
                                        "voice", source))

    def _unfinished(self) -> list[Task]:
        """The unfinished tasks this node sent."""
        return [t for t in self.tasks if t.source == self.agent_name and not t.done]

    def _page_message(self, client: str, msg: Any) -> None:
        if isinstance(msg, CommandMsg):
            self._command(client, msg)
        elif isinstance(msg, SayMsg):
            if msg.selection:
                self.typed.select(msg.selection)
            self._answer(self.typed.hear(msg.text, self.views(), self._unfinished()), "typed", client)
        elif isinstance(msg, SelectMsg):
            self.typed.select(msg.robots)
            self.spoken.select(msg.robots)
        elif isinstance(msg, CancelTaskMsg):
            task = self.tasks.get(msg.uid)
            if task is None or task.done:
                self.server.emit(ErrorMsg(message=f"no running task {msg.uid}"), client)
            else:
                self._retire(task, "cancelled from the GUI")

    def _command(self, client: str, msg: CommandMsg) -> None:
        known = set(strategies()) | set(STANDARD_ACTIONS)
        if msg.action not in known:
            self.server.emit(ErrorMsg(message=f"unknown action {msg.action!r}; expected one of "
                                      f"{', '.join(sorted(known))}"), client)
            return
        robots = list(msg.robots)
        if not robots and msg.action == "stop":
            robots = self.robots()  # the Stop button with nothing selected stops everyone
        try:
            if not robots:
                raise Refusal("Select robots first (checkbox, click, or shift-drag a rectangle)")
            tasks = tasks_for(msg.action, msg.params, robots, verb=self.settings.verb, source=self.agent_name)
        except Refusal as why:
            self.server.emit(ErrorMsg(message=str(why)), client)
            return
        self._send(msg.action, tasks)
        views = self.views()
        try:
            what = restate(msg.action, tasks[0].params.model_dump())
        except KeyError:
            what = short(tasks[0])
        lost = [r for r in robots if r in views and not views[r].up]
        if msg.action not in ("stop", "cancel", "clear"):
            self.typed.memory.last = Sent(f"{self.typed.who(robots, False, views)}, {what}", tasks)
        say = f"{ROGER}: {self.typed.who(robots, False, views)}, {what}" + (
            f" ({', '.join(lost)} {'is' if len(lost) == 1 else 'are'} lost)" if lost else "")
        self.server.emit(ReplyMsg(text=say, heard="", channel="page", client=client, accepted=True))
        self._log("info", f"page: {tasks[0].verb} {short(tasks[0])} -> {', '.join(robots)}")

    def _answer(self, reply: Reply, channel: str, client: str) -> None:
        if self.listener is not None:  # a spoken read-back waits: short utterances are heard against its answers
            self.listener.answering = self.spoken.pending is not None
        if reply.say is None:
            self._log("dim", f"({channel}, standing by) \u201c{reply.heard}\u201d ignored")
            return
        for uid in reply.withdraw:
            task = self.tasks.get(uid)
            if task is not None and not task.done:
                self._retire(task, "cancelled by the operator" if reply.action == "cancel"
                             else f"re-sent at a new speed ({channel})")
        if reply.tasks:
            self._send(reply.action, reply.tasks)
        if reply.targets:
            self.typed.select(reply.targets)
            self.spoken.select(reply.targets)
            self.server.emit(SelectOut(robots=reply.targets))
        if self.speaker is not None:
            self.speaker.say(reply.say)
        self.server.emit(ReplyMsg(text=reply.say, heard=reply.heard, channel=channel, client=client,
                                  accepted=reply.accepted, asked=reply.asked))
        detail = f" ({', '.join(reply.targets)})" if reply.targets else ""
        self._log("info" if reply.accepted else "warn",
                  f"{channel}: \u201c{reply.heard}\u201d \u2192 {reply.say}{detail}")

    def _send(self, action: str, tasks: list[Task]) -> None:
        """Publish tasks; a motion command first cancels the robot's previous unfinished task.

        A RemoteBotMotion `cancel` is left to do that on the robot (MissionControl cancels the
        robot's remote tasks and reports them), so the UI does not withdraw them as well. Obstacle
        avoidance is not a motion: it stays on until a command turns it off.
        """
        remote_cancel = any(t.verb == "RemoteBotMotion" and t.preposition == "cancel" for t in tasks)
        if self.settings.supersede and action not in ("teleport", "avoid_obstacles", "speed") and not remote_cancel:
            targets = {t.destination for t in tasks}
            for old in list(self.tasks):
                if old.source == self.agent_name and old.destination in targets and not old.done \
                        and old.preposition != "avoid_obstacles":
                    self._retire(old, f"superseded by {action}")
        for task in tasks:
            self.add(task)


    def _retire(self, task: Task, why: str) -> None:
        """Cancel a task (remove it) and keep it in the task list as cancelled, with a line in the log."""
        self.remove(task)
        self._retired_uids.add(task.uid)
        self._keep_row(task, why)
        self._log("dim", f"{task.destination}: {task.preposition} cancelled \u2014 {why}")

    def _keep_row(self, task: Task, why: str) -> None:
        self.retired.append(_task_row(task).model_copy(update={"state": "cancelled", "message": why}))
        self._dirty = True


def short(t: Task) -> str:
    """`goto x=1.0 y=2.0`: the preposition and the parameters that differ from their defaults."""
    args = " ".join(f"{k}={v}" for k, v in t.params.model_dump(exclude_defaults=True).items())
    return f"{t.preposition} {args}".rstrip()


def _task_row(t: Task) -> TaskRow:
    r = t.result
    params = {k: v for k, v in t.params.model_dump().items() if isinstance(v, (int, float, str))}
    return TaskRow(uid=t.uid, robot=t.destination, verb=t.verb, preposition=t.preposition, text=short(t),
                   params=params, source=t.source, created=t.created, state=t.state.value,
                   progress=r.progress if r else 0.0, message=r.message if r else "",
                   values={k: v for k, v in (r.values if r else {}).items() if isinstance(v, (int, float, str))})


def _metrics(names: list[str], robots: list[RobotRow], links: list[LinkRow], *, network_known: bool) -> Metrics:
    links = [lk for lk in links if not lk.stale]
    adj = netgraph.from_edges(((lk.a, lk.b, 1.0) for lk in links if lk.quality > 0), nodes=names)
    comps = netgraph.connected_components(adj) if names else []
    cut = sorted(netgraph.articulation_points(adj)) if names else []
    quality = [lk.quality for lk in links]
    return Metrics(robots=len(names), up=sum(1 for r in robots if r.up), links=len(links),
                   mean_quality=round(sum(quality) / len(quality), 3) if quality else None,
                   components=len(comps), articulation_points=cut,
                   degree=round(2 * len(links) / len(names), 2) if names else 0, network_known=network_known)
