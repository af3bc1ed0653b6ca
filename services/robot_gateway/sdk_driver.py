"""Kinova's own DSP driving the arm, through its SDK: the kinova_sdk backend's
:class:`~services.robot.arm_driver.ArmDriver` (no zenoh here).

The command layer offers no joint-level exchange and no low-level torque API: the node's loop runs at the DSP's own
cycle (10 ms), and every cycle reads the arm (4 SDK calls) and is a DSP tick, whose cycle forwards the latest robot
command to the arm's DSP (:class:`~services.robot_gateway.kinova_sdk.SdkArm`, the core's DSP), in the loop. A failed
SDK call, reading or forwarding, or values the arm should never report (NaN) is a failure of the link
(``sdk.errors``, the fault in the states); the node holds no motion of its own to stop.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, Optional

from services.robot.arm_driver import LinkHealth, NodeLoop
from services.robot.core import RobotCore
from services.robot.hardware import BusTiming, JointReading
from services.robot_gateway.kinova_sdk import ArmSession, KinovaSdk, SdkArm, SdkError


@dataclass
class SdkConnection:
    """The arm opened through Kinova's SDK, with its first reading: what the kinova_sdk backend starts from."""

    sdk: KinovaSdk
    session: ArmSession
    arm: SdkArm
    first_reading: JointReading

    def close(self) -> None:
        self.session.close()


class SdkDriver:
    #: no joint-level bus: the loop runs at the DSP's own cycle, each one a tick
    timing = BusTiming(1)
    simulated_in_process = False
    #: the SDK's calls go out from the loop's thread, one after the other
    dsp_beside_loop = False
    torque_joints = None
    lowlevel_unavailable = ("the kinova_sdk backend has no low-level torque API (the USB layer offers none); use the "
                            "rs485 backend")

    def __init__(self, connection: SdkConnection, loop: NodeLoop) -> None:
        self.connection = connection
        self.loop = loop
        self.core = RobotCore(connection.arm, connection.first_reading, self.timing)
        #: the Kinova API's calls go to the arm through the library
        self.api = connection.sdk
        self.link = LinkHealth()
        self.cycles = 0

    def cycle(self) -> Optional[int]:
        """Read the arm; every cycle is a tick, stamped with the host's clock (the arm gives no stamps)."""
        self.cycles += 1
        try:
            self.core.observe(self.connection.arm.read())
            self.link.answered()
        except Exception as exc:  # an SDK error code, or values the arm should never report (NaN)
            self._failed(exc)
        return time.time_ns()

    def run_dsp(self, dsp_cycle: Callable[[], float]) -> float:
        """The DSP cycle forwards the command to the arm's own DSP: a failed SDK call there is the link's."""
        try:
            return dsp_cycle()
        except SdkError as exc:
            self._failed(exc)
            return 0.0

    def close(self) -> None:
        """The arm's session ends (trajectories erased, StopControlAPI, CloseAPI)."""
        self.connection.close()

    def _failed(self, exc: Exception) -> None:
        self.link.failed(f"sdk: {exc}")
        self.loop.counters.inc("sdk.errors")
        self.loop.log.error("sdk", "%s", exc)
