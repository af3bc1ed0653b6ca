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
(at normal priority: late rather than never) and counts it."""
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


class SenderGone(Exception):
    """The child is not running or did not answer."""


class EStopSender:
    """``send`` as :class:`EStopClient`'s, carried out by the realtime child. ``session``/``keys``: the parent's
    own, for the fallback; ``zenoh``: the config the child opens its session with (the same identity);
    ``realtime_priority``: the child's (0: normal scheduling, as in lockstep). ``count``: a counter to increment
    by name (``estop.sent_by_child``, ``estop.fallback``, ``estop.child_exits``)."""

    def __init__(self, session, keys: Keys, zenoh: ZenohConfig, realtime_priority: int = ESTOP_REALTIME_PRIORITY,
                 count: Callable[[str], None] = lambda name: None) -> None:
        self._fallback = EStopClient(session, keys)
        self._count = count
        self._ids = itertools.count(1)
        self._write_lock = threading.Lock()
        #: answers by request id, and who waits for them
        self._answers: dict[int, Answer] = {}
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
        deadline = time.monotonic() + request.timeout_s + ANSWER_MARGIN_S
        with self._answered:
            while request.id not in self._answers:
                left = deadline - time.monotonic()
                if not self._ready.is_set():
                    raise SenderGone("exited")
                if left <= 0:
                    # alive but silent past the request's own timeout: hung. Ended, so that the next e-stop goes
                    # out from this process at once instead of waiting as long again
                    self._child.kill()
                    raise SenderGone("no answer: ended it")
                self._answered.wait(left)
            return self._answers.pop(request.id)

    def send(self, reset: bool, operator: str, reason: str = "", timeout_s: float = 5.0) -> Optional[m.SafetyStatus]:
        """Engage (``reset`` False) or release the e-stop; safety's status that confirmed it, or None."""
        request = Request(id=next(self._ids), reset=reset, operator=operator, reason=reason, timeout_s=timeout_s)
        try:
            answer = self._ask(request)
        except SenderGone as exc:
            self._count("estop.fallback")
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

    def carry_out(request: Request) -> None:
        status = client.send(request.reset, request.operator, request.reason, request.timeout_s)
        answer = Answer(id=request.id, status=None if status is None else m.encode(status))
        with write:
            answers.write(msgspec.json.encode(answer) + b"\n")
            answers.flush()

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
