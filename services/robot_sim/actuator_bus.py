"""The JACO-2's actuators as seen on their RS-485 bus: each answers the low-level messages of
``protocol.rs485`` at 500 Hz and drives its MuJoCo joint, in position or torque mode.

Per actuator (host 0x00, actuators at ``ACTUATOR_ADDRESSES``):

* ``GET_ACTUAL_POSITION`` (0x01) → ``SEND_ACTUAL_POSITION`` (0x02), float[0] = position (deg, physical).
* ``POSITION_AND_TORQUE_COMMAND`` (0x14) → one 0x15, 0x16 and 0x17 reply each. In position mode float[0] is the
  position target; in torque mode float[0] is the host's idea of the current position (a safety reference: more
  than ``reference_tolerance_deg`` off is a RELATIVE_POSITION fault) and float[2] the torque (N·m), clamped to the
  actuator's limit (a TORQUE fault is reported when it had to be). 0x17 carries float [position target (deg),
  torque command (N·m), mode (0 position / 1 torque), fault code] (this layout is mfvs's; the public sources do
  not give one).
* ``GET_TORQUE_VALIDATION_REQUEST`` (0x201), float[0] = the torque the host's model expects at the current
  position → ``SEND_TORQUE_VALIDATION`` (0x202), uint32[0] = 1 when it matches the measured torque within
  tolerance. Switching to torque mode needs a validation of the last second.
* ``SWITCH_CONTROL_MODE_REQUEST`` (0x203), uint32[0] = 0 position / 1 torque → ``SWITCH_CONTROL_MODE_REPLY``
  (0x204): 1 position OK, 257 torque OK, 0 refused.
* ``CLEAR_FAULT_FLAG`` (0x33), ``START_SERVO``/``STOP_SERVO`` → ``ACK`` (0x3F); other commands → ``NACK``.
* Faults (limits, torque, reference mismatch) are reported with ``REPORT_ERROR`` (0x30) once, latch, and make
  the actuator hold its position until ``CLEAR_FAULT_FLAG``.
* Torque mode falls back to holding the position when no torque command came for ``torque_timeout_s`` (250 ms).
* Gravity compensation: in torque mode the actuator adds the model's gravity torque (the real DSP's option).
* Position mode: the firmware's reference is a quadratic fitted to the last ~12 ms of targets (position, rate
  and acceleration, robust to a host whose commands jitter by a cycle), followed by a servo critically damped at
  ``SERVO_BANDWIDTH_RPS`` for the joint's current inertia, with inertia, friction and gravity feedforward: a
  4 Hz motion comes out within a few percent and a cycle of its target, on the shoulder as on the wrist.
"""
from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

import msgspec
import mujoco
import numpy as np

from protocol import rs485 as r
from services.common import jaco2
from services.common.config import ConfigStruct
from services.common.dsp import JointState
from services.common.metrics import Counters
from services.common.rs485_bus import BusError, RS485Bus


class ActuatorBusConfig(ConfigStruct):
    addresses: list[int] = msgspec.field(default_factory=lambda: list(r.ACTUATOR_ADDRESSES))
    torque_timeout_s: float = 0.25
    gravity_compensation: bool = True
    reference_tolerance_deg: float = 10.0
    #: torque validation: the host's expected torque must match the measured one within this (N·m or fraction)
    validation_tolerance_nm: float = 2.0
    validation_tolerance_fraction: float = 0.2
    validation_lifetime_s: float = 1.0


#: N·m per A of a geared motor, and a steady temperature: emulation constants for the reported current and
#: temperature (nothing in the simulation heats up)
TORQUE_PER_AMPERE = 0.08
ACTUATOR_TEMPERATURE_C = 35.0
#: the position-mode reference is fitted to the targets of about this long (a few bus cycles)
RATE_WINDOW_S = 0.012
#: bounds of the fitted reference's rate and acceleration (well beyond the arm's 48 deg/s and the DSP's
#: 200 deg/s², so they only cut glitches)
MAX_REFERENCE_RATE_DPS = 120.0
MAX_REFERENCE_ACCEL_DPS2 = 2000.0
#: a target older than this is not extrapolated (the host stopped sending)
STALE_TARGET_S = 0.02
#: position-mode servo of each actuator (its own firmware loop): critically damped at this natural frequency for
#: the inertia the joint currently drives, so that the shoulder follows its targets as promptly as the wrist (a
#: fixed PD would leave the heavy joints ~30 ms behind the light ones, and a Cartesian motion that needs both
#: would come out distorted)
SERVO_BANDWIDTH_RPS = 150.0


def quadratic_at_end(samples, t_end: float) -> tuple[float, float, float]:
    """Least-squares p(t) = a + b·x + c·x² with x = t − t_end over (t, p) samples: (a, b, 2c), i.e. the fitted
    position, rate and acceleration at t_end. Plain arithmetic: it runs for every actuator every cycle."""
    s0 = s1 = s2 = s3 = s4 = y0 = y1 = y2 = 0.0
    for t, p in samples:
        x = t - t_end
        x2 = x * x
        s0 += 1.0
        s1 += x
        s2 += x2
        s3 += x2 * x
        s4 += x2 * x2
        y0 += p
        y1 += p * x
        y2 += p * x2
    det = s0 * (s2 * s4 - s3 * s3) - s1 * (s1 * s4 - s3 * s2) + s2 * (s1 * s3 - s2 * s2)
    if abs(det) < 1e-30:
        return samples[-1][1], 0.0, 0.0
    a = (y0 * (s2 * s4 - s3 * s3) - s1 * (y1 * s4 - s3 * y2) + s2 * (y1 * s3 - s2 * y2)) / det
    b = (s0 * (y1 * s4 - s3 * y2) - y0 * (s1 * s4 - s3 * s2) + s2 * (s1 * y2 - y1 * s2)) / det
    c = (s0 * (s2 * y2 - y1 * s3) - s1 * (s1 * y2 - y1 * s2) + y0 * (s1 * s3 - s2 * s2)) / det
    return a, b, 2.0 * c


@dataclass
class Actuator:
    index: int
    address: int
    mode: r.ControlModeRequest = r.ControlModeRequest.POSITION
    target_deg: float = 0.0
    #: the target's rate, from the position commands of the last few cycles (the actuator's own interpolation)
    target_rate_dps: float = 0.0
    target_time_s: float = -math.inf
    #: the rate's own rate (deg/s²), for the servo's inertia feedforward
    target_accel_dps2: float = 0.0
    #: recent (time, target) pairs the rate is measured over
    target_history: collections.deque = field(default_factory=lambda: collections.deque(maxlen=16))
    torque_nm: float = 0.0
    last_torque_s: float = -math.inf
    validated_s: float = -math.inf
    fault: r.ActuatorError = r.ActuatorError.NONE
    reported: set = field(default_factory=set)


class ActuatorBusEmulator:
    """The seven actuators on one bus, driving a MuJoCo arm. ``process(now_s)`` every 2 ms handles the bus;
    ``apply(dt)`` every physics step sets the joint torques (the Simulation's actuator interface)."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, bus: RS485Bus,
                 config: ActuatorBusConfig | None = None, counters: Counters | None = None) -> None:
        self.model, self.data, self.bus = model, data, bus
        self.config = config or ActuatorBusConfig()
        self.counters = counters or bus.counters
        self.n = jaco2.N_JOINTS
        self.torque_limit = model.actuator_ctrlrange[: self.n, 1].copy()
        self.lower, self.upper = jaco2.model_limits()
        self.by_address = {}
        for i, address in enumerate(self.config.addresses):
            actuator = Actuator(i, address, target_deg=self._position_deg(i))
            self.by_address[address] = actuator
        self.actuators = list(self.by_address.values())
        self._gravity = np.zeros(self.n)
        self._mass = np.zeros((model.nv, model.nv))
        self._friction = model.dof_damping[: self.n].copy()
        self.now_s = 0.0

    # ------------------------------------------------------------------ state in actuator units
    def _position_deg(self, i: int) -> float:
        return float(jaco2.model_to_physical_deg(self.data.qpos[: self.n])[i])

    def _velocity_dps(self, i: int) -> float:
        return float(jaco2.model_rate_to_physical(self.data.qvel[: self.n])[i])

    def _torque_nm(self, i: int) -> float:
        """Measured joint torque in the actuator's (physical) sign."""
        return float(jaco2.SIGN[i] * self.data.actuator_force[i])

    def read(self) -> JointState:
        d = self.data
        return JointState(q=d.qpos[: self.n].copy(), dq=d.qvel[: self.n].copy(),
                          tau=d.actuator_force[: self.n].copy(), stamp_ns=int(round(d.time * 1e9)))

    # ------------------------------------------------------------------ the 500 Hz bus cycle
    def process(self, now_s: float) -> int:
        """Handle every message waiting on the bus; returns how many were handled."""
        self.now_s = now_s
        handled = 0
        replies = []
        try:
            incoming = self.bus.drain()
        except BusError:  # counted by the bus; the actuators keep their last command (torque mode times out)
            incoming = []
        for message in incoming:
            actuator = self.by_address.get(message.destination)
            if actuator is None:
                continue  # for someone else (or the host)
            handled += 1
            self.counters.inc(f"bus.rx.{message.command.name.lower()}")
            replies += self._handle(actuator, message)
        try:
            self.bus.send_all(replies)
        except BusError:
            pass  # counted by the bus; the host times out and holds the arm
        for actuator in self.actuators:
            if (actuator.mode is r.ControlModeRequest.TORQUE
                    and now_s - actuator.last_torque_s > self.config.torque_timeout_s):
                self._hold(actuator)
                self.counters.inc("torque_timeouts")
            self._check_limits(actuator)
        return handled

    def _follow(self, actuator: Actuator, position_deg: float) -> None:
        """Take a new position target: the firmware's reference is a quadratic fitted to the targets of the last
        RATE_WINDOW_S, which gives its position, rate and acceleration at once, consistently. (One cycle's
        difference would do on a perfectly periodic bus; a host whose commands jitter by a cycle, two in one
        cycle and none in the next, would make such a rate jump between zero and double.)"""
        history = actuator.target_history
        if history and self.now_s - history[-1][0] > STALE_TARGET_S:
            history.clear()  # the host paused: the old targets say nothing about the new motion
        if history and self.now_s - history[-1][0] < 0.5 * r.CYCLE_S:
            history[-1] = (self.now_s, position_deg)  # same cycle (or a catch-up right after): the newest wins
        else:
            history.append((self.now_s, position_deg))
        while len(history) > 3 and self.now_s - history[1][0] >= RATE_WINDOW_S:
            history.popleft()
        position, rate, accel = position_deg, 0.0, 0.0
        if len(history) >= 3:
            position, rate, accel = quadratic_at_end(history, self.now_s)
        elif len(history) == 2:
            (t0, p0), (t1, p1) = history
            rate = (p1 - p0) / (t1 - t0)
        # a reference no actuator could follow is a host glitch, not a trajectory
        actuator.target_deg = position
        actuator.target_rate_dps = min(max(rate, -MAX_REFERENCE_RATE_DPS), MAX_REFERENCE_RATE_DPS)
        actuator.target_accel_dps2 = min(max(accel, -MAX_REFERENCE_ACCEL_DPS2), MAX_REFERENCE_ACCEL_DPS2)
        actuator.target_time_s = self.now_s

    def _hold(self, actuator: Actuator) -> None:
        actuator.mode = r.ControlModeRequest.POSITION
        actuator.target_deg = self._position_deg(actuator.index)
        actuator.target_rate_dps = 0.0
        actuator.target_accel_dps2 = 0.0
        actuator.target_history.clear()
        actuator.torque_nm = 0.0

    def _fault(self, actuator: Actuator, error: r.ActuatorError) -> list:
        if actuator.fault is r.ActuatorError.NONE:
            actuator.fault = error
            self._hold(actuator)
            self.counters.inc(f"faults.{error.name.lower()}")
            return [r.report_error(error, actuator.address)]
        return []

    def _check_limits(self, actuator: Actuator) -> None:
        i = actuator.index
        if not np.isfinite(self.lower[i]):
            return
        q = self.data.qpos[i]
        if (q < self.lower[i] or q > self.upper[i]) and actuator.fault is r.ActuatorError.NONE:
            try:
                self.bus.send_all(self._fault(actuator, r.ActuatorError.POSITION_LIMIT))
            except BusError:
                pass  # the fault still latches; the host sees it in the 0x17 replies

    def _replies(self, actuator: Actuator) -> list:
        i = actuator.index
        torque = self._torque_nm(i)
        current = torque / TORQUE_PER_AMPERE
        return [
            r.AllValues1(current, self._position_deg(i), self._velocity_dps(i), torque).to_message(actuator.address),
            r.AllValues2((0.0, 0.0, 1.0), ACTUATOR_TEMPERATURE_C).to_message(actuator.address),
            r.RS485Message.with_floats(r.Command.SEND_ALL_VALUES_3, actuator.address, r.HOST_ADDRESS,
                                       [actuator.target_deg, actuator.torque_nm, float(actuator.mode),
                                        float(actuator.fault)]),
        ]

    def _handle(self, actuator: Actuator, message: r.RS485Message) -> list:
        cfg = self.config
        command = message.command
        i = actuator.index
        if command is r.Command.GET_ACTUAL_POSITION:
            return [r.RS485Message.with_floats(r.Command.SEND_ACTUAL_POSITION, actuator.address, r.HOST_ADDRESS,
                                               [self._position_deg(i)])]
        if command is r.Command.POSITION_AND_TORQUE_COMMAND:
            try:
                cmd = r.PositionTorqueCommand.from_message(message)
            except r.RS485Error:
                self.counters.inc("bus.rejected_payloads")
                return self._fault(actuator, r.ActuatorError.COMMAND) + self._replies(actuator)
            out = []
            if actuator.fault is not r.ActuatorError.NONE:
                return self._replies(actuator)
            if actuator.mode is r.ControlModeRequest.POSITION:
                self._follow(actuator, cmd.position_deg)
            else:
                if abs(cmd.position_deg - self._position_deg(i)) > cfg.reference_tolerance_deg:
                    return self._fault(actuator, r.ActuatorError.RELATIVE_POSITION) + self._replies(actuator)
                limit = float(self.torque_limit[i])
                torque = min(max(cmd.torque_nm, -limit), limit)
                if torque != cmd.torque_nm and r.ActuatorError.TORQUE not in actuator.reported:
                    actuator.reported.add(r.ActuatorError.TORQUE)  # clamped, reported once, not latched
                    out.append(r.report_error(r.ActuatorError.TORQUE, actuator.address))
                actuator.torque_nm = torque
                actuator.last_torque_s = self.now_s
            return out + self._replies(actuator)
        if command is r.Command.GET_TORQUE_VALIDATION_REQUEST:
            expected = message.floats[0]
            measured = self._torque_nm(i)
            ok = math.isfinite(expected) and abs(expected - measured) <= max(
                cfg.validation_tolerance_nm, cfg.validation_tolerance_fraction * abs(measured))
            if ok:
                actuator.validated_s = self.now_s
            return [r.RS485Message.with_uints(r.Command.SEND_TORQUE_VALIDATION, actuator.address, r.HOST_ADDRESS,
                                              [1 if ok else 0])]
        if command is r.Command.SWITCH_CONTROL_MODE_REQUEST:
            wanted = message.uints[0]
            if wanted == r.ControlModeRequest.POSITION:
                self._hold(actuator)
                return [r.switch_mode_reply(r.ControlModeReply.POSITION_OK, actuator.address)]
            recent = self.now_s - actuator.validated_s <= cfg.validation_lifetime_s
            if wanted == r.ControlModeRequest.TORQUE and recent and actuator.fault is r.ActuatorError.NONE:
                actuator.mode = r.ControlModeRequest.TORQUE
                actuator.torque_nm = 0.0
                actuator.last_torque_s = self.now_s
                return [r.switch_mode_reply(r.ControlModeReply.TORQUE_OK, actuator.address)]
            self.counters.inc("mode_switch_refused")
            return [r.switch_mode_reply(r.ControlModeReply.REFUSED, actuator.address)]
        if command is r.Command.CLEAR_FAULT_FLAG:
            actuator.fault = r.ActuatorError.NONE
            actuator.reported.clear()
            return [r.RS485Message(r.Command.ACK, actuator.address, r.HOST_ADDRESS)]
        if command in (r.Command.START_SERVO, r.Command.STOP_SERVO):
            return [r.RS485Message(r.Command.ACK, actuator.address, r.HOST_ADDRESS)]
        self.counters.inc("bus.unsupported")
        return [r.RS485Message(r.Command.NACK, actuator.address, r.HOST_ADDRESS)]

    # ------------------------------------------------------------------ physics
    def apply(self, dt: float) -> None:
        d = self.data
        q, dq = d.qpos[: self.n], d.qvel[: self.n]
        tau = np.empty(self.n)
        gravity = d.qfrc_bias[: self.n]  # at rest this is the gravity torque; it also cancels Coriolis terms
        mujoco.mj_fullM(self.model, d, self._mass)
        inertia = np.diag(self._mass)[: self.n]
        kp, kd = inertia * SERVO_BANDWIDTH_RPS**2, inertia * 2.0 * SERVO_BANDWIDTH_RPS
        accel = np.zeros(self.n)
        for a in self.actuators:
            i = a.index
            if a.mode is r.ControlModeRequest.TORQUE and a.fault is r.ActuatorError.NONE:
                tau[i] = jaco2.SIGN[i] * a.torque_nm + (gravity[i] if self.config.gravity_compensation else 0.0)
            else:
                # follow the target, extrapolated along its rate until the next command, with the inertia and
                # friction its motion needs as feedforward (so the servo follows without lag or overshoot)
                fresh = 0.0 <= self.now_s - a.target_time_s <= STALE_TARGET_S
                rate = jaco2.SIGN[i] * math.radians(a.target_rate_dps) if fresh else 0.0
                ahead = (self.now_s - a.target_time_s) if fresh else 0.0
                accel[i] = jaco2.SIGN[i] * math.radians(a.target_accel_dps2) if fresh else 0.0
                target = jaco2.SIGN[i] * math.radians(a.target_deg) + rate * ahead
                tau[i] = (gravity[i] + self._friction[i] * rate + kp[i] * (target - q[i]) + kd[i] * (rate - dq[i]))
        tau += self._mass[: self.n, : self.n] @ accel
        d.ctrl[: self.n] = np.clip(tau, -self.torque_limit, self.torque_limit)
