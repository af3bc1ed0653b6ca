"""The host's side of the RS-485 actuator bus: request/reply exchanges with the seven actuators, with the
checks a real bus needs. Every exchange waits at most ``timeout_s`` for its replies; a timeout, a missing or
unexpected reply, a NACK or an actuator error report is counted and raised as :class:`LinkError`, so the caller
(the gateway's 500 Hz loop) can stop the arm safely instead of acting on a partial picture.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from protocol import rs485 as r
from services.common import jaco2
from services.common.metrics import Counters
from services.common.rs485_bus import BusError, RS485Bus


class LinkError(RuntimeError):
    """The bus did not deliver what the exchange needed (the message says what)."""


@dataclass
class ActuatorReading:
    position_deg: np.ndarray
    velocity_dps: np.ndarray
    torque_nm: np.ndarray
    current_a: np.ndarray
    temperature_c: np.ndarray
    #: per actuator: mode (0 position, 1 torque) and fault code, from the 0x17 replies
    mode: np.ndarray
    fault: np.ndarray


class ActuatorLink:
    def __init__(self, bus: RS485Bus, addresses=r.ACTUATOR_ADDRESSES, timeout_s: float = 0.01,
                 counters: Counters | None = None) -> None:
        self.bus = bus
        self.addresses = list(addresses)
        self.timeout_s = timeout_s
        self.counters = counters or bus.counters
        self.errors: list[tuple[int, r.ActuatorError]] = []

    def _request(self, messages) -> None:
        """Send a request in one write, after taking what is still queued: the late replies of an exchange that
        timed out would otherwise answer this one, and every later reading would be a cycle old."""
        try:
            for message in self.bus.drain():
                if message.command is r.Command.REPORT_ERROR:
                    self._record_error(message)
                else:
                    self.counters.inc("link.stale_replies")
            self.bus.send_all(messages)
        except BusError as exc:
            raise LinkError(f"bus failure: {exc}") from exc

    def _record_error(self, message: r.RS485Message) -> None:
        error = r.parse_report_error(message)
        self.errors.append((message.source, error))
        self.counters.inc(f"link.actuator_errors.{error.name.lower()}")

    def _collect(self, expected: dict[tuple[int, r.Command], int]) -> list[r.RS485Message]:
        """Wait for the expected replies ((source, command) → count); error reports are kept aside."""
        remaining = dict(expected)
        replies = []
        deadline = time.monotonic() + self.timeout_s
        while any(remaining.values()):
            try:
                message = self.bus.recv(max(0.0, deadline - time.monotonic()))
            except BusError as exc:
                raise LinkError(f"bus failure: {exc}") from exc
            if message is None:
                self.counters.inc("link.timeouts")
                missing = [f"0x{a:02X}:{c.name}" for (a, c), n in remaining.items() if n]
                raise LinkError(f"no reply within {self.timeout_s * 1e3:.1f} ms from {', '.join(missing)}")
            key = (message.source, message.command)
            if message.command is r.Command.REPORT_ERROR:
                self._record_error(message)
                continue
            if message.command is r.Command.NACK:
                self.counters.inc("link.nacks")
                raise LinkError(f"actuator 0x{message.source:02X} refused the request (NACK)")
            if remaining.get(key, 0) <= 0:
                self.counters.inc("link.unexpected")
                continue
            remaining[key] -= 1
            replies.append(message)
        return replies

    def positions_deg(self) -> np.ndarray:
        self._request(r.RS485Message(r.Command.GET_ACTUAL_POSITION, r.HOST_ADDRESS, address)
                      for address in self.addresses)
        replies = self._collect({(a, r.Command.SEND_ACTUAL_POSITION): 1 for a in self.addresses})
        by_source = {m.source: m.floats[0] for m in replies}
        return np.array([by_source[a] for a in self.addresses])

    def command(self, positions_deg, torques_nm=None) -> ActuatorReading:
        """One 0x14 to every actuator (position targets, or safety references with torques in torque mode);
        returns what the 0x15-0x17 replies say."""
        torques = np.zeros(len(self.addresses)) if torques_nm is None else np.asarray(torques_nm, dtype=float)
        self._request(r.PositionTorqueCommand(float(position), float(torque)).to_message(address)
                      for address, position, torque in zip(self.addresses, positions_deg, torques, strict=True))
        expected = {}
        for a in self.addresses:
            for command in (r.Command.SEND_ALL_VALUES_1, r.Command.SEND_ALL_VALUES_2, r.Command.SEND_ALL_VALUES_3):
                expected[(a, command)] = 1
        replies = self._collect(expected)
        index = {a: i for i, a in enumerate(self.addresses)}
        n = len(self.addresses)
        out = ActuatorReading(*(np.zeros(n) for _ in range(7)))
        for message in replies:
            i = index[message.source]
            if message.command is r.Command.SEND_ALL_VALUES_1:
                v = r.AllValues1.from_message(message)
                out.current_a[i], out.position_deg[i] = v.current_a, v.position_deg
                out.velocity_dps[i], out.torque_nm[i] = v.velocity_dps, v.torque_nm
            elif message.command is r.Command.SEND_ALL_VALUES_2:
                out.temperature_c[i] = r.AllValues2.from_message(message).temperature_c
            else:
                floats = message.floats
                out.mode[i], out.fault[i] = floats[2], floats[3]
        return out

    def switch_to_torque(self, expected_torques_nm) -> None:
        """The torque-mode handshake for every actuator: validation of the expected torques, then the switch."""
        self._request(r.RS485Message.with_floats(r.Command.GET_TORQUE_VALIDATION_REQUEST, r.HOST_ADDRESS, address,
                                                 [float(torque)])
                      for address, torque in zip(self.addresses, expected_torques_nm, strict=True))
        replies = self._collect({(a, r.Command.SEND_TORQUE_VALIDATION): 1 for a in self.addresses})
        invalid = [f"0x{m.source:02X}" for m in replies if m.uints[0] != 1]
        if invalid:
            raise LinkError(f"torque validation failed for {', '.join(invalid)}")
        self._request(r.switch_mode_request(r.ControlModeRequest.TORQUE, address) for address in self.addresses)
        replies = self._collect({(a, r.Command.SWITCH_CONTROL_MODE_REPLY): 1 for a in self.addresses})
        refused = [f"0x{m.source:02X}" for m in replies if r.parse_switch_mode_reply(m) is not
                   r.ControlModeReply.TORQUE_OK]
        if refused:
            raise LinkError(f"torque mode refused by {', '.join(refused)}")

    def switch_to_position(self) -> None:
        self._request(r.switch_mode_request(r.ControlModeRequest.POSITION, address) for address in self.addresses)
        self._collect({(a, r.Command.SWITCH_CONTROL_MODE_REPLY): 1 for a in self.addresses})


def expected_torques_physical(q_model) -> np.ndarray:
    """The gravity torques the host's model expects at q (actuator sign), for the validation handshake."""
    from services.common.kinematics import ArmKinematics

    return jaco2.SIGN * ArmKinematics().gravity(q_model)
