"""Low-level torque control behind the robot's zenoh API (``robot/lowlevel/command`` in, ``robot/lowlevel/state``
out), for controllers that do their own dynamics. robot_sim and robot_gateway share it, so the semantics do not
depend on what drives the arm:

* the first fresh :class:`~protocol.messages.TorqueCommand` switches the joints to torque mode (the robot erases
  the DSP's trajectories and refuses robot commands while it lasts);
* every low-level cycle applies the latest command while it is fresh (``watchdog_s``, about two cycles); an older
  one is replaced by the arm's gravity and no other torque, so the arm holds: the actuators' own compensation
  where they have one (switched back on), else the host's model gravity at the measured angles; never zero torque
  on actuators that add no gravity;
* after ``release_s`` without commands the joints return to position mode, holding where they are, under the DSP
  (the real actuators' own torque-inactivity timeout is the same 250 ms);
* gravity (:func:`model_gravity_factor`): the arm is to have its gravity compensated unless Table 5.1's gravity
  setup switched it off (optimal-Z parameters all 0), and a client's torque comes on top of it
  (``gravity_compensation: true``) or includes it (``false``). Actuators that compensate themselves (Kinova's DSP,
  the simulator's: ``RobotHardware.actuators_compensate_gravity``) are told to stop where the arm is to have none,
  and the model's gravity is taken out of what they add that the arm is not to have. Actuators that add none (an
  RS-485 bus: the base's DSP is bypassed, kinova.md; abr/abr_jaco2 sends host-computed gravity) get the model's
  gravity ĝ(q) added where the arm is to have it, so a client on top of it faces what the model misses of the
  arm's gravity (the emulated actuators' own compensation misses nothing); with the arm's gravity off, a client
  faces the arm's true gravity wherever the actuators do not keep adding theirs;
* the torque-mode setup of Table 5.1 (:mod:`services.robot.torque_setup`) applies here, for every robot alike: the
  actuators' damping is added to each command, and a joint faster than the safety factor allows returns the arm to
  trajectory control (position mode, holding where it is); torque commands are then refused until the client has
  been quiet for ``release_s``, so a client starts torque control again only on purpose.

Time is the caller's monotonic wall clock: low-level control runs in realtime only.
"""
from __future__ import annotations

import copy
import enum
import threading
from typing import Callable, Optional, Protocol

import numpy as np

from protocol.messages import TorqueCommand
from services.robot.torque_setup import (TorqueSetup, arm_compensates_gravity, damping_torque, over_safety_speed,
                                         safety_speed_threshold)
from services.runtime.config import ConfigStruct


def model_gravity_factor(arm_gravity: bool, client_on_top: bool, actuators_add_gravity: bool) -> int:
    """How many times the model's gravity torque ĝ(q) is added to a client's torque before it is sent: the gravity
    the arm is to have from the robot (``arm_gravity``, Table 5.1's setup, for a client whose torque comes on top of
    it) less the gravity the actuators add themselves. +1: the host stands in for the compensation the actuators
    do not have (an RS-485 bus, where the base's DSP is bypassed); −1: the actuators add gravity the arm is not to
    have (a client whose torque includes it; Table 5.1's gravity off on actuators that cannot stop adding it),
    taken out as far as the model knows it; 0: what the actuators add is what the arm is to have."""
    return int(arm_gravity and client_on_top) - int(actuators_add_gravity)


class LowLevelConfig(ConfigStruct):
    #: a torque command older than this is not applied (the arm's gravity alone: the arm holds)
    watchdog_s: float = 0.005
    #: after this long without torque commands the joints return to position mode under the DSP
    release_s: float = 0.25

    def __post_init__(self) -> None:
        if not (0.0 < self.watchdog_s < self.release_s):
            raise ValueError("low-level timing needs 0 < watchdog_s < release_s")


class TorqueJoints(Protocol):
    """What low-level control needs from the joints (the simulator's servos, or the actuators on the bus)."""

    torque_mode: bool
    #: whether the actuators add the arm's gravity themselves in torque mode (services.robot.hardware)
    actuators_compensate_gravity: bool

    def enter_torque_mode(self) -> None: ...

    def leave_torque_mode(self) -> None: ...

    def set_torques(self, torques: np.ndarray) -> None:
        """The joint torques sent (model sign, N·m), on top of whatever gravity the actuators add themselves."""

    def set_gravity_compensation(self, on: bool) -> bool:
        """The actuators' own gravity compensation on or off (where they have one); False where they cannot switch
        it."""


class Outcome(enum.Enum):
    IDLE = "idle"            # no torque control
    ENGAGED = "engaged"      # switched to torque mode this cycle (and applied the command)
    APPLIED = "applied"
    WATCHDOG = "watchdog"    # the command is stale: the arm's gravity alone holds it
    RELEASED = "released"    # back to position mode
    REFUSED = "refused"      # the joints refused torque mode (detail says why)
    SAFETY_STOP = "safety_stop"  # a joint over the safety factor's speed: back to trajectory control


class LowLevelControl:
    def __init__(self, config: LowLevelConfig, joints: TorqueJoints,
                 gravity: Callable[[np.ndarray], np.ndarray], setup: TorqueSetup) -> None:
        self.config = config
        self.joints = joints
        self.gravity = gravity
        #: Table 5.1's setup (the Kinova API changes it between cycles, in the same thread as :meth:`step`)
        self.setup = setup
        self._latest: Optional[tuple[TorqueCommand, float]] = None
        #: when the safety factor stopped torque control (monotonic), until the client has been quiet
        self._stopped_at: Optional[float] = None
        self._lock = threading.Lock()

    @property
    def active(self) -> bool:
        return self.joints.torque_mode

    def receive(self, command: TorqueCommand, now_s: float) -> str:
        """A decoded, valid command (any thread). Returns why it is refused ('' when taken)."""
        with self._lock:
            if self._stopped_at is not None:
                last = self._latest[1] if self._latest is not None else self._stopped_at
                if now_s - last <= self.config.release_s:
                    self._latest = (None, now_s)  # the client is still sending: the quiet time starts again
                    return ("the torque safety factor returned the arm to trajectory control; stop sending for "
                            f"{self.config.release_s * 1e3:.0f} ms to start torque control again")
                self._stopped_at = None
            self._latest = (command, now_s)
        return ""

    def step(self, now_s: float, q: np.ndarray, dq: np.ndarray) -> tuple[Outcome, str]:
        """One low-level cycle (the loop thread): engage, apply, hold, release, or stop at the safety factor."""
        with self._lock:
            latest = self._latest
        if latest is None or latest[0] is None:
            return Outcome.IDLE, ""
        command, received = latest
        age = now_s - received
        # one setup for the whole cycle: the Kinova API's worker replaces its fields (each setter one field, a new
        # value, never changed in place) while this loop runs, and a cycle must not apply half of two setups
        setup = copy.copy(self.setup)
        if self.joints.torque_mode and age <= self.config.release_s:
            fast = over_safety_speed(setup, dq)
            if fast:
                return self._safety_stop(latest, fast, q, dq, setup)
        outcome = Outcome.APPLIED
        if not self.joints.torque_mode:
            if age > self.config.watchdog_s:  # an old command does not start torque control
                return Outcome.IDLE, ""
            try:
                self.joints.enter_torque_mode()
            except Exception as exc:
                self._forget(latest)
                try:  # some joints may have switched before the failure: put them all back
                    self.joints.leave_torque_mode()
                except Exception:
                    pass
                return Outcome.REFUSED, f"torque mode refused: {exc}"
            outcome = Outcome.ENGAGED
        if age > self.config.release_s:  # the client is gone: back to holding under the DSP
            try:
                self.joints.leave_torque_mode()
            except Exception as exc:  # still in torque mode: the arm's gravity holds it, and try again next cycle
                self._hold(q)
                return Outcome.REFUSED, f"leaving torque mode failed: {exc}"
            self._forget(latest)
            return Outcome.RELEASED, f"after {age * 1e3:.0f} ms without commands"
        if age > self.config.watchdog_s:
            self._hold(q)
            return Outcome.WATCHDOG, f"command {age * 1e3:.1f} ms old"
        torques = np.asarray(command.torques, dtype=float) + damping_torque(setup, dq)
        self.joints.set_torques(torques + self._gravity_to_add(
            q, arm_gravity=arm_compensates_gravity(setup), client_on_top=command.gravity_compensation))
        return outcome, ""

    def _hold(self, q: np.ndarray) -> None:
        """The hold on a stale command, or while the joints will not leave torque mode: the arm's gravity and no
        other torque, as a zero torque on top of its compensation, even where Table 5.1 switched that off (a real
        arm would leave it off and let the joints fall until its 250 ms fallback); a stalled client is not made to
        drop the arm. On actuators that add no gravity (an RS-485 bus) the host's model gravity at ``q`` holds it:
        zero torque there would let the arm fall."""
        self.joints.set_torques(self._gravity_to_add(q, arm_gravity=True, client_on_top=True))

    def _gravity_to_add(self, q: np.ndarray, arm_gravity: bool, client_on_top: bool) -> np.ndarray:
        """The model's gravity torque to add to a client's torque (:func:`model_gravity_factor`), after telling
        actuators that compensate themselves whether the arm is to have gravity."""
        factor = model_gravity_factor(arm_gravity, client_on_top, self._actuators_add_gravity(arm_gravity))
        return factor * np.asarray(self.gravity(q), dtype=float) if factor else np.zeros(len(q))

    def _actuators_add_gravity(self, arm_gravity: bool) -> bool:
        """Whether the actuators add the arm's gravity this cycle: those with their own compensation are switched
        to ``arm_gravity`` and keep adding it where they cannot be switched; those on an RS-485 bus never add it."""
        if not self.joints.actuators_compensate_gravity:
            return False
        switched = self.joints.set_gravity_compensation(arm_gravity)
        return arm_gravity or not switched

    def _safety_stop(self, latest, fast: list[int], q, dq, setup: TorqueSetup) -> tuple[Outcome, str]:
        threshold = np.degrees(safety_speed_threshold(setup))
        detail = ", ".join(f"joint {i + 1} at {abs(np.degrees(dq[i])):.0f}°/s (threshold {threshold[i]:.0f}°/s)"
                           for i in fast)
        with self._lock:  # a command that came meanwhile is refused too: the client has not paused
            self._stopped_at = latest[1]
            self._latest = (None, self._latest[1] if self._latest is not None else latest[1])
        try:
            self.joints.leave_torque_mode()
        except Exception as exc:  # still in torque mode: the arm's gravity holds it, and the next cycle tries again
            self._hold(q)
            return Outcome.REFUSED, f"the safety factor's stop failed to leave torque mode: {exc}"
        return Outcome.SAFETY_STOP, detail

    def _forget(self, latest) -> None:
        with self._lock:
            if self._latest is latest:
                self._latest = None
