"""The torque-mode setup of the JACO thesis's Table 5.1 (services/robot/torque_setup.py) and its Kinova API
functions."""
import math

import msgspec
import numpy as np
import pytest

from protocol import kinova
from protocol.messages import ProtocolError, decode
from services.model.arm import load_arm
from services.robot.dsp import DSPConfig, KinovaDSP
from services.robot.kinova_api import KinovaApi
from services.robot.torque_setup import (MAX_ACTUATOR_DAMPING, TorqueSetup, arm_compensates_gravity, configure,
                                         damping_torque, joint_of_address, over_safety_speed, safety_speed_threshold,
                                         table_5_1)
from services.model.kinematics import ArmKinematics

SIX = load_arm("j2n6s300")


def test_the_safety_factor_sets_a_threshold_from_each_joints_maximum_speed():
    setup = TorqueSetup(SIX)
    setup.safety_factor = 0.0
    assert np.degrees(safety_speed_threshold(setup)) == pytest.approx(SIX.max_speed_dps)
    setup.safety_factor = 0.75
    assert np.degrees(safety_speed_threshold(setup)) == pytest.approx(4 * SIX.max_speed_dps)
    assert over_safety_speed(setup, np.radians([0, 0, 0, 4 * 48.0 + 1, 0, -(4 * 48.0 + 1)])) == [3, 5]
    setup.safety_factor = 1.0
    assert np.all(np.isinf(safety_speed_threshold(setup))) and over_safety_speed(setup, np.full(6, 1e6)) == []


def test_table_5_1_as_the_thesis_set_it():
    """Safety factor 1, vibration controller 1, damping 0, gravity OPTIMAL with every parameter 0, gain 0."""
    setup = TorqueSetup(SIX)
    assert arm_compensates_gravity(setup) and np.all(setup.actuator_damping > 0)
    calls = table_5_1()
    assert [function for function, _ in calls] == [  # the thesis's order
        "SetTorqueSafetyFactor", "SetTorqueVibrationController", "SetTorqueActuatorDamping", "SetGravityType",
        "SetGravityOptimalZParam", "SetTorqueActuatorGain"]
    for function, argument in calls:
        assert configure(setup, function, argument) == "", function
    assert setup.safety_factor == 1.0 and setup.vibration_controller == 1.0
    assert not setup.actuator_damping.any() and not setup.actuator_gain.any()
    assert setup.gravity_type is kinova.GRAVITY_TYPE.OPTIMAL
    assert not arm_compensates_gravity(setup)
    assert not damping_torque(setup, np.ones(6)).any()
    # any other parameter set, or the manual type: the arm compensates with its own model
    configure(setup, "SetGravityOptimalZParam", kinova.GravityParameters(values=[0.1] + [0.0] * 41))
    assert arm_compensates_gravity(setup)
    configure(setup, "SetGravityOptimalZParam", kinova.GravityParameters())
    configure(setup, "SetGravityType", kinova.GravityTypeArgument(type=kinova.GRAVITY_TYPE.MANUAL_INPUT))
    assert arm_compensates_gravity(setup)


@pytest.mark.parametrize("function, argument, words", [
    ("SetTorqueSafetyFactor", kinova.FloatArgument(value=1.5), "within 0..1"),
    ("SetTorqueVibrationController", kinova.FloatArgument(value=-0.1), "within 0..1"),
    ("SetTorqueActuatorDamping", kinova.CommandArray(values=[1.0, -1.0] + [0.0] * 68), "first 6 values"),
    ("SetTorqueActuatorDamping", kinova.CommandArray(values=[MAX_ACTUATOR_DAMPING * 2] + [0.0] * 69), "within 0..20"),
    ("SetTorqueActuatorGain", kinova.CommandArray(values=[-1.0] + [0.0] * 69), "first 6 values"),
])
def test_a_bad_setting_is_refused_and_changes_nothing(function, argument, words):
    setup = TorqueSetup(SIX)
    before = (setup.safety_factor, setup.vibration_controller, setup.actuator_damping.copy(),
              setup.actuator_gain.copy(), setup.optimal_z)
    assert words in configure(setup, function, argument)
    assert (setup.safety_factor, setup.vibration_controller) == before[:2]
    assert np.array_equal(setup.actuator_damping, before[2]) and np.array_equal(setup.actuator_gain, before[3])
    assert setup.optimal_z is None


@pytest.mark.parametrize("message_type, bad", [
    (kinova.FloatArgument, {"value": math.nan}), (kinova.CommandArray, {"values": [math.inf] * 70}),
    (kinova.CommandArray, {"values": [0.0] * 6}), (kinova.GravityParameters, {"values": [math.nan] * 42}),
    (kinova.ActuatorAddress, {"address": 300}), (kinova.GravityTypeArgument, {"type": 2})])
def test_a_bad_argument_does_not_decode(message_type, bad):
    """What never reaches the setup: the wire types refuse NaN, arrays of another length, an address past a byte,
    a gravity type Kinova does not define."""
    with pytest.raises(ProtocolError):
        decode(msgspec.msgpack.encode(bad), message_type)


def test_the_values_past_the_arms_actuators_are_not_read():
    """Kinova's arrays hold 70 values whatever the arm: a 6-DoF arm reads the first six."""
    setup = TorqueSetup(SIX)
    assert configure(setup, "SetTorqueActuatorDamping", kinova.CommandArray(
        values=[1.0] * 6 + [1e9] * 64)) == ""
    assert setup.actuator_damping.tolist() == [1.0] * 6


class Sensors:
    def __init__(self):
        self.zeroed = []

    def zero_torque_sensor(self, joint):
        self.zeroed.append(joint)


def test_the_kinova_api_answers_table_5_1():
    sensors = Sensors()
    api = KinovaApi(robot=None, dsp=KinovaDSP(DSPConfig(), ArmKinematics(SIX)), sensors=sensors)
    assert api.call("SetTorqueSafetyFactor", kinova.FloatArgument(value=1.0)).code == kinova.ErrorCode.NO_ERROR_KINOVA
    assert api.torque_setup.safety_factor == 1.0
    refused = api.call("SetTorqueSafetyFactor", kinova.FloatArgument(value=2.0))
    assert refused.code == kinova.ErrorCode.ERROR_INVALID_PARAM and "0..1" in refused.message
    assert api.call("SetTorqueZero", kinova.ActuatorAddress(address=0x15)).code == kinova.ErrorCode.NO_ERROR_KINOVA
    assert sensors.zeroed == [5] and joint_of_address(SIX, 0x10) == 0
    wrong = api.call("SetTorqueZero", kinova.ActuatorAddress(address=0x16))  # a finger on the 6-DoF arm
    assert wrong.code == kinova.ErrorCode.ERROR_INVALID_PARAM and "no actuator at address 22" in wrong.message
    joint_zero = api.call("SetJointZero", kinova.ActuatorAddress(address=0x10))
    assert joint_zero.code == kinova.ErrorCode.ERROR_INVALID_PARAM and "not public" in joint_zero.message
    assert "SetTorqueSafetyFactor" in kinova.MUTATING_API_FUNCTIONS  # only the commanding service may call it
