"""The console's web side as deployed (`mfvs console`, its own process) against a real router and the safety
service, with aiohttp's client in place of a browser: what it serves, who may open its stream, requests that are
refused (counted in its health, the console running on) and the e-stop carried out; its session to the router
survives a router restart."""
import asyncio
import contextlib
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import aiohttp
import pytest

from protocol import messages as m
from protocol.conventions import ClockMode
from services.model.arm import load_arm
from services.runtime.service import query_health
from services.runtime.transport import Router, free_loopback_port, open_session
from services.safety.service import SafetyConfig, SafetyService
from services.stack.local import ConsoleProcess
from tests.stack import KEYS, wait_for

TOKEN = "a token for tests"
MFVS = str(Path(sys.executable).parent / "mfvs")


@pytest.fixture
def stack_with_safety():
    """A router on a fixed free port (so that it can be restarted there) and the safety service."""
    port = free_loopback_port()
    router = Router(port=port).start()
    safety = SafetyService(SafetyConfig(clock=ClockMode.REALTIME, zenoh=router.client_config())).start()
    state = {"router": router, "safety": safety, "port": port}
    try:
        yield state
    finally:
        safety.stop()
        state["router"].close()


def ws_url(url: str) -> str:
    return url.replace("http", "ws", 1) + "ws"


class Page:
    """A page's WebSocket (aiohttp's client): what the console sent, by type."""

    def __init__(self, url, origin=None, headers=None):
        self.url, self.origin, self.headers = url, origin if origin is not None else url.rstrip("/"), headers
        self.received: list[dict] = []
        self.frames: list[bytes] = []

    async def __aenter__(self):
        self.session = aiohttp.ClientSession()
        self.ws = await self.session.ws_connect(ws_url(self.url), origin=self.origin, headers=self.headers)
        return self

    async def __aexit__(self, *exc):
        await self.ws.close()
        await self.session.close()

    async def send(self, message):
        await (self.ws.send_bytes(message) if isinstance(message, bytes) else
               self.ws.send_str(message if isinstance(message, str) else json.dumps(message)))

    async def until(self, predicate, timeout=10.0, since=0):
        """The newest message (from the ``since``-th on) that ``predicate`` takes, received within ``timeout``."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            found = [r for r in self.received[since:] if predicate(r)]
            if found:
                return found[-1]
            try:
                message = await self.ws.receive(timeout=max(0.05, deadline - time.monotonic()))
            except asyncio.TimeoutError:
                break
            if message.type == aiohttp.WSMsgType.TEXT:
                self.received.append(json.loads(message.data))
            elif message.type == aiohttp.WSMsgType.BINARY:
                self.frames.append(message.data)
            else:
                raise AssertionError(f"the stream ended: {message}")
        raise AssertionError(f"nothing such arrived; received {[r['type'] for r in self.received]}")

    async def next_frame(self, timeout=10.0) -> bytes:
        """The next frame the console sends (what comes before it is kept in :attr:`received`)."""
        while True:
            message = await self.ws.receive(timeout=timeout)
            if message.type == aiohttp.WSMsgType.BINARY:
                self.frames.append(message.data)
                return message.data
            if message.type != aiohttp.WSMsgType.TEXT:
                raise AssertionError(f"the stream ended: {message}")
            self.received.append(json.loads(message.data))

    async def answer(self, message, timeout=10.0):
        """Send a request and wait for its result or refusal."""
        request_id = message.get("id") if isinstance(message, dict) else None
        before = len(self.received)
        await self.send(message)
        return await self.until(lambda r: r["type"] in ("result", "refused") and r.get("id") == request_id,
                                timeout, since=before)


def healths(client_config, timeout_s=2.0) -> dict:
    session = open_session(client_config)
    try:
        return query_health(session, KEYS, timeout_s)
    finally:
        session.close()


def console_errors(client_config) -> dict:
    found = healths(client_config)
    return dict(found["console"].errors) if "console" in found else {}


def test_the_page_its_files_and_nothing_else_are_served(stack_with_safety):
    router = stack_with_safety["router"]
    with ConsoleProcess(router.endpoint) as console:
        async def fetch():
            async with aiohttp.ClientSession() as session:
                async with session.get(console.url) as page:
                    html, headers = await page.text(), page.headers
                async with session.get(console.url + "static/console.js") as script:
                    js = await script.text()
                async with session.get(console.url + "static/../core.py") as escape:
                    escaped = escape.status
                async with session.get(console.url + "ws", headers={"Origin": console.url.rstrip("/")}) as plain:
                    plain_status = plain.status
                async with session.post(console.url + "ws") as posted:
                    posted_status = posted.status
            return html, headers, js, escaped, plain_status, posted_status

        html, headers, js, escaped, plain_status, posted_status = asyncio.run(fetch())
        assert "<canvas id=\"camera\"" in html and 'id="estop"' in html
        assert "http" not in html.replace("http-equiv", "")  # nothing from the internet
        assert "default-src 'self'" in headers["Content-Security-Policy"] and headers["X-Frame-Options"] == "DENY"
        assert "new WebSocket" in js
        assert escaped in (403, 404) and plain_status == 400 and posted_status == 405


def test_a_page_from_another_origin_or_host_cannot_open_the_stream(stack_with_safety):
    router = stack_with_safety["router"]
    with ConsoleProcess(router.endpoint) as console:
        port = console.url.rsplit(":", 1)[1].strip("/")

        async def attempt(origin, headers=None):
            async with aiohttp.ClientSession() as session:
                try:
                    async with session.ws_connect(ws_url(console.url), origin=origin, headers=headers):
                        return "opened"
                except aiohttp.WSServerHandshakeError as exc:
                    return exc.status

        assert asyncio.run(attempt("http://evil.example")) == 403
        assert asyncio.run(attempt(f"http://127.0.0.1:{int(port) + 1}")) == 403
        assert asyncio.run(attempt(f"http://evil.example:{port}", {"Host": f"evil.example:{port}"})) == 403
        assert asyncio.run(attempt(console.url.rstrip("/"))) == "opened"
        assert wait_for(lambda: console_errors(router.client_config()).get("refused.origin") == 2, timeout=10)
        assert console_errors(router.client_config()).get("refused.host") == 1


def test_without_the_token_nothing_is_shown_or_done_and_bad_requests_are_refused_and_counted(stack_with_safety):
    router, safety = stack_with_safety["router"], stack_with_safety["safety"]
    with ConsoleProcess(router.endpoint, "--token", TOKEN) as console:
        assert console.ready["token_required"]

        async def session():
            async with Page(console.url) as page:
                hello = await page.until(lambda r: r["type"] == "hello")
                assert hello["token_required"] and not hello["authenticated"]
                for action in ("task_start", "task_stop", "estop_engage", "estop_release"):
                    refusal = await page.answer({"type": "action", "action": action, "id": 1, "operator": "eve",
                                                 "confirm": True, "token": "a guess!"})
                    assert refusal["type"] == "refused" and refusal["reason"] == "token", refusal
                assert (await page.answer({"type": "auth", "token": "a guess!"}))["reason"] == "token"
                await asyncio.sleep(1.0)
                assert not page.frames and not [r for r in page.received if r["type"] == "status"]
                # malformed: each refused with a sentence, the stream stays open
                assert (await page.answer(b"\x00\x01binary"))["reason"] == "malformed"
                assert (await page.answer("{not json"))["reason"] == "malformed"
                # (a request that does not parse has no number the console could answer it under)
                assert (await page.answer({"type": "action", "action": "move_joint"}))["reason"] == "unknown_action"
                assert (await page.answer({"type": "action", "action": "task_start", "velocity": 1}))["reason"] == \
                    "malformed"
                await page.send({"type": "auth", "token": TOKEN})
                await page.until(lambda r: r["type"] == "auth" and r["ok"])
                status = await page.until(lambda r: r["type"] == "status")
                assert status["estop"]["engaged"] is False
                # with the token the rules still hold: a release of an e-stop that is not engaged is refused
                refusal = await page.answer({"type": "action", "action": "estop_release", "id": 4, "operator": "al",
                                             "confirm": True, "token": TOKEN})
                assert refusal["reason"] == "not_engaged"

        asyncio.run(session())
        assert not safety.core.estop_latched  # nothing was done
        errors = console_errors(router.client_config())
        assert errors.get("refused.token") == 5 and errors.get("refused.malformed") == 3, errors
        assert errors.get("refused.unknown_action") == 1 and errors.get("refused.not_engaged") == 1, errors
        assert console.process.poll() is None  # it keeps running


def test_the_estop_from_the_page_and_the_rules_around_it_and_the_session_survives_a_router_restart(stack_with_safety):
    router, safety = stack_with_safety["router"], stack_with_safety["safety"]
    with ConsoleProcess(router.endpoint) as console:
        async def engage_and_release(tag):
            async with Page(console.url) as page:
                await page.until(lambda r: r["type"] == "status" and r["estop"]["engaged"] is False, timeout=30)
                done = await page.answer({"type": "action", "action": "estop_engage", "id": 1, "operator": "bob",
                                          "reason": tag})
                assert done["type"] == "result" and done["ok"] and "engaged" in done["message"], done
                assert safety.core.estop_latched and safety.core.estop_reason == f"bob: {tag}"
                await page.until(lambda r: r["type"] == "status" and r["estop"]["engaged"] is True)
                again = await page.answer({"type": "action", "action": "estop_engage", "id": 2})
                assert again["reason"] == "already_engaged", again
                start = await page.answer({"type": "action", "action": "task_start", "id": 3, "operator": "bob"})
                assert start["reason"] == "estop_engaged", start
                unconfirmed = await page.answer({"type": "action", "action": "estop_release", "id": 4,
                                                 "operator": "bob"})
                assert unconfirmed["reason"] == "unconfirmed" and safety.core.estop_latched
                released = await page.answer({"type": "action", "action": "estop_release", "id": 5,
                                              "operator": "bob", "confirm": True})
                assert released["type"] == "result" and released["ok"], released
                assert not safety.core.estop_latched

        asyncio.run(engage_and_release("first"))
        # the router restarts on its port; safety and the console reconnect by themselves (zenoh's client sessions
        # retry), and the page's requests reach safety again
        stack_with_safety["router"].close()
        time.sleep(1.0)
        stack_with_safety["router"] = Router(port=stack_with_safety["port"]).start()
        assert wait_for(lambda: "console" in healths(router.client_config(), 1.0), timeout=30)
        asyncio.run(engage_and_release("after the restart"))
        assert console.process.poll() is None


def test_a_console_beyond_loopback_without_a_token_does_not_start(tmp_path):
    env = {"MFVS_RUN_DIR": str(tmp_path), "PATH": "/usr/bin:/bin"}
    out = subprocess.run([MFVS, "console", "--listen", "0.0.0.0", "--connect", "tcp/127.0.0.1:1"], capture_output=True,
                         text=True, timeout=60, env=env)
    assert out.returncode == 2 and "needs a token or password" in out.stderr and "Traceback" not in out.stderr
    empty = tmp_path / "token"
    empty.write_text("\n")
    out = subprocess.run([MFVS, "console", "--token-file", str(empty)], capture_output=True, text=True, timeout=60,
                         env=env)
    assert out.returncode == 2 and "is empty" in out.stderr
    out = subprocess.run([MFVS, "console", "--connect", f"tcp/127.0.0.1:{free_loopback_port()}"], capture_output=True,
                         text=True, timeout=60, env=env)
    assert out.returncode == 2 and "cannot reach the stack's router" in out.stderr, out.stderr


def test_behind_a_tls_deployment_it_serves_https_with_its_certificate_and_acts_as_the_operator(tmp_path):
    """`mfvs authority init --tls`'s deployment: the console, given the operator's config, serves HTTPS with the
    deployment's console certificate (a browser that trusts the deployment's CA verifies it), and its e-stop goes
    through the router's access control as the operator's."""
    import ssl

    from services.runtime.authority import write_deployment

    deployment = write_deployment(tmp_path / "authority", tls=True, port=free_loopback_port())
    operator = str(deployment.client_configs["operator"])
    with Router(port=None, config_file=deployment.router_config) as router:
        safety = SafetyService(SafetyConfig(clock=ClockMode.REALTIME, zenoh=router.client_config(
            config_file=str(deployment.client_configs["safety"])))).start()
        try:
            with ConsoleProcess(deployment.endpoint, "--zenoh-config", operator) as console:
                assert console.ready["tls"] and console.url.startswith("https://127.0.0.1:")
                trusted = ssl.create_default_context(cafile=str(tmp_path / "authority" / "certs" / "ca.pem"))

                async def engage():
                    async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(ssl=trusted)) as session:
                        async with session.get(console.url) as page:
                            assert page.status == 200
                        async with session.ws_connect(console.url.replace("https", "wss", 1) + "ws",
                                                      origin=console.url.rstrip("/")) as ws:
                            await ws.send_json({"type": "action", "action": "estop_engage", "id": 1})
                            while True:
                                answer = await ws.receive_json(timeout=15)
                                if answer["type"] in ("result", "refused"):
                                    return answer

                answer = asyncio.run(engage())
                assert answer["type"] == "result" and answer["ok"], answer
                assert safety.core.estop_latched
                # plain HTTP is refused by the TLS listener: no page without the certificate's protection
                async def plain():
                    async with aiohttp.ClientSession() as session:
                        try:
                            async with session.get(console.url.replace("https", "http", 1)) as response:
                                return response.status
                        except aiohttp.ClientError:
                            return "refused"
                assert asyncio.run(plain()) in ("refused", 400)
        finally:
            safety.stop()


def test_one_request_of_a_kind_at_a_time(stack_with_safety):
    """No controller answers: a task start waits for it (up to --timeout); a second start meanwhile is refused,
    not queued, and the e-stop is not held up by either."""
    router, safety = stack_with_safety["router"], stack_with_safety["safety"]
    with ConsoleProcess(router.endpoint, "--timeout", "3") as console:
        async def session():
            async with Page(console.url) as page:
                await page.until(lambda r: r["type"] == "status" and r["estop"]["engaged"] is False, timeout=30)
                await page.send({"type": "action", "action": "task_start", "id": 1, "operator": "al"})
                second = await page.answer({"type": "action", "action": "task_start", "id": 2, "operator": "al"})
                assert second["reason"] == "in_progress", second
                stop = await page.answer({"type": "action", "action": "estop_engage", "id": 3})
                assert stop["type"] == "result" and stop["ok"], stop
                first = await page.until(lambda r: r.get("id") == 1)
                assert first["type"] == "result" and not first["ok"] and "no controller answered" in first["message"]

        asyncio.run(session())
        assert safety.core.estop_latched


class Periodic:
    """A stand-in publisher on ``key``: ``self.publish()`` every ``period_s`` in a thread of its own, on a session
    of its own, while the block runs."""

    def __init__(self, client_config, key, period_s: float) -> None:
        self.period_s = period_s
        self.session = open_session(client_config)
        self.publisher = self.session.declare_publisher(key)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join(timeout=5)
        self.session.close()

    def _run(self):
        while not self.stop.wait(self.period_s):
            self.publish()

    def publish(self) -> None:
        raise NotImplementedError


class RobotStates(Periodic):
    """A robot's states every 20 ms, declaring whatever arm :attr:`declared` says (name, fingerprint, angles)."""

    def __init__(self, client_config, **declared) -> None:
        super().__init__(client_config, KEYS.robot_state, 0.02)
        self.declared = declared

    def publish(self):
        d = dict(self.declared)
        n = len(d["q"])
        state = m.RobotState(header=m.Header(stamp_ns=time.time_ns()), arm=d["arm"], arm_digest=d["digest"],
                             q=list(d["q"]), dq=[0.0] * n, tau=[0.0] * n,
                             pose=m.KinovaPose(X=0.4, Y=0.0, Z=0.5, ThetaX=0.0, ThetaY=0.0, ThetaZ=0.0),
                             control_mode=m.ControlMode.CARTESIAN_VELOCITY)
        self.publisher.put(m.encode(state))


def test_the_page_follows_the_arm_the_robot_declares_and_counts_one_this_host_does_not_describe(stack_with_safety):
    router = stack_with_safety["router"]
    six = load_arm("j2n6s300")
    with ConsoleProcess(router.endpoint) as console, \
            RobotStates(router.client_config(), arm=six.name, digest=six.digest, q=six.home) as robot:
        async def session():
            async with Page(console.url) as page:
                status = await page.until(lambda r: r["type"] == "status" and r["arm"] is not None, timeout=30)
                assert status["arm"]["name"] == "j2n6s300" and status["arm"]["described"], status["arm"]
                assert [j["label"] for j in status["joints"]] == list(six.joint_names)
                assert [j["deg"] for j in status["joints"]] == pytest.approx(list(six.home_deg), abs=0.01)
                assert status["speed"]["limit"] == six.max_linear_speed_mps
                assert "arm.not_described" not in status["console"]["errors"]
                # the robot restarted with a version of that arm's file this host does not have
                robot.declared = dict(arm=six.name, digest="0123456789abcdef", q=six.home)
                # a status between the two declarations may carry no arm yet: skip it
                status = await page.until(lambda r: r["type"] == "status" and r["arm"] and r["arm"]["problem"],
                                          timeout=30)
                assert not status["arm"]["described"] and "differs from this host's" in status["arm"]["problem"]
                assert len(status["joints"]) == 6 and status["joints"][1]["lower_deg"] is None
                assert any("differs from this host's" in e["text"] for e in status["events"])
                # then an arm it does not describe at all
                robot.declared = dict(arm="j2x9s999", digest="0123456789abcdef", q=[0.0] * 5)
                status = await page.until(lambda r: r["type"] == "status" and r["arm"]
                                          and r["arm"]["name"] == "j2x9s999",
                                          timeout=30)
                assert "does not describe" in status["arm"]["problem"] and len(status["joints"]) == 5

        asyncio.run(session())
        found = healths(router.client_config())["console"]
        assert found.errors.get("arm.not_described", 0) > 0 and "arm j2x9s999 not described here" in found.detail
        assert console.process.poll() is None


class Camera(Periodic):
    """A camera on the image key: a 160×120 grey frame at 30 Hz, its sequence number in the header."""

    def __init__(self, client_config) -> None:
        super().__init__(client_config, KEYS.camera_image, 1 / 30)
        self.seq = 0

    def publish(self):
        self.seq += 1
        now = time.time_ns()
        self.publisher.put(m.encode(m.Image(
            header=m.Header(seq=self.seq, stamp_ns=now, source_stamp_ns=now), width=160, height=120,
            encoding=m.ImageEncoding.MONO8, data=bytes([self.seq % 256]) * (160 * 120))))


def test_a_page_is_sent_one_frame_at_a_time_the_newest_once_it_drew_the_last(stack_with_safety):
    """Frames never queue on the way to a page: a page that has not said it drew its frame is sent no other
    (while the camera goes on), another page that draws is not held up by it, and the frame a page gets once it
    drew the last is the newest the camera took, not the one after the last it got."""
    from services.console.core import read_frame_packet

    router = stack_with_safety["router"]
    with ConsoleProcess(router.endpoint) as console, Camera(router.client_config()) as camera:
        async def session():
            async with Page(console.url) as slow, Page(console.url) as drawing:
                first = read_frame_packet(await slow.next_frame(timeout=30))[0]["seq"]
                # the other page draws 20 frames meanwhile; the one that did not draw is sent none
                for _ in range(20):
                    seq = read_frame_packet(await drawing.next_frame())[0]["seq"]
                    await drawing.send({"type": "drawn", "seq": seq})
                with contextlib.suppress(AssertionError):
                    await slow.until(lambda r: False, timeout=0.5)
                assert len(slow.frames) == 1
                assert camera.seq > first + 20
                # it drew: the next frame is the newest there is (the camera's, a frame or two ago at most)
                await slow.send({"type": "drawn", "seq": first})
                second = read_frame_packet(await slow.next_frame())[0]["seq"]
                assert second >= camera.seq - 3 > first + 1, (first, second, camera.seq)

        asyncio.run(session())
        errors = console_errors(router.client_config())
        assert errors.get("refused.malformed", 0) == 0 and errors.get("frames.unacknowledged", 0) == 0, errors


def test_a_page_message_that_says_it_drew_is_validated():
    from services.console.core import DrawnMessage, Refused, parse_page_message

    assert parse_page_message('{"type": "drawn", "seq": 12}') == DrawnMessage(seq=12)
    for bad in ('{"type": "drawn", "seq": -1}', '{"type": "drawn", "seq": "x"}', '{"type": "drawn", "at": 1}'):
        with pytest.raises(Refused) as refused:
            parse_page_message(bad)
        assert refused.value.reason == "malformed"


def test_a_page_that_draws_slower_than_the_camera_is_sent_halved_frames_and_whole_ones_once_it_keeps_up(
        stack_with_safety):
    import cv2
    import numpy as np

    from services.console.core import read_frame_packet

    router = stack_with_safety["router"]
    with ConsoleProcess(router.endpoint) as console, Camera(router.client_config()):
        async def session():
            async with Page(console.url) as page:
                async def draw(count: int, draw_s: float) -> list[tuple[dict, np.ndarray]]:
                    drawn = []
                    while len(drawn) < count:
                        header, jpeg = read_frame_packet(await page.next_frame())
                        await asyncio.sleep(draw_s)  # the page's decoding and drawing
                        drawn.append((header, cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_UNCHANGED)))
                        await page.send({"type": "drawn", "seq": header["seq"]})
                    return drawn

                slow = await draw(20, 0.1)  # three camera periods a frame
                assert slow[0][0]["scale"] == 1 and slow[-1][0]["scale"] == 2
                header, pixels = slow[-1]
                assert (header["width"], header["height"]) == (160, 120) and pixels.shape[:2] == (60, 80)
                fast = await draw(40, 0.0)
                assert fast[-1][0]["scale"] == 1 and fast[-1][1].shape[:2] == (120, 160)

        asyncio.run(session())
        errors = console_errors(router.client_config())
        assert errors.get("frames.halved", 0) >= 1 and errors.get("frames.whole", 0) >= 1, errors
