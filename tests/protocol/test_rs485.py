import struct

import numpy as np
import pytest

from protocol import rs485 as r
from tests.helpers import ARM


def test_message_layout_is_byte_exact():
    msg = r.RS485Message(r.Command.GET_ACTUAL_POSITION, r.HOST_ADDRESS, 0x10)
    assert msg.encode() == bytes([0x01, 0x00, 0x00, 0x10]) + bytes(16)
    assert len(msg.encode()) == r.MESSAGE_SIZE == 20


def test_command_ids_match_the_sdk_header():
    ids = {c.name: c.value for c in r.Command}
    assert ids["GET_ACTUAL_POSITION"] == 0x01 and ids["POSITION_AND_TORQUE_COMMAND"] == 0x14
    assert (ids["SEND_ALL_VALUES_1"], ids["SEND_ALL_VALUES_2"], ids["SEND_ALL_VALUES_3"]) == (0x15, 0x16, 0x17)
    assert ids["REPORT_ERROR"] == 0x30 and ids["CLEAR_FAULT_FLAG"] == 0x33
    assert (ids["NACK"], ids["ACK"]) == (0x3E, 0x3F)
    assert ids["SWITCH_CONTROL_MODE_REQUEST"] == 0x203 and ids["SWITCH_CONTROL_MODE_REPLY"] == 0x204
    assert ids["POSITION_AND_TORQUE_COMMAND_REDUCED"] == 0x200


def test_position_torque_command_bytes():
    cmd = r.PositionTorqueCommand(position_deg=180.0, torque_nm=2.5, kp=1000, mode=1, damping=3)
    frame = cmd.to_message(0x12).encode()
    expected = (
        struct.pack("<hBB", 0x14, 0x00, 0x12)
        + struct.pack("<f", 180.0) + struct.pack("<f", 0.0) + struct.pack("<f", 2.5)
        + struct.pack("<I", (1000 << 16) | (1 << 8) | 3)
    )
    assert frame == expected
    assert r.PositionTorqueCommand.from_message(r.RS485Message.decode(frame)) == cmd


def test_all_values_1_reply_bytes():
    reply = r.AllValues1(current_a=0.5, position_deg=123.25, velocity_dps=-4.0, torque_nm=1.5)
    frame = reply.to_message(0x13).encode()
    assert frame == struct.pack("<hBB4f", 0x15, 0x13, 0x00, 0.5, 123.25, -4.0, 1.5)
    assert r.AllValues1.from_message(r.RS485Message.decode(frame)) == reply


def test_position_mode_command_bytes():
    """Position mode as every public driver sends it: float[0] = float[1] = the target, uint32[2] = 1 (the
    extended answer: 0x15, 0x16, 0x17 back), uint32[3] = 0; no torque may ride along (float[2] is the flag)."""
    frame = r.PositionTorqueCommand(position_deg=181.5).to_message(0x12).encode()
    assert frame == struct.pack("<hBB2f2I", 0x14, 0x00, 0x12, 181.5, 181.5, 1, 0)
    assert r.PositionTorqueCommand.from_message(r.RS485Message.decode(frame)) == r.PositionTorqueCommand(181.5)
    batch = r.position_torque_records([0x12], [181.5])
    assert batch.tobytes() == frame
    with pytest.raises(r.RS485Error, match="carries no torque"):
        r.PositionTorqueCommand(181.5, torque_nm=1.0).to_message(0x12)
    halves = struct.pack("<hBB2f2I", 0x14, 0x00, 0x12, 181.5, 90.0, 1, 0)
    with pytest.raises(r.RS485Error, match="two different targets"):
        r.PositionTorqueCommand.from_message(r.RS485Message.decode(halves))
    torque = r.position_torque_records([0x12], [181.5], [2.5])
    assert torque.tobytes() == r.PositionTorqueCommand(181.5, 2.5, kp=r.TORQUE_KP, mode=1).to_message(0x12).encode()


def test_command_targets_read_each_record_as_its_actuators_mode_says():
    batch = np.concatenate([r.position_torque_records([0x10], [10.0]), r.position_torque_records([0x11], [20.0], [3.0]),
                            r.position_torque_records([0x12], [30.0])])
    batch["data"][2, 1] = 31.0  # a position command whose halves disagree
    position, torque, valid = r.command_targets(batch, np.array([False, True, False]))
    assert position.tolist() == [10.0, 20.0, 30.0] and torque.tolist() == [0.0, 3.0, 0.0]
    assert valid.tolist() == [True, True, False]
    # the position-mode flag's bytes, read as a torque, would be 1.4e-45 N·m: never taken as one
    assert r.command_targets(batch[:1], np.array([False]))[1][0] == 0.0


def test_all_values_2_and_3_layouts():
    """0x16 as Kinova's RS-485 example decodes it: float[0] PWM, float[1] position, int16 ax, ay, az (×0.001) and
    the temperature (×0.01 °C, signed) in bytes 8-15; 0x17: float[0] current, float[1] absolute position."""
    reply = r.AllValues2(pwm=0.25, position_deg=181.5, accel_g=(0.012, -0.5, 1.0), temperature_c=-3.57)
    frame = reply.to_message(0x10).encode()
    assert frame[4:] == struct.pack("<2f4h", 0.25, 181.5, 12, -500, 1000, -357)
    back = r.AllValues2.from_message(r.RS485Message.decode(frame))
    assert back.accel_g == pytest.approx((0.012, -0.5, 1.0)) and back.temperature_c == pytest.approx(-3.57)
    assert back.position_deg == 181.5
    words = np.frombuffer(frame[4:], dtype="<u4")  # as the example reads it, from DataLong[2] and [3]
    assert np.int16(words[3] >> 16) == -357 and np.int16(words[2] & 0xFFFF) == 12
    three = r.AllValues3(current_a=0.4, absolute_position_deg=181.25).to_message(0x10)
    assert three.floats == (pytest.approx(0.4), 181.25, 0.0, 0.0)
    assert r.AllValues3.from_message(three).absolute_position_deg == 181.25


def test_switch_mode_and_error_report():
    req = r.switch_mode_request(r.ControlModeRequest.TORQUE, 0x10)
    assert req.encode() == struct.pack("<hBB4I", 0x203, 0x00, 0x10, 1, 0, 0, 0)
    reply = r.switch_mode_reply(r.ControlModeReply.TORQUE_OK, 0x10)
    assert reply.encode()[4:8] == struct.pack("<I", 257)
    assert r.parse_switch_mode_reply(r.RS485Message.decode(reply.encode())) is r.ControlModeReply.TORQUE_OK
    err = r.report_error(r.ActuatorError.TORQUE, 0x11)
    assert err.uints == (0, 9, 0, 0)
    assert r.parse_report_error(err) is r.ActuatorError.TORQUE


@pytest.mark.parametrize("frame, words", [
    (b"", "20 bytes"),
    (bytes(19), "20 bytes"),
    (bytes(21), "20 bytes"),
    (struct.pack("<hBB", 0x77, 0, 0x10) + bytes(16), "unknown command id 0x77"),
])
def test_bad_frames_are_rejected(frame, words):
    with pytest.raises(r.RS485Error, match=words):
        r.RS485Message.decode(frame)


def test_nan_torque_is_rejected_both_ways():
    with pytest.raises(r.RS485Error):
        r.PositionTorqueCommand(180.0, float("nan")).to_message(0x10)
    frame = struct.pack("<hBB3fI", 0x14, 0, 0x10, 180.0, 0.0, float("nan"), 0)
    with pytest.raises(r.RS485Error):
        r.PositionTorqueCommand.from_message(r.RS485Message.decode(frame))


def test_payload_parsers_check_the_command():
    with pytest.raises(r.RS485Error):
        r.AllValues1.from_message(r.RS485Message(r.Command.ACK, 0x10, 0x00))


def test_batches():
    msgs = [r.RS485Message(r.Command.GET_ACTUAL_POSITION, 0, a) for a in ARM.bus_addresses]
    payload = r.encode_batch(msgs)
    assert len(payload) == 20 * 7 and r.decode_batch(payload) == msgs
    with pytest.raises(r.RS485Error):
        r.decode_batch(payload[:-1])
    with pytest.raises(r.RS485Error):
        r.encode_batch(msgs * 8)


def test_addresses_are_bytes():
    with pytest.raises(r.RS485Error):
        r.RS485Message(r.Command.ACK, 256, 0)
