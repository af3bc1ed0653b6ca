"""The robot node's configuration (:class:`RobotNodeConfig`, checked when it is made: an unknown arm, a DSP speed
outside the arm's ranges, a command window past the DSP's plan margin are refused then, not at the first tick), and
the margin the DSP's plan keeps before the next bus exchange, which bounds that window."""
from __future__ import annotations

import msgspec

from services.model.arm import DEFAULT_ARM, load_arm
from services.robot import arm_check
from services.robot.admission import AdmissionConfig
from services.robot.contact_watch import ContactConfig
from services.robot.dsp import DSPConfig, for_arm
from services.robot.hardware import CYCLE_S
from services.robot.lockstep_gate import LockstepConfig
from services.robot.lowlevel import LowLevelConfig
from services.runtime.service import ServiceConfig

#: the DSP's plan must be ready this long before the next bus exchange: the command window ends there at the latest
#: (the plan takes 0.2-0.4 ms; the rest is for a late wake-up of the DSP's thread: with 0.5 ms, one plan in about a
#: thousand missed its exchange on this host)
PLAN_MARGIN_S = 0.0007
#: the longest command window: a bus cycle less the plan's margin
MAX_COMMAND_WINDOW_S = CYCLE_S - PLAN_MARGIN_S


class RobotNodeConfig(ServiceConfig):
    #: the arm (its description: services/model/arms/<arm>.yaml); the node declares it in every state, and the other
    #: services run on it
    arm: str = DEFAULT_ARM
    dsp: DSPConfig = msgspec.field(default_factory=DSPConfig)
    lockstep: LockstepConfig = msgspec.field(default_factory=LockstepConfig)
    #: which robot commands are applied at all: fresh, not from the future, in sequence per sender
    admission: AdmissionConfig = msgspec.field(default_factory=AdmissionConfig)
    #: the low-level torque API's watchdog and release (services.robot.lowlevel)
    lowlevel: LowLevelConfig = msgspec.field(default_factory=LowLevelConfig)
    #: the commissioning check's verdict: kept where, or waived (services.robot.arm_check)
    arm_check: arm_check.ArmCheckConfig = msgspec.field(default_factory=arm_check.ArmCheckConfig)
    #: the contact monitor on the joints' torques (services.robot.contact_watch, docs/contact.md)
    contact: ContactConfig = msgspec.field(default_factory=ContactConfig)
    #: after this many consecutive failed exchanges the node reports itself unhealthy and refuses motion
    max_bus_errors: int = 5
    #: realtime: SCHED_FIFO priority of the robot's process where the OS grants it (0: normal scheduling), above
    #: the router's and safety's (30). A robot's hardware loop must not wait behind the rest of the host
    realtime_priority: int = 40
    #: realtime: after its tick's reading, the DSP waits up to this long for a command derived from a newer frame
    #: than the last one it took, before it plans with what it has: a command that just missed the tick is then
    #: applied at this tick rather than 10 ms later, with the same motion (the plan is first used at the next bus
    #: exchange, 2 ms after the tick, either way). Never later than PLAN_MARGIN_S before that exchange; a stop is
    #: never waited past. 0: plan at once
    command_window_s: float = MAX_COMMAND_WINDOW_S

    def __post_init__(self) -> None:
        for_arm(self.dsp, load_arm(self.arm))  # an unknown arm, or speeds outside its ranges, refused now
        if self.max_bus_errors < 1:
            raise ValueError("max_bus_errors must be at least 1")
        if not 0.0 <= self.command_window_s <= MAX_COMMAND_WINDOW_S:
            raise ValueError(f"command_window_s must be within 0..{MAX_COMMAND_WINDOW_S} s: the DSP's plan is needed "
                             f"at the next bus exchange, {CYCLE_S * 1e3:.0f} ms after its tick")
        if not 0 <= self.realtime_priority <= 99:
            raise ValueError("realtime_priority must be within 0..99 (SCHED_FIFO)")

