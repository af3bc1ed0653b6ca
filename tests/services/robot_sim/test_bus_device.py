"""robot_sim's actuators on an RS-485 bus carried by python-can (virtual interface), cycle by cycle on the arm's
timeline: replies byte for byte, interpolated position mode, the torque-mode handshake, the 250 ms torque
fallback, faults, missed and superseded frames, and garbled frames."""
import contextlib
import itertools
import math
import struct
import time

import numpy as np
import pytest

from protocol import rs485 as r
from services.robot.rs485_bus import BusConfig, RS485Bus
from services.robot_sim.bus_device import ActuatorBusDevice
from services.robot_sim.sim import Simulation
from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics

ARM = load_arm("j2s7s300")

_channels = itertools.count()


class Rig:
    """A simulated arm whose actuators sit on a bus (answering each frame as it comes, as in realtime), and the
    host's end of that bus."""

    def __init__(self):
        channel = f"test-bus-{next(_channels)}"
        self.sim = Simulation(render=False)
        self.host = RS485Bus(BusConfig(channel=channel))
        self.device_bus = RS485Bus(BusConfig(channel=channel))
        self.device = ActuatorBusDevice(self.sim)
        self.firmware = self.sim.firmware

    def cycle(self, n: int = 1) -> list[r.RS485Message]:
        """n cycles of 2 ms: the frames that came are answered, the boundary takes their commands, physics runs;
        returns what the host received."""
        return [message for message, _ in self.cycle_stamped(n)]

    def cycle_stamped(self, n: int = 1) -> list[tuple[r.RS485Message, int]]:
        for _ in range(n):
            batch, _ = self.device_bus.recv_batch(0.0)
            self.device_bus.send_batch(self.device.receive_batch(batch), self.device.values.stamp_ns)
            self.device_bus.send_batch(self.device.begin_cycle(), self.device.values.stamp_ns)
            self.sim.end_cycle()
        received = []
        while (item := self.host.recv_stamped(0.0)) is not None:
            received.append(item)
        return received

    def request(self, message: r.RS485Message) -> list[r.RS485Message]:
        self.host.send(message)
        return self.cycle(1)

    def close(self):
        self.host.close()
        self.device_bus.close()


@pytest.fixture
def rig():
    rig = Rig()
    yield rig
    rig.close()


def f32(x):
    return struct.unpack("<f", struct.pack("<f", x))[0]


def test_actual_position_reply_is_byte_exact_with_the_position_in_float_1(rig):
    """0x02 in 0x15's layout, as every public driver reads it: [current, position, velocity, torque]; a host that
    took float[0] for the position would take the motor current for a joint angle."""
    (reply,) = rig.request(r.RS485Message(r.Command.GET_ACTUAL_POSITION, r.HOST_ADDRESS, 0x11))
    position = ARM.model_to_physical_deg(rig.sim.q)[1]
    v = rig.device.values  # the cycle's (the sensors' noise differs from cycle to cycle)
    assert reply.encode()[:4] == struct.pack("<hBB", 0x02, 0x11, 0x00)
    assert reply.floats[r.POSITION_FLOAT] == f32(position)
    assert reply.floats[r.CURRENT_FLOAT] == pytest.approx(v.current_a[1], abs=0.05)
    assert reply.floats[r.VELOCITY_FLOAT] == pytest.approx(v.velocity_dps[1], abs=0.05)
    assert reply.floats[r.TORQUE_FLOAT] == pytest.approx(v.torque_nm[1], abs=0.5)
    # the arm holds against gravity at home: a current there, not an angle
    assert abs(reply.floats[r.CURRENT_FLOAT] - reply.floats[r.POSITION_FLOAT]) > 1.0


def test_position_and_torque_command_gets_one_reply_of_each_kind(rig):
    target = float(ARM.home_deg[0])
    replies = rig.request(r.PositionTorqueCommand(target).to_message(0x10))
    assert [m.command for m in replies] == [r.Command.SEND_ALL_VALUES_1, r.Command.SEND_ALL_VALUES_2,
                                            r.Command.SEND_ALL_VALUES_3]
    assert all(m.source == 0x10 and m.destination == 0x00 and len(m.encode()) == 20 for m in replies)
    values = r.AllValues1.from_message(replies[0])
    assert values.position_deg == pytest.approx(f32(target), abs=0.05)
    # 0x16 [PWM, position, int16 ax, ay, az, temperature]; 0x17 [current, absolute position, 0, 0]
    two = r.AllValues2.from_message(replies[1])
    assert two.position_deg == values.position_deg and two.accel_g == (0.0, 0.0, 1.0)
    assert two.temperature_c == pytest.approx(35.0)
    three = r.AllValues3.from_message(replies[2])
    assert (three.current_a, three.absolute_position_deg) == (values.current_a, values.position_deg)
    assert replies[2].floats[2:] == (0.0, 0.0)
    # one 0x14 per actuator gets 7 × 3 replies
    for address in ARM.bus_addresses:
        i = ARM.bus_addresses.index(address)
        rig.host.send(r.PositionTorqueCommand(float(ARM.home_deg[i])).to_message(address))
    replies = rig.cycle(1)
    assert len(replies) == 21 and {m.source for m in replies} == set(ARM.bus_addresses)


def test_replies_are_stamped_with_the_arm_cycle_they_report(rig):
    rig.cycle(3)  # boundaries at 0, 2 and 4 ms: the third cycle runs from 4 ms
    rig.host.send(r.PositionTorqueCommand(float(ARM.home_deg[0])).to_message(0x10))
    stamped = rig.cycle_stamped(1)
    # the command came during that cycle: the replies carry its values and its time
    assert {stamp for _, stamp in stamped} == {4_000_000}


def test_position_mode_moves_the_joint_to_the_target(rig):
    target = float(ARM.home_deg[3]) + 5.0
    for _ in range(400):
        rig.host.send(r.PositionTorqueCommand(target).to_message(0x13))
        rig.cycle(1)
    assert ARM.model_to_physical_deg(rig.sim.q)[3] == pytest.approx(target, abs=0.1)


def test_a_target_is_reached_at_the_end_of_the_cycle_that_takes_it(rig):
    """Interpolated position mode: the reference moves from where it is to the new target across one cycle."""
    address, home = 0x15, float(ARM.home_deg[5])
    actuator = rig.firmware.actuators[5]
    rig.host.send(r.PositionTorqueCommand(home + 0.01).to_message(address))
    rig.cycle(1)
    assert actuator.last_target_deg == f32(home + 0.01)
    assert actuator.target_rate_dps == pytest.approx((f32(home + 0.01) - home) / 0.002, rel=1e-3)
    assert rig.firmware.reference(actuator.target_time_s + 0.001)[0][5] == \
        pytest.approx((home + f32(home + 0.01)) / 2, abs=1e-4)


def test_a_missed_cycle_goes_on_one_cycle_then_holds_and_superseded_ones_are_counted(rig):
    """A host that is late: a cycle without a target continues the reference along its rate for that cycle (where
    the host's next target would have taken it), then the reference holds; two targets in one cycle keep the
    newer. Both are counted, and a target that only came late continues the motion without a jump."""
    address, home = 0x11, float(ARM.home_deg[1])
    actuator = rig.firmware.actuators[1]
    for k in range(5):
        rig.host.send(r.PositionTorqueCommand(home + 0.02 * k).to_message(address))
        rig.cycle(1)
    start, rate = actuator.target_deg, actuator.target_rate_dps  # the segment from the 4th target to the 5th
    assert rate == pytest.approx(0.02 / 0.002, rel=1e-3)
    rig.cycle(1)  # nothing came
    assert rig.firmware.counters.get("frames.missed") >= 1
    def reference(t_s: float) -> tuple[float, float]:
        position, rate = rig.firmware.reference(t_s)
        return position[1], rate[1]

    assert reference(actuator.target_time_s + 0.003) == pytest.approx((start + rate * 0.003, rate))
    assert reference(actuator.target_time_s + 0.0045) == pytest.approx((start + rate * 0.004, 0.0))  # it went on one cycle, and holds there
    # the late target and the next one come in the same cycle: the newer wins, from where the reference went on
    rig.host.send(r.PositionTorqueCommand(home + 0.10).to_message(address))
    rig.host.send(r.PositionTorqueCommand(home + 0.12).to_message(address))
    rig.cycle(1)
    assert actuator.last_target_deg == f32(home + 0.12)
    assert rig.firmware.counters.get("frames.superseded") == 1
    assert actuator.target_deg == pytest.approx(start + rate * 0.004, abs=1e-4)  # no jump
    assert actuator.target_rate_dps == pytest.approx(0.02 / 0.002, rel=0.05)  # at the host's pace


@pytest.mark.parametrize("joint", [1, 5])
def test_position_mode_follows_a_moving_target_without_lag_or_overshoot(rig, joint):
    """A heavy shoulder joint and a light wrist joint both follow a 4 Hz sinusoidal target sent at 500 Hz, each
    target for the end of the cycle that takes it (as the robot node plans), with the jitter of a host that is
    not hard realtime (every 7th command late by a cycle): the fundamental of the reported position matches the
    target's within 3 % and within a cycle."""
    address = ARM.bus_addresses[joint]
    home = float(ARM.home_deg[joint])
    f, amplitude = 4.0, 0.5

    def target(t):
        return home + amplitude * math.sin(2 * math.pi * f * t) * min(1.0, t / 0.3)

    times, positions = [], []
    for k in range(700):
        late = k % 7 == 3
        if not late:
            rig.host.send(r.PositionTorqueCommand(target((k + 1) * 0.002), 0.0).to_message(address))
        for reply, stamp in rig.cycle_stamped(1):
            if reply.command is r.Command.SEND_ALL_VALUES_1 and reply.source == address:
                times.append(stamp * 1e-9)
                positions.append(reply.floats[1] - home)
        if late:  # the late command arrives with the next one, in the same cycle
            rig.host.send(r.PositionTorqueCommand(target((k + 1) * 0.002), 0.0).to_message(address))
    t, y = np.array(times), np.array(positions)
    keep = t > 0.5
    t, y = t[keep], y[keep]
    a, b = 2 * np.mean(y * np.sin(2 * np.pi * f * t)), 2 * np.mean(y * np.cos(2 * np.pi * f * t))
    assert np.hypot(a, b) / amplitude == pytest.approx(1.0, abs=0.03)
    assert abs(np.arctan2(b, a)) / (2 * np.pi * f) < 0.002


def torque_mode(rig, address=0x12):
    i = ARM.bus_addresses.index(address)
    measured = float(ARM.sign[i] * rig.sim.data.actuator_force[i])
    (valid,) = rig.request(r.RS485Message.with_floats(r.Command.GET_TORQUE_VALIDATION_REQUEST, 0, address,
                                                      [measured]))
    assert valid.command is r.Command.SEND_TORQUE_VALIDATION and valid.uints[0] == 1
    (reply,) = rig.request(r.switch_mode_request(r.ControlModeRequest.TORQUE, address))
    return reply


def test_switching_to_torque_needs_a_validation(rig):
    rig.cycle(50)  # settle: the measured torque is the gravity load
    (refused,) = rig.request(r.switch_mode_request(r.ControlModeRequest.TORQUE, 0x12))
    assert refused.encode() == struct.pack("<hBB4I", 0x204, 0x12, 0x00, 0, 0, 0, 0)
    (invalid,) = rig.request(r.RS485Message.with_floats(r.Command.GET_TORQUE_VALIDATION_REQUEST, 0, 0x12, [99.0]))
    assert invalid.uints[0] == 0
    reply = torque_mode(rig)
    assert reply.encode() == struct.pack("<hBB4I", 0x204, 0x12, 0x00, 257, 0, 0, 0)
    (back,) = rig.request(r.switch_mode_request(r.ControlModeRequest.POSITION, 0x12))
    assert r.parse_switch_mode_reply(back) is r.ControlModeReply.POSITION_OK


def test_torque_mode_falls_back_to_position_after_250_ms_without_torque_commands(rig):
    rig.cycle(50)
    assert r.parse_switch_mode_reply(torque_mode(rig)) is r.ControlModeReply.TORQUE_OK
    position = float(ARM.model_to_physical_deg(rig.sim.q)[2])
    for _ in range(50):  # 100 ms of zero torque commands: joint 3 carries almost no gravity at home
        rig.host.send(r.PositionTorqueCommand(position, 0.0, mode=1).to_message(0x12))
        rig.cycle(1)
    actuator = rig.firmware.by_address[0x12]
    assert actuator.mode is r.ControlModeRequest.TORQUE
    last_command = actuator.last_torque_s
    while actuator.mode is r.ControlModeRequest.TORQUE and rig.sim.time_ns < 10e9:
        rig.cycle(1)
    fallback = rig.firmware.now_s
    assert fallback - last_command == pytest.approx(0.25, abs=0.0025)  # 250 ms ± one 2 ms cycle
    assert rig.firmware.counters.get("torque_timeouts") == 1


def test_on_its_bus_the_arm_adds_no_gravity_in_torque_mode_as_the_api_mode_s_actuators_do(rig):
    """Over RS-485 the base's DSP is bypassed (kinova.md: no gravity compensation; abr/abr_jaco2 sends
    host-computed gravity torques): joint 4, loaded by the forearm and hand at home, falls under zero torque in
    100 ms, and nothing turns the compensation on (no bus message does; the api mode's switch does not reach it).
    The same arm in robot_sim's process, standing for Kinova's DSP, holds under zero extra torque."""
    from services.robot.hardware import JointTargets
    from services.robot_sim.hardware import SimulatedHardware

    rig.firmware.set_gravity_compensation(True)
    assert not rig.firmware.compensating_gravity
    rig.cycle(50)
    assert r.parse_switch_mode_reply(torque_mode(rig, 0x13)) is r.ControlModeReply.TORQUE_OK
    start = float(ARM.model_to_physical_deg(rig.sim.q)[3])
    for _ in range(50):
        rig.host.send(r.PositionTorqueCommand(float(ARM.model_to_physical_deg(rig.sim.q)[3]), 0.0,
                                              mode=1).to_message(0x13))
        rig.cycle(1)
    fell = float(ARM.model_to_physical_deg(rig.sim.q)[3]) - start
    api = SimulatedHardware(Simulation(render=False))
    start_reading = reading = api.read()
    for _ in range(50):  # holding where it starts
        reading = api.exchange(JointTargets(q=start_reading.q))
    api.enter_torque_mode(ArmKinematics(ARM).gravity(reading.q))
    held = reading.q
    for _ in range(50):
        reading = api.exchange(JointTargets(q=reading.q, torques=np.zeros(7)))
    print(f"joint 4 under zero torque for 100 ms: {fell:.2f}° on the bus, "
          f"{np.degrees(reading.q - held)[3]:.3f}° in robot_sim's process")
    assert abs(fell) > 2.0  # about 4° here
    assert np.degrees(np.abs(reading.q - held)).max() < 0.05


def test_torque_over_the_limit_is_clamped_and_reported_once(rig):
    rig.cycle(50)
    torque_mode(rig)
    position = float(ARM.model_to_physical_deg(rig.sim.q)[2])
    replies = rig.request(r.PositionTorqueCommand(position, 500.0, mode=1).to_message(0x12))
    errors = [m for m in replies if m.command is r.Command.REPORT_ERROR]
    assert len(errors) == 1 and r.parse_report_error(errors[0]) is r.ActuatorError.TORQUE
    assert rig.firmware.by_address[0x12].torque_nm == pytest.approx(ARM.max_torque[2])
    replies = rig.request(r.PositionTorqueCommand(position, 500.0, mode=1).to_message(0x12))
    assert not [m for m in replies if m.command is r.Command.REPORT_ERROR]


def test_a_wrong_safety_reference_latches_a_fault_until_cleared(rig):
    rig.cycle(50)
    torque_mode(rig)
    replies = rig.request(r.PositionTorqueCommand(123.0, 1.0, mode=1).to_message(0x12))  # far from the real angle
    errors = [m for m in replies if m.command is r.Command.REPORT_ERROR]
    assert r.parse_report_error(errors[0]) is r.ActuatorError.RELATIVE_POSITION
    actuator = rig.firmware.by_address[0x12]
    assert actuator.fault is r.ActuatorError.RELATIVE_POSITION and actuator.mode is r.ControlModeRequest.POSITION
    (refused,) = rig.request(r.switch_mode_request(r.ControlModeRequest.TORQUE, 0x12))
    assert r.parse_switch_mode_reply(refused) is r.ControlModeReply.REFUSED
    (ack,) = rig.request(r.RS485Message(r.Command.CLEAR_FAULT_FLAG, 0, 0x12))
    assert ack.command is r.Command.ACK and actuator.fault is r.ActuatorError.NONE


def test_garbled_frames_are_rejected_and_counted_without_disturbing_the_loop(rig):
    q0 = rig.sim.q
    rig.host.send_raw(bytes(19), 0x10)  # truncated
    rig.host.send_raw(struct.pack("<hBB", 0x77, 0, 0x10) + bytes(16), 0x10)  # unknown command
    rig.host.send_raw(bytes(64), 0x10)  # too long
    replies = rig.request(r.RS485Message(r.Command.GET_ACTUAL_POSITION, 0, 0x10))
    assert [m.command for m in replies] == [r.Command.SEND_ACTUAL_POSITION]
    assert rig.device_bus.counters.get("bus.rejected") == 3
    rig.cycle(50)
    assert np.abs(rig.sim.q - q0).max() < math.radians(0.05)


def test_unsupported_commands_get_a_nack(rig):
    (nack,) = rig.request(r.RS485Message(r.Command.KP_GAIN, 0, 0x14))
    assert nack.command is r.Command.NACK and nack.source == 0x14


def test_host_cycles_split_what_a_stalled_loop_finds_queued():
    from services.robot_sim.arm_on_bus import host_cycles

    addresses = list(ARM.bus_addresses)
    first = r.position_torque_records(addresses, np.full(7, 1.0))
    second = r.position_torque_records(addresses, np.full(7, 2.0))
    other = r.to_records([r.RS485Message(r.Command.GET_ACTUAL_POSITION, r.HOST_ADDRESS, addresses[0])])
    cycles = host_cycles(np.concatenate([first, other, second]))
    assert [len(c) for c in cycles] == [8, 7]
    assert np.all(cycles[0]["data"][:7, 0] == 1.0) and cycles[0]["command"][7] == r.Command.GET_ACTUAL_POSITION
    assert np.all(cycles[1]["data"][:, 0] == 2.0)
    assert [len(c) for c in host_cycles(first)] == [7] and [len(c) for c in host_cycles(r.records(0))] == [0]


@contextlib.contextmanager
def arm_on_a_bus(config=None):
    """The emulated arm on a bus, its realtime loop not started (the test serves its boundaries), the host's end of
    that bus, and the simulation: ``(arm, host, sim)``."""
    from services.robot_sim.arm_on_bus import ArmOnBus

    channel = f"test-bus-{next(_channels)}"
    sim = Simulation(render=False)
    host, device_bus = RS485Bus(BusConfig(channel=channel)), RS485Bus(BusConfig(channel=channel))
    try:
        yield ArmOnBus(sim, device_bus, config), host, sim
    finally:
        host.close()
        device_bus.close()
        sim.close()


def test_a_loop_catching_up_gives_each_boundary_its_own_host_cycle():
    """A stalled emulated arm finds two cycles' targets queued: each of the two boundaries it then runs takes its
    own (the real actuators, never stalled, took them one cycle apart); taken together the newest would win and
    the arm would make two cycles' motion in one."""
    with arm_on_a_bus() as (arm, host, sim):
        addresses = list(ARM.bus_addresses)
        start = ARM.model_to_physical_deg(sim.q)
        for k in (1, 2):
            host.send_batch(r.position_torque_records(addresses, start + 0.01 * k))
        taken = []
        for _ in range(2):
            assert arm._serve(0.0, one_cycle=True) == 7
            taken.append([a.pending[0] for a in sim.firmware.actuators])
            arm._cycle()
        assert np.allclose(taken[0], start + 0.01, atol=1e-4) and np.allclose(taken[1], start + 0.02, atol=1e-4)
        assert arm.backlog == [] and arm.counters.get("frames.held_for_catch_up") == 1
        assert not sim.firmware.counters.get("frames.superseded")


def test_a_loop_catching_up_takes_each_host_cycle_no_earlier_than_it_was_sent():
    """A stalled emulated arm finds a 5 ms host's three cycles queued, sent 5 ms apart: catching up, it runs
    boundaries past on the host's clock, and takes each cycle at the first of them after it was sent (within a
    cycle), not one per boundary: taken one per 2 ms, the joints ran 2.15 times the host's rate."""
    with arm_on_a_bus() as (arm, host, sim):
        addresses = list(ARM.bus_addresses)
        start = ARM.model_to_physical_deg(sim.q)
        sent_ns = time.time_ns() - 50_000_000  # the host sent them 50, 45 and 40 ms ago; the arm was stalled
        for k in range(3):
            host.send_batch(r.position_torque_records(addresses, start + 0.01 * (k + 1)), sent_ns + k * 5_000_000)
        taken = []
        for boundary_ms in (0.5, 2.5, 4.5, 6.5, 8.5, 10.5):  # after the first cycle was sent, on the host's clock
            timeout_s = (sent_ns + boundary_ms * 1e6 - time.time_ns()) * 1e-9  # in the past: catching up
            got = arm._serve(timeout_s, one_cycle=True)
            taken.append(round(sim.firmware.actuators[0].pending[0] - start[0], 4) if got > 0 else None)
            arm._cycle()
        assert taken == [0.01, None, 0.02, None, 0.03, None], taken
        assert arm.backlog == []


def test_a_slower_hosts_cycle_bunched_behind_the_last_waits_for_the_next_boundary():
    """A host at 3.33 ms whose batch came late arrives just before the next one: in one read or in two within the
    same 2 ms window, the boundary takes the first host cycle and the second waits for the next boundary (taken
    together, the newest would win and the joints make two of the host's periods' motion in one)."""
    from services.robot_sim.arm_on_bus import ArmOnBusConfig, host_cycles

    addresses = list(ARM.bus_addresses)
    assert [len(c) for c in host_cycles(r.position_torque_records(addresses, np.ones(7)),
                                        {addresses[0]: 1})] == [6, 1]  # (one actuator commanded already)
    with arm_on_a_bus(ArmOnBusConfig(host_period_s=10e-3 / 3)) as (arm, host, sim):
        start = ARM.model_to_physical_deg(sim.q)
        for in_one_read in (True, False):
            base = start + (0.0 if in_one_read else 0.1)
            batches = [r.position_torque_records(addresses, base + 0.01 * k) for k in (1, 2)]
            window: dict = {}
            if in_one_read:
                host.send_batch(np.concatenate(batches))
                assert arm._serve(0.05, one_cycle=True, window=window) == 7
            else:
                host.send_batch(batches[0])
                assert arm._serve(0.05, one_cycle=True, window=window) == 7
                host.send_batch(batches[1])
                assert arm._serve(0.05, one_cycle=True, window=window) == 0  # read, held for the next boundary
            assert arm._serve(0.001, one_cycle=True, window=window) == -1  # nothing more at this boundary
            assert np.allclose([a.pending[0] for a in sim.firmware.actuators], base + 0.01, atol=1e-4)
            arm._cycle()
            assert arm._serve(0.0, one_cycle=True, window={}) == 7  # the next boundary takes it
            assert np.allclose([a.pending[0] for a in sim.firmware.actuators], base + 0.02, atol=1e-4)
            arm._cycle()
            assert arm.backlog == []


def test_the_torque_safety_configuration_is_acknowledged_and_limits_the_torque(rig):
    """0x208 as abr/abr_jaco2 sends it before torque mode: float[0] the most torque the actuator may give, ACKed
    (uint32[0] the command acknowledged); a torque command beyond it is clamped to it and reported once; a limit
    beyond what the actuator can give is refused (NACK)."""
    rig.cycle(50)
    (ack,) = rig.request(r.torque_config_safety(5.0, 0x12))
    assert ack.command is r.Command.ACK and ack.uints[0] == r.Command.TORQUE_CONFIG_SAFETY
    torque_mode(rig)
    position = float(ARM.model_to_physical_deg(rig.sim.q)[2])
    replies = rig.request(r.PositionTorqueCommand(position, 30.0, mode=1).to_message(0x12))
    assert [r.parse_report_error(m) for m in replies if m.command is r.Command.REPORT_ERROR] == [r.ActuatorError.TORQUE]
    assert rig.firmware.by_address[0x12].torque_nm == pytest.approx(5.0)
    (refused,) = rig.request(r.torque_config_safety(10 * float(ARM.max_torque[2]), 0x12))
    assert refused.command is r.Command.NACK


def test_the_finger_actuators_at_0x16_0x18_take_a_position_command_and_answer_its_position_and_current(rig):
    """abr/abr_jaco2's finger message (0x10 to 0x16-0x18, float[0] = float[1] = the target in finger units) closes
    the fingers; each answers 0x11 [current, position in units, velocity in units/s, 0] with the cycle's values."""
    hand = ARM.hand
    first = rig.request(r.RS485Message.with_floats(r.Command.GET_POSITION_COMMAND, r.HOST_ADDRESS, 0x16,
                                                   [3400.0, 3400.0, 0.0, 0.0]))
    assert [(m.command, m.source) for m in first] == [(r.Command.SEND_POSITION_CURRENT, 0x16)]
    assert first[0].floats[1] == pytest.approx(0.0, abs=1.0)  # the cycle it came in: still open
    for address in (0x17, 0x18):
        rig.host.send(r.RS485Message.with_floats(r.Command.GET_POSITION_COMMAND, r.HOST_ADDRESS, address,
                                                 [3400.0, 3400.0, 0.0, 0.0]))
    rig.cycle(600)  # 1.2 s: half the travel takes 0.6 s
    replies = [rig.request(r.RS485Message(r.Command.GET_ACTUAL_POSITION, r.HOST_ADDRESS, a))[0]
               for a in hand.bus_addresses]
    assert all(m.command is r.Command.SEND_ACTUAL_POSITION for m in replies)
    assert [m.floats[1] for m in replies] == pytest.approx([3400.0] * 3, abs=64.0)  # kinova-ros's tolerance
    assert np.allclose(rig.sim.fingers.position, hand.units_to_angle(3400.0), atol=1e-3)
    # halves that differ, or a NaN, are refused with a report; another command is not a finger's
    refused = rig.request(r.RS485Message.with_floats(r.Command.GET_POSITION_COMMAND, r.HOST_ADDRESS, 0x17,
                                                     [100.0, 200.0, 0.0, 0.0]))
    assert r.parse_report_error(refused[0]) is r.ActuatorError.COMMAND
    nack = rig.request(r.RS485Message(r.Command.POSITION_AND_TORQUE_COMMAND, r.HOST_ADDRESS, 0x18))
    assert nack[0].command is r.Command.NACK
    assert np.allclose(rig.sim.fingers.target, hand.units_to_angle(3400.0))
