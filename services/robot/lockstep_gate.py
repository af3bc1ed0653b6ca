"""In lockstep, the robot's ticks wait for the pipeline's answers: no zenoh here, and time and waits are given (a test
drives them with a clock of its own).

At each DSP tick the node publishes the state of that tick and :meth:`LockstepGate.wait_for_answer` waits
(``cycle_timeout_s``) for the pipeline's answer, a command stamped at or after the tick, and when a camera frame was
taken at the tick (``frame_timeout_s``) a command derived from that frame. It waits only while a service that
answers is alive (``answered_by``, safety, which answers each robot state in lockstep): observers of the robot
change nothing. The state (and the frame) are published again every ``retry_s`` while it waits, since a message
can be lost while routes are still being set up; on a starved host the answer may only be late, so vision and the
controller answer a frame they get again with the answer they gave it (one frame, one answer: a second, different
one, such as "out-of-order", would stand in for the first, reset the law and make the run differ from its replay).

Before its first cycle the node may wait for an answerer to be alive and the outputs it answers to be subscribed
(:meth:`LockstepGate.await_answerers`).
"""
from __future__ import annotations

import logging
import time
from typing import Callable, Optional

import msgspec

from services.robot.command_inbox import CommandInbox, Received
from services.runtime.config import ConfigStruct
from services.runtime.metrics import Counters


class LockstepConfig(ConfigStruct):
    #: wall time to wait for the answer to a tick before running the DSP cycle without it (a run that does is not
    #: repeatable). 0.5 s ran out once in part-c with the whole suite at 0.65 of a core: the wait is only for a hung
    #: answerer (a lost message is sent again every retry_s), so it is as long as a frame's
    cycle_timeout_s: float = 2.0
    #: wall time to wait for the pipeline's answer to a frame
    frame_timeout_s: float = 2.0
    #: publish the state (and the frame) again after this long without an answer
    retry_s: float = 0.25
    #: an arm behind a bus (robot_sim's actuator_bus mode) runs a cycle without its host's commands after this
    #: long; longer than the robot node's own waits, so that a host that is waiting is never overtaken
    bus_timeout_s: float = 5.0
    #: the robot node's exchanges with an arm behind a bus wait this long for the replies
    link_timeout_s: float = 5.0
    #: the robot node waits for the pipeline's answers while one of these services is alive (liveliness)
    answered_by: list[str] = msgspec.field(default_factory=lambda: ["safety"])
    #: before its first cycle, wait this long at most for one of ``answered_by`` to be alive and the outputs they
    #: answer to be subscribed (0: do not wait); a stack that started them before the robot sets it. Not there by
    #: then: counted (lockstep.timeouts.answerers), the run is not repeatable
    await_answerers_s: float = 0.0

    def __post_init__(self) -> None:
        if not (self.retry_s > 0 and self.cycle_timeout_s > 0 and self.frame_timeout_s > 0):
            raise ValueError("lockstep needs positive retry_s, cycle_timeout_s and frame_timeout_s")
        if self.bus_timeout_s <= max(self.frame_timeout_s, self.cycle_timeout_s):
            raise ValueError("lockstep.bus_timeout_s must exceed the node's own waits (frame_timeout_s, "
                             "cycle_timeout_s): the host may wait that long")


class LockstepGate:
    def __init__(self, config: LockstepConfig, inbox: CommandInbox, counters: Counters, log: logging.Logger,
                 stopping: Callable[[], bool], clock: Callable[[], float] = time.monotonic,
                 wait: Optional[Callable[[float], object]] = None) -> None:
        """``inbox``: where the answers arrive (its condition wakes the waits); ``stopping``: whether the node is
        stopping (the waits end); ``clock``: monotonic seconds; ``wait(timeout_s)``: wait on the inbox's condition,
        held (by default the condition's own wait)."""
        self.config = config
        self.inbox = inbox
        self.counters = counters
        self.log = log
        self._stopping = stopping
        self._clock = clock
        self._wait = wait or inbox.changed.wait
        #: the services of ``answered_by`` alive now (guarded by the inbox's condition)
        self._answerers: set[str] = set()

    def liveliness(self, service: str, alive: bool) -> None:
        """A service came (its liveliness token) or went: the ticks wait while one that answers is alive."""
        if service not in self.config.answered_by:
            return
        with self.inbox.changed:
            if alive:
                self._answerers.add(service)
            else:
                self._answerers.discard(service)
            self.inbox.changed.notify_all()

    @property
    def waits(self) -> bool:
        """Whether a tick waits for its answer: a service that answers is alive."""
        return bool(self._answerers)

    def await_answerers(self, outputs_matched: Callable[[], bool]) -> None:
        """Before the first cycle, until an answerer is alive and the outputs it answers have their subscribers
        (``outputs_matched``; at most ``await_answerers_s``). Both reach a session that just opened on zenoh's thread,
        some time after it opens (a liveliness query then finds nobody either, measured): a loop that did not wait
        ran its first ticks unanswered, or took no frame for nobody matched the camera's images, and a run differed
        from the next on a busy host."""
        patience = self.config.await_answerers_s
        if patience <= 0:
            return
        deadline = self._clock() + patience
        with self.inbox.changed:
            while not (self._answerers and outputs_matched()) and not self._stopping():
                left = deadline - self._clock()
                if left <= 0:
                    self.counters.inc("lockstep.timeouts.answerers")
                    self.log.warning("lockstep: %s after %.1f s: the arm runs on", "its outputs unmatched"
                                     if self._answerers else f"none of {', '.join(self.config.answered_by)} alive",
                                     patience)
                    return
                # the liveliness callback wakes this; a subscriber matched does not (polled), nor a stop
                self._wait(min(left, 0.1 if not self._answerers else 0.005))

    def wait_for_answer(self, tick_ns: int, frame_stamp: Optional[int], meanwhile: Callable[[], None],
                        again: Callable[[], None]) -> Optional[Received]:
        """Wait for the answer to the tick at ``tick_ns`` (to the frame taken at it, ``frame_stamp``, if any), then
        take the command waiting, the answer or not (a timeout is counted). ``meanwhile`` runs at every wake-up
        (the Kinova API calls waiting), ``again`` every ``retry_s`` (the state, and the frame, published again), both
        without the inbox's lock."""
        cfg = self.config
        start = self._clock()
        deadline = start + (cfg.frame_timeout_s if frame_stamp else cfg.cycle_timeout_s)
        next_retry = start + cfg.retry_s
        changed = self.inbox.changed
        with changed:
            while not self.inbox.answers(tick_ns, frame_stamp) and not self._stopping():
                changed.release()
                try:
                    meanwhile()
                finally:
                    changed.acquire()
                now = self._clock()
                if now >= deadline:
                    self.counters.inc("lockstep.timeouts.frame" if frame_stamp else "lockstep.timeouts.cycle")
                    break
                if now >= next_retry:
                    self.counters.inc("lockstep.retries")
                    changed.release()
                    try:
                        again()
                    finally:
                        changed.acquire()
                    next_retry = now + cfg.retry_s
                self._wait(min(deadline, next_retry) - now)
        return self.inbox.take()
