"""The emulated DSP running in the gateway, over the RS-485 link to robot_sim's actuators (realtime, virtual
bus): a mixed-frame velocity command moves the end effector as it does in robot_sim."""
import threading
import time

import numpy as np
import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from services.common.dsp import KinovaDSP
from services.common.kinematics import ArmKinematics
from services.robot_gateway.actuators import LinkActuators
from services.stack import simulated_link


def twist_command(linear, rotational):
    twist = m.Twist(header=m.Header(), frame=Frame.MIXED, angular=AngularConvention.SEED000, linear=linear,
                    rotational=rotational)
    return m.RobotCommand(header=m.Header(), mode=m.CommandMode.CARTESIAN_VELOCITY, twist=twist)


@pytest.fixture
def gateway():
    with simulated_link() as (runner, link):
        yield runner, LinkActuators(link)


def run_dsp(actuators, dsp, command, seconds):
    """The gateway's loops in miniature: bus every 2 ms, DSP every 10 ms (resending the command)."""
    start = time.monotonic()
    k = 0
    while time.monotonic() - start < seconds:
        deadline = start + k * 0.002
        time.sleep(max(0.0, deadline - time.monotonic()))
        actuators.cycle()
        if k % 5 == 0:
            if command is not None:
                dsp.submit(command)
            actuators.write(dsp.cycle(actuators.read()))
        k += 1


def ee_velocity(runner):
    with runner.lock:
        return runner.sim.ee_twist_base()


def test_mixed_velocity_through_the_gateway_matches_robot_sim(gateway):
    runner, actuators = gateway
    dsp = KinovaDSP(kinematics=ArmKinematics())
    linear = (0.04, -0.03, 0.03)
    samples = []
    thread = threading.Thread(target=run_dsp, args=(actuators, dsp, twist_command(linear, (0.0, 0.0, 0.2)), 1.6))
    thread.start()
    time.sleep(0.9)
    for _ in range(20):
        samples.append(ee_velocity(runner))
        time.sleep(0.03)
    thread.join()
    v = np.mean(samples, axis=0)
    assert np.linalg.norm(v[:3] - np.array(linear)) <= 0.05 * np.linalg.norm(linear)  # within 5 %
    assert actuators.bus_errors == 0


def test_bus_failure_holds_the_arm(gateway):
    runner, actuators = gateway
    runner.stop()  # the actuators fall silent
    actuators.write(np.full(7, 0.1))
    assert not actuators.cycle()
    assert actuators.bus_errors == 1 and actuators.faults[0].startswith("bus:")
    assert np.all(actuators.dq_ref == 0) and np.allclose(actuators.q_ref, actuators.read().q)
