"""The teach's waits are measured on the arm's clock (its states' stamps), not the wall's: a lockstep arm's time runs
only as fast as a busy host lets it, and a teach must not fail for the host being slow; an arm that went silent
fails it, in the wall's time."""
import time

import pytest

from protocol import messages as m
from protocol.keys import Keys
from services.runtime.transport import open_session
from services.vision.teach_client import ArmClock, ArmSilent
from tests.helpers import ARM_DECLARED
from tests.stack import wait_for

KEYS = Keys("arm0")


def state_at(stamp_ns: int) -> bytes:
    return m.encode(m.RobotState(**ARM_DECLARED, header=m.Header(stamp_ns=stamp_ns), q=[0.0] * 7, dq=[0.0] * 7,
                                 tau=[0.0] * 7, pose=m.KinovaPose(X=0, Y=0, Z=0, ThetaX=0, ThetaY=0, ThetaZ=0),
                                 control_mode=m.ControlMode.IDLE))


def heard(arm, clock: ArmClock, stamp_ns: int) -> bool:
    """Puts a state until the clock has it: a subscriber declared a moment ago on another session is not yet known
    to the router, and a single put before that reaches nobody (as a real arm's 100 Hz states would go on)."""
    return wait_for(lambda: arm.put(KEYS.robot_state, state_at(stamp_ns)) or clock.now_ns() == stamp_ns)


@pytest.fixture
def sessions(router):
    arm, client = open_session(router.client_config()), open_session(router.client_config())
    yield arm, client
    client.close()
    arm.close()


def test_a_timer_expires_after_the_arms_time_not_the_walls(sessions):
    arm, client = sessions
    clock = ArmClock(client, KEYS, silent_s=30.0)
    try:
        expired = clock.timer(0.5)
        assert not expired()  # no state yet: the arm's time has not started
        assert heard(arm, clock, 1_000_000_000)
        assert not expired()
        time.sleep(0.7)  # the wall's 0.7 s: the arm's time stood still (a lockstep arm on a host that was busy)
        assert not expired()
        arm.put(KEYS.robot_state, state_at(1_400_000_000))
        assert wait_for(lambda: clock.now_ns() == 1_400_000_000)
        assert not expired()
        arm.put(KEYS.robot_state, b"\x93not a state")  # malformed bytes are not a time
        arm.put(KEYS.robot_state, state_at(1_300_000_000))  # nor is an older stamp
        arm.put(KEYS.robot_state, state_at(1_500_000_000))
        assert wait_for(lambda: clock.now_ns() == 1_500_000_000)
        assert expired()
    finally:
        clock.close()


def test_an_arm_that_goes_silent_fails_the_wait_after_silent_s_of_the_walls_time(sessions):
    arm, client = sessions
    clock = ArmClock(client, KEYS, silent_s=0.4)
    try:
        expired = clock.timer(60.0)
        assert heard(arm, clock, 1_000_000_000)
        started = time.monotonic()
        with pytest.raises(ArmSilent, match="no state from the arm"):
            while not expired():
                time.sleep(0.02)
        assert time.monotonic() - started >= 0.3
    finally:
        clock.close()
