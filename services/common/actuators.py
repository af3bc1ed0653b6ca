"""The joint-level actuator interface the DSP drives (in the spirit of ros2_control's hardware interface):
``read()`` the measured joint state, ``write()`` joint velocity references for the next DSP cycle.

:class:`SimActuators` implements it on a MuJoCo model: each physics step a joint servo (what the actuators' own
position loops do) tracks the integrated references with a PD law plus the model's bias torques, clamped to the
actuators' torque limits. The RS-485 actuator level slots in underneath the same interface.
"""
from __future__ import annotations

from typing import Protocol

import mujoco
import numpy as np

from services.common import jaco2
from services.common.dsp import JointState


class ActuatorInterface(Protocol):
    def read(self) -> JointState: ...

    def write(self, dq_ref: np.ndarray) -> None: ...


# Servo gains per joint: stiff enough to follow the DSP's references within a cycle, well damped at 1 kHz.
KP = np.array([400.0, 400.0, 400.0, 300.0, 120.0, 120.0, 120.0])
KD = np.array([40.0, 40.0, 40.0, 30.0, 8.0, 8.0, 8.0])
#: a reference further than this from the measured angle is pulled back (no wind-up against a torque limit)
MAX_TRACKING_ERROR = np.radians(3.0)


class SimActuators:
    """Velocity-reference servos on the seven MuJoCo joints (the model's first seven dofs and actuators).

    Within a DSP cycle the velocity reference ramps linearly from the previous cycle's value to the new one, and
    the servo adds the model's inertia times that ramp, its bias forces and its joint friction as feedforward, so
    the joints follow the DSP's profile without lag (and do not coast after a stop).
    """

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, cycle_s: float = 0.01) -> None:
        self.model = model
        self.data = data
        self.n = jaco2.N_JOINTS
        if model.nv != self.n:
            raise ValueError(f"the model must have exactly {self.n} dofs, it has {model.nv}")
        self.cycle_s = cycle_s
        self.torque_limit = model.actuator_ctrlrange[: self.n, 1].copy()
        self.damping = model.dof_damping[: self.n].copy()
        self.saturated = np.zeros(self.n, dtype=bool)
        self._inertial = np.zeros(self.n)
        #: low-level torque control (services.common.lowlevel): the joints get ``torques`` plus the model's
        #: bias torques (gravity compensation) instead of the servo; velocity references are ignored meanwhile
        self.torque_mode = False
        self.torques = np.zeros(self.n)
        self.hold()

    def read(self) -> JointState:
        d = self.data
        return JointState(q=d.qpos[: self.n].copy(), dq=d.qvel[: self.n].copy(),
                          tau=d.actuator_force[: self.n].copy(), stamp_ns=int(round(d.time * 1e9)))

    def write(self, dq_ref: np.ndarray) -> None:
        dq_ref = np.asarray(dq_ref, dtype=float)
        if dq_ref.shape != (self.n,) or not np.all(np.isfinite(dq_ref)):
            raise ValueError("joint velocity references must be 7 finite numbers")
        self._from = self.dq_ref.copy()
        self._to = dq_ref.copy()
        self._elapsed = 0.0

    def hold(self) -> None:
        """Servo on the current angles with zero velocity (used at start and after a reset)."""
        self.q_ref = self.data.qpos[: self.n].copy()
        self.dq_ref = np.zeros(self.n)
        self._from = np.zeros(self.n)
        self._to = np.zeros(self.n)
        self._elapsed = self.cycle_s

    def enter_torque_mode(self) -> None:
        self.torques = np.zeros(self.n)
        self.torque_mode = True

    def leave_torque_mode(self) -> None:
        self.torque_mode = False
        self.hold()

    def set_torques(self, torques: np.ndarray) -> None:
        torques = np.asarray(torques, dtype=float)
        if torques.shape != (self.n,) or not np.all(np.isfinite(torques)):
            raise ValueError("joint torques must be 7 finite numbers")
        self.torques = torques.copy()

    def apply(self, dt: float) -> None:
        """One physics step of the joint servos: advance the reference and set the motor torques."""
        d = self.data
        q, dq = d.qpos[: self.n], d.qvel[: self.n]
        if self.torque_mode:
            tau = d.qfrc_bias[: self.n] + self.torques
            self.saturated = np.abs(tau) > self.torque_limit
            d.ctrl[: self.n] = np.clip(tau, -self.torque_limit, self.torque_limit)
            return
        if self._elapsed < self.cycle_s:
            ddq_ref = (self._to - self._from) / self.cycle_s
            self._elapsed += dt
        else:
            ddq_ref = np.zeros(self.n)
        self.dq_ref = self._from + (self._to - self._from) * min(1.0, self._elapsed / self.cycle_s)
        self.q_ref = self.q_ref + self.dq_ref * dt
        self.q_ref = q + np.clip(self.q_ref - q, -MAX_TRACKING_ERROR, MAX_TRACKING_ERROR)
        mujoco.mj_mulM(self.model, d, self._inertial, ddq_ref)
        tau = (self._inertial + d.qfrc_bias[: self.n] + self.damping * self.dq_ref
               + KP * (self.q_ref - q) + KD * (self.dq_ref - dq))
        self.saturated = np.abs(tau) > self.torque_limit
        d.ctrl[: self.n] = np.clip(tau, -self.torque_limit, self.torque_limit)
