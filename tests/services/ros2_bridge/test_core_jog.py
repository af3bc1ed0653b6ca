"""A stick from ROS 2 as a person's jog requests, without zenoh: sensor_msgs/Joy through the joy map, the dead band,
the spasm filter and the speed levels; geometry_msgs/TwistStamped by its frame; the stamps and sequences; and every
input refused, each by its counter's name. The ROS messages are the bytes ROS 2's own serializers made
(tests/protocol/ros2/fixtures, make_fixtures.py) or mfvs's codec's, which those fixtures check."""
import json
from pathlib import Path

import numpy as np
import pytest

from protocol import messages as m
from protocol.messages import JogMode
from protocol.ros2 import cdr
from services.jog.mapping import JogMapping, SpasmFilterConfig
from services.ros2_bridge import core
from services.ros2_bridge.core import InputError, JoyAxis, JoyMap, RosJogConfig

FIXTURES = Path(__file__).resolve().parents[2] / "protocol" / "ros2" / "fixtures"
SAMPLES = json.loads((FIXTURES / "fixtures.json").read_text())["samples"]
NOW = 1_767_225_600_123_456_789  # the fixtures' stamp, as the bridge's clock at receipt
NO_FILTER = RosJogConfig(mapping=JogMapping(dead_band=0.05, spasm_filter=SpasmFilterConfig(enabled=False)),
                         speed_level=3)


def stamp(ns: int) -> cdr.Time:
    return cdr.Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def joy(axes=(0.0,) * 8, pressed=(), stamp_ns=NOW, buttons=11, frame="joy") -> bytes:
    values = np.zeros(buttons, dtype=np.int32)
    values[list(pressed)] = 1
    return cdr.serialize(cdr.Joy(header=cdr.Header(stamp=stamp(stamp_ns), frame_id=frame),
                                 axes=np.array(axes, dtype=np.float32), buttons=values))


def twist(frame="base_link", linear=(0.0, 0.0, 0.0), angular=(0.0, 0.0, 0.0), stamp_ns=NOW) -> bytes:
    return cdr.serialize(cdr.TwistStamped(header=cdr.Header(stamp=stamp(stamp_ns), frame_id=frame),
                                          twist=cdr.Twist(cdr.Vector3(*linear), cdr.Vector3(*angular))))


def refused(kind: str, call, *args):
    with pytest.raises(InputError) as caught:
        call(*args)
    assert caught.value.kind == kind, caught.value
    return str(caught.value)


# ------------------------------------------------------------------------------------------ the ROS tools' bytes
def test_the_joy_drivers_bytes_become_a_held_translation_at_the_stamp_it_carries():
    relay = core.JogRelay(NO_FILTER)
    payload = (FIXTURES / SAMPLES["joy"]["rclpy"]).read_bytes()
    out = relay.joy(payload, NOW + 10_000_000, 0.0)
    jog = out.jog
    # axes [-0.0, 0.5, -1.0, 0.25, 1.0, ...], LB (4) and Start (7) held: X from axis 1, Y from 0, Z from 4
    assert jog.deadman and jog.mode is JogMode.TRANSLATION and jog.source == "jog/ros-joy"
    speed = NO_FILTER.mapping.speeds.linear_mps
    band = NO_FILTER.mapping.dead_band
    assert jog.linear == pytest.approx(((0.5 - band) / (1 - band) * speed, 0.0, speed))
    assert out.stamp_used and jog.header.source_stamp_ns == NOW and jog.header.stamp_ns == NOW + 10_000_000
    assert jog.header.seq == 1


def test_rosbags_bytes_decode_to_the_same_joy_and_twist():
    for name, message_type in (("joy", cdr.Joy), ("joy_empty", cdr.Joy), ("twist_stamped", cdr.TwistStamped),
                               ("twist_stamped_hand", cdr.TwistStamped)):
        ours = cdr.deserialize((FIXTURES / SAMPLES[name]["rosbags"]).read_bytes(), message_type)
        assert ours == cdr.deserialize((FIXTURES / SAMPLES[name]["rclpy"]).read_bytes(), message_type), name


def test_the_twist_fixtures_become_a_translation_and_a_wrist_turn():
    relay = core.JogRelay(RosJogConfig())
    base_ns = 1_767_225_601_000_000_005
    moved = relay.twist((FIXTURES / SAMPLES["twist_stamped"]["rclpy"]).read_bytes(), base_ns + 1_000_000).jog
    assert (moved.mode, moved.deadman, moved.linear, moved.angular) == (JogMode.TRANSLATION, True,
                                                                         (0.05, -0.1, 0.025), (0.0, 0.0, 0.0))
    assert moved.header.source_stamp_ns == base_ns and moved.source == "jog/ros-twist"
    turned = relay.twist((FIXTURES / SAMPLES["twist_stamped_hand"]["rosbags"]).read_bytes(), NOW).jog
    assert (turned.mode, turned.angular, turned.linear) == (JogMode.WRIST, (0.3, -0.2, 0.1), (0.0, 0.0, 0.0))
    assert (moved.header.seq, turned.header.seq) == (1, 2)
    # each encodes as the protocol's Jog (only its mode's part non-zero)
    for jog in (moved, turned):
        assert m.decode(m.encode(jog), m.Jog) == jog


def test_a_joy_with_no_device_open_is_refused_by_its_size():
    relay = core.JogRelay(RosJogConfig())
    text = refused("size", relay.joy, (FIXTURES / SAMPLES["joy_empty"]["rclpy"]).read_bytes(), NOW, 0.0)
    assert "0 axes and 0 buttons" in text and "5 axes and 8 buttons" in text


# ------------------------------------------------------------------------------------------ the joy map
def test_the_dead_man_mode_and_speed_buttons_step_on_a_press_only():
    relay = core.JogRelay(RosJogConfig(mapping=NO_FILTER.mapping))  # starts at speed level 1
    up = (0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # left stick up: +X
    first = relay.joy(joy(up, pressed=(4,)), NOW, 0.0).jog
    assert first.speed_level == 1 and first.linear[0] == pytest.approx(0.2 * 0.25)
    held = [relay.joy(joy(up, pressed=(4, 5)), NOW + i, 0.01 * i).jog for i in range(1, 4)]  # RB held: one step
    assert [j.speed_level for j in held] == [2, 2, 2] and held[0].linear[0] == pytest.approx(0.2 * 0.5)
    relay.joy(joy(up, pressed=(4,)), NOW + 5, 0.05)
    assert relay.joy(joy(up, pressed=(4, 5)), NOW + 6, 0.06).jog.speed_level == 3
    assert relay.joy(joy(up, pressed=(4,)), NOW + 7, 0.07).jog.speed_level == 3
    assert relay.joy(joy(up, pressed=(4, 5)), NOW + 8, 0.08).jog.speed_level == 3  # the top stays the top
    assert relay.joy(joy(up, pressed=(4, 2)), NOW + 9, 0.09).jog.speed_level == 2  # X: down
    # A cycles the modes: wrist turns about the hand's x with the same axis, fingers take the first
    wrist = relay.joy(joy(up, pressed=(4, 0)), NOW + 10, 0.10).jog
    assert wrist.mode is JogMode.WRIST and wrist.angular[0] == pytest.approx(0.6 * 0.5) and not any(wrist.linear)
    relay.joy(joy(up, pressed=(4,)), NOW + 11, 0.11)
    fingers = relay.joy(joy(up, pressed=(4, 0)), NOW + 12, 0.12).jog
    assert fingers.mode is JogMode.FINGERS and fingers.finger_rate == pytest.approx(0.5)
    relay.joy(joy(up, pressed=(4,)), NOW + 13, 0.13)
    assert relay.joy(joy(up, pressed=(4, 0)), NOW + 14, 0.14).jog.mode is JogMode.TRANSLATION
    # the dead-man let go: a release, whatever the stick says
    released = relay.joy(joy(up, pressed=()), NOW + 15, 0.15).jog
    assert not released.deadman and released.at_rest
    seqs = [j.header.seq for j in (first, *held, wrist, fingers, released)]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)


def test_the_resume_button_asks_once_per_press_and_moves_nothing():
    relay = core.JogRelay(RosJogConfig())
    assert not relay.joy(joy(pressed=(7,)), NOW, 0.0).resume  # held in the first message: not a press
    assert not relay.joy(joy(), NOW + 1, 0.01).resume
    pressed = relay.joy(joy(pressed=(7,)), NOW + 2, 0.02)
    assert pressed.resume and not pressed.jog.deadman and pressed.jog.at_rest  # Start alone: a resume, no motion
    assert not relay.joy(joy(pressed=(7,)), NOW + 3, 0.03).resume  # still held: no second ask
    assert not relay.joy(joy(pressed=(4,)), NOW + 4, 0.04).resume
    assert relay.joy(joy(pressed=(4, 7)), NOW + 5, 0.05).resume  # pressed again with the dead-man held
    without = core.JogRelay(RosJogConfig(joy=core.JoyMap(resume=-1)))
    without.joy(joy(), NOW, 0.0)
    assert not without.joy(joy(pressed=(7,)), NOW + 1, 0.01).resume
    with pytest.raises(ValueError, match="one button for two roles"):
        core.JoyMap(resume=4)


def test_a_button_held_in_the_first_message_is_not_a_press():
    relay = core.JogRelay(RosJogConfig())
    assert relay.joy(joy(pressed=(4, 0, 5)), NOW, 0.0).jog.mode is JogMode.TRANSLATION
    assert relay.stick.speed_level == 1


def test_a_custom_map_reads_its_own_axes_signs_and_buttons():
    cfg = RosJogConfig(speed_level=3, mapping=NO_FILTER.mapping,
                       joy=JoyMap(axes=[JoyAxis(index=3, invert=True), JoyAxis(index=0), JoyAxis(index=1)],
                                  deadman=1, mode=-1, speed_up=-1, speed_down=-1, resume=-1))
    relay = core.JogRelay(cfg)
    jog = relay.joy(joy((0.0, 0.0, 0.0, 1.0), pressed=(1,), buttons=2), NOW, 0.0).jog
    assert jog.deadman and jog.linear == pytest.approx((-0.2, 0.0, 0.0))
    with pytest.raises(ValueError, match="two roles"):
        JoyMap(deadman=0, mode=0)
    with pytest.raises(ValueError, match="three"):
        JoyMap(axes=[JoyAxis(index=0)])


def test_the_spasm_filter_ramps_a_sudden_push_and_never_slows_a_release():
    relay = core.JogRelay(RosJogConfig(speed_level=3))
    full = (0.0, 1.0) + (0.0,) * 6
    speeds = [relay.joy(joy(full, pressed=(4,)), NOW + i, i * 0.05).jog.linear[0] for i in range(10)]
    assert speeds[0] == 0.0 and speeds == sorted(speeds) and speeds[-1] == pytest.approx(0.2)
    assert relay.joy(joy(pressed=(4,)), NOW + 11, 0.55).jog.linear == (0.0, 0.0, 0.0)


# ------------------------------------------------------------------------------------------ twists
def test_a_zero_twist_is_a_release_and_a_moving_one_a_held_dead_man():
    relay = core.JogRelay(RosJogConfig())
    assert not relay.twist(twist(), NOW).jog.deadman
    assert not relay.twist(twist("end_effector"), NOW).jog.deadman
    assert relay.twist(twist(linear=(0.0, 0.0, -0.1)), NOW).jog.deadman


@pytest.mark.parametrize("frame, linear, angular, kind, says", [
    ("", (0.1, 0, 0), (0, 0, 0), "frame", "got ''"),
    ("world", (0.1, 0, 0), (0, 0, 0), "frame", "'base_link'"),
    ("end_effector", (0.1, 0, 0), (0, 0, 0), "frame", "along the base's axes"),
    ("base_link", (0, 0, 0), (0, 0, 0.2), "frame", "about the hand's own axes"),
    ("base_link", (0.1, 0, 0), (0, 0, 0.2), "mixed", "one mode at a time"),
    ("end_effector", (0.1, 0, 0), (0, 0, 0.2), "mixed", "one mode at a time"),
    ("base_link", (float("nan"), 0, 0), (0, 0, 0), "not_finite", "NaN"),
    ("end_effector", (0, 0, 0), (0, float("inf"), 0), "not_finite", "NaN or infinity"),
    ("base_link", (0.25, 0, 0), (0, 0, 0), "speed", "up to 0.2"),
    ("end_effector", (0, 0, 0), (0, 0, -0.7), "speed", "up to 0.6"),
])
def test_twists_a_jog_cannot_be_are_refused_with_the_reason(frame, linear, angular, kind, says):
    relay = core.JogRelay(RosJogConfig())
    assert says in refused(kind, relay.twist, twist(frame, linear, angular), NOW)
    assert relay.twist_stamper.seq == 0  # nothing made


# ------------------------------------------------------------------------------------------ bad joys
@pytest.mark.parametrize("payload, kind", [
    (joy((0.0,) * 4), "size"),                              # axis 4 missing
    (joy(buttons=5), "size"),                               # RB (5) missing
    (joy((0.0, float("nan")) + (0.0,) * 6, pressed=(4,)), "not_finite"),
    (joy((0.0, float("-inf")) + (0.0,) * 6), "not_finite"),
    (joy((0.0, 1.5) + (0.0,) * 6, pressed=(4,)), "range"),
    (b"\x00\x01\x00\x00garbage", "cdr"),
    (twist(), "cdr"),                                       # another type on the topic
])
def test_bad_joys_are_refused_by_name_and_leave_the_stick_as_it_was(payload, kind):
    relay = core.JogRelay(RosJogConfig())
    refused(kind, relay.joy, payload, NOW, 0.0)
    assert relay.joy_stamper.seq == 0 and relay.stick._held is None


def test_a_button_neither_0_nor_1_and_a_stamp_past_a_second_are_refused():
    relay = core.JogRelay(RosJogConfig())
    buttons = np.zeros(11, dtype=np.int32)
    buttons[4] = 2
    bad = cdr.serialize(cdr.Joy(axes=np.zeros(8, dtype=np.float32), buttons=buttons))
    refused("button", relay.joy, bad, NOW, 0.0)
    late = cdr.serialize(cdr.Joy(header=cdr.Header(stamp=cdr.Time(1, 1_000_000_000)),
                                 axes=np.zeros(8, dtype=np.float32), buttons=np.zeros(11, dtype=np.int32)))
    refused("stamp", relay.joy, late, NOW, 0.0)


# ------------------------------------------------------------------------------------------ stamps
@pytest.mark.parametrize("offset_ms, used, heard_offset_ms", [
    (0, True, 0), (-30, True, -30), (-50, True, -50), (20, True, 0),   # ahead of the bridge: the receipt
    (-51, False, 0), (-400, False, 0), (60, False, 0), (None, False, 0),  # off, or unstamped: the receipt
])
def test_the_device_counts_as_heard_at_its_stamp_only_within_the_skew(offset_ms, used, heard_offset_ms):
    relay = core.JogRelay(RosJogConfig())
    stamp_ns = 0 if offset_ms is None else NOW + offset_ms * 1_000_000
    out = relay.joy(joy(pressed=(4,), stamp_ns=stamp_ns), NOW, 0.0)
    assert out.stamp_used is used
    assert out.jog.header.source_stamp_ns == NOW + heard_offset_ms * 1_000_000 and out.jog.header.stamp_ns == NOW


def test_the_device_stamp_never_goes_back_and_each_source_counts_its_own_sequence():
    relay = core.JogRelay(RosJogConfig())
    first = relay.joy(joy(pressed=(4,), stamp_ns=NOW - 10_000_000), NOW, 0.0).jog
    second = relay.joy(joy(pressed=(4,), stamp_ns=NOW - 40_000_000), NOW + 1_000_000, 0.001).jog
    assert second.header.source_stamp_ns == first.header.source_stamp_ns == NOW - 10_000_000
    relay.twist(twist(linear=(0.1, 0.0, 0.0)), NOW)
    assert (relay.joy_stamper.seq, relay.twist_stamper.seq) == (2, 1)


def test_the_config_refuses_what_would_never_move_or_never_stop():
    with pytest.raises(ValueError, match="stamp_skew_s"):
        RosJogConfig(stamp_skew_s=0.3)
    with pytest.raises(ValueError, match="speed_level"):
        RosJogConfig(speed_level=4)
