"""The GUI's web server: aiohttp (HTTP + WebSocket) on thread `ui-http` with its own asyncio loop.

The plugin hands the server plain data (`publish(state)`, `emit(event)`) under a lock; a pump
on the server's loop sends the newest state to every page at most `rate_hz` times a second,
and events as they come. Page messages are validated (`protocol.parse_message`) and handed
to the plugin's callbacks; nothing on this thread touches the blackboard.
"""

from __future__ import annotations

import asyncio
import hmac
import json
import logging
import threading
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web

from erni.blackboard.errors import NetworkError
from erni.plugins.ui.protocol import BadMessage, PingMsg, parse_message

STATIC = Path(__file__).with_name("static")
MAX_AUDIO_FRAME = 64 * 1024

log = logging.getLogger("erni.ui.http")


TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml"}


def load_assets(folder: Path) -> dict[str, tuple[bytes, str]]:
    """Read the page's files once: requests are answered from memory, with no file I/O."""
    return {f.name: (f.read_bytes(), TYPES.get(f.suffix, "application/octet-stream"))
            for f in sorted(folder.iterdir()) if f.is_file()}


class WebServer:
    """Serves the page and its WebSocket; `start()` returns once the port is bound."""

    def __init__(self, host: str, port: int, *, token: str | None, on_message: Callable[[str, Any], None],
                 on_audio: Callable[[str, bytes], None], on_close: Callable[[str], None],
                 rate_hz: float = 10.0, static_dir: Path = STATIC,
                 announce: Callable[[str], None] | None = None) -> None:
        self.host, self.port = host, port
        self.token = token
        self.on_message, self.on_audio, self.on_close = on_message, on_audio, on_close
        self.period = 1.0 / rate_hz
        self.static_dir = static_dir
        self.announce = announce
        self.clients: dict[str, web.WebSocketResponse] = {}
        self.bad_messages = 0
        self._lock = threading.Lock()
        self._state: dict[str, Any] = {}
        self._version = 0
        self._events: deque[tuple[str | None, dict[str, Any]]] = deque(maxlen=1000)
        self._count = 0
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stopping: asyncio.Event | None = None
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
        """The address to open, with the token when one is required."""
        host = "127.0.0.1" if self.host in ("0.0.0.0", "") else self.host
        host = f"[{host}]" if ":" in host else host
        return f"http://{host}:{self.port}/" + (f"?token={self.token}" if self.token else "")

    def publish(self, state: dict[str, Any]) -> None:
        """Make `state` (JSON-ready data) the newest state; pages get it on the next pump."""
        with self._lock:
            self._state = state
            self._version += 1

    def state(self) -> dict[str, Any]:
        """Return the newest published state."""
        with self._lock:
            return self._state

    def emit(self, event: dict[str, Any], client: str | None = None) -> None:
        """Send an event to one page (`client`) or to all."""
        with self._lock:
            self._events.append((client, event))

    # -- the server's thread ----------------------------------------------------------------

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
        app = web.Application(middlewares=[self._auth], client_max_size=MAX_AUDIO_FRAME)
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
            await self._stopping.wait()
            pump.cancel()
            for ws in list(self.clients.values()):
                await ws.close(code=1001, message=b"control node stopping")
        finally:
            await runner.cleanup()

    @web.middleware
    async def _auth(self, request: web.Request, handler: Callable[..., Any]) -> web.StreamResponse:
        if self.token and not request.path.startswith("/static/"):
            given = request.query.get("token", "")
            if not hmac.compare_digest(given.encode(), self.token.encode()):
                return web.Response(status=403, text="missing or wrong token: open the URL the control "
                                    "node printed (it ends with ?token=...)\n")
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
        return web.json_response(state)

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse(heartbeat=5.0, max_msg_size=MAX_AUDIO_FRAME)
        await ws.prepare(request)
        self._count += 1
        client = f"page{self._count}"
        self.clients[client] = ws
        with self._lock:
            state = self._state
        try:
            await ws.send_str(json.dumps({"type": "hello", "client": client}))
            await ws.send_str(json.dumps({"type": "state", **state}))
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
        except BadMessage as err:
            await self._reject(ws, str(err))
            return
        if isinstance(msg, PingMsg):
            await ws.send_str('{"type":"pong"}')
            return
        try:
            self.on_message(client, msg)
        except Exception:  # a handler bug must not close the page's connection
            log.exception("GUI message %s failed", msg.type)

    async def _reject(self, ws: web.WebSocketResponse, why: str) -> None:
        self.bad_messages += 1
        log.info("bad message from a page: %s", why)
        await ws.send_str(json.dumps({"type": "error", "message": why}))

    async def _pump(self) -> None:
        sent = -1
        while True:
            await asyncio.sleep(self.period)
            with self._lock:
                version, state = self._version, self._state
                events = list(self._events)
                self._events.clear()
            if version != sent:
                sent = version
                text = json.dumps({"type": "state", **state})
                await asyncio.gather(*(self._send(ws, text) for ws in list(self.clients.values())))
            for client, event in events:
                text = json.dumps(event)
                targets = [self.clients[client]] if client in self.clients else (
                    [] if client else list(self.clients.values()))
                await asyncio.gather(*(self._send(ws, text) for ws in targets))

    @staticmethod
    async def _send(ws: web.WebSocketResponse, text: str) -> None:
        try:
            await asyncio.wait_for(ws.send_str(text), timeout=2.0)
        except (TimeoutError, ConnectionResetError, RuntimeError):
            pass
