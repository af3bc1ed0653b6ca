"""The host's side of the RS-485 actuator bus: request/reply exchanges with the seven actuators, with the
checks a real bus needs. Every exchange waits at most ``timeout_s`` for its replies; a timeout, a missing or
unexpected reply, a NACK or an actuator error report is counted and raised as :class:`LinkError`, so the caller
(the gateway's 500 Hz loop) can stop the arm safely instead of acting on a partial picture.

:class:`LinkHardware` is the robot node's hardware interface (services.robot.hardware) on such a link.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Callable, Optional

import numpy as np

from protocol import rs485 as r
from services.model.arm import ArmDescription
from services.runtime.metrics import Counters
from services.robot.rs485_bus import BusError, RS485Bus
from services.robot.hardware import (DEFAULT_TIMING, ActuatorValues, BusTiming, HardwareError, JointReading,
                                     JointTargets, physical_targets, reading_from_physical)


class LinkError(RuntimeError):
    """The bus did not deliver what the exchange needed (the message says what)."""


_REPORT_ERROR, _NACK = int(r.Command.REPORT_ERROR), int(r.Command.NACK)
#: the replies to a 0x14 are 0x15, 0x16, 0x17: their kind is the command id minus this
_FIRST_REPLY = int(r.Command.SEND_ALL_VALUES_1)
_REPLY_NAMES = ("SEND_ALL_VALUES_1", "SEND_ALL_VALUES_2", "SEND_ALL_VALUES_3")


class ActuatorLink:
    def __init__(self, bus: RS485Bus, addresses, timeout_s: float = 0.01, counters: Counters | None = None) -> None:
        """``addresses``: the actuators', joint by joint (an arm description's ``bus_addresses``)."""
        self.bus = bus
        self.addresses = list(addresses)
        self.timeout_s = timeout_s
        self.counters = counters or bus.counters
        self.errors: list[tuple[int, r.ActuatorError]] = []
        #: per actuator, its mode as the host set it with the 0x203/0x204 handshake (0 position, 1 torque), and the
        #: fault it last reported (0x30; kept until the gateway restarts, as the emulated firmware latches it): no
        #: public source finds either in a reply (0x17's floats 2 and 3 are not described: docs/rs485-sources.md)
        self.mode = np.zeros(len(self.addresses), dtype=int)
        self.fault = np.zeros(len(self.addresses), dtype=int)
        self.last_stamp_ns = 0
        self._joint_of = np.full(256, -1)
        self._joint_of[self.addresses] = np.arange(len(self.addresses))
        #: replies received past the last collected request's (the next request's, in a pipeline)
        self._carry: Optional[tuple[np.ndarray, np.ndarray]] = None
        #: take what is still queued before every request where looking costs nothing (python-can's queue); where
        #: every look is a transfer (Kinova's USB comm layer: a read each time) only before the first request and
        #: after a failed exchange, the only times a late reply can be waiting
        self.drain_every_request = getattr(bus, "polling_is_free", True)
        self._drain_next = True

    def _request(self, batch: np.ndarray) -> None:
        """Send a request batch in one write, after taking what is still queued: the late replies of an exchange
        that timed out would otherwise answer this one, and every later reading would be a cycle old."""
        try:
            if self.drain_every_request or self._drain_next:
                stale, _ = self.bus.recv_batch(0.0)
                self._drain_next = False
            else:
                stale = r.records(0)
            if self._carry is not None:
                stale = np.concatenate([self._carry[0], stale])
                self._carry = None
            if len(stale):
                errors = stale["command"] == _REPORT_ERROR
                self._record_errors(stale[errors])
                if not errors.all():
                    self.counters.inc("link.stale_replies", int(np.count_nonzero(~errors)))
            self.bus.send_batch(batch)
        except BusError as exc:
            raise self._failure(f"bus failure: {exc}") from exc

    def _failure(self, message: str) -> LinkError:
        """A failed exchange: late replies may follow, so the next request takes what is queued first."""
        self._drain_next = True
        return LinkError(message)

    def _record_errors(self, reports: np.ndarray) -> None:
        """Actuators' error reports (0x30, the code in uint32[1]): each latched as its actuator's fault (the node
        holds the arm on a fault); code 0 is "no error", not a fault; an unknown code is a fault too."""
        for source, code in zip(reports["source"].tolist(), reports["data"].view("<u4")[:, 1].tolist()):
            if code == r.ActuatorError.NONE:
                continue
            joint = self._joint_of[source] if 0 <= source < len(self._joint_of) else -1
            if joint >= 0:
                self.fault[joint] = code
            try:
                error = r.ActuatorError(code)
            except ValueError:
                self.counters.inc("link.actuator_errors.unknown")
                continue
            self.errors.append((source, error))
            self.counters.inc(f"link.actuator_errors.{error.name.lower()}")

    def _receive(self, deadline: float, missing: Callable[[], list[str]]) -> tuple[np.ndarray, np.ndarray]:
        """What has arrived by ``deadline`` (monotonic); nothing at all is a timeout that names ``missing()``."""
        try:
            batch, stamps = self.bus.recv_batch(max(0.0, deadline - time.monotonic()))
        except BusError as exc:
            raise self._failure(f"bus failure: {exc}") from exc
        if len(batch) == 0:
            self.counters.inc("link.timeouts")
            raise self._failure(f"no reply within {self.timeout_s * 1e3:.1f} ms from {', '.join(missing())}")
        return batch, stamps

    def _report(self, command: int, source: int, batch: np.ndarray, k: int) -> bool:
        """Whether message ``k`` is an actuator's error report (recorded); a NACK fails the request."""
        if command == _REPORT_ERROR:
            self._record_errors(batch[k : k + 1])
            return True
        if command == _NACK:
            self.counters.inc("link.nacks")
            raise self._failure(f"actuator 0x{source:02X} refused the request (NACK)")
        return False

    def _collect(self, expected: dict[tuple[int, r.Command], int]) -> np.ndarray:
        """Wait for the expected replies ((source, command) → count) and return them as a batch; error reports
        are kept aside. The newest reply's stamp goes to :attr:`last_stamp_ns`."""
        remaining = {(source, int(command)): n for (source, command), n in expected.items()}
        missing = sum(remaining.values())
        kept = []
        deadline = time.monotonic() + self.timeout_s
        self.last_stamp_ns = 0
        while missing > 0:
            batch, stamps = self._receive(deadline, lambda: [f"0x{a:02X}:{r.Command(c).name}"
                                                             for (a, c), n in remaining.items() if n])
            take = []
            for k, (command, source) in enumerate(zip(batch["command"].tolist(), batch["source"].tolist())):
                if self._report(command, source, batch, k):
                    continue
                if remaining.get((source, command), 0) <= 0:
                    self.counters.inc("link.unexpected")
                    continue
                remaining[(source, command)] -= 1
                missing -= 1
                take.append(k)
            if take:
                kept.append(batch[take])
                self.last_stamp_ns = max(self.last_stamp_ns, int(stamps[take].max()))
        return np.concatenate(kept) if kept else r.records(0)

    def _by_address(self, batch: np.ndarray) -> np.ndarray:
        """The joint index of each record's source."""
        return self._joint_of[batch["source"]]

    def positions_deg(self) -> np.ndarray:
        self._request(r.to_records(r.RS485Message(r.Command.GET_ACTUAL_POSITION, r.HOST_ADDRESS, address)
                                   for address in self.addresses))
        replies = self._collect({(a, r.Command.SEND_ACTUAL_POSITION): 1 for a in self.addresses})
        out = np.zeros(len(self.addresses))
        out[self._by_address(replies)] = replies["data"][:, r.POSITION_FLOAT]  # float[0] is the motor current
        return out

    def command(self, positions_deg, torques_nm=None) -> ActuatorValues:
        """One 0x14 to every actuator (position targets, or safety references with torques in torque mode);
        returns what the 0x15-0x17 replies say."""
        self.send_command(positions_deg, torques_nm, drain=True)
        return self.collect_command(time.monotonic() + self.timeout_s)

    def send_command(self, positions_deg, torques_nm=None, drain: bool = False) -> None:
        """The 0x14 batch only (``drain``: after taking what is still queued, see :meth:`_request`)."""
        try:
            batch = r.position_torque_records(self.addresses, positions_deg, torques_nm)
        except r.RS485Error as exc:
            raise LinkError(str(exc)) from exc
        if drain:
            self._request(batch)
            return
        try:
            self.bus.send_batch(batch)
        except BusError as exc:
            raise self._failure(f"bus failure: {exc}") from exc

    def collect_command(self, deadline: float) -> ActuatorValues:
        """The replies to a 0x14 batch, waiting until ``deadline`` (monotonic) at most."""
        table = self._collect_values(deadline)
        v1 = table[:, 0]["data"].astype(np.float64)  # 0x15 [current, position, velocity, torque]
        if not np.isfinite(v1).all():
            self.counters.inc("link.bad_values")
            raise self._failure("an actuator reported a non-finite value")
        temperature = table[:, 1]["data"].view("<i2")[:, r.TEMPERATURE_SHORT] * 0.01  # 0x16's int16 (×0.01 °C)
        return ActuatorValues(position_deg=v1[:, 1], velocity_dps=v1[:, 2], torque_nm=v1[:, 3], current_a=v1[:, 0],
                               temperature_c=temperature, mode=self.mode.copy(), fault=self.fault.copy(),
                               stamp_ns=self.last_stamp_ns)

    def _collect_values(self, deadline: float) -> np.ndarray:
        """The 0x15, 0x16 and 0x17 reply of every actuator, as a (joint, kind) table of records: the first of each
        in the order they arrive; what comes after the table is full belongs to the next request and is kept for
        it (the transport keeps order, and the host may have sent that request already)."""
        n = len(self.addresses)
        table = r.records(3 * n).reshape(n, 3)
        got = np.zeros((n, 3), dtype=bool)
        missing = 3 * n
        self.last_stamp_ns = 0
        joint_of = self._joint_of
        while missing:
            if self._carry is not None:
                (batch, stamps), self._carry = self._carry, None
            else:
                batch, stamps = self._receive(deadline, lambda: [f"0x{self.addresses[j]:02X}:{_REPLY_NAMES[k]}"
                                                                 for j, k in zip(*np.nonzero(~got))])
            if missing == 3 * n and self._whole_reply_set(batch, n):  # the usual cycle: one vectorised take
                head = batch[: 3 * n]
                table[joint_of[head["source"]], head["command"] - _FIRST_REPLY] = head
                self.last_stamp_ns = int(stamps[: 3 * n].max())
                if len(batch) > 3 * n:
                    self._carry = (batch[3 * n :], stamps[3 * n :])
                return table
            commands, sources = batch["command"].tolist(), batch["source"].tolist()
            for k, (command, source) in enumerate(zip(commands, sources)):
                if not missing:
                    self._carry = (batch[k:], stamps[k:])
                    break
                if self._report(command, source, batch, k):
                    continue
                joint, kind = joint_of[source], command - _FIRST_REPLY
                if joint < 0 or not 0 <= kind < 3 or got[joint, kind]:
                    self.counters.inc("link.unexpected")
                    continue
                table[joint, kind] = batch[k]
                got[joint, kind] = True
                missing -= 1
                self.last_stamp_ns = max(self.last_stamp_ns, int(stamps[k]))
        return table

    def _whole_reply_set(self, batch: np.ndarray, n: int) -> bool:
        """Whether ``batch`` starts with the 0x15, 0x16 and 0x17 of each of the ``n`` actuators, once each and
        nothing else among them (no report, no NACK): then :meth:`_collect_values` takes them at once, and
        anything else goes through its message-by-message path, which counts and reports."""
        if len(batch) < 3 * n:
            return False
        head = batch[: 3 * n]
        joints = self._joint_of[head["source"]]
        kinds = head["command"].astype(np.int64) - _FIRST_REPLY
        if (joints < 0).any() or (kinds < 0).any() or (kinds > 2).any():
            return False
        return len(np.unique(joints * 3 + kinds)) == 3 * n

    def configure_torque_limits(self, max_torques_nm) -> None:
        """0x208 to every actuator, the most torque it may give in torque mode, each acknowledged (abr/abr_jaco2
        sends the arm's maximum torques and waits for every ACK before torque mode)."""
        self._request(r.to_records(r.torque_config_safety(float(limit), address)
                                   for address, limit in zip(self.addresses, max_torques_nm, strict=True)))
        replies = r.from_records(self._collect({(a, r.Command.ACK): 1 for a in self.addresses}))
        wrong = [f"0x{m.source:02X}" for m in replies if m.uints[0] != r.Command.TORQUE_CONFIG_SAFETY]
        if wrong:
            raise LinkError(f"the torque limits were not acknowledged by {', '.join(wrong)}")

    def switch_to_torque(self, expected_torques_nm) -> None:
        """The torque-mode handshake for every actuator: validation of the expected torques, then the switch."""
        self._request(r.to_records(
            r.RS485Message.with_floats(r.Command.GET_TORQUE_VALIDATION_REQUEST, r.HOST_ADDRESS, address,
                                       [float(torque)])
            for address, torque in zip(self.addresses, expected_torques_nm, strict=True)))
        replies = r.from_records(self._collect({(a, r.Command.SEND_TORQUE_VALIDATION): 1 for a in self.addresses}))
        invalid = [f"0x{m.source:02X}" for m in replies if m.uints[0] != 1]
        if invalid:
            raise LinkError(f"torque validation failed for {', '.join(invalid)}")
        self._request(r.to_records(r.switch_mode_request(r.ControlModeRequest.TORQUE, address)
                                   for address in self.addresses))
        replies = r.from_records(self._collect({(a, r.Command.SWITCH_CONTROL_MODE_REPLY): 1
                                                for a in self.addresses}))
        refused = [f"0x{m.source:02X}" for m in replies if r.parse_switch_mode_reply(m) is not
                   r.ControlModeReply.TORQUE_OK]
        self._set_modes(replies, r.ControlModeReply.TORQUE_OK, 1)
        if refused:
            raise LinkError(f"torque mode refused by {', '.join(refused)}")

    def _set_modes(self, replies, accepted: r.ControlModeReply, mode: int) -> None:
        """Each actuator whose 0x204 says ``accepted`` is in ``mode`` now."""
        for reply in replies:
            joint = self._joint_of[reply.source]
            if joint >= 0 and r.parse_switch_mode_reply(reply) is accepted:
                self.mode[joint] = mode

    def switch_to_position(self) -> None:
        self._request(r.to_records(r.switch_mode_request(r.ControlModeRequest.POSITION, address)
                                   for address in self.addresses))
        replies = r.from_records(self._collect({(a, r.Command.SWITCH_CONTROL_MODE_REPLY): 1
                                                for a in self.addresses}))
        self._set_modes(replies, r.ControlModeReply.POSITION_OK, 0)


class LinkHardware:
    """The robot node's hardware interface on an RS-485 link: each exchange is one 0x14 to every actuator and its
    21 replies. The reading's stamp is the replies' (the emulated arm's timeline, or the interface's receive time
    on a real arm).

    Pipelined, as a fieldbus master runs its cycle: an exchange sends this cycle's targets and returns the replies
    to the previous cycle's, which have had a whole cycle to come back (they are waited for, up to the link's
    timeout from their sending, only when they have not). So the host keeps its 2 ms cycle whatever the round trip
    up to a cycle costs, at the price of one cycle more between a reading and the targets made from it. The first
    exchange, and the first after a failure, wait for their own replies."""

    simulated_in_process = False
    #: over RS-485 the base's DSP is bypassed and no actuator computes the arm's gravity (kinova.md; abr/abr_jaco2
    #: sends host-computed gravity torques): the host sends it with every torque
    actuators_compensate_gravity = False

    def __init__(self, link: ActuatorLink, arm: ArmDescription, pipelined: bool = True,
                 counted_from_ns: Optional[int] = None, timing: BusTiming = DEFAULT_TIMING) -> None:
        """``counted_from_ns``: the emulated arm in lockstep behind a wire that carries no stamps (Kinova's USB
        comm layer): its timeline is counted here instead, this plus one bus cycle per exchange sent (the arm
        steps once per host batch, from ``protocol.conventions.LOCKSTEP_EPOCH_NS``); in step only."""
        if counted_from_ns is not None and pipelined:
            raise ValueError("a counted timeline needs exchanges in step (lockstep), not pipelined")
        self.link = link
        self.arm = arm
        self.counted_from_ns = counted_from_ns
        #: the host's cycle on this bus (the node paces its exchanges on it)
        self.timing = timing
        if counted_from_ns is not None and timing != DEFAULT_TIMING:
            raise ValueError("a counted timeline is the emulated arm's 2 ms cycles, one per exchange")
        #: the readings are stamped on the emulated arm's own timeline: the replies' stamps (the bus says whether
        #: its interface keeps them), or counted here
        self.arm_timeline = link.bus.arm_timeline or counted_from_ns is not None
        self.pipelined = pipelined
        #: 0x14 batches sent so far (the counted timeline's cycles)
        self._sent = 0
        #: when the request whose replies are still to be collected went out (None: none is)
        self._outstanding: Optional[float] = None
        #: the next exchange waits for its own replies (at start, after a failure, after a mode switch)
        self._resync = True
        self._last: Optional[ActuatorValues] = None

    def read(self) -> JointReading:
        """The joints' positions (a GET_ACTUAL_POSITION round), before the first exchange."""
        try:
            positions = self.link.positions_deg()
        except LinkError as exc:
            raise HardwareError(str(exc)) from exc
        zeros = np.zeros(len(positions))
        stamp = self.link.last_stamp_ns if self.counted_from_ns is None else self._counted_stamp(self._sent)
        return reading_from_physical(ActuatorValues(positions, zeros, zeros, zeros, zeros, zeros.astype(int),
                                                    zeros.astype(int), stamp), self.arm)

    def _counted_stamp(self, cycle: int) -> int:
        return self.counted_from_ns + self.timing.stamp_ns(cycle)

    def exchange(self, targets: JointTargets) -> JointReading:
        position_deg, torque_nm = physical_targets(targets, self.arm)
        torques = torque_nm if targets.torques is not None else None
        link = self.link
        try:
            # in step: the first exchange, the first after a failure, and in torque mode (a torque loop is only as
            # good as its delay: it gets the replies of its own cycle)
            if self._resync or not self.pipelined or torques is not None:
                link.send_command(position_deg, torques, drain=True)
                cycle, self._sent = self._sent, self._sent + 1
                reading = link.collect_command(time.monotonic() + link.timeout_s)
                if self.counted_from_ns is not None:
                    reading = dataclasses.replace(reading, stamp_ns=self._counted_stamp(cycle))
                self._resync = False
            else:  # this cycle's targets out on time; then the previous cycle's replies (or, right after an
                # exchange in step, its reading again)
                sent = time.monotonic()
                link.send_command(position_deg, torques)
                reading = self._collect_outstanding() or self._last
                self._outstanding = sent
        except LinkError as exc:
            self._outstanding, self._resync = None, True  # start afresh, after draining what is left
            raise HardwareError(str(exc)) from exc
        self._last = reading
        return reading_from_physical(reading, self.arm)

    def _collect_outstanding(self) -> Optional[ActuatorValues]:
        if self._outstanding is None:
            return None
        sent, self._outstanding = self._outstanding, None
        return self.link.collect_command(sent + self.link.timeout_s)

    def _settle(self) -> None:
        """Collect what is outstanding before a request of another kind (a mode switch)."""
        try:
            self._collect_outstanding()
        except LinkError:
            pass
        self._outstanding, self._resync = None, True

    def enter_torque_mode(self, expected_torques: np.ndarray) -> None:
        self._settle()
        try:
            self.link.configure_torque_limits(self.arm.max_torque)  # the description's (kinova.md: 40/80/40/20/...)
            self.link.switch_to_torque(self.arm.sign * np.asarray(expected_torques, dtype=float))
        except LinkError as exc:
            raise HardwareError(str(exc)) from exc

    def leave_torque_mode(self) -> None:
        self._settle()
        try:
            self.link.switch_to_position()
        except LinkError as exc:
            raise HardwareError(str(exc)) from exc

    def zero_torque_sensor(self, joint: int) -> None:
        raise HardwareError("SetTorqueZero over RS-485: none of the actuators' RS-485 messages that are public "
                            "(kinova.md) zeroes a torque sensor; zero them through Kinova's SDK (the kinova_sdk "
                            "backend) or Kinova's Development Center")

    def set_gravity_compensation(self, on: bool) -> bool:
        # no public RS-485 message switches it (0x213 "torque feed-forward" is named in kinova.md, not described)
        return False

    def close(self) -> None:
        self.link.bus.close()


def expected_torques_physical(arm: ArmDescription, q_model) -> np.ndarray:
    """The gravity torques the host's model of ``arm`` expects at q (actuator sign), for the validation handshake."""
    from services.model.kinematics import ArmKinematics

    return arm.sign * ArmKinematics(arm).gravity(q_model)
