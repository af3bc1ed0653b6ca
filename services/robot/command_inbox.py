"""What comes in for the arm, between zenoh's threads and the thread that runs the DSP: no zenoh here.

Robot commands are admitted (services.robot.admission: fresh, not from the future, in sequence per sender) and the
latest one is held for the DSP's next tick (a newer one replaces one not taken yet: a command is the motion from
now on); torque commands are admitted by the same rules for low-level control. A sender's new session (its
liveliness token again) restarts its numbering for both.

One condition, :attr:`CommandInbox.changed`, guards all of it and wakes the DSP wherever it waits for a command: a
command came, a Kinova API call is queued (the DSP runs it while it waits), an answerer came or went
(services.robot.lockstep_gate), the node stops.
"""
from __future__ import annotations

import threading
import time
from typing import Callable, Optional

from protocol.messages import CommandMode, Header, RobotCommand
from services.robot.admission import AdmissionConfig, CommandAdmission, Rejection

#: a robot command as it waits for the DSP: the command and when it arrived (the node's clock, ns)
Received = tuple[RobotCommand, int]


def fresh(command: RobotCommand, last_source_ns: int) -> bool:
    """A command the DSP does not wait past: a stop or an emergency stop, or one derived from a newer frame than the
    last one taken (``last_source_ns``) or from no frame at all (an operator's or an API's)."""
    if command.mode in (CommandMode.STOP, CommandMode.EMERGENCY_STOP):
        return True
    source = command.header.source_stamp_ns
    return not source or source > last_source_ns


class CommandInbox:
    def __init__(self, config: AdmissionConfig) -> None:
        self.changed = threading.Condition()
        #: which robot commands are taken at all; its age rule applies again at the tick that applies one
        self.admission = CommandAdmission(config)
        self._torque_admission = CommandAdmission(config)
        self._waiting: Optional[Received] = None
        #: the source stamp of the newest frame a command taken was derived from
        self._last_source_ns = 0

    def offer(self, command: RobotCommand, recv_ns: int) -> Optional[Rejection]:
        """A robot command, held for the DSP if admitted; else why not."""
        with self.changed:
            rejection = self.admission.admit(command.header, recv_ns)
            if rejection is None:
                self._waiting = (command, recv_ns)
                self.changed.notify_all()
        return rejection

    def admit_torque(self, header: Header, recv_ns: int) -> Optional[Rejection]:
        """Whether a torque command may go on to low-level control (it bypasses safety: the same rules)."""
        with self.changed:
            return self._torque_admission.admit(header, recv_ns)

    def new_session(self, sender: str) -> None:
        """A sender started a new session: its numbering may start again."""
        with self.changed:
            self.admission.new_session(sender)
            self._torque_admission.new_session(sender)

    def wake(self) -> None:
        """Wake the DSP wherever it waits (something it acts on while waiting came, or the node stops)."""
        with self.changed:
            self.changed.notify_all()

    def answers(self, tick_ns: int, frame_stamp: Optional[int]) -> bool:
        """Whether the command waiting answers the tick at ``tick_ns`` (stamped at or after it) and, when a frame was
        taken at the tick, that frame (derived from it or a later one). Called holding :attr:`changed`."""
        if self._waiting is None:
            return False
        header = self._waiting[0].header
        if header.stamp_ns < tick_ns:
            return False
        return not frame_stamp or header.source_stamp_ns >= frame_stamp

    def take(self, wait_until: Optional[float] = None,
             done: Callable[[], bool] = lambda: False) -> Optional[Received]:
        """The command waiting, if any; with ``wait_until`` (monotonic) first wait until then for a :func:`fresh`
        one, should the one waiting (or none) not be, unless ``done()``."""
        with self.changed:
            while wait_until is not None and not (self._waiting is not None
                                                  and fresh(self._waiting[0], self._last_source_ns)):
                remaining = wait_until - time.monotonic()
                if remaining <= 0.0 or done():
                    break
                self.changed.wait(remaining)
            taken, self._waiting = self._waiting, None
            if taken is not None:
                self._last_source_ns = max(self._last_source_ns, taken[0].header.source_stamp_ns)
        return taken
