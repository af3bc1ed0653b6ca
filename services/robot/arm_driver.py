"""What drives the arm: the one seam between the robot node's loop (services.robot.node) and the arm, no zenoh here.

Every cycle of its loop the node calls :meth:`ArmDriver.cycle`, which talks to the arm and says whether the cycle is
a DSP tick, and it runs a tick's DSP cycle through :meth:`ArmDriver.run_dsp`. Two kinds of arm:

* :class:`JointDriver`: the emulated Kinova DSP (:class:`~services.robot.core.RobotCore`) driving the joints of a
  :class:`~services.robot.hardware.RobotHardware` (robot_sim's simulated arm, the actuators behind robot_gateway's
  RS-485 link). Every bus cycle the core's targets are exchanged for a reading; every ``cycles_per_dsp``-th
  exchange is a DSP tick, or on the arm's own 10 ms grid where the readings carry its timeline. The DSP plans
  beside the loop, and low-level torque control drives the joints directly;
* Kinova's own DSP through the SDK (services.robot_gateway.sdk_driver): every cycle (10 ms) reads the arm and is a
  tick, whose DSP cycle forwards the command to the arm, in the loop.

Either says how its link to the arm is doing in :class:`LinkHealth`: the node refuses motion and reports itself
unhealthy after ``max_bus_errors`` failures in a row, and the faults go out in every state.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable, Optional, Protocol

import numpy as np

from services.model import frames
from services.model.kinematics import ArmKinematics
from services.robot.core import RobotCore
from services.robot.dsp import DSPConfig, KinovaDSP
from services.robot.hardware import (DSP_CYCLE_NS, EXTRAPOLATED_CYCLES, BusTiming, HardwareError, JointReading,
                                     RobotHardware)
from services.robot.kinova_api import KinovaApi
from services.robot.lowlevel import TorqueJoints
from services.robot.torque_setup import TorqueSetup
from services.runtime.clock import SimulatedClock, WallClock
from services.runtime.logs import RateLimitedLogger
from services.runtime.metrics import Counters, DurationStats, RateMeter

#: a fault is shortened to this in the states
FAULT_CHARS = 120


class LinkHealth:
    """How the link to the arm is doing: failures in a row, and what the last one said (in every state until the
    arm answers again). Written by the thread that talks to the arm, read by any."""

    def __init__(self) -> None:
        self.consecutive_errors = 0
        self.faults: list[str] = []

    def failed(self, fault: str) -> None:
        self.consecutive_errors += 1
        self.faults = [fault[:FAULT_CHARS]]

    def answered(self) -> None:
        self.consecutive_errors = 0
        self.faults = []

    def failing(self, max_errors: int) -> bool:
        """Whether the arm has not answered ``max_errors`` times in a row: no motion, and the node is unhealthy."""
        return self.consecutive_errors >= max_errors


@dataclass(frozen=True)
class NodeLoop:
    """What a driver shares with the node's loop it runs in: no zenoh."""

    #: the node's name, in the logs
    name: str
    lockstep: bool
    #: the node's clock (lockstep: the arm's stamps move it)
    clock: WallClock | SimulatedClock
    counters: Counters
    log: RateLimitedLogger
    #: cycles the arm ran without a target from the loop (the states' ``timing.missed_per_s``)
    missed: RateMeter
    #: how long the exchanges with the arm took
    exchange_time: DurationStats


class ArmDriver(Protocol):
    #: the rules between the commands and the arm; its ``dsp`` interprets the commands
    core: RobotCore
    #: what answers ``robot/api/*``: ``call(function, argument) -> ApiReply``
    api: object
    #: the loop's cycle: the bus's, or the DSP's own where there is no joint-level bus (``BusTiming(1)``)
    timing: BusTiming
    #: the arm steps only when the loop drives it: cycles the loop was late for may run back to back
    simulated_in_process: bool
    #: the DSP cycle may run on a thread of its own while the loop goes on with the next cycles (realtime)
    dsp_beside_loop: bool
    #: the joints as low-level torque control drives them (None: no low-level torque API, see below)
    torque_joints: Optional[TorqueJoints]
    #: why the low-level torque API is not offered ('' when it is)
    lowlevel_unavailable: str
    link: LinkHealth
    #: the cycles run with the arm so far (a DSP plan taken after another cycle went out is late)
    cycles: int

    def cycle(self) -> Optional[int]:
        """One cycle of the loop with the arm; the stamp of the DSP tick it is (ns), or None."""

    def run_dsp(self, dsp_cycle: Callable[[], float]) -> float:
        """Run a tick's DSP cycle, which says how long it waited for a command (s); a failure of the link to the
        arm in it is counted as one (then 0.0), any other goes to the caller."""

    def close(self) -> None: ...


class CoreView:
    """What the emulated Kinova API reads of the robot: the latest reading and the reference (model units)."""

    def __init__(self, core: RobotCore, kin: ArmKinematics) -> None:
        self.core, self.kin = core, kin

    @property
    def q(self) -> np.ndarray:
        return self.core.reading.q

    @property
    def dq(self) -> np.ndarray:
        return self.core.reading.dq

    @property
    def tau(self) -> np.ndarray:
        return self.core.reading.tau

    @property
    def q_ref(self) -> np.ndarray:
        return self.core.q_ref.copy()

    @property
    def current_a(self) -> np.ndarray:
        return self.core.reading.current_a

    @property
    def fingers(self):
        return self.core.reading.fingers

    @property
    def finger_targets(self) -> Optional[np.ndarray]:
        return None if self.core.fingers is None else self.core.fingers.target.copy()

    def command_fingers(self, command) -> Optional[str]:
        return self.core.queue_fingers(command)

    def ee_pose(self) -> np.ndarray:
        """GetCartesianPosition: the arm's own report where it gives one, else the description's kinematics."""
        reading = self.core.reading
        if reading.arm_pose is not None:
            return reading.arm_pose
        return frames.homogeneous(*self.kin.pose(reading.q))


class HardwareTorqueJoints:
    """Low-level control's view of the joints: mode switches go through the hardware's handshake, the core follows
    (under the lock it shares with the DSP's thread)."""

    def __init__(self, hardware: RobotHardware, core: RobotCore, core_lock: threading.Lock,
                 gravity: Callable[[np.ndarray], np.ndarray]) -> None:
        self.hardware, self.core, self.core_lock, self.gravity = hardware, core, core_lock, gravity

    @property
    def torque_mode(self) -> bool:
        return self.core.torque_mode

    @property
    def actuators_compensate_gravity(self) -> bool:
        return self.hardware.actuators_compensate_gravity

    def enter_torque_mode(self) -> None:
        # what the joints measure now: the arm's gravity load, whichever side compensates it in torque mode
        self.hardware.enter_torque_mode(self.gravity(self.core.reading.q))
        with self.core_lock:
            self.core.enter_torque_mode()

    def leave_torque_mode(self) -> None:
        self.hardware.leave_torque_mode()
        with self.core_lock:
            self.core.leave_torque_mode()

    def set_torques(self, torques) -> None:
        with self.core_lock:
            self.core.torques = np.asarray(torques, dtype=float).copy()

    def set_gravity_compensation(self, on: bool) -> bool:
        return self.hardware.set_gravity_compensation(on)


class JointDriver:
    """The emulated Kinova DSP on the joints of ``hardware`` (RobotCore + RobotHardware)."""

    dsp_beside_loop = True
    lowlevel_unavailable = ""

    def __init__(self, hardware: RobotHardware, reading: JointReading, loop: NodeLoop, *, dsp: DSPConfig,
                 kin: ArmKinematics, gravity: Callable[[np.ndarray], np.ndarray], torque_setup: TorqueSetup,
                 core_lock: threading.Lock) -> None:
        """``reading``: the hardware's first; ``kin``: the DSP's kinematics (its thread's); ``gravity``: the
        arm's gravity torque at given angles, on the loop's thread; ``core_lock``: serialises the core between the
        loop and the DSP's thread."""
        self.hardware = hardware
        self.loop = loop
        self.timing = hardware.timing
        self.simulated_in_process = hardware.simulated_in_process
        self.core = RobotCore(KinovaDSP(dsp, kin), reading, self.timing)
        self.core_lock = core_lock
        self.api = KinovaApi(CoreView(self.core, kin), self.core.dsp, torque_setup, hardware)
        self.torque_joints = HardwareTorqueJoints(hardware, self.core, core_lock, gravity)
        self.link = LinkHealth()
        self.cycles = 0
        self._stale_seen = 0
        self._last_stamp: Optional[int] = None
        #: ticks on the arm's grid: the grid's period of the last tick (stamp // DSP cycle), and its exchange
        self._last_dsp_period: Optional[int] = None
        self._last_dsp_index = 0

    def cycle(self) -> Optional[int]:
        """The exchange: the core's targets out, the reading in."""
        loop = self.loop
        with self.core_lock:
            targets = self.core.targets()
            stale = self.core.dsp_stale_cycles
        start = time.monotonic()
        try:
            reading = self.hardware.exchange(targets)
        except HardwareError as exc:
            reading = None
            self.link.failed(f"bus: {exc}")
            loop.counters.inc("bus.failed_exchanges")
            loop.missed.tick()
            loop.log.warning("exchange", "%s: exchange failed: %s", loop.name, exc)
            if self.link.consecutive_errors > EXTRAPOLATED_CYCLES:
                # the actuators went on along their last targets for as many cycles as the reference did, and
                # hold now: the reference holds too (one lost exchange is a missed cycle, not a stop)
                with self.core_lock:
                    self.core.stop()
        else:
            loop.exchange_time.add(time.monotonic() - start)
            self.link.answered()
            self._count_gap(reading.stamp_ns)
            with self.core_lock:
                self.core.observe(reading)
            if loop.lockstep and reading.stamp_ns > 0:
                loop.clock.advance_to(reading.stamp_ns)  # in lockstep the node's time is the arm's
        if stale > self._stale_seen:
            loop.counters.inc("dsp.stale_holds", stale - self._stale_seen)
            self._stale_seen = stale
        index = self.cycles
        self.cycles += 1
        if not self._is_dsp_tick(index, reading):
            return None
        return reading.stamp_ns if reading is not None else loop.clock.now_ns()

    def run_dsp(self, dsp_cycle: Callable[[], float]) -> float:
        return dsp_cycle()

    def close(self) -> None:
        self.hardware.close()

    def _count_gap(self, stamp_ns: int) -> None:
        """Cycles the arm ran between two of our exchanges (from the readings' stamps on its timeline) beyond the
        one each exchange takes: missed, whoever was late."""
        if self._last_stamp is not None and stamp_ns > 0 and not self.simulated_in_process:
            gap = self.timing.cycles_in(stamp_ns - self._last_stamp) - 1
            if gap > 0:
                self.loop.counters.inc("cycles.arm_missed", gap)
                for _ in range(gap):
                    self.loop.missed.tick()
        self._last_stamp = stamp_ns

    def _is_dsp_tick(self, index: int, reading: Optional[JointReading]) -> bool:
        if self.loop.lockstep and reading is not None and reading.stamp_ns > 0:
            return reading.stamp_ns % DSP_CYCLE_NS == 0  # the simulator's 10 ms grid
        if not self.hardware.arm_timeline:
            return index % self.timing.cycles_per_dsp == 0
        # on the arm's grid, in phase with its camera: the first reading at or past each 10 ms line (a lost
        # reading is no tick, unless a whole DSP cycle of exchanges passed without one: the state goes on)
        if reading is not None and reading.stamp_ns > 0:
            period = reading.stamp_ns // DSP_CYCLE_NS
            tick = self._last_dsp_period is None or period > self._last_dsp_period
            if self._last_dsp_period is None and reading.stamp_ns % DSP_CYCLE_NS:
                tick = False  # joined mid-cycle: the first tick is at the next line
            self._last_dsp_period = period
        else:
            tick = index - self._last_dsp_index >= self.timing.cycles_per_dsp
        if tick:
            self._last_dsp_index = index
        return tick
