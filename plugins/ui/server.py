"""The GUI's web server: aiohttp (HTTP + WebSocket) on thread `ui-http` with its own asyncio loop.

The plugin hands the server typed messages (`publish(picture)`, `emit(event)`: `protocol.Picture`
and `protocol.Event`) under a lock; a pump
on the server's loop sends the newest state to every page when it changed, at most `rate_hz`
times a second, and events at once. Page messages are validated (`protocol.parse_message`)
and handed to the plugin's callbacks; nothing on this thread touches the blackboard.

Every request is checked before it is served (`_guard`): the `Host` header must name this
control node (a local address, localhost, this host's name, or a name in `allowed_hosts`), so
a page whose own domain was rebound to this address (DNS rebinding) is refused; a request that
carries an `Origin` must come from this same origin, so a page of another site cannot open the
WebSocket or read the state; and everything but the page's static assets needs the token.

What the server sends is JSON a browser parses (`page_json`): a number that is not finite (no
validated message holds one, but a state published as plain data may: the page's own checks are
tested so) goes as `null`, never as `NaN`, which `JSON.parse` refuses and which would blank the
page. Bad page messages and refused requests are logged at most once every `LOG_PERIOD` seconds
each, with the count held back since.
"""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
import json
import logging
import math
import socket
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web
from pydantic import JsonValue

from erni.blackboard.errors import NetworkError
from erni.logs import RateLimitedLog
from erni.plugins.ui.protocol import (
    BadMessage,
    ErrorMsg,
    Event,
    HelloMsg,
    HostileMessage,
    JsonDict,
    Picture,
    PingMsg,
    PongMsg,
    parse_message,
)

STATIC = Path(__file__).with_name("static")
PONG = PongMsg().model_dump_json()
MAX_AUDIO_FRAME = 64 * 1024

log = logging.getLogger("erni.ui.http")
LOG_PERIOD = 10.0
"""Seconds between two log lines of one kind (a bad page message, a refused request, a number sent as null)."""


def page_json(data: JsonValue, on_non_finite: Callable[[], None] | None = None) -> str:
    """JSON text of plain data for the page: a NaN or an infinity anywhere in it becomes null (what
    `JSON.parse` reads), so the text is always JSON; `on_non_finite` is called when one was there."""
    try:
        return json.dumps(data, allow_nan=False)
    except ValueError:  # a non-finite number somewhere: the slow walk, only then
        if on_non_finite is not None:
            on_non_finite()
        return json.dumps(_finite_or_null(data), allow_nan=False)


def _finite_or_null(data: JsonValue) -> JsonValue:
    if isinstance(data, float):
        return data if math.isfinite(data) else None
    if isinstance(data, dict):
        return {k: _finite_or_null(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [_finite_or_null(v) for v in data]
    return data


TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml"}


def load_assets(folder: Path) -> dict[str, tuple[bytes, str]]:
    """Read the page's files once: requests are answered from memory, with no file I/O."""
    return {f.name: (f.read_bytes(), TYPES.get(f.suffix, "application/octet-stream"))
            for f in sorted(folder.iterdir()) if f.is_file()}


_ANY = ("0.0.0.0", "", "::")


def public_address(family: int = socket.AF_INET) -> str:
    """This host's address on its default route (what a remote operator can open); loopback if none.

    A UDP socket "connected" to a documentation address sends nothing but makes the kernel pick
    the outgoing interface, whose address is the answer.
    """
    probe = ("192.0.2.1", 9) if family == socket.AF_INET else ("2001:db8::1", 9)
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as s:
            s.connect(probe)
            address = str(s.getsockname()[0])
    except OSError:
        address = ""
    if address and not ipaddress.ip_address(address).is_unspecified:
        return address
    try:
        address = socket.gethostbyname(socket.gethostname())
    except OSError:
        address = ""
    return address or ("127.0.0.1" if family == socket.AF_INET else "::1")


def is_local_address(host: str) -> bool:
    """True when `host` is an IP address of this machine (it can be bound)."""
    try:
        ip = ipaddress.ip_address(host.strip("[]"))
    except ValueError:
        return False
    family = socket.AF_INET6 if ip.version == 6 else socket.AF_INET
    try:
        with socket.socket(family, socket.SOCK_DGRAM) as s:
            s.bind((str(ip), 0))
        return True
    except OSError:
        return False


def split_host(value: str) -> tuple[str, int | None]:
    """`host:port`, `[v6]:port`, `host` -> (lower-case host, port or None)."""
    value = value.strip().lower()
    if value.startswith("["):
        end = value.find("]")
        host, rest = value[1:end], value[end + 1:]
        return host, int(rest[1:]) if rest.startswith(":") and rest[1:].isdigit() else None
    if value.count(":") == 1:
        host, _, port = value.partition(":")
        return host, int(port) if port.isdigit() else None
    return value, None


class WebServer:
    """Serves the page and its WebSocket; `start()` returns once the port is bound."""

    def __init__(self, host: str, port: int, *, token: str, on_message: Callable[[str, Any], None],
                 on_audio: Callable[[str, bytes], None], on_close: Callable[[str], None],
                 rate_hz: float = 10.0, static_dir: Path = STATIC,
                 announce: Callable[[str], None] | None = None, allowed_hosts: tuple[str, ...] = ()) -> None:
        if not token:
            raise NetworkError("the GUI needs a token (an empty one would let any local program in)")
        self.host, self.port = host, port
        self.token = token
        self.allowed_hosts = {h.lower() for h in allowed_hosts}
        self._host_ok: dict[str, bool] = {}
        self.on_message, self.on_audio, self.on_close = on_message, on_audio, on_close
        self.period = 1.0 / rate_hz
        self.static_dir = static_dir
        self.announce = announce
        self.clients: dict[str, web.WebSocketResponse] = {}
        self.bad_messages = 0
        self.non_finite = 0  # messages to a page that held a number that is not finite (sent as null)
        self._rare = RateLimitedLog(log, LOG_PERIOD)
        self._lock = threading.Lock()
        self._state: JsonDict = {}
        self._version = 0
        self._events: deque[tuple[str | None, Event]] = deque(maxlen=1000)
        self._count = 0
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping: asyncio.Event | None = None
        self._wake: asyncio.Event | None = None
        self.refused = 0
        self._thread = threading.Thread(target=self._run, name="ui-http", daemon=True)

    # -- from the plugin's threads ----------------------------------------------------------

    def start(self) -> WebServer:
        """Bind and serve; raise OSError naming the address if it cannot be bound."""
        self._thread.start()
        self._ready.wait(timeout=15)
        if self._error is not None:
            self._thread.join(timeout=5)
            raise NetworkError(f"cannot serve the GUI on {self.host}:{self.port}: {self._error}")
        return self

    def stop(self) -> None:
        """Close every page's WebSocket and the listening socket; join the thread."""
        if self._loop is not None and self._stopping is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._stopping.set)
        if self._thread.is_alive():
            self._thread.join(timeout=10)

    @property
    def url(self) -> str:
        """The address a browser opens, with the token; bound to any address: this host's real address."""
        host = self.host
        if host in _ANY:
            host = public_address(socket.AF_INET6 if host == "::" else socket.AF_INET)
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}/?token={self.token}"

    def host_allowed(self, name: str) -> bool:
        """True when a Host header naming `name` addresses this control node (not a rebound domain).

        Accepted: an IP address of this machine (what a user types), localhost, this host's own
        names, and the names in `allowed_hosts`. Any other domain name is refused: a page whose
        domain was rebound to this address still sends its own name.
        """
        name = name.lower().strip("[]")
        ok = self._host_ok.get(name)
        if ok is None:
            if name in self.allowed_hosts or name in ("localhost", socket.gethostname().lower(),
                                                      socket.getfqdn().lower()):
                ok = True
            elif _is_ip(name):
                ok = not ipaddress.ip_address(name).is_unspecified and is_local_address(name)
            else:
                ok = False
            if len(self._host_ok) < 256:  # hostile Host headers must not grow the cache without end
                self._host_ok[name] = ok
        return ok

    def publish(self, state: Picture | JsonDict) -> None:
        """Make `state` the newest state; pages get it on the next pump.

        A `Picture` is what the plugin publishes; JSON-ready data is taken as it is (a test hands the
        page what no Picture holds, to see the page's own checks)."""
        if isinstance(state, Picture):
            state = state.model_dump(mode="json")
        with self._lock:
            self._state = state
            self._version += 1
        self._nudge()

    def _nudge(self) -> None:
        """Wake the pump now (from any thread)."""
        loop, wake = self._loop, self._wake
        if loop is not None and wake is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(wake.set)
            except RuntimeError:  # the loop closed meanwhile
                pass

    def state(self) -> JsonDict:
        """Return the newest published state, as the page gets it (JSON-ready data)."""
        with self._lock:
            return self._state

    def emit(self, event: Event, client: str | None = None) -> None:
        """Send an event to one page (`client`) or to all, at once."""
        with self._lock:
            self._events.append((client, event))
        self._nudge()

    # -- the server's thread ----------------------------------------------------------------

    def _json(self, data: JsonValue) -> str:
        """`page_json`, counting and logging (rarely) a number that had to go as null."""
        return page_json(data, self._non_finite)

    def _non_finite(self) -> None:
        self.non_finite += 1
        self._rare.warning("non-finite", "a message to the page held a number that is not finite: sent as null")

    def _run(self) -> None:
        self._loop = asyncio.new_event_loop()
        self._loop.set_default_executor(ThreadPoolExecutor(max_workers=2, thread_name_prefix="ui-http-io"))
        try:
            self._loop.run_until_complete(self._main())
        except BaseException as err:  # reported by start()
            self._error = err
        finally:
            self._ready.set()
            self._loop.run_until_complete(self._loop.shutdown_default_executor())  # name resolution threads
            self._loop.close()

    async def _main(self) -> None:
        self._stopping = asyncio.Event()
        self._wake = asyncio.Event()
        app = web.Application(middlewares=[self._guard], client_max_size=MAX_AUDIO_FRAME)
        self.assets = load_assets(self.static_dir)
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._websocket)
        app.router.add_get("/api/state", self._api_state)
        app.router.add_get("/static/{name}", self._asset)
        runner = web.AppRunner(app, access_log=None, handle_signals=False)
        await runner.setup()
        try:
            site = web.TCPSite(runner, self.host, self.port, reuse_address=True)
            await site.start()
            self.port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
            if self.announce is not None:
                self.announce(self.url)
            self._ready.set()
            pump = asyncio.create_task(self._pump())
            self._nudge()
            await self._stopping.wait()
            pump.cancel()
            for ws in list(self.clients.values()):
                await ws.close(code=1001, message=b"control node stopping")
        finally:
            await runner.cleanup()

    def refusal(self, request: web.Request) -> str | None:
        """Why a request may not be served (one line), or None: Host, Origin and token are checked."""
        host_header = request.headers.get("Host", "")
        host, _ = split_host(host_header)
        if not host or not self.host_allowed(host):
            return (f"Host {host_header!r} is not this control node (a page of another site, or a domain "
                    "rebound to this address); open the URL the control node printed, or add the name "
                    "to the UI's allowed_hosts")
        origin = request.headers.get("Origin")
        if origin is not None:
            scheme, _, rest = origin.lower().partition("://")
            if scheme not in ("http", "https") or rest != host_header.lower():
                return f"a page from {origin[:100]!r} may not use this control node (only its own page may)"
        if request.path.startswith("/static/"):
            return None  # the page's assets are not secret
        given = request.query.get("token", "")
        bearer = request.headers.get("Authorization", "")
        if bearer.startswith("Bearer "):
            given = given or bearer[7:]
        if not hmac.compare_digest(given.encode(), self.token.encode()):
            return "missing or wrong token: open the URL the control node printed (it ends with ?token=...)"
        return None

    @web.middleware
    async def _guard(self, request: web.Request, handler: Callable[..., Any]) -> web.StreamResponse:
        why = self.refusal(request)
        if why is not None:
            self.refused += 1
            self._rare.info("refused", f"refused {request.method} {request.path[:100]!r}: {why}")
            return web.Response(status=403, text=why + "\n")
        response: web.StreamResponse = await handler(request)
        return response

    async def _index(self, request: web.Request) -> web.StreamResponse:
        body, kind = self.assets["index.html"]
        return web.Response(body=body, content_type=kind, headers={"Cache-Control": "no-cache"})

    async def _asset(self, request: web.Request) -> web.StreamResponse:
        found = self.assets.get(request.match_info["name"])
        if found is None:
            raise web.HTTPNotFound(text=f"no asset {request.match_info['name']!r}\n")
        return web.Response(body=found[0], content_type=found[1], headers={"Cache-Control": "no-cache"})

    async def _api_state(self, request: web.Request) -> web.StreamResponse:
        with self._lock:
            state = self._state
        return web.json_response(state, dumps=self._json)

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse(heartbeat=5.0, max_msg_size=MAX_AUDIO_FRAME)
        await ws.prepare(request)
        self._count += 1
        client = f"page{self._count}"
        self.clients[client] = ws
        with self._lock:
            state = self._state
        try:
            await ws.send_str(self._json(HelloMsg(client=client).model_dump(mode="json")))
            await ws.send_str(self._json({"type": "state", **state}))
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    await self._text(client, ws, msg.data)
                elif msg.type == WSMsgType.BINARY:
                    if len(msg.data) % 2:
                        await self._reject(ws, "audio frame of odd length: expected 16-bit samples")
                    else:
                        self.on_audio(client, msg.data)
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            self.clients.pop(client, None)
            self.on_close(client)
        return ws

    async def _text(self, client: str, ws: web.WebSocketResponse, text: str) -> None:
        try:
            msg = parse_message(text)
        except HostileMessage as err:  # no page sends it: answer once and hang up
            await self._reject(ws, f"{err}; closing the connection")
            await ws.close(code=1009, message=b"message too deep or too long")
            return
        except BadMessage as err:
            await self._reject(ws, str(err))
            return
        if isinstance(msg, PingMsg):
            await ws.send_str(PONG)
            return
        try:
            self.on_message(client, msg)
        except Exception:  # a handler bug must not close the page's connection
            log.exception("GUI message %s failed", msg.type)

    async def _reject(self, ws: web.WebSocketResponse, why: str) -> None:
        self.bad_messages += 1
        self._rare.info("bad message", f"bad message from a page: {why}")
        await ws.send_str(self._json(ErrorMsg(message=why).model_dump(mode="json")))

    async def _pump(self) -> None:
        """Send events at once and the state when it changed, at most once a period; idle, send nothing."""
        assert self._wake is not None
        loop = asyncio.get_running_loop()
        sent, last = -1, -self.period
        while True:
            with self._lock:
                pending = self._version != sent
            wait = max(0.0, last + self.period - loop.time()) if pending else None
            if wait is None or wait > 0:
                try:
                    await asyncio.wait_for(self._wake.wait(), timeout=wait)
                except TimeoutError:
                    pass
            self._wake.clear()
            with self._lock:
                version, state = self._version, self._state
                events = list(self._events)
                self._events.clear()
            if version != sent and loop.time() - last >= self.period:
                sent, last = version, loop.time()
                text = self._json({"type": "state", **state})
                await asyncio.gather(*(self._send(ws, text) for ws in list(self.clients.values())))
            for client, event in events:
                text = self._json(event.model_dump(mode="json"))
                targets = [self.clients[client]] if client in self.clients else (
                    [] if client else list(self.clients.values()))
                await asyncio.gather(*(self._send(ws, text) for ws in targets))

    @staticmethod
    async def _send(ws: web.WebSocketResponse, text: str) -> None:
        try:
            await asyncio.wait_for(ws.send_str(text), timeout=2.0)
        except (TimeoutError, ConnectionResetError, RuntimeError):
            pass


def _is_ip(host: str) -> bool:
    try:
        ipaddress.ip_address(host.strip("[]"))
        return True
    except ValueError:
        return False
