"""services/robot/lockstep_gate.py on a clock of the test's own, no zenoh: a tick waits for the pipeline's answer only
while an answerer is alive, publishes again every retry_s, gives up at its timeout (counted), and before the first
tick the node waits for an answerer and for the outputs it answers to be matched."""
import logging

import pytest

from protocol import messages as m
from services.robot.admission import AdmissionConfig
from services.robot.command_inbox import CommandInbox
from services.robot.lockstep_gate import LockstepConfig, LockstepGate
from services.runtime.metrics import Counters

TICK = 5_000_000_000
FRAME = TICK


class FakeTime:
    """Monotonic time that moves only when the gate waits: to the end of the wait, or to the first event (a message
    arriving, as zenoh's thread would deliver it) due before then."""

    def __init__(self) -> None:
        self.now = 100.0
        self.events: list[tuple[float, object]] = []
        self.waits: list[float] = []

    def at(self, t_s: float, event) -> None:
        self.events.append((self.now + t_s, event))

    def clock(self) -> float:
        return self.now

    def wait(self, timeout_s: float) -> None:
        self.waits.append(timeout_s)
        due = sorted((e for e in self.events if e[0] <= self.now + timeout_s), key=lambda e: e[0])
        if not due:
            self.now += timeout_s
            return
        self.events.remove(due[0])
        self.now = max(self.now, due[0][0])
        due[0][1]()


class Rig:
    def __init__(self, **config) -> None:
        self.time = FakeTime()
        self.inbox = CommandInbox(AdmissionConfig(max_age_s=1e9, max_future_s=1e9))
        self.counters = Counters()
        self.stopping = False
        self.gate = LockstepGate(LockstepConfig(**config), self.inbox, self.counters, logging.getLogger("test"),
                                 stopping=lambda: self.stopping, clock=self.time.clock, wait=self.time.wait)
        self.published_again: list[float] = []
        self.api_runs = 0
        self.seq = 0

    def answer(self, stamp_ns: int, source_ns: int = 0):
        def arrive() -> None:
            self.seq += 1
            header = m.Header(seq=self.seq, stamp_ns=stamp_ns, source_stamp_ns=source_ns)
            assert self.inbox.offer(m.RobotCommand(header=header, mode=m.CommandMode.STOP), stamp_ns) is None
        return arrive

    def meanwhile(self) -> None:
        self.api_runs += 1

    def again(self) -> None:
        self.published_again.append(self.time.now)

    def wait(self, frame_stamp=None):
        start = self.time.now
        taken = self.gate.wait_for_answer(TICK, frame_stamp, self.meanwhile, self.again)
        return taken, self.time.now - start


def test_only_an_answerer_alive_makes_the_ticks_wait():
    rig = Rig()
    assert not rig.gate.waits
    rig.gate.liveliness("vision", True)  # an observer of the robot changes nothing
    assert not rig.gate.waits
    rig.gate.liveliness("safety", True)
    assert rig.gate.waits
    rig.gate.liveliness("safety", False)
    assert not rig.gate.waits


def test_the_answer_to_the_tick_ends_the_wait_and_is_taken():
    rig = Rig()
    rig.time.at(0.1, rig.answer(TICK - 1))  # the last tick's answer, late: not this one's
    rig.time.at(0.2, rig.answer(TICK))
    taken, waited = rig.wait()
    assert taken[0].header.stamp_ns == TICK and waited == pytest.approx(0.2)
    assert rig.api_runs == 2  # at the start and at the wake-up without the answer: calls do not wait for it
    assert rig.counters.snapshot() == {} and rig.published_again == []


def test_a_late_answer_is_asked_again_every_retry_s_until_the_timeout_which_is_counted():
    rig = Rig(cycle_timeout_s=0.5, retry_s=0.2)
    rig.time.at(0.1, rig.answer(TICK - 1))
    taken, waited = rig.wait()
    assert waited == pytest.approx(0.5) and rig.counters.get("lockstep.timeouts.cycle") == 1
    assert [t - 100.0 for t in rig.published_again] == pytest.approx([0.2, 0.4])
    assert rig.counters.get("lockstep.retries") == 2
    assert taken[0].header.stamp_ns == TICK - 1  # what was there is taken all the same: the run goes on


def test_a_frame_taken_at_the_tick_waits_for_a_command_derived_from_it_and_longer():
    rig = Rig(cycle_timeout_s=0.5, frame_timeout_s=2.0, retry_s=0.25)
    rig.time.at(0.1, rig.answer(TICK, source_ns=FRAME - 1))  # answers the tick, from the frame before
    rig.time.at(1.2, rig.answer(TICK + 1, source_ns=FRAME))
    taken, waited = rig.wait(frame_stamp=FRAME)
    assert taken[0].header.source_stamp_ns == FRAME and waited == pytest.approx(1.2)
    assert rig.counters.get("lockstep.timeouts.cycle") == 0 and rig.counters.get("lockstep.retries") == 4
    rig.time.at(0.1, rig.answer(TICK + 2, source_ns=FRAME - 1))
    taken, waited = rig.wait(frame_stamp=FRAME + 10)  # no answer to this frame comes
    assert waited == pytest.approx(2.0) and rig.counters.get("lockstep.timeouts.frame") == 1


def test_a_stopping_node_waits_no_more():
    rig = Rig()

    def stop() -> None:
        rig.stopping = True

    rig.time.at(0.1, stop)
    taken, waited = rig.wait()
    assert taken is None and waited == pytest.approx(0.1) and rig.counters.snapshot() == {}


def test_the_first_tick_waits_for_an_answerer_and_the_outputs_it_answers():
    rig = Rig(await_answerers_s=3.0)
    matched = []
    rig.time.at(0.5, lambda: rig.gate.liveliness("safety", True))
    rig.time.at(0.8, lambda: matched.append(True))  # the camera's images get their subscriber (polled, no wake-up)
    rig.gate.await_answerers(lambda: bool(matched))
    assert 100.8 <= rig.time.now <= 100.81 and rig.counters.snapshot() == {}
    assert max(rig.time.waits) == pytest.approx(0.1) and rig.time.waits[-1] <= 0.005  # polled faster once alive


def test_no_answerer_by_the_deadline_is_counted_and_the_arm_runs_on():
    rig = Rig(await_answerers_s=1.0)
    rig.gate.await_answerers(lambda: True)
    assert rig.time.now == pytest.approx(101.0) and rig.counters.get("lockstep.timeouts.answerers") == 1
    rig = Rig()  # await_answerers_s 0: no wait at all
    rig.gate.await_answerers(lambda: False)
    assert rig.time.now == 100.0 and rig.time.waits == []
