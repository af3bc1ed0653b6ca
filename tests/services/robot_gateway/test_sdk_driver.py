"""services/robot_gateway/sdk_driver.py without zenoh, the SDK or a node: every cycle reads the arm and is a DSP tick
run in the loop; a failed SDK call, reading or forwarding, is the link's failure, counted and said; there are no
joints for low-level control. (The driver on Kinova's own library, through the gateway: test_kinova_sdk.py.)"""
import logging
import time

import numpy as np
import pytest

from services.robot.arm_driver import NodeLoop
from services.robot.hardware import JointReading
from services.robot_gateway.kinova_sdk import SdkError
from services.robot_gateway.sdk_driver import SdkConnection, SdkDriver
from services.runtime.clock import WallClock
from services.runtime.logs import RateLimitedLogger
from services.runtime.metrics import Counters, DurationStats, RateMeter
from tests.helpers import ARM


class ArmBehindTheSdk:
    """The arm as SdkArm reads it: its joints, or the error code a failed call returns."""

    def __init__(self) -> None:
        self.q = ARM.home.copy()
        self.failing = False

    def read(self) -> JointReading:
        if self.failing:
            raise SdkError("GetAngularPosition", 1015)
        return JointReading(q=self.q.copy(), dq=np.zeros(ARM.n_joints), tau=np.zeros(ARM.n_joints),
                            stamp_ns=time.time_ns())


class Session:
    closed = False

    def close(self) -> None:
        self.closed = True


@pytest.fixture
def sdk():
    arm, session = ArmBehindTheSdk(), Session()
    loop = NodeLoop("robot_gateway", False, WallClock(), Counters(), RateLimitedLogger(logging.getLogger("test")),
                    RateMeter(), DurationStats())
    connection = SdkConnection(sdk=object(), session=session, arm=arm, first_reading=arm.read())
    return SdkDriver(connection, loop), arm, session


def test_every_cycle_reads_the_arm_and_is_a_tick_at_the_dsp_s_own_period(sdk):
    driver, arm, _ = sdk
    assert driver.timing.period_ms == 10.0 and not driver.dsp_beside_loop
    arm.q[0] += 0.1
    before = time.time_ns()
    tick = driver.cycle()
    assert before <= tick <= time.time_ns() and driver.core.reading.q[0] == arm.q[0] and driver.cycles == 1
    assert driver.core.dsp is arm and driver.api is driver.connection.sdk  # the arm's own DSP and API


def test_a_failed_sdk_call_reading_or_forwarding_is_the_link_s_and_the_arm_answering_ends_it(sdk):
    driver, arm, _ = sdk
    arm.failing = True
    assert driver.cycle() is not None  # the tick goes on: the state says what failed
    assert driver.link.consecutive_errors == 1 and driver.link.faults[0].startswith("sdk: Kinova SDK GetAngularPos")

    def forwarding_fails() -> float:
        raise SdkError("SendBasicTrajectory", 1)

    assert driver.run_dsp(forwarding_fails) == 0.0
    assert driver.link.failing(2) and driver.loop.counters.get("sdk.errors") == 2
    with pytest.raises(ZeroDivisionError):  # anything else is no failure of the link: the caller's
        driver.run_dsp(lambda: 1 / 0)
    arm.failing = False
    driver.cycle()
    assert driver.link.consecutive_errors == 0 and driver.link.faults == []
    assert driver.run_dsp(lambda: 0.003) == 0.003


def test_no_joints_for_low_level_control_and_closing_ends_the_arm_s_session(sdk):
    driver, _, session = sdk
    assert driver.torque_joints is None and "no low-level torque API" in driver.lowlevel_unavailable
    driver.close()
    assert session.closed
