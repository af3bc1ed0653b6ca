"""The hand's fingers in the robot node: a second actuator group beside the arm's joints, on the same bus cycle, never
joints of the arm (its chain, its DSP and every joint vector stay the arm's).

The rule is a finger keeps its target until a finger command changes it. A robot command without a finger part, a
stop, an emergency stop, a refused or stale command, a lost safety service: none of them moves a finger, so a cup in
the hand stays squeezed whatever happens to the arm's commands (Kinova's own ``UserPosition::InitStruct()`` sets
POSITION_MODE with the fingers at 0, which opens the hand: kinova-ros clears the whole point after it for that
reason). Only a finger command opens the hand.

A position command sets the targets (clipped to the travel); the finger actuators move toward them at their own top
speed (the emulated firmware's, the real hand's). A velocity command moves the targets at its rates for one DSP
period (10 ms), as the arm's velocity commands last one cycle: a stream that stops leaves the targets where they got.
Closing on an object by velocity, a target would run on past the finger blocked on it; it is kept within
:data:`MAX_VELOCITY_LEAD` of where the finger is, so that the finger goes on squeezing when the stream stops and
opens as soon as it is asked, without first unwinding a target far inside the object.
"""
from __future__ import annotations

import math

import numpy as np

from protocol.messages import FingerCommand, FingerMode
from services.model.arm import HandDescription
from services.robot.hardware import BusTiming, FingerReading

#: how far a velocity command's targets may run ahead of (or behind) where each finger is (rad). mfvs's choice: an
#: eighth of the KG-3's 80 deg travel, more than a finger servo needs to reach its force limit (the emulated
#: firmware's saturates within a few degrees), so that a finger blocked on an object squeezes with its full force
MAX_VELOCITY_LEAD = math.radians(10.0)


class FingerRefused(ValueError):
    """A finger command the hand cannot take (the number of fingers differs from the hand's)."""


class FingerGroup:
    """The fingers' targets, one bus cycle at a time (the robot node's :class:`~services.robot.core.RobotCore`
    holds one when its hardware reports fingers)."""

    def __init__(self, hand: HandDescription, reading: FingerReading, timing: BusTiming) -> None:
        self.hand = hand
        self.cycle_s = timing.period_s
        self._cycles_per_dsp = timing.cycles_per_dsp
        #: at start the fingers hold where they are
        self.target = hand.clip(reading.position)
        self.reading = reading
        self._rate = np.zeros(hand.n_fingers)
        self._rate_cycles = 0

    def check(self, command: FingerCommand) -> None:
        """Raises :class:`FingerRefused` when ``command`` does not fit the hand."""
        if len(command.values) != self.hand.n_fingers:
            raise FingerRefused(f"this hand has {self.hand.n_fingers} fingers, the command {len(command.values)} "
                                "finger values")

    def submit(self, command: FingerCommand) -> None:
        """Take a finger command (at a DSP cycle), already :meth:`check`-ed."""
        values = np.asarray(command.values, dtype=float)
        if command.mode is FingerMode.POSITION:
            self.target = self.hand.clip(values)
            self._rate_cycles = 0
        else:
            top = self.hand.max_speed
            self._rate = np.clip(values, -top, top)
            self._rate_cycles = self._cycles_per_dsp

    def observe(self, reading: FingerReading) -> None:
        self.reading = reading

    def targets(self) -> np.ndarray:
        """This bus cycle's targets (rad): a velocity command's rates advance them for one DSP period."""
        if self._rate_cycles > 0:
            self._rate_cycles -= 1
            position = self.reading.position
            ahead = np.clip(self.target + self._rate * self.cycle_s, position - MAX_VELOCITY_LEAD,
                            position + MAX_VELOCITY_LEAD)
            self.target = self.hand.clip(ahead)  # a new array: the state publisher reads it from another thread
        return self.target.copy()
