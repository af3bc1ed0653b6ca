"""The stick's stream on the wire: its requests on ``Keys.desired_jog`` (a control-path key: sent at once, above
the images), its resume button as the controller's ``resume_task``, asked beside the stream so that a slow answer
never holds a request back."""
from __future__ import annotations

import threading
from typing import Callable, Optional

from protocol import messages as m
from protocol.keys import Keys
from services.controller.task_client import TaskUnavailable, call_task
from services.jog.config import JogConfig
from services.jog.sender import JogStamper, Reading, SendReport, stream
from services.runtime.transport import GuardedPublisher, publisher_options


class ResumeButton:
    """Each press asks the controller to resume its paused task, on a thread of its own; the answers are kept."""

    def __init__(self, session, keys: Keys, operator: str) -> None:
        self.session, self.keys, self.operator = session, keys, operator
        self.replies: list[str] = []
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()

    def press(self) -> None:
        thread = threading.Thread(target=self._ask, name="jog-resume", daemon=True)
        self._threads.append(thread)
        thread.start()

    def _ask(self) -> None:
        try:
            status = call_task(self.session, self.keys, m.RESUME_TASK,
                               m.TaskRequest(operator=self.operator, reason="the stick's resume button"), 2.0)
            reply = status.message if status.ok else f"refused: {status.message}"
        except TaskUnavailable as exc:
            reply = f"refused: {exc}"
        with self._lock:
            self.replies.append(reply)

    def wait(self, timeout_s: float = 3.0) -> list[str]:
        for thread in self._threads:
            thread.join(timeout_s)
        with self._lock:
            return list(self.replies)


def run_stick(session, keys: Keys, config: JogConfig, read: Callable[[float], Optional[Reading]], rate_hz: float,
              source: Optional[str] = None, stop: Optional[threading.Event] = None) -> tuple[SendReport, list[str]]:
    """Stream a stick (a script's or a device's ``read``) to safety until it ends; (what was sent, what each resume
    press was answered)."""
    publisher = GuardedPublisher.declare(session, keys.desired_jog, **publisher_options(keys.desired_jog))
    button = ResumeButton(session, keys, (source or config.source).replace("/", "-"))
    stamper = JogStamper(source or config.source)
    try:
        report = stream(read, config.mapping, stamper, lambda jog: publisher.put(m.encode(jog)), rate_hz,
                        resume=button.press, stop=stop)
        if report.last is not None and report.last.deadman:  # the stream ended holding: say released, once
            from services.jog.mapping import JogMotion

            released = stamper.message(JogMotion(report.last.mode, report.last.speed_level, False), heard=True)
            publisher.put(m.encode(released))
            report.sent, report.last = report.sent + 1, released
    finally:
        publisher.undeclare()
    return report, button.wait()
