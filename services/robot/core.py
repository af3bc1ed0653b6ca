"""The robot node's rules, one bus cycle at a time, with no zenoh, no threads and no clock of its own: what the
JACO-2's main board does between the Kinova API and the actuators.

Every bus cycle (2 ms) the node asks :meth:`RobotCore.targets` for the actuators' targets, exchanges them with the
hardware, and hands the reading to :meth:`RobotCore.observe`. When exchanges fail for longer than the actuators
go on along their last targets (``EXTRAPOLATED_CYCLES``), the node stops the reference where the targets are
(:meth:`RobotCore.stop`); one lost exchange is a missed cycle.
Every fifth cycle (10 ms) :meth:`RobotCore.dsp_cycle` applies the latest robot command and runs the DSP
(:class:`~services.robot.dsp.KinovaDSP`), whose joint velocities the next cycles integrate into targets.

The reference advances by exactly one cycle of the DSP's velocities per exchange, never by the time that passed:
a host that is late loses that motion (and counts it) instead of sending a bigger step that the arm would follow
faster than commanded. Across a DSP cycle the velocity ramps linearly from the last cycle's to the new one (as the
DSP's 100 Hz planner is interpolated into the joints' faster loop), so the targets accelerate exactly as the DSP
decided, with no kink for the actuators to overshoot.

The hand's fingers, where the hardware has them, are a second group on the same cycle
(:class:`~services.robot.fingers.FingerGroup`): a robot command's finger part sets their targets, and nothing else
moves them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from protocol.messages import FingerCommand, RobotCommand
from services.robot.dsp import CommandRefused, KinovaDSP
from services.robot.fingers import FingerGroup, FingerRefused
from services.robot.hardware import DEFAULT_TIMING, BusTiming, JointReading, JointTargets
from services.runtime.arrays import clip, constant

#: a reference further than this from the measured angle is pulled back (no wind-up against a torque limit or a
#: joint the arm cannot move)
MAX_TRACKING_ERROR = math.radians(3.0)
_TRACKING_BOUNDS = constant(-MAX_TRACKING_ERROR), constant(MAX_TRACKING_ERROR)
#: the joints keep the DSP's last velocities at most this many DSP periods without a new DSP cycle; then they hold
#: where they are: a DSP that stopped deciding must not leave the arm moving
MAX_DSP_PERIODS_WITHOUT_DSP = 2


@dataclass(frozen=True)
class Refusal:
    #: what refused it: ``convention`` (the DSP cannot read the command's frame or angular convention),
    #: ``torque_control`` (low-level control owns the joints) or ``fingers`` (its finger part does not fit the hand)
    kind: str
    reason: str


@dataclass(frozen=True)
class Plan:
    """What a DSP cycle decided: the joints' velocities, and the finger command it took (None: the fingers keep
    their targets)."""

    dq_ref: np.ndarray
    fingers: Optional[FingerCommand] = None


class RobotCore:
    def __init__(self, dsp: KinovaDSP, reading: JointReading, timing: BusTiming = DEFAULT_TIMING) -> None:
        self.dsp = dsp
        #: the bus's cycle: the DSP's velocities are ramped over its ``cycles_per_dsp`` exchanges
        self.timing = timing
        self.cycle_s = timing.period_s
        self._cycles_per_dsp = timing.cycles_per_dsp
        self._max_cycles_without_dsp = MAX_DSP_PERIODS_WITHOUT_DSP * timing.cycles_per_dsp
        self._cycle = constant(self.cycle_s)  # (an operand every bus cycle: services.runtime.arrays)
        self.reading = reading
        #: the arm's joints (as many as the readings carry)
        self.n_joints = len(reading.q)
        self.q_ref = reading.q.copy()
        #: the DSP's joint velocities, and the ramp toward them: from ``_dq_from``, over the ``_step``-th
        #: exchange since the DSP cycle
        self.dq_ref = np.zeros(self.n_joints)
        self._dq_from = np.zeros(self.n_joints)
        self._step = self._cycles_per_dsp
        #: bus cycles in which the DSP was too late and the joints were held (see MAX_DSP_PERIODS_WITHOUT_DSP)
        self.dsp_stale_cycles = 0
        #: the DSP's trajectories are to be erased at its next cycle (torque control took the joints)
        self._erase_requested = False
        #: the joints were held since the DSP's last plan: its next cycle starts from rest
        self._held = False
        #: low-level torque control owns the joints: targets carry ``torques``, robot commands are refused
        self.torque_mode = False
        self.torques = np.zeros(self.n_joints)
        #: the hand's fingers (None: the hardware reports none)
        hand = None if reading.fingers is None else dsp.arm.hand
        self.fingers = None if hand is None else FingerGroup(hand, reading.fingers, timing)
        #: a finger command from the Kinova API (a trajectory point's hand part), for the next DSP cycle
        self._queued_fingers: Optional[FingerCommand] = None

    # ------------------------------------------------------------------ the bus cycle
    def targets(self) -> JointTargets:
        """This cycle's targets: one cycle further along the DSP's joint velocities (position mode), or the
        low-level torques with the measured angles as the actuators' safety reference (torque mode)."""
        q_meas = self.reading.q
        fingers = None if self.fingers is None else self.fingers.targets()
        if self.torque_mode:
            return JointTargets(q=q_meas.copy(), torques=self.torques.copy(), fingers=fingers)
        self._step += 1
        if self._step > self._max_cycles_without_dsp and (self.dq_ref.any() or self._dq_from.any()):
            self.stop()
            self.dsp_stale_cycles += 1
        fraction = min(1.0, (self._step - 0.5) / self._cycles_per_dsp)  # the ramp's mean over this exchange
        q_ref = self.q_ref + (self._dq_from + (self.dq_ref - self._dq_from) * fraction) * self._cycle
        self.q_ref = q_meas + clip(q_ref - q_meas, _TRACKING_BOUNDS[0], _TRACKING_BOUNDS[1])
        return JointTargets(q=self.q_ref.copy(), fingers=fingers)

    def observe(self, reading: JointReading) -> None:
        self.reading = reading
        if self.fingers is not None and reading.fingers is not None:
            self.fingers.observe(reading.fingers)
        if self.torque_mode and not np.any(reading.mode == 1):
            # the actuators dropped back to position mode (their 250 ms torque timeout): follow them
            self.torque_mode = False
            self.hold()

    def stop(self) -> None:
        """Stop where the targets are (a failed exchange, a DSP too late): the reference stays, so the arm is not
        pulled back to a reading that may be a few cycles old."""
        self.dq_ref = np.zeros(self.n_joints)
        self._dq_from = np.zeros(self.n_joints)
        self._step = self._cycles_per_dsp
        self._held = True

    def hold(self) -> None:
        """Stop where the arm is measured to be (a mode switch: the targets held no meaning in torque mode)."""
        self.q_ref = self.reading.q.copy()
        self.stop()

    # ------------------------------------------------------------------ the DSP cycle
    def dsp_cycle(self, command: Optional[RobotCommand]) -> Optional[Refusal]:
        """Apply ``command`` (if any) and run the DSP on the latest reading; why the command was refused, if it
        was (the arm then behaves as if it had not come)."""
        plan, refusal = self.dsp_plan(command, self.reading)
        self.take_plan(plan)
        return refusal

    def dsp_plan(self, command: Optional[RobotCommand], reading: JointReading) -> tuple[Plan, Optional[Refusal]]:
        """The DSP's part of a cycle (it touches only the DSP): apply ``command``, run the DSP on ``reading``;
        what it decided, and why the command was refused, if it was (its finger part too: a command is taken or
        refused whole)."""
        refusal = None
        fingers, self._queued_fingers = self._queued_fingers, None
        if self._held:
            self._held = False
            self.dsp.joints_held()
        if self._erase_requested:
            self._erase_requested = False
            self.dsp.erase_all_trajectories()
        if command is not None:
            if self.torque_mode:
                refusal = Refusal("torque_control", "low-level torque control is active")
            else:
                refusal = self._finger_refusal(command)
                if refusal is None:
                    try:
                        self.dsp.submit(command)
                        fingers = command.fingers or fingers
                    except CommandRefused as exc:
                        refusal = Refusal("convention", str(exc))
        return Plan(np.asarray(self.dsp.cycle(reading), dtype=float), fingers), refusal

    def queue_fingers(self, command: FingerCommand) -> Optional[str]:
        """A finger command from the Kinova API, taken at the next DSP cycle (the thread that runs the DSP calls
        this between its cycles); why not, if it does not fit the hand. A robot command's own finger part in that
        cycle is newer and wins."""
        problem = self._finger_problem(command)
        if problem is None:
            self._queued_fingers = command
        return problem

    def _finger_refusal(self, command: RobotCommand) -> Optional[Refusal]:
        problem = None if command.fingers is None else self._finger_problem(command.fingers)
        return None if problem is None else Refusal("fingers", problem)

    def _finger_problem(self, command: FingerCommand) -> Optional[str]:
        """Why the hand cannot take ``command``, or None."""
        if self.fingers is None:
            return "a finger command, and this arm reports no fingers"
        try:
            self.fingers.check(command)
        except FingerRefused as exc:
            return str(exc)
        return None

    def take_plan(self, plan: Plan) -> None:
        """The DSP's new joint velocities (the next bus cycles ramp to them) and finger command."""
        if plan.fingers is not None and self.fingers is not None:
            self.fingers.submit(plan.fingers)
        if self.torque_mode:
            return
        fraction = min(1.0, self._step / self._cycles_per_dsp)  # where the last ramp got to
        self._dq_from = self._dq_from + (self.dq_ref - self._dq_from) * fraction
        self.dq_ref = plan.dq_ref
        self._step = 0

    # ------------------------------------------------------------------ low-level torque control
    def enter_torque_mode(self) -> None:
        """Low-level control takes the joints; the DSP forgets its trajectories at its next cycle (it may be
        computing one now, in another thread)."""
        self.torques = np.zeros(self.n_joints)
        self.torque_mode = True
        self._erase_requested = True

    def leave_torque_mode(self) -> None:
        self.torque_mode = False
        self.hold()
