"""The robot node's rules running in the gateway, over the RS-485 link to robot_sim's actuators (in-process bus, no
zenoh): a mixed-frame velocity command moves the end effector as it does in robot_sim. The arm runs a cycle per
exchange here (lockstep), so the figures are exact; tests/services/robot_gateway/test_service.py runs both sides in realtime, as
processes."""
import numpy as np
import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from services.robot.dsp import DSPConfig, KinovaDSP
from services.robot.core import RobotCore
from services.robot.hardware import CYCLES_PER_DSP
from services.robot.hardware import HardwareError
from services.robot_gateway.link import LinkHardware
from services.stack import simulated_link
from services.model.kinematics import ArmKinematics
from tests.helpers import ARM


def twist_command(linear, rotational):
    twist = m.Twist(header=m.Header(), frame=Frame.MIXED, angular=AngularConvention.SEED000, linear=linear,
                    rotational=rotational)
    return m.RobotCommand(header=m.Header(), mode=m.CommandMode.CARTESIAN_VELOCITY, twist=twist)


@pytest.fixture
def gateway():
    with simulated_link(lockstep=True) as (arm, link):
        hardware = LinkHardware(link, ARM, pipelined=False)  # in step with the arm, as the gateway runs in lockstep
        yield arm, hardware, RobotCore(KinovaDSP(DSPConfig(), ArmKinematics(ARM)), hardware.read())


def run_dsp(hardware, core, command, cycles, on_cycle=None):
    """The gateway's loop in miniature: an exchange per bus cycle, the DSP every fifth (resending the command)."""
    for k in range(cycles):
        reading = hardware.exchange(core.targets())
        core.observe(reading)
        if k % CYCLES_PER_DSP == 0:
            core.dsp_cycle(command)
        if on_cycle is not None:
            on_cycle(reading)


def test_mixed_velocity_through_the_gateway_matches_robot_sim(gateway):
    arm, hardware, core = gateway
    linear = (0.04, -0.03, 0.03)
    start = arm.sim.time_ns
    run_dsp(hardware, core, twist_command(linear, (0.0, 0.0, 0.2)), 450)  # 0.9 s: past the acceleration ramp
    samples = []

    def sample(_reading):
        with arm.lock:  # the arm finishes its cycle (physics) after it replied
            samples.append(arm.sim.ee_twist_base())

    run_dsp(hardware, core, twist_command(linear, (0.0, 0.0, 0.2)), 350, sample)
    with arm.lock:
        assert arm.sim.time_ns - start == 800 * 2_000_000  # one arm cycle per exchange
    v = np.mean(samples, axis=0)
    assert np.linalg.norm(v[:3] - np.array(linear)) <= 0.02 * np.linalg.norm(linear)  # within 2 %
    assert hardware.link.bus.counters.get("link.timeouts") == 0


def test_bus_failure_holds_the_arm(gateway):
    arm, hardware, core = gateway
    arm.stop(close_bus=False)  # the actuators fall silent
    core.dq_ref = np.full(7, 0.1)
    with pytest.raises(HardwareError, match="no reply"):
        hardware.exchange(core.targets())
    core.hold()
    assert np.all(core.dq_ref == 0) and np.allclose(core.targets().q, core.reading.q)
