"""The hand's fingers as a second actuator group of the robot node (services/robot/fingers.py): a finger keeps its
target until a finger command changes it, whatever else happens to the arm's commands; a command whose finger part
does not fit the hand is refused whole."""
import math

import msgpack
import numpy as np
import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics
from services.robot.core import RobotCore
from services.robot.dsp import DSPConfig, KinovaDSP
from services.robot.fingers import MAX_VELOCITY_LEAD
from services.robot.hardware import CYCLES_PER_DSP, FingerReading, JointReading
from services.robot.state_message import finger_state

ARM = load_arm("j2s7s300")
HAND = ARM.hand


def reading(fingers=(0.1, 0.2, 0.3)):
    n = ARM.n_joints
    hand = None if fingers is None else FingerReading(position=np.array(fingers, dtype=float),
                                                      velocity=np.zeros(3), current_a=np.zeros(3))
    return JointReading(q=ARM.home.copy(), dq=np.zeros(n), tau=np.zeros(n), fingers=hand)


def core_with(fingers=(0.1, 0.2, 0.3)):
    return RobotCore(KinovaDSP(DSPConfig(), ArmKinematics(ARM)), reading(fingers))


def command(mode=m.CommandMode.STOP, fingers=None, **kw):
    return m.RobotCommand(header=m.Header(), mode=mode, fingers=fingers, **kw)


def twist_command(fingers=None):
    twist = m.Twist(header=m.Header(), frame=Frame.MIXED, angular=AngularConvention.SEED000,
                    linear=(0.05, 0.0, 0.0), rotational=(0.0, 0.0, 0.0))
    return command(m.CommandMode.CARTESIAN_VELOCITY, fingers, twist=twist)


def bus_cycles(core, n, command_every_dsp=None):
    """``n`` bus cycles of the node's loop, the DSP every fifth with ``command_every_dsp`` (None: no command)."""
    targets = []
    for k in range(n):
        targets.append(core.targets())
        if k % CYCLES_PER_DSP == CYCLES_PER_DSP - 1:
            core.dsp_cycle(command_every_dsp)
    return targets


def test_every_arm_carries_the_kg3_and_its_numbers_are_its_sources():
    for name in ("j2s7s300", "j2n6s300", "j2s6s300"):
        hand = load_arm(name).hand
        assert hand.name == "kg3" and hand.finger_names == ("finger_1", "finger_2", "finger_3")
        assert hand.bus_addresses == (0x16, 0x17, 0x18)  # kinova.md, abr_jaco2's HAND_ADDRESS
    # kinova-ros: 6800 units = 80 deg; dm_control's data-sheet closing time 1.2 s
    assert HAND.units_to_angle(6800) == pytest.approx(math.radians(80))
    assert HAND.angle_to_units(math.radians(40)) == pytest.approx(3400)
    assert HAND.max_speed == pytest.approx(math.radians(80) / 1.2)


def test_the_hands_file_is_part_of_the_arms_fingerprint(tmp_path, monkeypatch):
    from services.model import arm as arm_module

    hands = tmp_path / "hands"
    hands.mkdir()
    text = (arm_module.HANDS_DIR / "kg3.yaml").read_text()
    (hands / "kg3.yaml").write_text(text)
    monkeypatch.setattr(arm_module, "HANDS_DIR", hands)
    before = arm_module.read_description(ARM.path).digest
    (hands / "kg3.yaml").write_text(text.replace("closing_time_s: 1.2", "closing_time_s: 1.5"))
    after = arm_module.read_description(ARM.path)
    assert after.hand.closing_time_s == 1.5 and after.digest != before


@pytest.mark.parametrize("edit, words", [
    (lambda t: t.replace("hand: kg3", "hand: kg9"), "unknown hand 'kg9'"),
    (lambda t: t.replace("bus_addresses: [0x10", "bus_addresses: [0x16"), "distinct addresses"),
])
def test_an_arm_file_naming_a_hand_badly_is_refused(tmp_path, edit, words):
    from services.model.arm import ArmError, read_description

    path = tmp_path / "j2s7s300.yaml"
    path.write_text(edit(ARM.path.read_text()))
    with pytest.raises(ArmError, match=words):
        read_description(path)


def test_the_fingers_hold_where_they_are_until_a_finger_command():
    core = core_with()
    targets = bus_cycles(core, 20, None)
    assert all(np.array_equal(t.fingers, [0.1, 0.2, 0.3]) for t in targets)


def test_a_position_command_sets_the_targets_within_the_travel_and_they_stay_after_it():
    core = core_with()
    core.dsp_cycle(command(fingers=m.FingerCommand(mode=m.FingerMode.POSITION, values=[1.0, 5.0, -1.0])))
    closed = HAND.closed_angle
    for later in (None, command(), command(m.CommandMode.EMERGENCY_STOP), twist_command()):
        for t in bus_cycles(core, 10, later):
            assert np.allclose(t.fingers, [1.0, closed, 0.0])


def test_a_velocity_command_moves_the_targets_for_one_dsp_period_at_most_at_the_fingers_top_speed():
    core = core_with((0.5, 0.5, 0.5))
    core.dsp_cycle(command(fingers=m.FingerCommand(mode=m.FingerMode.VELOCITY, values=[0.2, -0.2, 100.0])))
    targets = [t.fingers for t in bus_cycles(core, 3 * CYCLES_PER_DSP, None)]
    dsp_period = CYCLES_PER_DSP * core.cycle_s
    expected = [0.5 + 0.2 * dsp_period, 0.5 - 0.2 * dsp_period, 0.5 + HAND.max_speed * dsp_period]
    assert np.allclose(targets[CYCLES_PER_DSP - 1], expected)
    assert np.allclose(targets[-1], expected)  # no new velocity command: the targets stay where they got


def test_a_velocity_stream_closing_on_a_blocked_finger_keeps_its_target_a_bounded_lead_ahead():
    core = core_with((0.5, 0.5, 0.5))  # the reading never changes: every finger is blocked
    close = command(fingers=m.FingerCommand(mode=m.FingerMode.VELOCITY, values=[HAND.max_speed] * 3))
    targets = bus_cycles(core, 100 * CYCLES_PER_DSP, close)
    assert np.allclose(targets[-1].fingers, 0.5 + MAX_VELOCITY_LEAD)
    # opening again starts at once from the lead, not from a target wound up far inside the object
    core.dsp_cycle(command(fingers=m.FingerCommand(mode=m.FingerMode.VELOCITY, values=[-HAND.max_speed] * 3)))
    assert np.all(core.targets().fingers < 0.5 + MAX_VELOCITY_LEAD)


def test_a_command_whose_finger_part_does_not_fit_is_refused_whole_and_moves_nothing():
    core = core_with()
    refusal = core.dsp_cycle(twist_command(m.FingerCommand(mode=m.FingerMode.POSITION, values=[1.0, 1.0])))
    assert refusal.kind == "fingers" and "3 fingers" in refusal.reason
    targets = bus_cycles(core, 10, None)
    assert np.array_equal(targets[-1].fingers, [0.1, 0.2, 0.3])
    assert np.allclose(targets[-1].q, ARM.home)  # the twist was not applied either


def test_an_arm_whose_hardware_reports_no_fingers_refuses_a_finger_command_and_carries_none():
    core = core_with(None)
    assert core.fingers is None and core.targets().fingers is None
    refusal = core.dsp_cycle(command(fingers=m.FingerCommand(mode=m.FingerMode.POSITION, values=[1.0] * 3)))
    assert refusal.kind == "fingers" and "no fingers" in refusal.reason
    assert core.dsp_cycle(command()) is None


def test_an_emergency_stop_cannot_carry_a_finger_command_and_a_finger_vector_has_at_most_three():
    with pytest.raises(ValueError, match="emergency stop carries no finger command"):
        command(m.CommandMode.EMERGENCY_STOP, m.FingerCommand(mode=m.FingerMode.POSITION, values=[0.0] * 3))
    plain = msgpack.unpackb(m.encode(command(fingers=m.FingerCommand(mode=m.FingerMode.POSITION,
                                                                      values=[0.0] * 3))))
    plain["fingers"]["values"].append(0.0)
    with pytest.raises(m.ProtocolError, match="fingers.values"):
        m.decode(msgpack.packb(plain), m.RobotCommand)
    plain["fingers"]["values"] = [0.0, math.nan, 0.0]
    with pytest.raises(m.ProtocolError, match="non-finite"):
        m.decode(msgpack.packb(plain), m.RobotCommand)
    with pytest.raises(ValueError, match="different lengths"):
        m.FingerState(position=[0.0] * 3, velocity=[0.0] * 3, current_a=[0.0] * 2, target=[0.0] * 3)


def test_the_state_carries_the_fingers_with_the_targets_they_hold():
    core = core_with()
    core.dsp_cycle(command(fingers=m.FingerCommand(mode=m.FingerMode.POSITION, values=[0.7, 0.8, 0.9])))
    state = finger_state(core.reading, core.fingers.target)
    assert state.position == [0.1, 0.2, 0.3] and state.target == [0.7, 0.8, 0.9]
    assert finger_state(reading(None), None) is None
