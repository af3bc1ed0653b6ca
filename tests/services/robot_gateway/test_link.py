"""The host's RS-485 link against robot_sim's actuators running in realtime on a python-can virtual bus."""
import time

import numpy as np
import pytest

from protocol import rs485 as r
from services.robot_gateway.link import ActuatorLink, LinkError, expected_torques_physical
from services.stack import simulated_link
from services.model.arm import load_arm

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


def test_torque_mode_round_trip_holds_the_arm_with_gravity_compensation(link):
    link, runner = link
    time.sleep(0.2)
    with runner.lock:
        q = runner.sim.q
    link.switch_to_torque(expected_torques_physical(ARM, q))
    positions = link.positions_deg()
    for _ in range(100):  # 0.2 s of zero extra torque: the actuators' gravity compensation holds the arm
        reading = link.command(positions, np.zeros(7))
        time.sleep(0.002)
    assert np.all(reading.mode == 1)
    assert np.abs(reading.position_deg - positions).max() < 1.0
    link.switch_to_position()
    assert np.all(link.command(link.positions_deg()).mode == 0)


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
