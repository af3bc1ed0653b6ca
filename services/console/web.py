"""The console's side toward the browser, on aiohttp's own HTTP and WebSocket server: the page and its files (shipped
in the package, nothing from the internet), and one WebSocket per open page that carries the camera frames
(binary), the overlays and the status (JSON text) to it and the person's requests from it.

Each request is parsed and judged by the core (:mod:`services.console.core`: the token beyond loopback, the
rules), then carried out by the service (:class:`services.console.service.ConsoleService`) in a worker thread, so
that an e-stop never waits behind a task request in progress. A page is sent one camera frame at a time: the next
only once it says it drew the last (its "drawn" message), so frames never queue in a socket or a browser, and the
console encodes a frame only when some page is ready for one (the newest then). A page gets the newest overlay and
status when it is ready for them; what it missed is dropped and counted, never queued."""
from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import socket
import ssl
import time
from collections import deque
from pathlib import Path
from typing import Optional

from aiohttp import WSMsgType, web

from services.console.core import (MAX_PAGE_MESSAGE_BYTES, Access, ActionMessage, AuthMessage, DrawnMessage, Refused,
                                   decide, parse_page_message)
from services.console.jog import JogRefused, JogSnapshot
from services.console.service import ConsoleService

STATIC = Path(__file__).resolve().parent / "static"
DEFAULT_PORT = 8080
#: how often each page gets the status (s)
STATUS_PERIOD_S = 0.2
#: ping an open page this often; one that does not answer is closed (s)
HEARTBEAT_S = 10.0
#: answers and refusals a page has not read yet, at most (older ones are dropped)
MAX_UNREAD_ANSWERS = 64
#: a page that has not said it drew its frame this long after it was sent is sent the newest anyway (a page that
#: lost one without saying so must not go dark for good); counted as frames.unacknowledged (s)
DRAW_TIMEOUT_S = 5.0
#: a page is told of its stick's refusals (50 snapshots a second) at most this often per reason (s)
JOG_REFUSAL_TELL_S = 1.0

_HEADERS = {
    # the page's own files and its own WebSocket, nothing else; never framed by another site (a framed console could
    # be clicked through by the framing page)
    "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; connect-src 'self'; "
                               "style-src 'self'; script-src 'self'; frame-ancestors 'none'; base-uri 'none'; "
                               "form-action 'none'",
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}


class Page:
    """One open page: its WebSocket, whether it gave the token, and what is waiting to be sent to it."""

    def __init__(self, ws: web.WebSocketResponse, authenticated: bool, number: int = 0) -> None:
        self.ws = ws
        #: the console's number for this page (its stick's holder is named by it)
        self.number = number
        #: when the page was last told of a refusal of its stick's, by reason (monotonic s)
        self.jog_told: dict[str, float] = {}
        self.authenticated = authenticated
        self.answers: deque[str] = deque(maxlen=MAX_UNREAD_ANSWERS)
        #: the newest frame, overlay and status not yet sent (each replaces the one before)
        self.newest: dict[str, object] = {}
        self.wake = asyncio.Event()
        #: when the frame the page has not yet said it drew was sent (monotonic s), or None
        self.frame_sent_at: Optional[float] = None

    def drawing(self, now: float) -> bool:
        """Whether the page is still drawing the frame it was sent (and is not yet sent another)."""
        return self.frame_sent_at is not None and now - self.frame_sent_at < DRAW_TIMEOUT_S

    def wants_frame(self, now: float) -> bool:
        """Whether a frame encoded now would be sent to this page at once."""
        return self.authenticated and not self.drawing(now) and "frame" not in self.newest

    def tell(self, message: dict) -> None:
        self.answers.append(json.dumps(message))
        self.wake.set()

    def offer(self, kind: str, payload) -> bool:
        """Queue ``payload`` as the newest of its ``kind``; True when it replaced one the page had not taken."""
        dropped = kind in self.newest
        self.newest[kind] = payload
        self.wake.set()
        return dropped

    async def pump(self, service: ConsoleService) -> None:
        """Send what waits, answers first (they are few and must arrive), then the newest status, overlay, and the
        newest frame once the page drew the last."""
        while not self.ws.closed:
            await self.wake.wait()
            self.wake.clear()
            while self.answers:
                await self.ws.send_str(self.answers.popleft())
            for kind in ("status", "overlay", "frame"):
                if kind == "frame" and self.drawing(time.monotonic()):
                    continue  # it stays the newest until the page draws the last
                payload = self.newest.pop(kind, None)
                if payload is None or self.ws.closed:
                    continue
                if isinstance(payload, bytes):
                    if self.frame_sent_at is not None:  # past DRAW_TIMEOUT_S without the page's word
                        service.counters.inc("frames.unacknowledged")
                    self.frame_sent_at = time.monotonic()
                    await self.ws.send_bytes(payload)
                    service.rates.tick("frames.sent")
                else:
                    await self.ws.send_str(payload)


class ConsoleWeb:
    """The console's web server over a started :class:`ConsoleService`."""

    def __init__(self, service: ConsoleService, access: Access, ssl_context: Optional[ssl.SSLContext] = None) -> None:
        self.service = service
        self.access = access
        self.ssl_context = ssl_context
        self.pages: set[Page] = set()
        #: pages that gave the token (or needed none), and those of them a frame encoded now would go to: read by
        #: the service's threads, written in the loop's
        self._watching = 0
        self._wanting_frames = 0
        self.loop: Optional[asyncio.AbstractEventLoop] = None
        self.app = web.Application(middlewares=[self._headers])
        self.app.router.add_get("/", self._index)
        self.app.router.add_get("/ws", self._websocket)
        self.app.router.add_static("/static/", STATIC, show_index=False, follow_symlinks=False)
        self._runner: Optional[web.AppRunner] = None
        self._tasks: list[asyncio.Task] = []
        #: the kinds of request being carried out now (each in a worker thread)
        self._in_flight: set = set()
        self.port = 0
        self._pages_opened = 0

    @property
    def scheme(self) -> str:
        return "https" if self.ssl_context is not None else "http"

    # ------------------------------------------------------------------ serving
    async def start(self, host: str, port: int) -> None:
        self.loop = asyncio.get_running_loop()
        self.service.on_frame = lambda packet: self.loop.call_soon_threadsafe(self._offer, "frame", packet)
        self.service.on_overlay = lambda overlay: self.loop.call_soon_threadsafe(self._offer, "overlay",
                                                                                   json.dumps(overlay))
        self.service.wants_frames = lambda: self._wanting_frames > 0
        self._runner = web.AppRunner(self.app, access_log=None, handle_signals=False)
        await self._runner.setup()
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        sock = socket.socket(family, kind, proto)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        self.port = sock.getsockname()[1]
        await web.SockSite(self._runner, sock, ssl_context=self.ssl_context).start()
        self._tasks.append(asyncio.create_task(self._send_status()))

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        for page in list(self.pages):
            with contextlib.suppress(Exception):
                await page.ws.close(message=b"the console is stopping")
        if self._runner is not None:
            await self._runner.cleanup()

    def url(self, host: str) -> str:
        shown = f"[{host}]" if ":" in host else host
        return f"{self.scheme}://{shown}:{self.port}/"

    # ------------------------------------------------------------------ HTTP
    @web.middleware
    async def _headers(self, request: web.Request, handler):
        response = await handler(request)
        response.headers.update(_HEADERS)
        return response

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "index.html")

    def _refuse(self, reason: str, message: str, page: Optional[Page] = None, request_id: Optional[int] = None):
        self.service.refused(reason, message)
        if page is not None:
            page.tell({"type": "refused", "id": request_id, "reason": reason, "message": message})

    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        try:
            self.access.check_origin(request.headers.get("Origin"), request.host, request.scheme)
        except Refused as refusal:
            self._refuse(refusal.reason, refusal.message)
            return web.Response(status=403, text=f"refused: {refusal.message}\n")
        ws = web.WebSocketResponse(heartbeat=HEARTBEAT_S, max_msg_size=4 * MAX_PAGE_MESSAGE_BYTES)
        if not ws.can_prepare(request).ok:
            return web.Response(status=400, text="this is the console's stream: open / in a browser\n")
        await ws.prepare(request)
        self._pages_opened += 1
        page = Page(ws, authenticated=not self.access.token_required, number=self._pages_opened)
        self.pages.add(page)
        self.service.counters.inc("pages.opened")
        self._count_watchers()
        pump = asyncio.create_task(page.pump(self.service))
        page.tell({"type": "hello", "robot_id": self.service.config.robot_id,
                   "token_required": self.access.token_required, "authenticated": page.authenticated,
                   "actions": ["task_start", "task_stop", "estop_engage", "estop_release", "teach", "grasp",
                               "open_hand", "task_resume"],
                   "page": page.number, "jog": self.service.jog_status()})
        try:
            async for message in ws:
                if message.type == WSMsgType.TEXT:
                    self._on_text(page, message.data)
                elif message.type == WSMsgType.BINARY:
                    self._refuse("malformed", "the console takes requests as JSON text, not binary messages", page)
                elif message.type == WSMsgType.ERROR:
                    self._refuse("malformed", f"the page's stream failed: {ws.exception()}")
        finally:
            self.pages.discard(page)
            self.service.jog_page_gone(page.number)  # a page that held the stick lets go at once
            self._count_watchers()
            pump.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await pump
        return ws

    def _count_watchers(self) -> None:
        now = time.monotonic()
        self._watching = sum(p.authenticated for p in self.pages)
        wanting = sum(p.wants_frame(now) for p in self.pages)
        if wanting and not self._wanting_frames:
            self.service.frame_wanted()
        self._wanting_frames = wanting
        self.service.pages_open = self._watching

    # ------------------------------------------------------------------ requests
    def _on_text(self, page: Page, text: str) -> None:
        try:
            message = parse_page_message(text)
        except Refused as refusal:
            self._refuse(refusal.reason, refusal.message, page)
            return
        if isinstance(message, DrawnMessage):
            if page.frame_sent_at is not None:
                self.service.frame_drawn(time.monotonic() - page.frame_sent_at)
            page.frame_sent_at = None
            # a frame encoded for another page while this one drew may be old by now: the page is sent the newest
            # image, encoded for it now
            page.newest.pop("frame", None)
            self._count_watchers()
            return
        if isinstance(message, JogSnapshot):
            self._on_jog(page, message)
            return
        if isinstance(message, AuthMessage):
            if not self.access.token_ok(message.token):
                self._refuse("token", "wrong token: nothing is shown or done without the right one", page)
                return
            page.authenticated = True
            self._count_watchers()
            page.tell({"type": "auth", "ok": True})
            return
        assert isinstance(message, ActionMessage)
        with self.service.lock:
            situation = self.service.model.situation(time.time())
        try:
            command = decide(message, self.access, situation)
            if command.action in self._in_flight:  # one of each at a time: a flood of requests queues nothing
                raise Refused("in_progress", f"a {command.action.value.replace('_', ' ')} is being carried out: "
                                             "wait for its answer")
        except Refused as refusal:
            self._refuse(refusal.reason, refusal.message, page, message.id)
            return
        self._in_flight.add(command.action)
        self._tasks.append(asyncio.create_task(self._carry_out(page, message.id, command)))
        self._tasks = [t for t in self._tasks if not t.done()]

    def _on_jog(self, page: Page, snapshot: JogSnapshot) -> None:
        try:
            if not page.authenticated:
                raise JogRefused("token", "this page has not given the token: its stick moves nothing")
            self.service.jog_snapshot(page.number, snapshot)
        except JogRefused as refusal:
            self.service.jog_refused(refusal)
            now = time.monotonic()
            if now - page.jog_told.get(refusal.reason, -1e9) >= JOG_REFUSAL_TELL_S:
                page.jog_told[refusal.reason] = now
                page.tell({"type": "refused", "id": None, "reason": refusal.reason, "message": refusal.message,
                           "jog": True})

    async def _carry_out(self, page: Page, request_id: int, command) -> None:
        try:
            done, what = await asyncio.get_running_loop().run_in_executor(None, self.service.perform, command)
        except Exception as exc:  # the stack's session failed under it: say so, keep serving
            self.service.counters.inc("errors.action")
            done, what = False, f"{command.action.value} failed: {exc}"
        finally:
            self._in_flight.discard(command.action)
        page.tell({"type": "result", "id": request_id, "action": command.action.value, "ok": done,
                   "message": what})

    # ------------------------------------------------------------------ to the pages
    def _offer(self, kind: str, payload) -> None:
        for page in self.pages:
            if page.authenticated and page.offer(kind, payload):
                self.service.counters.inc(f"dropped.{kind}")
        if kind == "frame":
            self._count_watchers()

    async def _send_status(self) -> None:
        while True:
            await asyncio.sleep(STATUS_PERIOD_S)
            self._count_watchers()  # a page past DRAW_TIMEOUT_S takes a frame again
            if not self._watching:
                continue
            with self.service.lock:
                snapshot = self.service.model.snapshot(time.time())
            snapshot["console"] = {"errors": self.service.counters.snapshot(), "wall_stamps": self.service.wall_stamps}
            snapshot["jog"] = self.service.jog_status()
            self._offer("status", json.dumps(snapshot))


def tls_context(certificate: str, key: str) -> ssl.SSLContext:
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.load_cert_chain(certificate, key)
    return context


async def serve(service: ConsoleService, access: Access, host: str, port: int,
                ssl_context: Optional[ssl.SSLContext] = None, on_ready=None, stop: Optional[asyncio.Event] = None):
    """Serve until SIGTERM/SIGINT (or ``stop``); ``on_ready(web)`` once it listens."""
    console = ConsoleWeb(service, access, ssl_context)
    stop = stop or asyncio.Event()
    loop = asyncio.get_running_loop()
    with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):  # not the main thread: ``stop`` only
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
    await console.start(host, port)
    try:
        if on_ready is not None:
            on_ready(console)
        await stop.wait()
    finally:
        await console.stop()
