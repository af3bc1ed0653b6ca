"""The robot's states as pure functions of what the node knows when it publishes them: no zenoh, no clock, no locks.

:func:`robot_state` is ``…/robot/state``, one at every DSP tick: the joints of the tick's reading, the end effector
by the description's kinematics (and by the arm's own report where it gives one), what the DSP is doing and the
limits it applies, the faults (the DSP's active limits, the link's, the actuators', a refused command's for a
while), how the loop kept time, and the commissioning check's verdict. :func:`lowlevel_state` is
``…/robot/lowlevel/state``, one every bus cycle. The node makes the header (its sequence numbers are the service's)
and publishes what these return.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from protocol.messages import (ActuatorMode, ArmCheckState, ContactState, FingerState, Header, KinovaPose, LoopTiming,
                               LowLevelState, RobotState)
from services.model import frames
from services.model.arm import ArmDescription
from services.model.kinematics import ArmKinematics
from services.robot.dsp import KinovaDSP
from services.robot.hardware import JointReading

#: a message carries at most this many faults (RobotState.faults, LowLevelState.faults)
MAX_FAULTS = 32
#: a refused command's reason is shortened to this in the states' faults
REFUSAL_CHARS = 120
#: a refused command is named in this many states' faults (a second at 100 Hz): long enough for a reader polling
#: the state to see it
STATES_NAMING_A_REFUSAL = 100


class RecentRefusal:
    """The last robot command refused, named in the next :data:`STATES_NAMING_A_REFUSAL` states."""

    def __init__(self) -> None:
        self._reason = ""
        self._states_left = 0

    def note(self, reason: str) -> None:
        self._reason, self._states_left = reason, STATES_NAMING_A_REFUSAL

    def for_next_state(self) -> str:
        """The reason to name in the state about to go out ('' once it was named long enough)."""
        if self._states_left <= 0:
            return ""
        self._states_left -= 1
        return self._reason


def kinova_pose(T: np.ndarray) -> KinovaPose:
    """A 4×4 transform (base frame) as the Kinova API's pose."""
    return KinovaPose(**frames.kinova_pose(T[:3, :3], T[:3, 3]))


def robot_state(header: Header, arm: ArmDescription, reading: JointReading, kinematics: ArmKinematics, dsp: KinovaDSP,
                *, link_faults: list[str], refused: str, applied: Optional[Header], timing: LoopTiming,
                arm_check: ArmCheckState, finger_targets: Optional[np.ndarray] = None,
                contact: Optional[ContactState] = None) -> RobotState:
    """The state of the tick whose reading is ``reading``. ``link_faults``: what the last failed exchange with the
    arm said (none once it answers again); ``refused``: the reason of a command refused lately ('' for none);
    ``applied``: the header of the command the last DSP cycle applied, the robot's hop appended. ``dsp``: what
    interprets the commands (the emulated Kinova DSP, or an arm's own through the SDK, which offers the same status,
    queue and limits); ``kinematics``: the publishing thread's own (ArmKinematics keeps a workspace);
    ``finger_targets``: the targets the fingers hold, where the reading has fingers; ``contact``: the contact
    monitor's view of the cycle (services.robot.contact_watch), where it runs."""
    R, p = kinematics.pose(reading.q)
    status = dsp.status
    faults = list(status.active_limits) + link_faults + reading.faults()
    if refused:
        faults.append(f"refused: {refused}"[:REFUSAL_CHARS])
    return RobotState(
        header=header, arm=arm.name, arm_digest=arm.digest,
        q=reading.q.tolist(), dq=reading.dq.tolist(), tau=reading.tau.tolist(),
        pose=KinovaPose(**frames.kinova_pose(R, p)),
        control_mode=status.mode, fifo_count=dsp.fifo_count, faults=faults[:MAX_FAULTS],
        watchdog_tripped=status.watchdog_tripped, angular_convention=dsp.config.angular_convention,
        applied_command=applied, timing=timing, limits=dsp.motion_limits(),
        arm_pose=kinova_pose(reading.arm_pose) if reading.arm_pose is not None else None,
        arm_check=arm_check, fingers=finger_state(reading, finger_targets), contact=contact,
    )


def finger_state(reading: JointReading, targets: Optional[np.ndarray]) -> Optional[FingerState]:
    """The fingers of ``reading`` with the targets they hold (None where the reading has no fingers)."""
    fingers = reading.fingers
    if fingers is None or targets is None:
        return None
    return FingerState(position=fingers.position.tolist(), velocity=fingers.velocity.tolist(),
                       current_a=fingers.current_a.tolist(), target=np.asarray(targets, dtype=float).tolist())


def lowlevel_state(header: Header, reading: JointReading, torque_mode: bool, link_faults: list[str],
                   cycle_ns: int) -> LowLevelState:
    """The joints of the bus cycle whose reading is ``reading``, for a torque client: in which mode the actuators
    are, their currents and temperatures, and the bus's cycle (a client counts the states it did not see)."""
    return LowLevelState(
        header=header, mode=ActuatorMode.TORQUE if torque_mode else ActuatorMode.POSITION,
        q=reading.q.tolist(), dq=reading.dq.tolist(), tau=reading.tau.tolist(),
        current_a=reading.current_a.tolist(), temperature_c=reading.temperature_c.tolist(),
        faults=(link_faults + reading.faults())[:MAX_FAULTS], cycle_ns=cycle_ns)
