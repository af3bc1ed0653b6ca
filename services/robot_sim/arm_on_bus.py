"""The simulated arm behind its RS-485 bus, in one thread: the bus device (services.robot_sim.bus_device) fed with
frames, and the arm's cycle boundaries placed in time. No zenoh: robot_sim's ``actuator_bus`` mode adds the camera
and the clock through the ``on_*`` callbacks; tests and benchmarks run it bare.

* realtime: boundaries every 2 ms of wall time (catching up after a stall of at most ``MAX_CATCH_UP_CYCLES``;
  a longer one is dropped and the stamps skip it), locked to the host's frames so that they arrive half a cycle
  after a boundary (``BusSyncConfig``), as actuators synchronise to their bus master; each frame is answered as
  it arrives, with the values of the current cycle, and its command is taken at the next boundary. The loop asks
  for realtime priority (it stands in for the actuators' own processors);
* lockstep: a boundary when every actuator has its command (the host's batch), after which the replies go out.
  The arm's time starts with its host's first batch (however long the host takes to come up, so that a run is the
  same run whatever the start-up order); a host that stops for ``timing.bus_timeout_s`` after that is gone, and
  the arm runs a cycle alone (``lockstep.timeouts.bus``). While it waits after a DSP tick, the
  tick (and its frame) are published again every ``timing.retry_s`` (``on_retry``).

Stamps (the frames' timestamps and the ticks) are ``epoch_ns`` plus the arm's time.
"""
from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from protocol import rs485
from services.runtime.config import ConfigStruct
from services.runtime.metrics import Counters, DurationStats, LoopTimer
from services.runtime.threads import run_loop, start_thread
from services.robot.rs485_bus import BusError, RS485Bus
from services.robot.hardware import CYCLE_NS, CYCLE_S
from services.robot.hardware import CYCLES_PER_DSP, DSP_CYCLE_NS
from services.robot.lockstep_gate import LockstepConfig
from services.runtime.pacing import request_realtime
from services.robot_sim.bus_device import ActuatorBusDevice
from services.robot_sim.sim import Simulation

#: a loop this many cycles late runs them back to back; a longer stall is dropped
MAX_CATCH_UP_CYCLES = 50

#: the emulated actuators' loop runs this much above the configured realtime priority
ACTUATOR_PRIORITY_ABOVE = 5


def host_cycles(batch: np.ndarray, commanded: Optional[dict[int, int]] = None) -> list[np.ndarray]:
    """A batch of messages split into the host's cycles, in order: a second position command (0x14) for the same
    actuator starts the next cycle; any other message stays with the cycle it came in. What a stalled loop
    finds queued for several cycles, each of which the real actuators would have taken at its own boundary.
    ``commanded``: the actuators already commanded in the current cycle (their next command starts the next;
    the first of the list returned may then be empty)."""
    return [cycle.messages for cycle in queued_cycles(batch, np.zeros(len(batch), dtype=np.int64), commanded)]


@dataclass
class QueuedCycle:
    """A host cycle's messages waiting for a boundary, and when the last of them was sent (ns, the bus's stamps:
    the sender's, or the hub's on receipt; 0: unknown)."""

    messages: np.ndarray
    sent_ns: int = 0


def queued_cycles(batch: np.ndarray, stamps: np.ndarray,
                  commanded: Optional[dict[int, int]] = None) -> list[QueuedCycle]:
    """:func:`host_cycles` with when each was sent: the latest of its messages' ``stamps`` (ns)."""
    commands = batch["command"] == rs485.Command.POSITION_AND_TORQUE_COMMAND
    cycle_of = np.zeros(len(batch), dtype=int)
    seen: dict[int, int] = dict(commanded or {})
    current = 0
    for i, (is_command, destination) in enumerate(zip(commands.tolist(), batch["destination"].tolist())):
        if is_command:
            current = seen.get(destination, 0)
            seen[destination] = current + 1
        cycle_of[i] = current
    return [QueuedCycle(batch[cycle_of == k], int(stamps[cycle_of == k].max(initial=0)))
            for k in range(int(cycle_of.max(initial=0)) + 1)]


class BusSyncConfig(ConfigStruct):
    """Realtime: how the actuators' cycle boundaries lock to the host's frames."""

    #: fraction of the phase error corrected per cycle
    gain: float = 0.1
    #: at most this much phase correction per cycle (s)
    max_step_s: float = 0.00005

    def __post_init__(self) -> None:
        if not (0.0 <= self.gain <= 1.0 and 0.0 <= self.max_step_s < CYCLE_S / 4):
            raise ValueError("bus sync needs 0 <= gain <= 1 and 0 <= max_step_s < a quarter cycle")


def _start_on_the_grid(sim_time_ns: int) -> int:
    """The epoch of a timeline starting about now at ``sim_time_ns``, waited for so that the arm's 10 ms grid
    (its DSP ticks, its camera's trigger) falls on multiples of 10 ms of the stamps, where the robot node finds it
    (the bus's arm_timeline: services.robot_sim.hardware, robot_gateway.link)."""
    now = time.time_ns()
    epoch = now - sim_time_ns + (-(now - sim_time_ns)) % DSP_CYCLE_NS
    time.sleep(max(0.0, (epoch + sim_time_ns - time.time_ns()) * 1e-9))
    return epoch


class HostGrid:
    """Where a host slower than the actuators' cycle sends on its own period: its batches arrive on a grid of
    ``period_s`` blurred by its wake-ups and the transport, and a segment started at each arrival would carry that
    blur into the joints' pace (a batch 0.5 ms late on a 3.33 ms host: a segment 15 % slower, the next faster).
    The grid is followed as the actuators' own boundaries follow a 2 ms host (:class:`BusSyncConfig`): a tenth of
    each arrival's error, jumping to an arrival more than half a period off (the start, a host that paused)."""

    GAIN = 0.1

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        #: when the last batch was due on the grid (monotonic), None before the first
        self.due: Optional[float] = None

    def lead(self, boundary: float, arrived: float) -> float:
        """A batch that arrived at ``arrived`` is taken at ``boundary``: how long before the boundary it was due
        (0 to one actuator cycle)."""
        if self.due is None:
            self.due = arrived
        else:
            expected = self.due + self.period_s * max(1, round((arrived - self.due) / self.period_s))
            error = arrived - expected
            self.due = arrived if abs(error) > self.period_s / 2 else expected + self.GAIN * error
        return min(max(boundary - self.due, 0.0), CYCLE_S)


@dataclass
class ArmOnBusConfig:
    lockstep: bool = False
    epoch_ns: int = 0
    sync: BusSyncConfig = field(default_factory=BusSyncConfig)
    timing: LockstepConfig = field(default_factory=LockstepConfig)
    realtime_priority: int = 0
    #: stop after this much of the arm's time (0: run until stopped)
    max_sim_time_s: float = 0.0
    #: the host's bus cycle: the boundaries lock to its frames only when it is the actuators' own (a host at 5 ms
    #: sends on every 2.5th boundary: there is no phase to lock to, and the actuators free-run, as the real
    #: ones' own cycle does)
    host_period_s: float = CYCLE_S


class ArmOnBus:
    def __init__(self, sim: Simulation, bus: RS485Bus, config: ArmOnBusConfig | None = None,
                 counters: Counters | None = None, on_boundary: Optional[Callable[[int], None]] = None,
                 on_tick: Optional[Callable[[int], None]] = None, on_retry: Optional[Callable[[int], None]] = None,
                 on_epoch: Optional[Callable[[int], None]] = None, log: logging.Logger | None = None) -> None:
        self.sim = sim
        self.bus = bus
        self.config = config or ArmOnBusConfig()
        self.counters = counters or Counters()
        self.device = ActuatorBusDevice(sim, self.counters, defer_replies=self.config.lockstep)
        self.epoch_ns = self.config.epoch_ns
        self._on_boundary, self._on_tick, self._on_retry, self._on_epoch = on_boundary, on_tick, on_retry, on_epoch
        self.log = log or logging.getLogger("mfvs.robot_sim.bus")
        self.loop_timer = LoopTimer(CYCLE_S)
        #: realtime: how far the host's frames arrive from mid-cycle (the lock to the host)
        self.phase_error = DurationStats()
        self.received_at = 0.0
        #: realtime: host cycles found queued after a stall, each waiting for its own boundary (:meth:`_serve`)
        self.backlog: list[QueuedCycle] = []
        #: held while a boundary runs: tests and benchmarks read the simulation between cycles under it
        self.lock = threading.Lock()
        self.finished = threading.Event()
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._last_tick: Optional[int] = None
        self.set_host_period(self.config.host_period_s)

    def set_host_period(self, period_s: float) -> None:
        """The host's bus cycle, in the one place every part of the actuators that depends on it learns it: the
        firmware's segments, the grid a slower host's batches come on, the phase lock (only to a host at the
        actuators' own cycle)."""
        self.config.host_period_s = period_s
        self.sim.firmware.set_host_period(period_s)
        #: realtime, a host slower than the actuators' cycle: the grid its batches come on
        self._host_grid = HostGrid(period_s) if period_s != CYCLE_S else None

    def start(self) -> "ArmOnBus":
        self._thread = start_thread(self.run, "robot_sim-bus")
        return self

    def stop(self, close_bus: bool = True) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if close_bus:
            self.bus.close()

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _done(self) -> bool:
        limit = self.config.max_sim_time_s
        return self._stop.is_set() or (limit > 0 and self.sim.time_ns >= limit * 1e9)

    def run(self) -> None:
        run_loop(self._run_lockstep if self.config.lockstep else self._run_realtime, "actuator loop", self.log,
                 self.counters, self.finished)

    def _set_epoch(self, epoch_ns: int) -> None:
        self.epoch_ns = epoch_ns
        if self._on_epoch is not None:
            self._on_epoch(epoch_ns)

    # ------------------------------------------------------------------ bus I/O
    def _send(self, replies: np.ndarray) -> None:
        if len(replies):
            try:
                self.bus.send_batch(replies, self.epoch_ns + self.device.values.stamp_ns)
            except BusError:
                pass  # counted by the bus; the host times out and holds the arm

    def _serve(self, timeout_s: float, one_cycle: bool = False, window: Optional[dict[int, int]] = None) -> int:
        """Receive what comes within ``timeout_s`` and answer it; how many commands (0x14) it held (-1: nothing
        came). :attr:`received_at` is when it came (monotonic). ``one_cycle`` (the loop catching up after a
        stall): only the first host cycle of what is queued; the later ones wait in :attr:`backlog` for their own
        boundaries, which is where the real actuators, never stalled, took them (taken together, the newest would
        win and the arm would make two cycles' motion in one). ``window`` (a host slower than the actuators'
        cycle): the actuators commanded since the last boundary, so that a host cycle bunched behind the one taken
        waits for the next boundary whether it came in the same read or a later one.

        A host cycle is taken at a boundary no earlier than it was sent (its stamps): a loop catching up runs
        boundaries that are past on the host's clock, and the real actuators took what was sent after them at a
        later one. Taken at the first boundary it finds instead, a queue of a host slower than the 2 ms cycle went
        out at one cycle per 2 ms: the joints ran up to 2.15 times the host's rate (a 5 ms host, 5 cycles queued)."""
        # this boundary on the bus stamps' clock, and a cycle more: a stamp taken on receipt comes after the boundary
        # a loop on time serves now, and the real actuators take what arrives within a cycle at the next boundary
        due_ns = time.time_ns() + int(timeout_s * 1e9) + CYCLE_NS
        if self.backlog:
            if window or self.backlog[0].sent_ns > due_ns:  # a host cycle was taken here, or this one is not due
                time.sleep(max(0.0, timeout_s))
                return -1
            batch = self.backlog.pop(0).messages
        else:
            try:
                batch, stamps = self.bus.recv_batch(max(0.0, timeout_s))
            except BusError:  # counted by the bus; the actuators keep their last command (torque mode times out)
                time.sleep(min(max(0.0, timeout_s), 0.01))
                return -1
            if len(batch) == 0:
                return -1
            if one_cycle:
                first, *self.backlog = queued_cycles(batch, stamps, window)
                late = first.sent_ns > due_ns and len(first.messages)
                if late:
                    self.backlog.insert(0, first)  # sent after this boundary: a later one takes it
                if self.backlog:
                    self.counters.inc("frames.held_for_catch_up", len(self.backlog))
                if late:
                    return -1
                batch = first.messages
        if len(batch) == 0:  # (all of it held for the next boundary)
            return 0
        if window is not None:
            commanded = batch["destination"][batch["command"] == rs485.Command.POSITION_AND_TORQUE_COMMAND]
            for destination in commanded.tolist():
                window[destination] = 1
        self.received_at = time.monotonic()
        with self.lock:
            self._send(self.device.receive_batch(batch))
        return int(np.count_nonzero(batch["command"] == rs485.Command.POSITION_AND_TORQUE_COMMAND))

    def _cycle(self) -> None:
        """One boundary: the actuators take their commands (and report), a frame may be taken, physics runs; then
        the DSP tick's clock, if the boundary was on the 10 ms grid."""
        with self.lock:
            self.loop_timer.tick()
            tick = self.epoch_ns + self.sim.time_ns if self.sim.time_ns % DSP_CYCLE_NS == 0 else None
            self._send(self.device.begin_cycle())
            if self._on_boundary is not None:
                self._on_boundary(self.sim.time_ns)
            self.sim.end_cycle()
        if tick is not None and self._on_tick is not None:
            self._on_tick(tick)
        self._last_tick = tick

    # ------------------------------------------------------------------ realtime: paced, locked to the host
    def _run_realtime(self) -> None:
        # above every other realtime loop of the robot (its host's included): the emulated actuators stand in for
        # the arm's own processors, which no host load ever delays
        priority = min(99, self.config.realtime_priority + ACTUATOR_PRIORITY_ABOVE) if self.config.realtime_priority else 0
        if request_realtime(priority, "emulated actuators"):
            self.counters.inc("realtime_priority.granted")
        self._set_epoch(_start_on_the_grid(self.sim.time_ns))  # the arm's time starts now, as wall time does
        sync = self.config.sync
        boundary = time.monotonic() + CYCLE_S
        locked = False
        while not self._done():
            first_command, commands = None, 0
            catching_up = time.monotonic() >= boundary
            # a host slower than the actuators' cycle: one of its cycles per boundary, the next (bunched behind a late
            # one) waits for the next boundary, where the firmware carries it on (taken together, the newest would
            # win and the joints would make two of the host's periods' motion in one)
            window = {} if self._host_grid is not None else None
            while True:  # serve the bus until the boundary (when the loop is late: one host cycle of what is queued)
                received = self._serve(boundary - time.monotonic(), one_cycle=catching_up or window is not None,
                                       window=window)
                if catching_up:
                    break
                if received < 0:
                    if time.monotonic() >= boundary:
                        break
                    continue
                if received and first_command is None:
                    first_command = self.received_at
                commands += received
            behind = int((time.monotonic() - boundary) / CYCLE_S)
            if behind > MAX_CATCH_UP_CYCLES:  # a stall too long to catch up: drop it, the stamps skip it
                behind = -(-behind // CYCLES_PER_DSP) * CYCLES_PER_DSP  # whole DSP cycles: the grid stays put
                self.counters.inc("cycles.dropped", behind)
                self._set_epoch(self.epoch_ns + behind * CYCLE_NS)
                boundary += behind * CYCLE_S
                if self.backlog:  # the dropped cycles' commands: the next boundary takes the newest
                    self.backlog = [QueuedCycle(np.concatenate([c.messages for c in self.backlog]),
                                                max(c.sent_ns for c in self.backlog))]
            elif behind > 0:
                self.counters.inc("cycles.late")
            # a host slower than the actuators' cycle: its batch was due this long before the boundary (its
            # targets' segments start there: services.robot_sim.firmware)
            self.sim.firmware.host_lead_s = (self._host_grid.lead(boundary, self.received_at)
                                             if commands and self._host_grid is not None else 0.0)
            self._cycle()
            # lock the boundaries to the host, whose frames should arrive half a cycle after a boundary: from the
            # first frame of the cycle (a cycle that got none says nothing about the phase); far off (at the start,
            # or after the host's phase moved), jump there, close to it, follow gently
            correction = 0.0
            if behind == 0 and first_command is not None and self.config.host_period_s == CYCLE_S:
                error = (first_command - (boundary - CYCLE_S)) - CYCLE_S / 2
                self.phase_error.add(abs(error))
                if abs(error) > CYCLE_S / 4 and (not locked or commands > len(self.device.index)):
                    correction = error
                    self.counters.inc("sync.jumps")
                else:
                    correction = max(-sync.max_step_s, min(sync.max_step_s, sync.gain * error))
                locked = True
            boundary += CYCLE_S + correction

    # ------------------------------------------------------------------ lockstep: a cycle per host batch
    def _run_lockstep(self) -> None:
        timing = self.config.timing
        self._last_tick = None
        host_seen = False
        while not self._done():
            start = time.monotonic()
            next_retry = start + timing.retry_s
            while not self.device.batch_complete and not self._stop.is_set():
                now = time.monotonic()
                if host_seen and now - start >= timing.bus_timeout_s:  # the host is gone: a cycle alone
                    self.counters.inc("lockstep.timeouts.bus")
                    break
                if self._last_tick is not None and now >= next_retry:  # the host waits for that tick's answer
                    self.counters.inc("lockstep.retries")
                    if self._on_retry is not None:
                        self._on_retry(self._last_tick)
                    next_retry = now + timing.retry_s
                until = min(next_retry, start + timing.bus_timeout_s) if host_seen else next_retry
                self._serve(max(until, now + 0.001) - now)
            host_seen = host_seen or self.device.batch_complete
            self._cycle()
