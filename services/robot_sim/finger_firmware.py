"""The KG-3's finger actuators, emulated on the MuJoCo fingers (services/robot_sim/scene.py: ``_add_hand``): what
each does with the targets its bus brings, one bus cycle (2 ms) at a time on the arm's timeline, beside the arm's
actuators (:mod:`services.robot_sim.firmware`) and on the same boundaries.

Per finger: a target received during a cycle is taken at the next boundary (the newest wins); the finger's reference
moves toward it at the finger's top speed (the hand's full travel in its closing time) and holds there; a position
servo on the hinge follows the reference, its force limited to the finger's share of the grip, so a finger blocked
on an object squeezes it with that force for as long as its target lies beyond the object. No target keeps the last
one: nothing but a new target moves a finger. Each finger reports its angle, its rate and a current proportional to
the force its motor gives (the hand file's ``full_force_current_a`` at its full force).

The KG-3's fingers are driven through a worm gear and lead screw, which an external force cannot turn: a finger
opens only when its motor opens it. Emulated as a ratchet on each hinge (:data:`FINGER_HOLDING_FACTOR`): a stiff,
damped spring holds the finger from being pushed open past the most closed position it reached (never beyond where
its motor is), less the gear's backlash. Without it, two fingers' force on an object pushed the third (the thumb,
alone on its side) open, and the object slid out of the hand.

Where it departs from the real hand (whose firmware is not public): the reference's constant speed, the servo's
stiffness, the gear's holding torque and its backlash are mfvs's choices.
"""
from __future__ import annotations

import math
from typing import Optional

import mujoco
import numpy as np

from services.model.arm import ArmDescription
from services.robot.hardware import FingerReading
from services.robot_sim import scene as scene_mod

#: the worm gear's holding torque, as a multiple of the motor's full torque (mfvs's choice: a self-locking gear holds
#: well beyond what drives it; above this an external force does push the finger open, as a gear would slip)
FINGER_HOLDING_FACTOR = 4.0
#: the gear's backlash (rad): how far a finger gives before the gear holds it (mfvs's choice, half a degree: a small
#: worm gear's play). A finger resting open sags by less than this against its stop, so the gear leaves it alone
GEAR_BACKLASH = math.radians(0.5)


class FingerFirmware:
    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, arm: ArmDescription) -> None:
        if arm.hand is None:
            raise ValueError(f"the {arm.name} carries no hand")
        self.hand = arm.hand
        self.model, self.data = model, data
        names = scene_mod.finger_names(arm)
        self._qpos = np.array([model.joint(joint).qposadr[0] for _, joint, _ in names])
        self._dof = np.array([model.joint(joint).dofadr[0] for _, joint, _ in names])
        self._actuators = np.array([model.actuator(motor).id for _, _, motor in names])
        self.full_force_nm = scene_mod.finger_torque_limit_nm(arm)
        #: how far a reference moves in one physics step (rad)
        self._step = self.hand.max_speed * model.opt.timestep
        n = self.hand.n_fingers
        #: the target taken (rad), where the reference is now (rad), and the newest target of the cycle not yet taken
        self.target = np.zeros(n)
        self.reference = np.zeros(n)
        self.pending: Optional[np.ndarray] = None
        #: the gear's ratchet: the most closed each finger has been since its motor last opened it (rad), its
        #: stiffness (the servo's) and its torque limit
        self.locked = np.zeros(n)
        self._lock_stiffness = self.full_force_nm / scene_mod.FINGER_FULL_FORCE_WITHIN
        #: ... damped as the servo is (its kv: MuJoCo's position actuator keeps −kv as its third bias parameter), or
        #: the one-sided spring bounces a blocked finger
        self._lock_damping = -model.actuator_biasprm[self._actuators, 2]
        self._holding_nm = FINGER_HOLDING_FACTOR * self.full_force_nm
        self.hold_all()

    @property
    def position(self) -> np.ndarray:
        return self.data.qpos[self._qpos].copy()

    def hold_all(self) -> None:
        """Every finger holding where it is (at start and after a reset)."""
        self.target = self.hand.clip(self.position)
        self.reference = self.target.copy()
        self.locked = self.position
        self.pending = None
        self.data.ctrl[self._actuators] = self.reference
        self.data.qfrc_applied[self._dof] = 0.0

    def command(self, targets_rad) -> None:
        """The fingers' targets (rad, 0 open), taken at the next boundary."""
        self.pending = self.hand.clip(np.asarray(targets_rad, dtype=float))

    def command_one(self, finger: int, target_rad: float) -> None:
        """One finger's target (a bus message to its actuator), taken at the next boundary with the others'."""
        pending = self.target.copy() if self.pending is None else self.pending.copy()
        pending[finger] = float(self.hand.clip(target_rad))
        self.pending = pending

    def begin_cycle(self) -> None:
        """A cycle boundary: the newest target of the cycle that ended is taken."""
        if self.pending is not None:
            self.target, self.pending = self.pending, None

    def apply(self) -> None:
        """The reference one physics step further toward the targets, as the servos' setpoints (every step)."""
        step = self._step
        self.reference = self.reference + np.clip(self.target - self.reference, -step, step)
        self.data.ctrl[self._actuators] = self.reference
        self.data.qfrc_applied[self._dof] = self._gear_torque(self.position, self.data.qvel[self._dof])

    def _gear_torque(self, q: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """The worm gear's torque on each hinge (closing positive): none while the finger closes or its motor opens
        it; against being pushed open (below where it reached and its motor is) past the backlash, a damped spring back to the most closed position, within the
        holding torque."""
        # the gear holds what the finger reached, never beyond where its motor is (the reference): opening, the motor
        # takes the hold down with it
        self.locked = np.minimum(np.maximum(self.locked, q), self.reference)
        give = self.locked - GEAR_BACKLASH - q
        pushed_open = give > 0.0
        torque = self._lock_stiffness * give - self._lock_damping * dq
        return np.where(pushed_open, np.clip(torque, 0.0, self._holding_nm), 0.0)

    def force_fraction(self) -> np.ndarray:
        """How much of its full force each finger's motor gives now (signed: positive closing)."""
        return self.data.actuator_force[self._actuators] / self.full_force_nm

    def reading(self) -> FingerReading:
        return FingerReading(position=self.position, velocity=self.data.qvel[self._dof].copy(),
                             current_a=self.force_fraction() * self.hand.full_force_current_a)
