"""The e-stop sent from a small process of its own at realtime priority, for a service that is not realtime itself
(the console, the ROS 2 bridge): from the moment an e-stop is stamped to the router, nothing at normal priority.

Why a process: in the console's, the e-stop was stamped and handed to zenoh's threads there, which run at the
process's normal priority beside its image decoding, a browser, vision and the controller; on a slowed host they
waited for a CPU behind all of them, and safety's emergency stop went out 115 ms after the console sent the e-stop
(2-10 ms otherwise; the robot's budget for the whole delivery is 20 ms). zenoh's threads take the priority of the
thread that opens the session, and one process has one zenoh runtime and one interpreter lock, so a realtime thread
in the console would wait for both behind its normal threads. Making the whole console realtime would put its
image decoding above vision's.

The parent (:class:`EStopSender`) writes each request as a JSON line to the child's stdin and reads its answers
from the child's stdout; the child (``python -m services.safety.estop_sender``) carries each one out with an
:class:`~services.safety.estop_client.EStopClient` in a thread of its own (an engage never waits behind a release
waiting for its confirmation), stamping the e-stop as it sends it. The child ends when its stdin closes (the parent
stopped or died). Until the child is up, or when it is gone or does not answer, the parent sends the e-stop itself
(at normal priority: late rather than never) and counts it. The child says when an engage is on the wire, before
safety confirms it: one it has not put within ``ON_THE_WIRE_BUDGET_S`` the parent sends too (safety takes the
first of two engages; the second changes nothing), so a hung child costs an e-stop that much, not its whole
timeout. A child silent past a request's timeout is ended."""
from __future__ import annotations

import argparse
import itertools
import logging
import signal
import subprocess
import sys
import threading
import time
from typing import Callable, Optional

import msgspec

from protocol import messages as m
from protocol.conventions import ClockMode
from protocol.keys import Keys
from services.paths import REPO
from services.runtime.threads import start_thread
from services.runtime.transport import ZenohConfig, open_session
from services.safety.estop_client import EStopClient

log = logging.getLogger(__name__)

#: SCHED_FIFO priority of the sender: that of safety and the router, which carry the e-stop on (safety.yaml,
#: ``mfvs router``), below the robot's loop (40), above every normal-priority process
ESTOP_REALTIME_PRIORITY = 30
#: what the parent waits beyond a request's own timeout for the child's answer before it takes the child for hung
ANSWER_MARGIN_S = 1.0
#: how long an engage may take to be on the wire from the child before the parent sends it too: far above the
#: child's few milliseconds at realtime priority (2-10 ms measured, 15 ms at 0.65 of a core), far below the 250 ms
#: in which an operator's e-stop must be confirmed (issue 49)
ON_THE_WIRE_BUDGET_S = 0.05
#: the child's word that it is ready, its first line
READY = "ready"


class Request(msgspec.Struct, forbid_unknown_fields=True):
    id: int
    reset: bool
    operator: str
    reason: str
    timeout_s: float


class Answer(msgspec.Struct, forbid_unknown_fields=True):
    id: int
    #: safety's status that confirmed it (encoded as on the wire), or None when none did in time
    status: Optional[bytes]
    #: an early word: the request is on the wire, its confirmation still to come (``status`` None)
    on_the_wire: bool = False


class SenderGone(Exception):
    """The child is not running or did not answer."""


class SenderLate(SenderGone):
    """The child has not put an engage on the wire within ON_THE_WIRE_BUDGET_S."""


class EStopSender:
    """``send`` as :class:`EStopClient`'s, carried out by the realtime child. ``session``/``keys``: the parent's
    own, for the fallback; ``zenoh``: the config the child opens its session with (the same identity);
    ``realtime_priority``: the child's (0: normal scheduling, as in lockstep). ``count``: a counter to increment
    by name (``estop.sent_by_child``, ``estop.fallback``, ``estop.child_late``, ``estop.child_exits``)."""

    def __init__(self, session, keys: Keys, zenoh: ZenohConfig, realtime_priority: int = ESTOP_REALTIME_PRIORITY,
                 count: Callable[[str], None] = lambda name: None) -> None:
        self._fallback = EStopClient(session, keys)
        self._count = count
        self._ids = itertools.count(1)
        self._write_lock = threading.Lock()
        #: answers by request id, the requests the child said are on the wire, and who waits for them
        self._answers: dict[int, Answer] = {}
        self._on_the_wire: set[int] = set()
        #: requests the parent carried out itself (the child was late): their answers are dropped
        self._abandoned: set[int] = set()
        self._answered = threading.Condition()
        self._ready = threading.Event()
        self._closed = False
        command = [sys.executable, "-m", "services.safety.estop_sender", "--robot-id", keys.robot_id,
                   "--zenoh", msgspec.json.encode(zenoh).decode(), "--realtime-priority", str(realtime_priority)]
        self._child = subprocess.Popen(command, cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                       stderr=None, bufsize=0)
        self._reader = start_thread(self._read_answers, "estop-answers")

    @classmethod
    def for_service(cls, service) -> "EStopSender":
        """The sender of a running service's e-stops: its session, keys and zenoh config, its counters; at normal
        priority in lockstep (as the services themselves, services.runtime.service.service_main)."""
        lockstep = ClockMode(service.config.clock) is ClockMode.LOCKSTEP
        return cls(service.session, service.keys, service.config.zenoh,
                   realtime_priority=0 if lockstep else ESTOP_REALTIME_PRIORITY, count=service.counters.inc)

    def health(self) -> tuple[bool, str]:
        """Whether e-stops go out at the sender's priority, in words (for the service's health)."""
        if self.ready:
            return True, "e-stop sender ready"
        if self._child.poll() is None:
            return True, "e-stop sender starting"
        return False, f"e-stop sender exited ({self._child.returncode}): e-stops go out at this service's priority"

    @property
    def ready(self) -> bool:
        """Whether the child is up and answering (else e-stops go out from this process)."""
        return self._ready.is_set() and self._child.poll() is None

    def wait_ready(self, timeout_s: float) -> bool:
        return self._ready.wait(timeout_s) and self._child.poll() is None

    def _read_answers(self) -> None:
        assert self._child.stdout is not None
        started = time.monotonic()
        for line in self._child.stdout:
            if line.strip() == READY.encode():
                log.info("e-stop sender ready after %.2f s", time.monotonic() - started)
                self._ready.set()
                continue
            try:
                answer = msgspec.json.decode(line, type=Answer)
            except msgspec.DecodeError:  # malformed JSON or the wrong fields
                log.warning("e-stop sender: not an answer: %r", line[:200])
                continue
            with self._answered:
                if answer.on_the_wire:
                    if answer.id not in self._abandoned:
                        self._on_the_wire.add(answer.id)
                elif answer.id in self._abandoned:
                    self._abandoned.discard(answer.id)
                else:
                    self._answers[answer.id] = answer
                self._answered.notify_all()
        self._ready.clear()
        if not self._closed:
            self._count("estop.child_exits")
            log.error("the e-stop sender exited (code %s): e-stops now go out from this process, at its priority",
                      self._child.wait())
        with self._answered:
            self._answered.notify_all()

    def _ask(self, request: Request) -> Answer:
        if not self.ready:
            raise SenderGone("not running")
        assert self._child.stdin is not None
        try:
            with self._write_lock:
                self._child.stdin.write(msgspec.json.encode(request) + b"\n")
        except (BrokenPipeError, OSError, ValueError) as exc:
            raise SenderGone(f"cannot write to it ({exc})") from None
        asked = time.monotonic()
        deadline = asked + request.timeout_s + ANSWER_MARGIN_S
        on_the_wire_by = None if request.reset else asked + ON_THE_WIRE_BUDGET_S  # (a release is not urgent)
        with self._answered:
            while request.id not in self._answers:
                now = time.monotonic()
                if not self._ready.is_set():
                    raise SenderGone("exited")
                if now >= deadline:
                    # alive but silent past the request's own timeout: hung. Ended, so that the next e-stop goes
                    # out from this process at once
                    self._child.kill()
                    raise SenderGone("no answer: ended it")
                if on_the_wire_by is not None and request.id not in self._on_the_wire:
                    if now >= on_the_wire_by:
                        self._abandon(request.id, deadline)
                        raise SenderLate(f"engage not on the wire after {ON_THE_WIRE_BUDGET_S * 1e3:.0f} ms")
                    self._answered.wait(on_the_wire_by - now)
                    continue
                self._answered.wait(deadline - now)
            self._on_the_wire.discard(request.id)
            return self._answers.pop(request.id)

    def _abandon(self, request_id: int, deadline: float) -> None:
        """The parent carries the request out itself; the child's answers to it are dropped, and a child that has
        not answered it at all by ``deadline`` is hung and ended (called with the answers' lock held)."""
        self._abandoned.add(request_id)
        self._on_the_wire.discard(request_id)

        def end_if_silent() -> None:
            with self._answered:
                silent = request_id in self._abandoned and not self._closed
            if silent and self._child.poll() is None:
                log.error("the e-stop sender did not answer request %d: ended", request_id)
                self._child.kill()

        timer = threading.Timer(max(0.0, deadline - time.monotonic()), end_if_silent)
        timer.daemon = True
        timer.start()

    def send(self, reset: bool, operator: str, reason: str = "", timeout_s: float = 5.0) -> Optional[m.SafetyStatus]:
        """Engage (``reset`` False) or release the e-stop; safety's status that confirmed it, or None."""
        request = Request(id=next(self._ids), reset=reset, operator=operator, reason=reason, timeout_s=timeout_s)
        try:
            answer = self._ask(request)
        except SenderGone as exc:
            self._count("estop.fallback")
            if isinstance(exc, SenderLate):
                self._count("estop.child_late")
            log.warning("e-stop sender %s: sending the e-stop from this process", exc)
            return self._fallback.send(reset, operator, reason, timeout_s)
        self._count("estop.sent_by_child")
        return None if answer.status is None else m.decode(answer.status, m.SafetyStatus)

    def close(self) -> None:
        self._closed = True
        if self._child.stdin is not None:
            try:
                self._child.stdin.close()  # the child's end of input: it closes its session and exits
            except OSError:
                pass
        try:
            self._child.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            self._child.kill()
            self._child.wait()
        self._reader.join(timeout=5.0)
        self._fallback.close()

    def __enter__(self) -> "EStopSender":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---------------------------------------------------------------------------------------------- the child
def _serve(client: EStopClient, requests, answers) -> None:
    """Each request line from ``requests`` carried out in a thread of its own; each answer a line to ``answers``."""
    write = threading.Lock()

    def answer(reply: Answer) -> None:
        with write:
            answers.write(msgspec.json.encode(reply) + b"\n")
            answers.flush()

    def carry_out(request: Request) -> None:
        status = client.send(request.reset, request.operator, request.reason, request.timeout_s,
                             on_sent=lambda: answer(Answer(id=request.id, status=None, on_the_wire=True)))
        answer(Answer(id=request.id, status=None if status is None else m.encode(status)))

    for line in requests:
        try:
            request = msgspec.json.decode(line, type=Request)
        except msgspec.DecodeError as exc:  # malformed JSON or the wrong fields
            log.warning("e-stop sender: not a request (%s): %r", exc, line[:200])
            continue
        start_thread(lambda request=request: carry_out(request), f"estop-{request.id}")


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m services.safety.estop_sender", description=__doc__.split("\n")[0])
    parser.add_argument("--robot-id", required=True)
    parser.add_argument("--zenoh", required=True, help="the session's config, as JSON")
    parser.add_argument("--realtime-priority", type=int, default=ESTOP_REALTIME_PRIORITY)
    args = parser.parse_args(argv)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a terminal's Ctrl-C is the parent's; it ends us by closing stdin
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="estop_sender: %(message)s")
    from services.runtime.pacing import request_realtime

    # before the session: zenoh's threads inherit the priority of the thread that starts them
    request_realtime(args.realtime_priority, "e-stop sender")
    session = open_session(msgspec.json.decode(args.zenoh, type=ZenohConfig))
    try:
        with EStopClient(session, Keys(args.robot_id)) as client:
            time.sleep(0.2)  # let the declarations reach the router, as `mfvs estop` does
            sys.stdout.buffer.write(READY.encode() + b"\n")
            sys.stdout.buffer.flush()
            _serve(client, sys.stdin.buffer, sys.stdout.buffer)
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
