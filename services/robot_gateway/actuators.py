"""The DSP's joint-level actuator interface over the RS-485 link: the same ``read()``/``write()`` the simulator's
actuators offer, so :class:`services.common.dsp.KinovaDSP` runs unchanged in the gateway.

A 500 Hz loop (:meth:`LinkActuators.cycle`, called every 2 ms) integrates the DSP's joint velocity references into
position targets and sends them to the actuators (position mode, 0x14), reading their state from the replies.
A bus failure (:class:`~services.robot_gateway.link.LinkError`) is counted and the targets are frozen at the last
measured angles, so the arm holds still rather than follow a stale reference; the DSP sees ``faults``.
"""
from __future__ import annotations

import math
import threading
import time

import numpy as np

from services.common import jaco2
from services.common.dsp import JointState
from services.robot_gateway.link import ActuatorLink, ActuatorReading, LinkError

#: the reference advances by the real time since the last exchange, up to this: the DSP's velocity holds through
#: a host loop that stalled for a few cycles (a busy machine), not through one that stopped
MAX_STALL_S = 0.05
#: a reference further than this from the measured angle is pulled back (as the simulator's servos do)
MAX_TRACKING_ERROR = math.radians(3.0)


class LinkActuators:
    def __init__(self, link: ActuatorLink, cycle_s: float = 0.002) -> None:
        self.link = link
        self.cycle_s = cycle_s
        self.lock = threading.Lock()
        self.faults: list[str] = []
        self.bus_errors = 0
        positions = link.positions_deg()
        self.q_ref = jaco2.physical_deg_to_model(positions)
        self.dq_ref = np.zeros(jaco2.N_JOINTS)
        self.state = JointState(q=self.q_ref.copy(), dq=np.zeros(jaco2.N_JOINTS))
        self.reading: ActuatorReading | None = None
        self._last_cycle: float | None = None
        #: low-level torque control: the actuators are in torque mode and get ``torques_nm`` (actuator sign)
        self.torque_mode = False
        self.torques_nm = np.zeros(jaco2.N_JOINTS)

    # ---- the interface the DSP uses
    def read(self) -> JointState:
        with self.lock:
            return JointState(q=self.state.q.copy(), dq=self.state.dq.copy(), tau=self.state.tau.copy(),
                              stamp_ns=self.state.stamp_ns)

    def write(self, dq_ref: np.ndarray) -> None:
        dq_ref = np.asarray(dq_ref, dtype=float)
        if dq_ref.shape != (jaco2.N_JOINTS,) or not np.all(np.isfinite(dq_ref)):
            raise ValueError("joint velocity references must be 7 finite numbers")
        with self.lock:
            self.dq_ref = dq_ref.copy()

    # ---- the 500 Hz bus cycle
    def cycle(self, stamp_ns: int = 0) -> bool:
        """One exchange with the actuators; False (and the arm held) when the bus failed. The reference advances
        by the time since the last exchange (an exchange waits for the actuators' cycle, so the loop can run a
        little under its nominal 500 Hz)."""
        now = time.monotonic()
        dt = self.cycle_s if self._last_cycle is None else min(max(now - self._last_cycle, 0.0), MAX_STALL_S)
        self._last_cycle = now
        with self.lock:
            q_meas = self.state.q
            if self.torque_mode:  # the position field is the safety reference: where the joint is
                targets, torques = jaco2.model_to_physical_deg(q_meas), self.torques_nm.copy()
            else:
                self.q_ref = self.q_ref + self.dq_ref * dt
                self.q_ref = q_meas + np.clip(self.q_ref - q_meas, -MAX_TRACKING_ERROR, MAX_TRACKING_ERROR)
                targets, torques = jaco2.model_to_physical_deg(self.q_ref), None
        try:
            reading = self.link.command(targets, torques)
        except LinkError as exc:
            with self.lock:
                self.bus_errors += 1
                self.q_ref = self.state.q.copy()  # hold where the arm was last seen
                self.dq_ref = np.zeros(jaco2.N_JOINTS)
                self.faults = [f"bus: {exc}"]
            return False
        with self.lock:
            self.reading = reading
            self.state = JointState(q=jaco2.physical_deg_to_model(reading.position_deg),
                                    dq=jaco2.physical_rate_to_model(reading.velocity_dps),
                                    tau=jaco2.SIGN * reading.torque_nm, stamp_ns=stamp_ns)
            self.faults = [f"actuator {i + 1}: fault {int(code)}" for i, code in enumerate(reading.fault) if code]
            if self.torque_mode and not np.any(reading.mode == 1):
                # the actuators dropped back to position mode (their 250 ms torque timeout): follow them
                self.torque_mode = False
                self.q_ref, self.dq_ref = self.state.q.copy(), np.zeros(jaco2.N_JOINTS)
        return True

    def enter_torque_mode(self) -> None:
        """The torque-mode handshake (validation against the model's gravity torques, then the switch)."""
        from services.robot_gateway.link import expected_torques_physical

        self.link.switch_to_torque(expected_torques_physical(self.read().q))
        with self.lock:
            self.torques_nm = np.zeros(jaco2.N_JOINTS)
            self.torque_mode = True

    def set_torques(self, torques: np.ndarray) -> None:
        """Extra joint torques (model sign, N·m) for the next exchanges in torque mode."""
        with self.lock:
            self.torques_nm = jaco2.SIGN * np.asarray(torques, dtype=float)

    def leave_torque_mode(self) -> None:
        self.link.switch_to_position()
        with self.lock:
            self.torque_mode = False
            self.q_ref, self.dq_ref = self.state.q.copy(), np.zeros(jaco2.N_JOINTS)
