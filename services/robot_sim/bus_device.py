"""The simulated arm's face on its RS-485 bus: what each actuator answers to the messages of ``protocol.rs485``
(host 0x00, actuators at ``ActuatorConfig.addresses``). Pure: no bus, no threads, no wall time; the service feeds
it the frames and sends what it returns, and decides when cycles end (:mod:`services.robot_sim.service`).

* ``GET_ACTUAL_POSITION`` (0x01) → ``SEND_ACTUAL_POSITION`` (0x02): float [current (A), position (deg,
  physical), velocity (deg/s), torque (N·m)], 0x15's layout: the position in float[1], where Kinova's RS-485
  examples, abr/abr_jaco2, abr/abr_control, sammy-tri/drake-jaco-driver and farmange/libkinova all read it.
* ``POSITION_AND_TORQUE_COMMAND`` (0x14) → one 0x15, 0x16 and 0x17 reply each, with the values of the current
  cycle (the state at its boundary); the command itself is taken at the next boundary
  (:class:`~services.robot_sim.firmware.ActuatorFirmware`). In lockstep the replies wait for that boundary, so
  they carry the state the command acts from. The command is read as the actuator's mode says
  (:func:`protocol.rs485.command_targets`): in position mode float[0] and float[1] must agree (Kinova's header
  asks both halves to; the public drivers send them equal) and float[2] is the extended-answer flag, not a torque;
  in torque mode float[2] is the torque. A command that is not valid is refused with a COMMAND error report (what
  a real actuator does then is not public: our choice). The replies' layouts are the public drivers'
  (docs/rs485-sources.md): 0x15 [current, position, velocity, torque]; 0x16 [PWM, position, int16 ax, ay, az,
  temperature]; 0x17 [current, absolute position, 0, 0]. PWM is not modelled (0) and the accelerometers read
  1 g along z (our choices); the two positions are the joint's.
* ``GET_TORQUE_VALIDATION_REQUEST`` (0x201), float[0] = the torque the host's model expects → 
  ``SEND_TORQUE_VALIDATION`` (0x202), uint32[0] = 1 when it matches the measured torque within tolerance.
* ``SWITCH_CONTROL_MODE_REQUEST`` (0x203), uint32[0] = 0 position / 1 torque → ``SWITCH_CONTROL_MODE_REPLY``
  (0x204): 1 position OK, 257 torque OK, 0 refused.
* ``TORQUE_CONFIG_SAFETY`` (0x208), float[0] = the most torque the actuator is to give in torque mode (N·m; float[1]
  the speed fraction, 1 = off, not emulated) → ``ACK``, as abr/abr_jaco2 waits for; a limit that is not positive or
  beyond what the actuator gives → ``NACK``. The other torque configuration messages (0x209-0x215), the gains
  (0x24/0x25) and 0x200 are not emulated (``NACK``).
* ``CLEAR_FAULT_FLAG`` (0x33), ``START_SERVO``/``STOP_SERVO`` → ``ACK`` (0x3F), uint32[0] the command acknowledged
  (drake-jaco-driver reads it there); other commands → ``NACK``.
* The hand's finger actuators (the hand file's addresses, 0x16-0x18): ``GET_POSITION_COMMAND`` (0x10), float[0] =
  float[1] = the target in Kinova's finger units (abr/abr_jaco2 sends them so), taken at the next boundary →
  ``SEND_POSITION_CURRENT`` (0x11) with the cycle's values in 0x02's layout [current A, position in units,
  velocity in units/s, 0] (the layout is not public: our choice, where abr_jaco2 reads a position);
  ``GET_ACTUAL_POSITION`` (0x01) → 0x02 in the same layout. A target that is not finite, or whose halves differ,
  is refused with a COMMAND report; anything else to a finger → ``NACK``.
* Faults are reported with ``REPORT_ERROR`` (0x30) once (the firmware latches them).
* Torque mode adds no gravity compensation: driven over RS-485 the base's DSP is bypassed (kinova.md), and the
  host sends the arm's gravity with its torques (as abr/abr_jaco2 does), whatever ``actuators.gravity_compensation``
  says for the api mode.
"""
from __future__ import annotations

import numpy as np

from protocol import rs485 as r
from services.runtime.metrics import Counters
from services.robot.hardware import ActuatorValues
from services.robot_sim.firmware import TORQUE
from services.robot_sim.sim import Simulation


class ActuatorBusDevice:
    def __init__(self, sim: Simulation, counters: Counters | None = None, defer_replies: bool = False) -> None:
        self.sim = sim
        self.firmware = sim.firmware
        # driven over their bus, the actuators have no DSP to compute the arm's gravity: the host sends it
        self.firmware.bypass_dsp()
        self.counters = counters or self.firmware.counters
        #: lockstep: a 0x14's replies go out at the boundary that takes it (with the state it acts from)
        self.defer_replies = defer_replies
        self.index = {a.address: a.index for a in self.firmware.actuators}
        self._joint_of = np.full(256, -1)
        self._addresses = np.array([a.address for a in self.firmware.actuators])
        self._joint_of[self._addresses] = np.arange(len(self._addresses))
        #: per joint, its three replies without their data
        self._reply_template = r.records(3 * len(self._addresses)).reshape(-1, 3)
        self._reply_template["source"] = self._addresses[:, None]
        self._reply_template["destination"] = r.HOST_ADDRESS
        self._reply_template["command"] = [r.Command.SEND_ALL_VALUES_1, r.Command.SEND_ALL_VALUES_2,
                                           r.Command.SEND_ALL_VALUES_3]
        self.values: ActuatorValues = self.firmware.values(sim.time_ns)
        self._deferred: list[int] = []
        self._commanded: set[int] = set()
        #: the finger actuators by address (none without a hand), and their values at the cycle's boundary
        hand = sim.arm.hand if sim.fingers is not None else None
        self.finger_index = {} if hand is None else {a: i for i, a in enumerate(hand.bus_addresses)}
        self.finger_values = None if sim.fingers is None else sim.fingers.reading()

    # ------------------------------------------------------------------ batches (the hot path)
    def receive_batch(self, batch: np.ndarray) -> np.ndarray:
        """The replies to a batch of messages, as a batch. The cycle's 0x14 commands are handled together; any
        other message one by one, before them."""
        joints = self._joint_of[batch["destination"]]
        commands = (batch["command"] == r.Command.POSITION_AND_TORQUE_COMMAND) & (joints >= 0)
        if commands.all():
            return self._commands(batch, joints)
        out = [r.to_records(self.receive(message)) for message in r.from_records(batch[~commands])]
        if commands.any():
            out.append(self._commands(batch[commands], joints[commands]))
        out = [b for b in out if len(b)]
        return np.concatenate(out) if out else r.records(0)

    def _commands(self, batch: np.ndarray, joints: np.ndarray) -> np.ndarray:
        self.counters.inc("bus.rx.position_and_torque_command", len(batch))
        positions, torques, valid = r.command_targets(batch, self.firmware.mode[joints] == TORQUE)
        replied, reports = [], []
        for joint, position, torque, ok in zip(joints.tolist(), positions.tolist(), torques.tolist(), valid.tolist()):
            if ok:
                self.firmware.command(joint, position, torque)
                self._commanded.add(joint)
                if self.defer_replies:
                    self._deferred.append(joint)
                    continue
            else:
                self.counters.inc("bus.rejected_payloads")
                reports += self._report(int(self._addresses[joint]),
                                        self.firmware.fault(joint, r.ActuatorError.COMMAND))
            replied.append(joint)
        if not reports:
            return self.replies_batch(replied) if replied else r.records(0)
        return np.concatenate([r.to_records(reports), self.replies_batch(replied)])

    def replies_batch(self, joints) -> np.ndarray:
        """0x15, 0x16 and 0x17 of each of ``joints`` with this cycle's values, as a batch."""
        joints = list(joints)
        v = self.values
        values = np.zeros((len(joints), 3, 4))
        values[:, 0] = np.stack([v.current_a, v.position_deg, v.velocity_dps, v.torque_nm], axis=1)[joints]
        values[:, 1, 1] = v.position_deg[joints]  # 0x16 [PWM (not modelled: 0), position, four int16 below]
        values[:, 2, :2] = np.stack([v.current_a, v.position_deg], axis=1)[joints]  # 0x17 [current, position, 0, 0]
        out = self._reply_template[joints].reshape(-1)  # a copy: the ids and addresses of each joint's three
        out["data"] = values.reshape(-1, 4)
        ints = out["data"][1::3].view("<i2")  # 0x16's int16 ax, ay, az (×0.001: 1 g along z), temperature (×0.01)
        ints[:, r.ACCEL_SHORTS] = (0, 0, 1000)
        ints[:, r.TEMPERATURE_SHORT] = np.rint(v.temperature_c[joints] / 0.01)
        return out

    def receive(self, message: r.RS485Message) -> list[r.RS485Message]:
        """The replies to one message (none when it is not for an actuator, or deferred to the boundary)."""
        i = self.index.get(message.destination)
        if i is None:
            finger = self.finger_index.get(message.destination)
            return [] if finger is None else self._finger(finger, message)  # for someone else (or the host)
        if message.command is not r.Command.POSITION_AND_TORQUE_COMMAND:  # those are counted as a batch
            self.counters.inc(f"bus.rx.{message.command.name.lower()}")
        address = message.destination
        firmware = self.firmware
        command = message.command
        if command is r.Command.GET_ACTUAL_POSITION:
            v = self.values  # the cycle's current, velocity and torque; the position as the joint is now
            return [r.RS485Message.with_floats(r.Command.SEND_ACTUAL_POSITION, address, r.HOST_ADDRESS,
                                               [float(v.current_a[i]), firmware.position_deg(i),
                                                float(v.velocity_dps[i]), float(v.torque_nm[i])])]
        if command is r.Command.POSITION_AND_TORQUE_COMMAND:
            return r.from_records(self._commands(r.to_records([message]), np.array([i])))
        if command is r.Command.GET_TORQUE_VALIDATION_REQUEST:
            ok = firmware.validate_torque(i, message.floats[0])
            return [r.RS485Message.with_uints(r.Command.SEND_TORQUE_VALIDATION, address, r.HOST_ADDRESS,
                                              [1 if ok else 0])]
        if command is r.Command.SWITCH_CONTROL_MODE_REQUEST:
            return [r.switch_mode_reply(firmware.switch_mode(i, message.uints[0]), address)]
        if command is r.Command.CLEAR_FAULT_FLAG:
            firmware.clear_fault(i)
            return [r.ack(command, address)]
        if command in (r.Command.START_SERVO, r.Command.STOP_SERVO):
            return [r.ack(command, address)]
        if command is r.Command.TORQUE_CONFIG_SAFETY:
            if firmware.configure_torque_limit(i, message.floats[0]):
                return [r.ack(command, address)]
        self.counters.inc("bus.unsupported")
        return [r.RS485Message(r.Command.NACK, address, r.HOST_ADDRESS)]

    def _finger(self, finger: int, message: r.RS485Message) -> list[r.RS485Message]:
        """A message to finger actuator ``finger``."""
        self.counters.inc(f"bus.rx.finger.{message.command.name.lower()}")
        address, hand, command = message.destination, self.sim.arm.hand, message.command
        if command is r.Command.GET_POSITION_COMMAND:
            first, second = message.floats[:2]
            if not (np.isfinite(first) and first == second):
                self.counters.inc("bus.rejected_payloads")
                return [r.report_error(r.ActuatorError.COMMAND, address)]
            self.sim.fingers.command_one(finger, float(hand.units_to_angle(first)))
            reply = r.Command.SEND_POSITION_CURRENT
        elif command is r.Command.GET_ACTUAL_POSITION:
            reply = r.Command.SEND_ACTUAL_POSITION
        else:
            self.counters.inc("bus.unsupported")
            return [r.RS485Message(r.Command.NACK, address, r.HOST_ADDRESS)]
        v = self.finger_values
        return [r.RS485Message.with_floats(reply, address, r.HOST_ADDRESS, [
            float(v.current_a[finger]), float(hand.angle_to_units(v.position[finger])),
            float(hand.angle_to_units(v.velocity[finger])), 0.0])]

    @property
    def batch_complete(self) -> bool:
        """Every actuator has a 0x14 for the next boundary (lockstep ends a cycle on this)."""
        return len(self._commanded) == len(self.index)

    # ------------------------------------------------------------------ the boundary
    def begin_cycle(self) -> np.ndarray:
        """The cycle boundary: the actuators take their commands and report; returns what goes on the bus now
        (fault reports, and in lockstep the deferred replies), as a batch stamped with :attr:`values`' time.
        Physics is the caller's (``sim.end_cycle()``), so that a camera frame can be taken at the boundary
        first."""
        self.values = self.sim.begin_cycle()
        if self.sim.fingers is not None:
            self.finger_values = self.sim.fingers.reading()
        self._commanded.clear()
        reports = []
        for address, error in self.firmware.reports:
            reports += self._report(address, error)
        self.firmware.reports.clear()
        parts = [r.to_records(reports)] if reports else []
        if self._deferred:
            parts.append(self.replies_batch(self._deferred))
            self._deferred.clear()
        return np.concatenate(parts) if parts else r.records(0)

    def _report(self, address: int, error) -> list[r.RS485Message]:
        return [] if error is None else [r.report_error(error, address)]
