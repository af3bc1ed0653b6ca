"""Authority over the robot, enforced by a real zenoh router: access control by user (acl) and by certificate
(tls). Only safety may command the robot; only robot services may publish robot state."""
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from protocol import kinova
from protocol import messages as m
from protocol.conventions import AngularConvention, ClockMode, Frame
from services.common.authority import write_deployment
from services.common.transport import Router, ZenohConfig, free_loopback_port, open_session
from services.robot_sim.service import RobotSimConfig, RobotSimService
from tests.stack import KEYS, Recorder, wait_for

REPO = Path(__file__).resolve().parents[1]


def velocity_command(stamp=0):
    header = m.Header(stamp_ns=stamp)
    twist = m.Twist(header=header, frame=Frame.MIXED, angular=AngularConvention.SEED000, linear=(0.05, 0.0, 0.0),
                    rotational=(0.0, 0.0, 0.0))
    return m.encode(m.RobotCommand(header=header, mode=m.CommandMode.CARTESIAN_VELOCITY, twist=twist))


INTRUDER = textwrap.dedent("""
    import sys, time
    from services.common.transport import ZenohConfig, open_session
    from tests.test_authority import velocity_command
    endpoint, config_file, key = sys.argv[1:4]
    session = open_session(ZenohConfig(connect=[endpoint], config_file=config_file))
    publisher = session.declare_publisher(key)
    for _ in range(150):          # 1.5 s of commands at 100 Hz
        publisher.put(velocity_command(time.time_ns()))
        time.sleep(0.01)
    session.close()
    print("sent", flush=True)
""")


def run_intruder(endpoint, config_file, key=KEYS.robot_command):
    out = subprocess.run([sys.executable, "-c", INTRUDER, endpoint, str(config_file), key], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "sent" in out.stdout, out.stderr
    return out


def session_as(deployment, service):
    return open_session(ZenohConfig(connect=[deployment.endpoint], config_file=str(deployment.client_configs[service])))


@pytest.fixture(scope="module", params=["acl", "tls"])
def deployment(request, tmp_path_factory):
    tls = request.param == "tls"
    port = free_loopback_port()
    deployment = write_deployment(tmp_path_factory.mktemp(request.param), tls=tls, port=port)
    with Router(port=port, config_file=deployment.router_config, scheme="tls" if tls else "tcp"):
        yield deployment


def test_only_safety_can_command_the_robot(deployment):
    robot = RobotSimService(RobotSimConfig(clock=ClockMode.REALTIME, zenoh=ZenohConfig(
        connect=[deployment.endpoint], config_file=str(deployment.client_configs["robot_sim"]))))
    robot.start()
    try:
        operator = session_as(deployment, "operator")
        states = Recorder(operator, KEYS.robot_state, m.RobotState)
        assert wait_for(lambda: len(states) > 20)
        q0 = np.array(states.last().q)
        # a second process, authenticated as the vision service, publishes commands: refused by the router
        run_intruder(deployment.endpoint, deployment.client_configs["vision"])
        assert "command" not in robot.rates.snapshot()
        assert np.abs(np.array(states.last().q) - q0).max() < 1e-6
        # the controller's identity cannot either
        run_intruder(deployment.endpoint, deployment.client_configs["controller"])
        assert "command" not in robot.rates.snapshot()
        # the same commands from the safety identity do reach the robot and move it
        run_intruder(deployment.endpoint, deployment.client_configs["safety"])
        assert robot.rates.snapshot().get("command", 0) > 0
        assert np.abs(np.array(states.last().q) - q0).max() > 1e-3
        states.close()
        operator.close()
    finally:
        robot.stop()


@pytest.fixture
def robot(deployment):
    service = RobotSimService(RobotSimConfig(clock=ClockMode.REALTIME, zenoh=ZenohConfig(
        connect=[deployment.endpoint], config_file=str(deployment.client_configs["robot_sim"]))))
    service.start()
    yield service
    service.stop()


def api_call(session, function):
    replies = [r for r in session.get(KEYS.robot_api(function), timeout=3.0) if r.ok is not None]
    return [m.decode(r.ok.payload.to_bytes(), kinova.API_FUNCTIONS[function][1]) for r in replies]


def test_only_safety_changes_the_robot_through_its_api(deployment, robot):
    """Everyone may read the arm through the Kinova API; moving it, or changing its zones and limits, is
    safety's alone (the router drops the other identities' queries)."""
    for name in ("operator", "controller", "vision", "torque_controller"):
        session = session_as(deployment, name)
        assert [reply.code for reply in api_call(session, "GetAngularPosition")] == [1], name
        for function in ("MoveHome", "EraseAllProtectionZones", "SendBasicTrajectory"):
            assert api_call(session, function) == [], (name, function)
        session.close()
    assert robot.counters.get("rejected.api") == 0  # they never reached the robot
    safety = session_as(deployment, "safety")
    assert [reply.code for reply in api_call(safety, "EraseAllTrajectories")] == [1]
    safety.close()


def test_only_the_torque_controller_identity_commands_torques(deployment, robot):
    """Low-level torque commands bypass safety: only the identity given to a tested torque controller may send
    them."""
    def torques_from(name):
        session = session_as(deployment, name)
        publisher = session.declare_publisher(KEYS.lowlevel_command)
        time.sleep(0.2)
        start = time.monotonic()
        for k in range(100):  # 0.2 s at 500 Hz
            time.sleep(max(0.0, start + k * 0.002 - time.monotonic()))
            publisher.put(m.encode(m.TorqueCommand(header=m.Header(stamp_ns=time.time_ns()), torques=[0.0] * 7)))
        session.close()

    for name in ("safety", "controller", "operator"):
        torques_from(name)
        assert not robot.lowlevel.active and "lowlevel_command" not in robot.rates.snapshot(), name
    torques_from("torque_controller")
    assert robot.rates.snapshot().get("lowlevel_command", 0) > 0
    assert wait_for(lambda: not robot.lowlevel.active, timeout=2)  # released 250 ms after the last command


def test_only_robots_publish_robot_state(deployment):
    safety = session_as(deployment, "safety")
    states = Recorder(safety, KEYS.robot_state, m.RobotState)
    fake = m.encode(m.RobotState(header=m.Header(), q=[0.0] * 7, dq=[0.0] * 7, tau=[0.0] * 7,
                                 pose=m.KinovaPose(X=0, Y=0, Z=0, ThetaX=0, ThetaY=0, ThetaZ=0),
                                 control_mode=m.ControlMode.IDLE))
    for service in ("vision", "controller", "operator"):
        session = session_as(deployment, service)
        time.sleep(0.2)
        session.put(KEYS.robot_state, fake)
        session.close()
    robot = session_as(deployment, "robot_sim")
    time.sleep(0.2)
    robot.put(KEYS.robot_state, fake)
    assert wait_for(lambda: len(states) == 1, timeout=5)
    time.sleep(0.3)
    assert len(states) == 1  # only the robot's
    robot.close()
    safety.close()


def test_other_traffic_flows_for_every_service(deployment):
    vision = session_as(deployment, "vision")
    controller = session_as(deployment, "controller")
    got = Recorder(controller, KEYS.features, m.Features)
    token = vision.liveliness().declare_token(KEYS.liveliness("vision"))
    time.sleep(0.3)
    vision.put(KEYS.features, m.encode(m.Features(header=m.Header(), status=m.FeatureStatus.TAG_LOST)))
    assert wait_for(lambda: len(got) == 1, timeout=5)
    alive = [str(r.ok.key_expr) for r in controller.liveliness().get(KEYS.liveliness_all)]
    assert alive == [KEYS.liveliness("vision")]
    token.undeclare()
    vision.close()
    controller.close()


def test_unauthenticated_clients_cannot_join(deployment, tmp_path):
    bad = tmp_path / "bad.json5"
    if deployment.tls:
        certs = deployment.router_config.parent / "certs"
        # no client certificate
        bad.write_text('{"mode": "client", "transport": {"link": {"tls": {"root_ca_certificate": "%s", '
                       '"enable_mtls": true}}}}' % (certs / "ca.pem"))
        with pytest.raises(zenoh.ZError):
            open_session(ZenohConfig(connect=[deployment.endpoint], config_file=str(bad)))
        # a certificate from another CA that claims to be safety
        bad.write_text('{"mode": "client", "transport": {"link": {"tls": {"root_ca_certificate": "%s", '
                       '"enable_mtls": true, "connect_private_key": "%s", "connect_certificate": "%s"}}}}'
                       % (certs / "ca.pem", certs / "rogue_safety.key", certs / "rogue_safety.pem"))
        with pytest.raises(zenoh.ZError):
            open_session(ZenohConfig(connect=[deployment.endpoint], config_file=str(bad)))
        # plain TCP to the TLS port
        with pytest.raises(zenoh.ZError):
            open_session(ZenohConfig(connect=[deployment.endpoint.replace("tls/", "tcp/")]))
    else:
        bad.write_text('{"mode": "client", "transport": {"auth": {"usrpwd": {"user": "safety", '
                       '"password": "not-the-password"}}}}')
        with pytest.raises(zenoh.ZError):
            open_session(ZenohConfig(connect=[deployment.endpoint], config_file=str(bad)))
        with pytest.raises(zenoh.ZError):
            open_session(ZenohConfig(connect=[deployment.endpoint]))  # no credentials at all
