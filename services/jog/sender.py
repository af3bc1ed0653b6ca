"""The stick's stream: read it at a fixed rate, map it (services/jog/mapping.py), stamp and sequence it, send it.

Each request carries a rising sequence number and two stamps (protocol.messages.Jog): when it was made, and when
the device was last heard (``source_stamp_ns``): safety stops the arm when either grows old (docs/contracts.md). The
stream keeps its rate on an absolute schedule (services/runtime/pacing.py's remote-arm policy): a slot the host was
late for is skipped and counted, never sent in a burst; the script's time is the schedule's, so a late host never
stretches a step's motion.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable, Optional

from protocol.messages import Header, Jog
from services.jog.mapping import JogMapping, JogMotion, StickInput, StickMapper
from services.jog.script import DeviceCondition, JogScript, step_at
from services.runtime.pacing import CyclePacer


@dataclass
class Reading:
    """The stick at one slot: what it says, whether the device was heard (False: it is not, but the stream goes
    on), whether anything is sent (False: a silent stream), whether the resume button was pressed since the last."""

    stick: StickInput
    heard: bool = True
    send: bool = True
    resume: bool = False


@dataclass
class SendReport:
    sent: int = 0
    #: slots the host was late for (skipped, not sent late)
    missed: int = 0
    #: resume presses (each the controller's resume_task, asked beside the stream)
    resumes: int = 0
    last: Optional[Jog] = None


class JogStamper:
    """Stamps and sequences a stick's requests from one source (``jog/<device>``)."""

    def __init__(self, source: str, now_ns: Callable[[], int] = time.time_ns) -> None:
        self.source = source
        self.now_ns = now_ns
        self.seq = 0
        self.heard_ns = 0

    def message(self, motion: JogMotion, heard: bool, *, now_ns: Optional[int] = None,
                heard_ns: Optional[int] = None) -> Jog:
        """The next request. ``now_ns``: its stamp (default: the clock's now); ``heard_ns``, with ``heard``: when
        the device was heard, if not now (a relay's device stamps its own messages; such a stamp never takes the
        last one back)."""
        now = self.now_ns() if now_ns is None else now_ns
        if heard:
            self.heard_ns = now if heard_ns is None else max(self.heard_ns, heard_ns)
        self.seq += 1
        return Jog(header=Header(seq=self.seq, stamp_ns=now, source_stamp_ns=self.heard_ns), mode=motion.mode,
                   deadman=motion.deadman, speed_level=motion.speed_level, source=self.source, linear=motion.linear,
                   angular=motion.angular, finger_rate=motion.finger_rate)


def stream(read: Callable[[float], Optional[Reading]], mapping: JogMapping, stamper: JogStamper,
           publish: Callable[[Jog], None], rate_hz: float, resume: Optional[Callable[[], None]] = None,
           stop: Optional[threading.Event] = None, clock=time.monotonic, sleep=time.sleep) -> SendReport:
    """Send the stick's requests at ``rate_hz`` until ``read`` says the stream is over (None) or ``stop`` is set.
    ``read(t_s)``: the stick at ``t_s`` after the start, by the schedule. ``resume()``: the resume button's action,
    which must not block (services/jog/client.py asks the controller on a thread of its own)."""
    mapper = StickMapper(mapping)
    pacer = CyclePacer(1.0 / rate_hz, catch_up_cycles=0, clock=clock, sleep=sleep)
    report = SendReport()
    while stop is None or not stop.is_set():
        slot = pacer.wait()
        report.missed += slot.missed
        t_s = slot.index * pacer.period_s
        reading = read(t_s)
        if reading is None:
            break
        if reading.resume and resume is not None:
            report.resumes += 1
            resume()
        if not reading.send:
            continue
        message = stamper.message(mapper(reading.stick, t_s), reading.heard)
        publish(message)
        report.sent += 1
        report.last = message
    return report


def script_reader(script: JogScript) -> Callable[[float], Optional[Reading]]:
    """The script as a stick read at each slot: its step at that time; the resume button pressed once, at the first
    slot of a step that asks for it."""
    pressed: set[int] = set()

    def read(t_s: float) -> Optional[Reading]:
        found = step_at(script, t_s)
        if found is None:
            return None
        index, step = found
        resume = step.resume and index not in pressed
        pressed.add(index)
        stick = StickInput(axes=tuple(step.axes), mode=step.mode, speed_level=step.speed_level, deadman=step.deadman)
        return Reading(stick, heard=step.device is DeviceCondition.OK, send=step.device is not DeviceCondition.SILENT,
                       resume=resume)

    return read
