"""How the robot's timing loops keep time on a busy host: an absolute 500 Hz schedule that says, every cycle,
whether it was late and how many cycles it missed, and realtime scheduling where the OS grants it.

Two policies, because there are two kinds of time:

* the arm simulated in this process (robot_sim) has no time but the loop's: cycles the loop was late for run back
  to back (up to ``catch_up_cycles``), so the simulation keeps up with the wall clock; a stall longer than that is
  dropped, and the simulated arm's stamps jump ahead by what was dropped;
* a remote arm (actuators on a bus, the emulated ones in their own process) keeps its own time: a cycle the host
  was late for is gone. A slot the loop reaches more than ``skip_after`` of a cycle late (half: its frame would
  land in the arm's next cycle) is skipped, counted as missed, and the loop waits for the next: the arm loses
  that cycle's motion, and never receives a burst of targets.
"""
from __future__ import annotations

import logging
import os
import sys
import time
from dataclasses import dataclass

log = logging.getLogger("mfvs.pacing")

#: the GIL's switch interval in processes with a timing loop: another thread's Python code can hold the loop up
#: at most this long (the default 5 ms is more than two bus cycles)
SWITCH_INTERVAL_S = 0.0001


@dataclass
class Slot:
    index: int
    #: started more than ``late_fraction`` of a cycle after its slot
    late: bool
    #: cycles skipped before this one (the arm ran them without this loop)
    missed: int
    #: how far behind its slot the cycle started (s)
    lag_s: float


class CyclePacer:
    def __init__(self, period_s: float, catch_up_cycles: int, late_fraction: float = 0.5,
                 skip_after: float = 0.5, clock=time.monotonic, sleep=time.sleep) -> None:
        self.period_s = period_s
        self.catch_up_cycles = catch_up_cycles
        self.late_fraction = late_fraction
        self.skip_after = skip_after
        self._clock, self._sleep = clock, sleep
        self.start = clock()
        self._last = -1

    def _slot_time(self, index: int) -> float:
        return self.start + index * self.period_s

    def wait(self) -> Slot:
        now = self._clock()
        index = self._last + 1
        missed = 0
        if self.catch_up_cycles > 0:
            behind = int((now - self._slot_time(index)) / self.period_s)
            if behind > self.catch_up_cycles:  # too far behind to catch up: drop the stall
                missed = behind
                index += behind
        else:
            behind = (now - self._slot_time(index)) / self.period_s  # in cycles
            if behind > self.skip_after:
                missed = int(behind - self.skip_after) + 1
                index += missed
        delay = self._slot_time(index) - now
        if delay > 0:
            self._sleep(delay)
            now = self._clock()
        self._last = index
        lag = max(0.0, now - self._slot_time(index))
        return Slot(index=index, late=lag > self.late_fraction * self.period_s, missed=missed, lag_s=lag)


def request_realtime(priority: int, what: str) -> bool:
    """SCHED_FIFO at ``priority`` for the calling thread (0: leave the scheduling as it is), and a short GIL switch
    interval for its process. False, with a warning, when the OS refuses (no CAP_SYS_NICE): the loop then runs
    at normal priority and counts its lateness."""
    if priority <= 0:
        return False
    sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL_S))
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as exc:
        log.warning("%s: realtime priority %d refused (%s); running at normal priority", what, priority, exc)
        return False
    return True


def normal_priority() -> None:
    """The calling thread back to normal scheduling (a thread of a realtime process inherits its priority)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass
