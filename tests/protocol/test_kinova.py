import math

import msgpack
import pytest

from protocol import kinova as k
from protocol import messages as m


def test_position_type_values_are_kinovas():
    expected = {
        "NOMOVEMENT_POSITION": 0, "CARTESIAN_POSITION": 1, "ANGULAR_POSITION": 2, "RETRACTED": 3,
        "PREDEFINED1": 4, "PREDEFINED2": 5, "PREDEFINED3": 6, "CARTESIAN_VELOCITY": 7, "ANGULAR_VELOCITY": 8,
        "PREDEFINED4": 9, "PREDEFINED5": 10, "ANY_TRAJECTORY": 11, "TIME_DELAY": 12,
    }
    assert {e.name: e.value for e in k.POSITION_TYPE} == expected


def test_error_codes_and_ranges():
    assert k.ErrorCode.NO_ERROR_KINOVA == 1
    assert k.ErrorCode.UNKNOWN_ERROR == 666
    assert k.ErrorCode.ERROR_RS485_TIMEOUT == 1020
    assert k.ErrorCode.ERROR_COMM_TIMEOUT == 1022  # the header's name
    assert k.ErrorCode.ERROR_NO_DEVICE_FOUND == 1015 and k.ErrorCode.ERROR_LOAD_COMM_DLL == 2002
    assert k.ErrorCode.ERROR_INVALID_PARAM == 2100
    assert k.ErrorCode.ERROR_API_NOT_INITIALIZED == 2101
    assert k.ErrorCode.ERROR_NACK_RECEIVED == 9999
    # every code the headers define has its name: 1001-1022, 2001-2015, 2100-2102, 5001-5003
    assert {int(c) for c in k.ErrorCode} == {1, 666, 9999, *range(1001, 1023), *range(2001, 2016),
                                             *range(2100, 2103), *range(5001, 5004)}
    assert all(k.is_known_error_code(c) for c in (1, 666, 1001, 1015, 2001, 2015, 2100, 2102, 5003, 9999))
    assert not any(k.is_known_error_code(c) for c in (0, 2, 1000, 1023, 2016, 2103, 5004, 10000))
    assert k.error_name(1015) == "ERROR_NO_DEVICE_FOUND" and "do not define" in k.error_name(1023)


def test_hand_mode_has_the_headers_seven_values():
    assert [(h.name, h.value) for h in k.HAND_MODE] == [
        ("HAND_NOMOVEMENT", 0), ("POSITION_MODE", 1), ("VELOCITY_MODE", 2), ("NO_FINGER", 3), ("ONE_FINGER", 4),
        ("TWO_FINGERS", 5), ("THREE_FINGERS", 6)]


def test_zone_shapes_and_torque_switch_values():
    assert [s.value for s in k.ShapeType] == list(range(7))
    assert k.ShapeType.PrismSquareBase_Z == 2 and k.ShapeType.Pyramid == 6
    assert (k.GENERALCONTROL_TYPE.POSITION, k.GENERALCONTROL_TYPE.TORQUE) == (0, 1)
    assert (k.MAX_ZONES, k.ZONE_SHAPE_POINTS, k.TRAJECTORY_FIFO_SIZE, k.TORQUE_COMMAND_SIZE) == (10, 8, 2000, 70)


def velocity_point():
    return k.TrajectoryPoint(
        Position=k.UserPosition(
            Type=k.POSITION_TYPE.CARTESIAN_VELOCITY,
            CartesianPosition=k.CartesianInfo(X=0.05, Y=0.0, Z=-0.02, ThetaX=0.1, ThetaY=0.0, ThetaZ=0.0),
        ),
        LimitationsActive=1,
        Limitations=k.Limitation(speedParameter1=0.1, speedParameter2=0.6),
    )


def test_trajectory_point_round_trip_and_kinova_field_names():
    point = velocity_point()
    assert m.decode(m.encode(point), k.TrajectoryPoint) == point
    plain = msgpack.unpackb(m.encode(point))
    assert plain["Position"]["Type"] == 7
    assert set(plain["Position"]["CartesianPosition"]) == {"X", "Y", "Z", "ThetaX", "ThetaY", "ThetaZ"}
    assert plain["Limitations"]["speedParameter1"] == pytest.approx(0.1)


def test_trajectory_point_refuses_unknown_type_and_nan():
    plain = msgpack.unpackb(m.encode(velocity_point()))
    plain["Position"]["Type"] = 13
    with pytest.raises(m.ProtocolError) as err:
        m.decode(msgpack.packb(plain), k.TrajectoryPoint)
    assert err.value.field == "Position.Type"
    plain["Position"]["Type"] = 7
    plain["Position"]["CartesianPosition"]["ThetaZ"] = math.nan
    with pytest.raises(m.ProtocolError) as err:
        m.decode(msgpack.packb(plain), k.TrajectoryPoint)
    assert err.value.field == "Position.CartesianPosition.ThetaZ"


def test_zone_list_round_trip_and_consistency():
    corners = [k.CartesianInfo(X=x, Y=y, Z=0.0) for x, y in ((-0.2, -0.2), (0.2, -0.2), (0.2, 0.2), (-0.2, 0.2))]
    top = [k.CartesianInfo(X=c.X, Y=c.Y, Z=0.3) for c in corners]
    zone = k.Zone(ID=1, zoneShape=k.ZoneShape(shapeType=k.ShapeType.PrismSquareBase_Z, Points=corners + top))
    zones = k.ZoneList(NbZones=1, Zones=[zone])
    assert m.decode(m.encode(zones), k.ZoneList) == zones
    plain = msgpack.unpackb(m.encode(zones))
    plain["NbZones"] = 2
    with pytest.raises(m.ProtocolError, match="NbZones is 2"):
        m.decode(msgpack.packb(plain), k.ZoneList)
    plain["NbZones"] = 1
    plain["Zones"][0]["zoneShape"]["Points"].pop()
    with pytest.raises(m.ProtocolError, match="length"):
        m.decode(msgpack.packb(plain), k.ZoneList)


def test_zone_list_holds_at_most_ten():
    plain = {"NbZones": 11, "Zones": [m.to_builtins(k.Zone(ID=i)) for i in range(11)]}
    with pytest.raises(m.ProtocolError):
        m.decode(msgpack.packb(plain), k.ZoneList)


def test_angular_info_list_helpers():
    info = k.AngularInfo.from_list([270, 170, 0, 80, 0, 220, 0])
    assert info.Actuator6 == 220.0 and info.as_list()[1] == 170.0
    # a 6-DoF arm's six angles: the seventh actuator reads 0, as Kinova's SDK gives it
    assert k.AngularInfo.from_list([1.0] * 6).as_list() == [1.0] * 6 + [0.0]
    for wrong in ([], [0.0] * 8):
        with pytest.raises(ValueError):
            k.AngularInfo.from_list(wrong)


def test_model_codes_parse_as_kinova_writes_them():
    assert k.parse_model_code("j2n6s300") == k.ModelCode("j", 2, "n", 6, "s", 3)
    assert k.parse_model_code(" J2S7S300\0\0") == k.ModelCode("j", 2, "s", 7, "s", 3)  # as a C char[20] may hold it
    assert k.parse_model_code("m1n6s300").code == "m1n6s300"
    assert all(k.parse_model_code(text) is None for text in ("", "JACO2", "j2n5s300", "j2x6s300", "j2n6s300x",
                                                             "j2n6s399"))


def test_an_arm_is_driven_only_as_the_arm_it_reports_itself_to_be():
    assert k.arm_type_refusal("j2s7s300", "j2s7s300", 7) is None
    assert k.arm_type_refusal("j2n6a200", "j2n6s300", 6) is None  # fingers and mode do not change the kinematics
    assert k.arm_type_refusal("j2s7s300", "my-arm", 7) is None  # a configured name that is no code: joints decide
    reason = k.arm_type_refusal("j2n6s300", "j2s7s300", 7)
    assert "j2n6s300 with 6 joints" in reason and "j2s7s300 has 7" in reason
    assert "wrist" in k.arm_type_refusal("j2s6s300", "j2n6s300", 6)
    assert "MICO 1" in k.arm_type_refusal("m1n6s300", "j2n6s300", 6)
    reason = k.arm_type_refusal("JACO2", "j2s7s300", 7)
    assert "'JACO2'" in reason and "cannot be checked" in reason


@pytest.mark.parametrize("raw, text", [
    (b"PJ00650019161750\0\0\0\0", "PJ00650019161750"),
    (b"j2s7s300\0garbage after the NUL", "j2s7s300"),
    (b"\x90\xe1\n\x7f\0", "????"),  # a record the comm layer did not fill: whatever the memory held
    (b"", ""),
])
def test_a_device_records_strings_print_on_one_readable_line(raw, text):
    """(Two devices once printed their unfilled serial numbers raw: a newline in one split the gateway's one-line
    error in three.)"""
    assert k.device_text(raw) == text
