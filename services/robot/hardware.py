"""The robot's one hardware interface, in the shape of ros2_control's: what the robot node needs from an arm's
joints, whatever drives them (the simulated arm in robot_sim's process, or actuators on an RS-485 bus).

One call per bus cycle, :meth:`RobotHardware.exchange`, writes that cycle's targets and reads the joints back, as
the actuators' 0x14 command and its 0x15-0x17 replies do on the real bus. The readings are what the bus carries
(physical degrees as float32), converted to model units by :func:`reading_from_physical`, so that the simulated
arm in-process and the same arm behind the bus give the node identical numbers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Protocol

import numpy as np

from services.model.arm import ArmDescription

#: the DSP's tick: the arm's 100 Hz high-level loop (kinova.md: the high-level API at 100 Hz)
DSP_CYCLE_NS = 10_000_000


@dataclass(frozen=True)
class BusTiming:
    """The actuator bus's cycle, a property of the hardware behind it: a whole fraction of the DSP's 10 ms tick, so
    that every ``cycles_per_dsp``-th exchange is a DSP tick.

    Which periods: Kinova's RS-485 example budgets 2.5 ms a cycle (its 500 Hz sleep plus the exchange), abr_jaco2
    runs about 3 ms, drake-jaco-driver caps at 250 Hz, Kinova's staff give 300-500 Hz for direct actuator access
    (kinova-ros issue 423): 2, 2.5, 3.33 and 5 ms (5, 4, 3, 2 cycles a tick). 4 ms is refused: 10 ms is 2.5 of
    them, so the DSP's tick would fall between exchanges (every 8 or 12 ms, not the arm's 100 Hz)."""

    cycles_per_dsp: int = 5

    def __post_init__(self) -> None:
        if not isinstance(self.cycles_per_dsp, int) or not 1 <= self.cycles_per_dsp <= max(BUS_PERIODS):
            # (1: a backend with no joint-level bus, which runs at its DSP's own cycle)
            raise ValueError(f"a bus cycle must divide the DSP's 10 ms tick into 1..{max(BUS_PERIODS)} cycles")

    @property
    def period_ns(self) -> int:
        """One cycle (3.33 ms: 3 333 333 ns, the tick's rest in the last cycle of each tick: see :meth:`stamp_ns`)."""
        return DSP_CYCLE_NS // self.cycles_per_dsp

    @property
    def period_s(self) -> float:
        return DSP_CYCLE_NS / self.cycles_per_dsp * 1e-9

    @property
    def period_ms(self) -> float:
        return round(DSP_CYCLE_NS / self.cycles_per_dsp * 1e-6, 2)

    def stamp_ns(self, cycle: int) -> int:
        """When cycle number ``cycle`` is due, counted from the first (cycle 0, a tick): every tick exactly on the
        10 ms grid, whatever rounding a period of 3.33 ms takes."""
        ticks, within = divmod(cycle, self.cycles_per_dsp)
        return ticks * DSP_CYCLE_NS + within * self.period_ns

    def cycles_in(self, span_ns: int) -> int:
        """How many cycles ``span_ns`` holds, to the nearest (a gap between two stamps)."""
        return int(round(span_ns * self.cycles_per_dsp / DSP_CYCLE_NS))

    @classmethod
    def from_period_ms(cls, period_ms: float) -> "BusTiming":
        """The timing of a period in milliseconds as a user writes it (2, 2.5, 3.33 or 3.333, 5)."""
        if not isinstance(period_ms, (int, float)) or isinstance(period_ms, bool) or not math.isfinite(period_ms):
            raise ValueError(f"bus period_ms must be a number of milliseconds, not {period_ms!r}")
        for cycles, nominal in BUS_PERIODS.items():
            if abs(period_ms - nominal) < 0.01:
                return cls(cycles)
        if abs(period_ms - 4.0) < 0.01:
            raise ValueError("bus period_ms 4 does not divide the DSP's 10 ms tick (2.5 cycles): the tick would fall "
                             "between exchanges; use 3.33 or 5")
        periods = ", ".join(f"{v:g}" for v in BUS_PERIODS.values())
        raise ValueError(f"bus period_ms {period_ms:g} is not one of {periods} "
                         "(a whole fraction of the DSP's 10 ms tick, within what USB sustains)")


#: cycles a DSP tick → the period they give (ms)
BUS_PERIODS = {5: 2.0, 4: 2.5, 3: 3.33, 2: 5.0}
#: the emulated arm's actuator cycle, and the bus's unless its hardware says otherwise (500 Hz: Kinova's RS-485
#: example's loop)
DEFAULT_TIMING = BusTiming()
CYCLE_NS = DEFAULT_TIMING.period_ns
CYCLE_S = DEFAULT_TIMING.period_s
CYCLES_PER_DSP = DEFAULT_TIMING.cycles_per_dsp
#: cycles an actuator goes on along its last target's rate when no target comes, before it holds (robot_sim's
#: firmware emulates one, as servo drives commonly do; the real actuators' behaviour is not public)
EXTRAPOLATED_CYCLES = 1


class HardwareError(RuntimeError):
    """An exchange that did not deliver a complete reading (bus timeout, NACK, a failed bus): the node holds the
    arm at its last measured angles."""


@dataclass
class JointReading:
    """The joints at one bus cycle, model units (rad, rad/s, N·m; current in A, temperature in °C)."""

    q: np.ndarray
    dq: np.ndarray
    tau: np.ndarray
    #: (None: zeros, one per joint)
    current_a: Optional[np.ndarray] = None
    temperature_c: Optional[np.ndarray] = None
    #: per actuator: 0 position mode, 1 torque mode
    mode: Optional[np.ndarray] = None
    #: per actuator: the latched fault (protocol.rs485.ActuatorError), 0 for none
    fault: Optional[np.ndarray] = None
    #: when the reading was taken: on the emulated arm's own timeline (robot_sim), or on the host's clock when
    #: the bus gives no better (a real arm); 0 when unknown
    stamp_ns: int = 0
    #: the end effector's pose (4×4, base frame) as the arm itself reports it (Kinova's DSP through the SDK, the
    #: simulator's physics), when it does: an RS-485 bus carries joints only
    arm_pose: Optional[np.ndarray] = None
    #: the hand's fingers, where the hardware has them (None: it reports none)
    fingers: Optional["FingerReading"] = None

    def __post_init__(self) -> None:
        n = len(self.q)
        for name in ("current_a", "temperature_c"):
            if getattr(self, name) is None:
                setattr(self, name, np.zeros(n))
        for name in ("mode", "fault"):
            if getattr(self, name) is None:
                setattr(self, name, np.zeros(n, dtype=int))

    def faults(self) -> list[str]:
        return [f"actuator {i + 1}: fault {int(code)}" for i, code in enumerate(self.fault) if code]


@dataclass
class FingerReading:
    """The hand's fingers at one bus cycle, a second actuator group beside the joints: each finger's proximal angle
    (rad, 0 open), its rate (rad/s) and its actuator's current (A)."""

    position: np.ndarray
    velocity: np.ndarray
    current_a: np.ndarray


@dataclass
class JointTargets:
    """One bus cycle's command, model units: position targets; in torque mode ``torques`` (model sign, N·m, on
    top of whatever gravity the actuators add themselves: none on an RS-485 bus, where the host's gravity is in
    ``torques``; see :attr:`RobotHardware.actuators_compensate_gravity`) with ``q`` the actuators' safety reference
    (where the joints are). ``fingers``: each finger's angle target (rad), where the hardware has fingers; the
    fingers take position targets only, in torque mode too."""

    q: np.ndarray
    torques: Optional[np.ndarray] = None
    fingers: Optional[np.ndarray] = None


def physical_targets(targets: JointTargets, arm: ArmDescription) -> tuple[np.ndarray, np.ndarray]:
    """(position deg, torque N·m) in the actuators' own (physical) units and signs, as 0x14 carries them."""
    torques = np.zeros(arm.n_joints) if targets.torques is None else arm.sign * np.asarray(targets.torques)
    return arm.model_to_physical_deg(targets.q), torques


@dataclass
class ActuatorValues:
    """What the arm's actuators report for one cycle (the 0x15-0x17 replies), in their own units and signs:
    physical degrees and deg/s, N·m, A, °C, and per actuator the mode (0 position, 1 torque) and the fault code.
    The emulated firmware produces them (float64), the bus link decodes them (float32 on the wire)."""

    position_deg: np.ndarray
    velocity_dps: np.ndarray
    torque_nm: np.ndarray
    current_a: np.ndarray
    temperature_c: np.ndarray
    mode: np.ndarray
    fault: np.ndarray
    #: the cycle's time on the arm's timeline (an emulated arm), or when the replies came (a real one)
    stamp_ns: int = 0


def reading_from_physical(values: ActuatorValues, arm: ArmDescription) -> JointReading:
    """A reading in model units from the actuators' own values: the one conversion both the bus link and the
    in-process simulated arm use."""
    return JointReading(q=arm.physical_deg_to_model(values.position_deg),
                        dq=arm.physical_rate_to_model(values.velocity_dps),
                        tau=arm.sign * np.asarray(values.torque_nm, dtype=float),
                        current_a=arm.sign * np.asarray(values.current_a, dtype=float),
                        temperature_c=np.asarray(values.temperature_c, dtype=float),
                        mode=np.asarray(values.mode, dtype=int), fault=np.asarray(values.fault, dtype=int),
                        stamp_ns=int(values.stamp_ns))


class RobotHardware(Protocol):
    """An arm's joints, one bus cycle at a time."""

    #: True when the arm is simulated in this process and steps only when exchanged with: the node may then run
    #: cycles it was late for back to back (the arm's time is the node's). A remote arm keeps its own time: a late
    #: cycle is skipped and counted, never sent as a burst of targets (which the arm would follow faster).
    simulated_in_process: bool
    #: True when the readings are stamped on the arm's own timeline, whose 10 ms grid is the arm's DSP cycle (the
    #: emulated actuators', whose camera is triggered on it): the robot node then runs its DSP when a reading's
    #: stamp crosses that grid, in phase with the camera. False (a real arm: receive times): every fifth cycle.
    arm_timeline: bool
    #: True when the actuators add the arm's gravity themselves in torque mode (Kinova's DSP does, through the SDK;
    #: the simulator's actuators in robot_sim's process stand for it), which :meth:`set_gravity_compensation` may
    #: switch off. False on an RS-485 bus: the base's DSP is bypassed and a single actuator cannot compute the
    #: arm's gravity (kinova.md; abr/abr_jaco2 sends host-computed gravity torques), so the host sends its model's
    #: gravity with every torque (services.robot.lowlevel)
    actuators_compensate_gravity: bool
    #: the bus's cycle (the node's loop runs on it; every ``cycles_per_dsp``-th exchange is a DSP tick)
    timing: BusTiming

    def exchange(self, targets: JointTargets) -> JointReading:
        """Send this cycle's targets, return the joints' state (raises :class:`HardwareError`)."""

    def enter_torque_mode(self, expected_torques: np.ndarray) -> None:
        """The torque-mode handshake: ``expected_torques`` (model sign) are what the host's model expects the
        joints to measure now (gravity); raises :class:`HardwareError` when the actuators refuse."""

    def leave_torque_mode(self) -> None:
        """Back to position mode, holding where the joints are (raises :class:`HardwareError`)."""

    def zero_torque_sensor(self, joint: int) -> None:
        """SetTorqueZero: the joint's torque sensor reads 0 where it stands (raises :class:`HardwareError` where the
        hardware cannot)."""

    def set_gravity_compensation(self, on: bool) -> bool:
        """The actuators' own gravity compensation in torque mode on or off (Table 5.1's gravity setup), where
        :attr:`actuators_compensate_gravity`; False where the hardware has no way to switch it (the host then takes
        its model's gravity back out of what it sends)."""

    def close(self) -> None: ...
