"""The swap: robot_sim in actuator-bus mode plus robot_gateway offer the same zenoh robot as robot_sim alone."""
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from protocol import kinova
from protocol import messages as m
from protocol.conventions import AngularConvention, ClockMode, Frame
from services.model import jaco2
from services.model.kinematics import ArmKinematics
from services.robot.rs485_bus import BusConfig
from services.runtime.transport import open_session
from services.robot_gateway.service import GatewayConfig, robot_gateway_service
from services.robot_sim.service import RobotSimConfig, robot_sim_service
from services.stack import RobotProcesses, RouterProcess
from tests.helpers import REPO, CpuLoad
from tests.stack import KEYS, Recorder, wait_for



def test_same_keys_and_same_motion_as_robot_sim():
    """The gateway profile as deployed (the router, the CAN hub, robot_sim's actuators and robot_gateway as
    processes, a stand-in for safety's resend loop as another) offers the robot's zenoh API and moves the arm as
    commanded, within 2 %, while every core is kept busy by another program: the emulated arm keeps its own time,
    and a late host shows up as counted late or missed cycles, never as a faster arm."""
    linear = np.array([0.04, -0.03, 0.03])
    with RouterProcess() as router, RobotProcesses(router.client_config()), CpuLoad():
        client = open_session(router.client_config())
        try:
            states = Recorder(client, KEYS.robot_state, m.RobotState)
            assert wait_for(lambda: len(states) > 20)
            assert states.last().q == pytest.approx(jaco2.HOME.tolist(), abs=1e-3)
            # the Kinova API answers through the gateway
            replies = list(client.get(KEYS.robot_api("GetAngularPosition"), timeout=5.0))
            position = m.decode(replies[0].ok.payload.to_bytes(), kinova.AngularPositionReply)
            assert position.result.Actuators.as_list() == pytest.approx(jaco2.HOME_DEG.tolist(), abs=0.05)
            # a mixed-frame velocity command resent every 5 ms (latest wins on the robot) for 1.5 s
            subprocess.run([sys.executable, "-m", "bench.command_source", "--connect", router.endpoint,
                            "--linear", *map(str, linear), "--rotational", "0", "0", "0.2", "--seconds", "1.5"],
                           cwd=REPO, check=True, timeout=30)
            recent = [s for s in states.snapshot() if s.applied_command is not None][-20:]
            kin = ArmKinematics()
            v = np.mean([(kin.jacobian_base(s.q) @ np.asarray(s.dq))[:3] for s in recent], axis=0)
            error = np.linalg.norm(v - linear) / np.linalg.norm(linear)
            timing = recent[-1].timing
            print(f"same motion under load: {100 * error:.2f} % off; bus {timing.rate_hz:.1f} Hz, late "
                  f"{timing.late_per_s:.1f}/s, missed {timing.missed_per_s:.1f}/s")
            assert error <= 0.02, health_counters(client)
            assert len(recent) == 20 and recent[-1].applied_command.trace[-1].service == "robot_gateway"
            # the camera still comes from the simulator
            images = Recorder(client, KEYS.camera_image, m.Image)
            assert wait_for(lambda: len(images) > 2)
        finally:
            client.close()


def health_counters(client) -> dict:
    """The robot services' counters and details (what a failure message needs to say where the time went)."""
    out = {}
    for name in ("robot_gateway", "robot_sim"):
        for reply in client.get(KEYS.health(name), timeout=2.0):
            if reply.ok is not None:
                health = m.decode(reply.ok.payload.to_bytes(), m.ServiceHealth)
                out[name] = {"errors": dict(health.errors), "detail": health.detail}
    return out


def test_sim_in_bus_mode_does_not_offer_the_robot_api(router):
    sim = robot_sim_service(RobotSimConfig(clock=ClockMode.REALTIME, zenoh=router.client_config(),
                                         mode="actuator_bus", bus=BusConfig(channel="bus-only"))).start()
    client = open_session(router.client_config())
    try:
        states = Recorder(client, KEYS.robot_state, m.RobotState)
        time.sleep(0.5)
        assert len(states) == 0
        assert list(client.get(KEYS.robot_api("GetAngularPosition"), timeout=1.0)) == []
    finally:
        client.close()
        sim.stop()


def test_lockstep_gateway_refuses_an_arm_on_wall_time(router):
    """In lockstep the gateway exchanges as fast as the arm answers: an arm on the wall clock (a real one, or the
    emulated actuators in realtime) would be driven faster than commanded, so the gateway does not start."""
    arm = robot_sim_service(RobotSimConfig(clock=ClockMode.REALTIME, zenoh=router.client_config(),
                                           mode="actuator_bus", bus=BusConfig(channel="wall-time-arm"))).start()
    try:
        with pytest.raises(ValueError, match="lockstep needs robot_sim's emulated actuators in lockstep"):
            robot_gateway_service(GatewayConfig(clock=ClockMode.LOCKSTEP, zenoh=router.client_config(),
                                                bus=BusConfig(channel="wall-time-arm"))).start()
    finally:
        arm.stop()


def test_without_actuators_the_gateway_does_not_start(router):
    with pytest.raises(Exception, match="no reply"):
        robot_gateway_service(GatewayConfig(zenoh=router.client_config(), bus=BusConfig(channel="empty-bus"),
                                          link_timeout_s=0.02, connect_timeout_s=1.0)).start()


def test_kinova_sdk_backend_fails_clearly_without_the_library():
    with pytest.raises(RuntimeError, match="Kinova SDK library"):
        robot_gateway_service(GatewayConfig(backend="kinova_sdk", sdk_library="/nonexistent/libkinova.so"))
    with pytest.raises(ValueError, match="realtime only"):
        GatewayConfig(backend="kinova_sdk", clock=ClockMode.LOCKSTEP)  # a real arm has no simulated clock


def test_servo_runs_through_the_gateway_profile():
    """`mfvs servo --profile gateway`: the Table-2-like task with the seed's gains runs through robot_gateway and
    the RS-485 bus (realtime; the hub, the actuators and the gateway as processes) and converges to 5e-5 in about
    as many iterations as through robot_sim (131 in lockstep, 129-133 in realtime, 134-136 through the gateway:
    `mfvs bench swap --scenario examples/scenarios/table2_qvga.yaml`). The QVGA variant leaves the robot's 500 Hz
    loops enough of this machine's two cores (see the scenario file)."""
    from pathlib import Path

    from services.servo import load_scenario, run

    scenario = load_scenario(REPO / "examples" / "scenarios" / "table2_qvga.yaml")
    result = run(scenario, profile="gateway")
    assert result.converged, (result.status, result.iterations, result.final_error_norm)
    assert result.iterations < 300  # generous against 134-136 measured
    assert result.max_joint_limit_violation_deg == 0.0
