"""The host's RS-485 link against robot_sim's actuators running in realtime on a python-can virtual bus."""
import time

import numpy as np
import pytest

from protocol import rs485 as r
from services.robot.hardware import JointTargets
from services.robot_gateway.link import ActuatorLink, LinkError, LinkHardware
from services.stack.local import simulated_link
from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics
from services.model.dynamics import DynamicsModel
from tests.helpers import emulated_arm_gravity

ARM = load_arm("j2s7s300")


@pytest.fixture
def link():
    with simulated_link() as (runner, link):
        yield link, runner


def test_positions_and_all_values(link):
    link, runner = link
    positions = link.positions_deg()
    assert positions == pytest.approx(ARM.home_deg, abs=0.05)
    reading = link.command(positions)
    assert reading.position_deg == pytest.approx(ARM.home_deg, abs=0.05)
    assert np.all(reading.mode == 0) and np.all(reading.fault == 0)
    assert np.all(reading.temperature_c == pytest.approx(35.0))


def _torque_cycles(hardware: LinkHardware, q: np.ndarray, torques_at, seconds: float) -> np.ndarray:
    """``seconds`` of torque mode from angles ``q``, each cycle's torques (model sign) computed from the angles and
    rates just measured, as the robot node does; the angles at the end."""
    start = time.monotonic()
    dq = np.zeros(ARM.n_joints)
    while time.monotonic() - start < seconds:
        reading = hardware.exchange(JointTargets(q=q, torques=torques_at(q, dq)))
        q, dq = reading.q, reading.dq
        time.sleep(0.002)
    assert np.all(reading.mode == 1) and not reading.fault.any()
    return q


def _moved_in_torque_mode(torques_at, seconds: float = 0.2) -> np.ndarray:
    """A fresh arm at home on its bus (the gateway's hardware interface to robot_sim's actuators), switched to
    torque mode and brought to rest there by its own gravity and some damping (the actuators give no torque from
    the switch to the first torque command, and the arm starts to fall), then ``seconds`` of ``torques_at(q)``; how
    far each joint moved meanwhile (deg)."""
    arm_gravity = emulated_arm_gravity(ARM)
    damping = np.diag(DynamicsModel(ARM).mass(ARM.home)) / 0.02  # N·m·s/rad: a joint's velocity gone in ~20 ms
    with simulated_link(settle_s=0.2) as (_, link):
        hardware = LinkHardware(link, ARM, pipelined=False)
        q = hardware.read().q
        hardware.enter_torque_mode(ArmKinematics(ARM).gravity(q))
        rest = _torque_cycles(hardware, q, lambda q, dq: arm_gravity(q) - damping * dq, 0.15)
        moved = _torque_cycles(hardware, rest, lambda q, dq: torques_at(q), seconds) - rest
        hardware.leave_torque_mode()
        assert np.all(hardware.exchange(JointTargets(q=hardware.read().q)).mode == 0)
        return np.degrees(moved)


def test_over_the_bus_zero_torque_lets_the_arm_fall_and_its_gravity_holds_it():
    """robot_sim's actuators on their RS-485 bus add no gravity, as a real JACO-2's with the base's DSP bypassed
    (kinova.md; abr/abr_jaco2 sends host-computed gravity): zero torque lets the arm fall where gravity loads it
    (joints 2 and 4 at home, by degrees in 0.2 s); the description's gravity ĝ(q) holds it up but for what the
    description misses (the emulated hand is heavier: joint 4 sags about a seventh as far); the arm's own gravity
    (ĝ plus that miss) holds it still."""
    assert not LinkHardware.actuators_compensate_gravity  # so the robot node sends its gravity (test_lowlevel.py)
    model = ArmKinematics(ARM)
    falling = -np.sign(model.gravity(ARM.home))  # the way gravity turns each joint at home
    loaded = np.abs(model.gravity(ARM.home)) > 1.0  # N·m: joints 2 and 4
    fell = _moved_in_torque_mode(lambda q: np.zeros(ARM.n_joints))
    sagged = _moved_in_torque_mode(model.gravity)
    held = _moved_in_torque_mode(emulated_arm_gravity(ARM))
    print(f"over the bus in 0.2 s: zero torque {fell.round(2).tolist()}°, ĝ {sagged.round(2).tolist()}°, "
          f"the arm's gravity {held.round(2).tolist()}°")
    assert np.all(fell[loaded] * falling[loaded] > 2.0)  # 3.9° and 15.9° here
    assert np.all(sagged[loaded] * falling[loaded] > 0.0)  # the hand the description misses (2.2° at joint 4)
    assert np.all(np.abs(sagged) < 0.25 * np.abs(fell).max())
    assert np.abs(held).max() < 0.05


def test_bad_validation_is_refused(link):
    link, _ = link
    with pytest.raises(LinkError, match="validation failed"):
        link.switch_to_torque(np.full(7, 50.0))


def test_missing_replies_time_out_and_nacks_raise(link):
    link, _ = link
    ghost = ActuatorLink(link.bus, addresses=[0x30], timeout_s=0.02)
    with pytest.raises(LinkError, match="no reply"):
        ghost.positions_deg()
    assert link.bus.counters.get("link.timeouts") == 1
    link.bus.send(r.RS485Message(r.Command.KP_GAIN, 0, 0x10))
    with pytest.raises(LinkError, match="NACK"):
        ActuatorLink(link.bus, addresses=[0x10], timeout_s=0.05)._collect({(0x10, r.Command.ACK): 1})


def test_replies_of_the_next_cycle_that_come_early_are_kept_for_it():
    """Pipelined, the host sends the next cycle's targets before it collects the last cycle's replies; when both
    cycles' replies arrive in one read, the second cycle's belong to the next collection (a copy of the collector
    without this counted them as unexpected, and the next exchange then timed out)."""
    with simulated_link(lockstep=True) as (_, link):
        home = ARM.home_deg.astype(float)
        link.command(home)
        link.send_command(home)
        link.send_command(home + 0.01)
        time.sleep(0.3)  # both cycles' 21 replies are waiting now
        first = link.collect_command(time.monotonic() + 1.0)
        second = link.collect_command(time.monotonic() + 1.0)  # from what the first read kept
        assert second.stamp_ns >= first.stamp_ns > 0
        assert link.counters.get("link.unexpected") == 0 and link.counters.get("link.timeouts") == 0


class _QueuedBus:
    """A bus whose receive hands out prepared batches, one per call (the link's collection logic, without time)."""

    def __init__(self, batches):
        from services.runtime.metrics import Counters
        self.batches = list(batches)
        self.counters = Counters()

    def recv_batch(self, timeout):
        if not self.batches:
            return r.records(0), np.zeros(0, dtype=np.int64)
        batch = self.batches.pop(0)
        return batch, np.arange(len(batch), dtype=np.int64) + 1000


def _replies(addresses, order, extra=()):
    """The 0x15-0x17 of each address, in ``order`` (indices into the 3·n list), the joint's index in data[1]."""
    batch = r.records(3 * len(addresses))
    for j, address in enumerate(addresses):
        for kind in range(3):
            row = batch[3 * j + kind]
            row["source"], row["destination"] = address, r.HOST_ADDRESS
            row["command"] = int(r.Command.SEND_ALL_VALUES_1) + kind
            row["data"] = (kind, float(j), 0.0, 0.0)
    return np.concatenate([batch[list(order)], *extra]) if extra else batch[list(order)]


@pytest.mark.parametrize("seed", range(5))
def test_a_whole_reply_set_in_any_order_is_taken_at_once_and_the_same_as_one_by_one(seed):
    addresses = list(ARM.bus_addresses)
    order = np.random.default_rng(seed).permutation(3 * len(addresses))
    next_cycle = _replies(addresses, range(3))  # the next request's first replies, already here
    whole = ActuatorLink(_QueuedBus([_replies(addresses, order, extra=[next_cycle])]), addresses)
    table = whole._collect_values(time.monotonic() + 1.0)
    # the same replies split in two batches take the message-by-message path
    split = _replies(addresses, order)
    piecewise = ActuatorLink(_QueuedBus([split[:5], split[5:]]), addresses)
    assert np.array_equal(table, piecewise._collect_values(time.monotonic() + 1.0))
    assert np.array_equal(table["data"][:, :, 1], np.repeat(np.arange(len(addresses))[:, None], 3, axis=1))
    assert whole.last_stamp_ns == 1000 + 3 * len(addresses) - 1
    assert np.array_equal(whole._carry[0], next_cycle)  # kept for the next collection


def test_a_duplicate_reply_in_a_full_batch_is_counted_not_taken():
    addresses = list(ARM.bus_addresses)
    n = 3 * len(addresses)
    duplicated = _replies(addresses, [0] + list(range(n - 1)))  # the first twice, the last one missing ...
    late = _replies(addresses, [n - 1])  # ... comes in the next batch
    link = ActuatorLink(_QueuedBus([duplicated, late]), addresses)
    table = link._collect_values(time.monotonic() + 1.0)
    assert link.counters.get("link.unexpected") == 1
    assert np.array_equal(table, _replies(addresses, range(n)).reshape(len(addresses), 3))


def test_mode_comes_from_the_handshake_and_faults_from_error_reports_never_from_0x17(link):
    """No public source describes 0x17's floats 2 and 3 (docs/rs485-sources.md): the link takes each actuator's
    mode from its 0x204 reply and its fault from its 0x30 reports (a report of code 0 is no fault; a fault stays),
    whatever 0x17 carries."""
    link, runner = link
    positions = link.positions_deg()
    assert not link.command(positions).mode.any()
    link.switch_to_torque(ArmKinematics(ARM).gravity(ARM.home) * ARM.sign)
    reading = link.command(positions, np.zeros(ARM.n_joints))
    assert reading.mode.tolist() == [1] * ARM.n_joints and not reading.fault.any()
    link.switch_to_position()
    assert not link.command(positions).mode.any()
    no_error = r.to_records([r.report_error(r.ActuatorError.NONE, ARM.bus_addresses[1])])
    relative = r.to_records([r.report_error(r.ActuatorError.RELATIVE_POSITION, ARM.bus_addresses[2])])
    link._record_errors(no_error)
    link._record_errors(relative)
    reading = link.command(positions)
    assert reading.fault.tolist() == [0, 0, int(r.ActuatorError.RELATIVE_POSITION), 0, 0, 0, 0]
    assert link.counters.get("link.actuator_errors.relative_position") == 1
    assert link.counters.get("link.actuator_errors.none") == 0
