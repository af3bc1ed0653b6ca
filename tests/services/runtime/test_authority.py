"""Authority over the robot, enforced by a real zenoh router: access control by user (acl) and by certificate
(tls). Only safety may command the robot; only robot services may publish robot state."""
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
import zenoh
import zenoh.ext

from protocol import kinova
from protocol import messages as m
from protocol.conventions import AngularConvention, ClockMode, Frame
from protocol.keys import Keys
from services.runtime.authority import DEFAULT_SERVICES, announces, write_deployment
from services.runtime.transport import Router, ZenohConfig, free_loopback_port, open_session
from services.robot_sim.service import RobotSimConfig, RobotSimService
from tests.stack import KEYS, Recorder, next_seq, wait_for
from tests.helpers import REPO
from tests.helpers import ARM_DECLARED



def velocity_command(stamp=0):
    header = m.Header(stamp_ns=stamp, seq=next_seq())
    twist = m.Twist(header=header, frame=Frame.MIXED, angular=AngularConvention.SEED000, linear=(0.05, 0.0, 0.0),
                    rotational=(0.0, 0.0, 0.0))
    return m.encode(m.RobotCommand(header=header, mode=m.CommandMode.CARTESIAN_VELOCITY, twist=twist))


INTRUDER = textwrap.dedent("""
    import sys, time
    from services.runtime.transport import ZenohConfig, open_session
    from tests.services.runtime.test_authority import velocity_command
    endpoint, config_file, *keys = sys.argv[1:]
    session = open_session(ZenohConfig(connect=[endpoint], config_file=config_file))
    publishers = [session.declare_publisher(key) for key in keys]
    for _ in range(150):          # 1.5 s of commands at 100 Hz on each key
        for publisher in publishers:
            publisher.put(velocity_command(time.time_ns()))
        time.sleep(0.01)
    session.close()
    print("sent", flush=True)
""")


def run_intruder(endpoint, config_file, keys=(KEYS.robot_command,)):
    """A second process that publishes commands on each of ``keys`` at 100 Hz for 1.5 s."""
    out = subprocess.run([sys.executable, "-c", INTRUDER, endpoint, str(config_file), *keys], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "sent" in out.stdout, out.stderr
    return out


def run_intruders(endpoint, config_files) -> None:
    """:func:`run_intruder` for each identity's config at once (each its own process)."""
    intruders = [subprocess.Popen([sys.executable, "-c", INTRUDER, endpoint, str(config), KEYS.robot_command],
                                  cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for config in config_files]
    for intruder in intruders:
        stdout, stderr = intruder.communicate(timeout=60)
        assert intruder.returncode == 0 and "sent" in stdout, stderr


#: a test whose rule the tls deployment enforces exactly as the acl one (the same role table; only how the router
#: learns the identity differs, which test_each_identity_writes_exactly_its_own_keys, test_unauthenticated_clients_
#: cannot_join and test_only_safety_can_command_the_robot check on both): on tls in the slow run only
ACL_ONLY_IN_QUICK_RUN = pytest.mark.parametrize(
    "deployment", ["acl", pytest.param("tls", marks=pytest.mark.slow)], indirect=True)


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
        # two more processes, authenticated as the vision and the controller service, publish commands at once:
        # refused by the router
        run_intruders(deployment.endpoint, [deployment.client_configs["vision"],
                                            deployment.client_configs["controller"]])
        assert "command" not in robot.rates.snapshot()
        assert np.abs(np.array(states.last().q) - q0).max() < 1e-6
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


@ACL_ONLY_IN_QUICK_RUN
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


@ACL_ONLY_IN_QUICK_RUN
def test_only_the_operator_starts_and_stops_the_task(deployment):
    """The stack moves only for a started task, and only the operator identity may start or stop it (the router
    drops the others' requests: no reply); everyone may read it."""
    from services.controller.service import ControllerConfig, ControllerService
    from services.controller.task_client import TaskUnavailable, call_task, start_task, stop_task

    controller = ControllerService(ControllerConfig(zenoh=ZenohConfig(
        connect=[deployment.endpoint], config_file=str(deployment.client_configs["controller"])))).start()
    try:
        for name in ("vision", "safety", "robot_sim", "torque_controller"):
            session = session_as(deployment, name)
            with pytest.raises(TaskUnavailable):
                start_task(session, KEYS, operator=name, timeout_s=1.0)
            assert call_task(session, KEYS, m.GET_TASK).state is m.TaskState.IDLE, name
            session.close()
        assert not controller.core.task.running
        operator = session_as(deployment, "operator")
        assert start_task(operator, KEYS, operator="test").state is m.TaskState.RUNNING
        assert controller.core.task.running
        vision = session_as(deployment, "vision")
        with pytest.raises(TaskUnavailable):
            stop_task(vision, KEYS, operator="vision", timeout_s=1.0)
        assert call_task(vision, KEYS, m.GET_TASK).state is m.TaskState.RUNNING
        vision.close()
        assert stop_task(operator, KEYS, operator="test").state is m.TaskState.IDLE
        operator.close()
    finally:
        controller.stop()


@ACL_ONLY_IN_QUICK_RUN
def test_only_the_torque_controller_identity_commands_torques(deployment, robot):
    """Low-level torque commands bypass safety: only the identity given to a tested torque controller may send
    them, and make the torque-mode setup before (Table 5.1's functions; safety may too, as it may every function
    that changes how the arm moves)."""
    def torques_from(name):
        session = session_as(deployment, name)
        publisher = session.declare_publisher(KEYS.lowlevel_command)
        time.sleep(0.2)
        start = time.monotonic()
        for k in range(100):  # 0.2 s at 500 Hz
            time.sleep(max(0.0, start + k * 0.002 - time.monotonic()))
            publisher.put(m.encode(m.TorqueCommand(header=m.Header(seq=next_seq(), stamp_ns=time.time_ns()),
                                                   torques=[0.0] * 7)))
        session.close()

    def safety_factor_from(name):
        session = session_as(deployment, name)
        replies = [r for r in session.get(KEYS.robot_api("SetTorqueSafetyFactor"), timeout=3.0,
                                          payload=m.encode(kinova.FloatArgument(value=1.0))) if r.ok is not None]
        session.close()
        return [m.decode(r.ok.payload.to_bytes(), kinova.ApiReply).code for r in replies]

    for name in ("safety", "controller", "operator"):
        torques_from(name)
        assert not robot.lowlevel.active and "lowlevel_command" not in robot.rates.snapshot(), name
    for name in ("controller", "operator", "vision"):  # Table 5.1's setup: the torque client's (and safety's)
        assert safety_factor_from(name) == [], name
    assert robot.torque_setup.safety_factor < 1.0
    assert safety_factor_from("torque_controller") == [kinova.ErrorCode.NO_ERROR_KINOVA]
    assert robot.torque_setup.safety_factor == 1.0
    torques_from("torque_controller")
    assert robot.rates.snapshot().get("lowlevel_command", 0) > 0
    assert wait_for(lambda: not robot.lowlevel.active, timeout=2)  # released 250 ms after the last command


@ACL_ONLY_IN_QUICK_RUN
def test_only_the_jog_identity_moves_the_arm_with_a_stick(deployment, robot):
    """Behind the authority router, with safety as shipped: a stick's requests from any identity but the jog's
    reach nobody and move nothing; the jog identity's move the arm (the stick's source is safety's only by the
    router's word: safety cannot tell who published)."""
    from services.safety.service import SafetyConfig, SafetyService

    safety = SafetyService(SafetyConfig(zenoh=ZenohConfig(connect=[deployment.endpoint],
                                                          config_file=str(deployment.client_configs["safety"]))))
    safety.start()
    watcher = session_as(deployment, "safety")
    states = Recorder(watcher, KEYS.robot_state, m.RobotState)
    try:
        assert wait_for(lambda: len(states) > 5)

        def push(identity, seconds=0.6):
            session = session_as(deployment, identity)
            time.sleep(0.2)
            start = time.time_ns()
            for i in range(int(seconds * 50)):
                now = time.time_ns()
                session.put(KEYS.desired_jog, m.encode(m.Jog(
                    header=m.Header(seq=start // 1000 + i, stamp_ns=now, source_stamp_ns=now),
                    mode=m.JogMode.TRANSLATION, deadman=True, linear=(0.0, 0.05, 0.0))))
                time.sleep(0.02)
            session.close()

        q0 = np.array(states.last().q)
        for identity in ("operator", "controller", "vision", "torque_controller"):
            push(identity)
        assert "jog" not in safety.rates.snapshot() and np.abs(np.array(states.last().q) - q0).max() < 1e-6
        push("jog")
        assert wait_for(lambda: np.abs(np.array(states.last().q) - q0).max() > 1e-3, timeout=5)
    finally:
        states.close()
        watcher.close()
        safety.stop()


def test_only_robots_publish_robot_state(deployment):
    safety = session_as(deployment, "safety")
    states = Recorder(safety, KEYS.robot_state, m.RobotState)
    fake = m.encode(m.RobotState(**ARM_DECLARED, header=m.Header(), q=[0.0] * 7, dq=[0.0] * 7, tau=[0.0] * 7,
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


@ACL_ONLY_IN_QUICK_RUN
def test_other_traffic_flows_for_every_service(deployment):
    vision = session_as(deployment, "vision")
    controller = session_as(deployment, "controller")
    got = Recorder(controller, KEYS.features, m.Features)
    token = vision.liveliness().declare_token(KEYS.liveliness("vision"))
    time.sleep(0.3)
    vision.put(KEYS.features, m.encode(m.Features(header=m.Header(), status=m.FeatureStatus.TARGET_LOST)))
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


WILDCARD_FORMS = ["mfvs/jaco/robot/*", "mfvs/jaco/robot/**", "mfvs/jaco/robot/comm$*", "mfvs/jaco/**", "mfvs/*/robot/command",
                  "mfvs/**/command", "**"]


@ACL_ONLY_IN_QUICK_RUN
def test_no_wildcard_reaches_the_robot_for_an_identity_that_may_not_command(deployment, robot):
    """Zenoh's access control applies a rule to a key expression included in the rule's: the per-identity allow
    lists include no wildcard form of a protected key, so the router drops them (as it drops the literal key). One
    intruder publishes on every form at once: a form that got through would show in the robot's command rate."""
    operator = session_as(deployment, "operator")
    states = Recorder(operator, KEYS.robot_state, m.RobotState)
    assert wait_for(lambda: len(states) > 5)
    q0 = np.array(states.last().q)
    run_intruder(deployment.endpoint, deployment.client_configs["operator"], WILDCARD_FORMS)
    assert "command" not in robot.rates.snapshot()
    assert np.abs(np.array(states.last().q) - q0).max() < 1e-6
    states.close()
    operator.close()


def concrete_keys() -> list[str]:
    k = KEYS
    return [k.camera_image, k.camera_info, k.features, k.vision_goal, k.desired_twist, k.desired_joint_velocity,
            k.desired_jog, k.controller_status, k.robot_command, k.safety_status, k.estop, k.robot_state, k.lowlevel_command,
            k.lowlevel_state, k.clock] + [k.health(s) for s in (*DEFAULT_SERVICES, "console")]


def test_each_identity_writes_exactly_its_own_keys(deployment):
    """Every identity puts on every key of the stack, and on the wildcard forms above; a subscriber to everything
    sees exactly what the role table (services.runtime.authority.writes) allows: one writer per key that can move
    the arm, health only in one's own name, no wildcard."""
    from services.runtime.authority import writes
    table = writes(Keys("jaco"))
    rules = writes(Keys.all_robots())

    def allowed(identity, key):  # zenoh's rule: the key expression is included in one of the identity's
        own = rules.get(identity, []) + [Keys.all_robots().health(name) for name in announces(identity)]
        return any(zenoh.KeyExpr(rule).includes(zenoh.KeyExpr(key)) for rule in own)

    listener = session_as(deployment, "robot_sim")
    seen: list[tuple[str, bytes]] = []
    sub = listener.declare_subscriber("**", lambda s: seen.append((str(s.key_expr), s.payload.to_bytes())))
    time.sleep(0.3)
    expected = set()
    for identity in DEFAULT_SERVICES:
        session = session_as(deployment, identity)
        time.sleep(0.2)
        for key in concrete_keys() + WILDCARD_FORMS:
            marker = f"{identity}>{key}".encode()
            session.put(key, marker)
            if allowed(identity, key):
                expected.add((key, marker))
        time.sleep(0.2)
        session.close()
    assert wait_for(lambda: expected <= set(seen), timeout=5), sorted(expected - set(seen))
    time.sleep(0.3)
    ours = {(key, payload) for key, payload in seen if b">" in payload}
    assert ours == expected, sorted(ours - expected)
    writers = {}
    for identity, keys in table.items():
        for key in keys:
            writers.setdefault(key, []).append(identity)
    for key in (KEYS.camera_image, KEYS.features, KEYS.desired_twist, KEYS.desired_joint_velocity, KEYS.desired_jog,
                KEYS.robot_command, KEYS.lowlevel_command):  # the keys that can cause motion: one writer each
        assert len(writers[key]) == 1, (key, writers[key])
    sub.undeclare()
    listener.close()


def test_without_the_acl_the_robot_still_drops_commands_on_a_wildcard(router):
    """Defence in depth: on an open router (no access control) a command published on a wildcard that intersects
    the robot's key reaches its subscription, and the robot drops it, counted, because it is not on the literal key
    its one writer uses: each form in turn, on one robot."""
    robot = RobotSimService(RobotSimConfig(clock=ClockMode.REALTIME, zenoh=router.client_config())).start()
    try:
        client = open_session(router.client_config())
        states = Recorder(client, KEYS.robot_state, m.RobotState)
        assert wait_for(lambda: len(states) > 5)
        q0 = np.array(states.last().q)
        for key in ["mfvs/jaco/robot/*", "mfvs/jaco/robot/**", "mfvs/jaco/robot/comm$*", "mfvs/*/robot/command"]:
            rejected = robot.counters.get("rejected.command.key")
            publisher = client.declare_publisher(key)
            time.sleep(0.3)
            for _ in range(50):
                publisher.put(velocity_command(time.time_ns()))
                time.sleep(0.01)
            assert wait_for(lambda: robot.counters.get("rejected.command.key") >= rejected + 45, timeout=5), key
            publisher.undeclare()
            assert "command" not in robot.rates.snapshot(), key
        time.sleep(0.2)
        assert np.abs(np.array(states.last().q) - q0).max() < 1e-6
        client.put(KEYS.robot_command, velocity_command(time.time_ns()))  # the literal key still works
        assert wait_for(lambda: robot.rates.snapshot().get("command", 0) > 0, timeout=5)
        states.close()
        client.close()
    finally:
        robot.stop()


def test_with_a_camera_identity_the_camera_keys_are_its_alone_and_the_operator_may_check_the_arm(tmp_path):
    """A real-arm deployment (`mfvs authority init --services ...,camera`): the camera service is the camera keys'
    one writer and robot_sim is no longer one; the operator may ask the robot for its commissioning check, which
    only a robot may answer."""
    port = free_loopback_port()
    deployment = write_deployment(tmp_path, port=port, services=("robot_sim", "camera", "operator", "vision"))
    with Router(port=port, config_file=deployment.router_config):
        listener = session_as(deployment, "vision")
        seen = []
        listener.declare_subscriber(KEYS.camera_image, lambda s: seen.append(s.payload.to_bytes()))
        time.sleep(0.3)
        for identity in ("robot_sim", "camera", "operator"):
            session = session_as(deployment, identity)
            time.sleep(0.2)
            session.put(KEYS.camera_image, identity.encode())
            time.sleep(0.2)
            session.close()
        assert wait_for(lambda: seen == [b"camera"], timeout=3.0), seen
        robot = session_as(deployment, "robot_sim")
        answered = []
        queryable = robot.declare_queryable(KEYS.robot_check_arm, lambda q: (answered.append(1), q.reply(
            q.key_expr, m.encode(m.ArmCheckReply(ok=False, message="test")))))
        time.sleep(0.3)
        for identity, expected in (("vision", 0), ("operator", 1)):
            session = session_as(deployment, identity)
            replies = [r for r in session.get(KEYS.robot_check_arm, timeout=2.0) if r.ok is not None]
            assert len(replies) == expected, identity
            session.close()
        rogue = session_as(deployment, "camera")  # a camera may not answer in the robot's name
        rogue.declare_queryable(KEYS.robot_check_arm, lambda q: q.reply(q.key_expr, b"rogue"))
        time.sleep(0.3)
        operator = session_as(deployment, "operator")
        payloads = [r.ok.payload.to_bytes() for r in operator.get(KEYS.robot_check_arm, timeout=2.0)
                    if r.ok is not None]
        assert b"rogue" not in payloads and len(payloads) == 1
        for s in (operator, rogue, robot, listener):
            s.close()
        queryable  # kept declared until here


@ACL_ONLY_IN_QUICK_RUN
def test_the_console_acts_as_the_operator_and_says_how_it_is_doing_in_its_own_name(deployment):
    """`mfvs console` with the operator's config: alive and answering health as ``console`` (so `mfvs status`
    lists it); its e-stop is the operator's; the operator's identity announces no other service."""
    from services.console.service import ConsoleConfig, ConsoleService
    from services.runtime.service import query_health

    console = ConsoleService(ConsoleConfig(zenoh=ZenohConfig(
        connect=[deployment.endpoint], config_file=str(deployment.client_configs["operator"])))).start()
    observer = session_as(deployment, "vision")
    try:
        assert wait_for(lambda: "console" in query_health(observer, KEYS, 1.0), timeout=10)
        alive = [str(r.ok.key_expr) for r in observer.liveliness().get(KEYS.liveliness_all, timeout=2) if r.ok]
        assert KEYS.liveliness("console") in alive
        impostor = session_as(deployment, "operator")
        impostor.liveliness().declare_token(KEYS.liveliness("safety"))
        time.sleep(0.5)
        alive = [str(r.ok.key_expr) for r in observer.liveliness().get(KEYS.liveliness_all, timeout=2) if r.ok]
        assert KEYS.liveliness("safety") not in alive
        impostor.close()
    finally:
        observer.close()
        console.stop()


def test_with_a_ros2_domain_the_ros2_nodes_and_the_bridge_speak_ros_2_and_nothing_of_mfvs(tmp_path):
    """`mfvs authority init --ros2-domain 0`: an identity for the lab's ROS 2 nodes. The ROS 2 bridge, the
    operator's tool, declares its node, serves its latched topics and answers its services on domain 0; a ROS 2
    node with the ros2 identity sees the node, joins late and gets the description from the cache, and calls a
    service; it may not publish on any mfvs key, on another domain or on a wildcard, and the other identities
    (vision here) may not speak ROS 2."""
    from services.robot_sim.service import RobotSimConfig, RobotSimService
    from services.ros2_bridge.service import Ros2BridgeConfig, Ros2BridgeService
    from services.runtime.authority import ROS2_IDENTITY

    port = free_loopback_port()
    deployment = write_deployment(tmp_path / "authority", port=port, ros2_domains=(0,))
    assert ROS2_IDENTITY in deployment.client_configs
    with Router(port=port, config_file=deployment.router_config):
        as_ = lambda name: ZenohConfig(connect=[deployment.endpoint],  # noqa: E731
                                       config_file=str(deployment.client_configs[name]))
        robot = RobotSimService(RobotSimConfig(clock=ClockMode.REALTIME, zenoh=as_("robot_sim"))).start()
        bridge = Ros2BridgeService(Ros2BridgeConfig(domain_id=0, zenoh=as_("operator"))).start()
        ros = open_session(as_(ROS2_IDENTITY))
        watcher = session_as(deployment, "robot_sim")
        try:
            def tokens() -> list[str]:
                return [str(r.ok.key_expr) for r in ros.liveliness().get("@ros2_lv/0/**", timeout=2.0) if r.ok]
            assert wait_for(lambda: any("/NN/" in t for t in tokens()) and any("robot_description" in t
                                                                                for t in tokens()), timeout=30)
            token = next(t for t in tokens() if "/MP/" in t and "robot_description" in t).split("/")
            description_key = f"0/{token[9].replace('%', '/').lstrip('/')}/{token[10]}/{token[11]}"
            got = []
            late = zenoh.ext.declare_advanced_subscriber(
                ros, description_key, lambda sample: got.append(sample.payload.to_bytes()),
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True))
            assert wait_for(lambda: got, timeout=15), "the ros2 identity got no latched description"
            assert b"<robot" in got[0]
            late.undeclare()
            # a ROS 2 node's own endpoint, and a service call (refused for its missing attachment: it reached the
            # bridge, which says why)
            listener = ros.liveliness().declare_token(f"@ros2_lv/0/{ros.zid()}/0/0/NN/%/%/listener")
            start = next(t for t in tokens() if "/SS/" in t and "start_task" in t).split("/")
            start_key = f"0/{start[9].replace('%', '/').lstrip('/')}/{start[10]}/{start[11]}"
            replies = list(ros.get(start_key, payload=b"\x00\x01\x00\x00\x00", timeout=5.0))
            assert replies and replies[0].err is not None and b"attachment" in replies[0].err.payload.to_bytes()
            operator = session_as(deployment, "operator")  # the bridge's identity sees the ROS 2 node
            assert wait_for(lambda: f"@ros2_lv/0/{ros.zid()}/0/0/NN/%/%/listener" in
                            [str(r.ok.key_expr) for r in operator.liveliness().get("@ros2_lv/0/**", timeout=2.0)
                             if r.ok], timeout=10)
            operator.close()
            # what the ros2 identity may not do: mfvs's keys, another domain, a wildcard; nor may vision speak ROS 2
            heard = []
            everything = watcher.declare_subscriber("**", lambda s: heard.append(str(s.key_expr)))
            time.sleep(0.3)
            refused = [KEYS.robot_command, KEYS.estop, KEYS.vision_goal, KEYS.features, "1/joint_states/x/y", "**",
                       "*/**"]
            for key in refused:
                ros.put(key, b"x")
            vision = session_as(deployment, "vision")
            refused.append("0/impostor/sensor_msgs::msg::dds_::JointState_/x")
            vision.put(refused[-1], b"x")
            impostor = vision.liveliness().declare_token(f"@ros2_lv/0/{vision.zid()}/0/0/NN/%/%/impostor")
            ros.put("0/chatter/std_msgs::msg::dds_::String_/x", b"x")  # the control: this one passes
            assert wait_for(lambda: "0/chatter/std_msgs::msg::dds_::String_/x" in heard, timeout=5)
            time.sleep(0.5)
            assert not set(heard) & set(refused), sorted(set(heard) & set(refused))
            assert not any("impostor" in t for t in tokens()), tokens()
            for declared in (listener, impostor, everything):
                declared.undeclare()
            vision.close()
        finally:
            watcher.close()
            ros.close()
            bridge.stop()
            robot.stop()


def test_a_ros_2_stick_reaches_jog_request_only_through_the_jog_identitys_session(tmp_path):
    """The bridge runs as the operator, who may not put on jog/request (one writer per motion key: the jog
    identity). A sensor_msgs/Joy from a ROS 2 node (the ros2 identity) through a bridge with no ``jog_zenoh``: the
    router drops its jog request; through one given the jog identity's client config: safety hears it."""
    import struct

    from services.ros2_bridge import core
    from services.ros2_bridge.service import Ros2BridgeConfig, Ros2BridgeService
    from services.runtime.authority import ROS2_IDENTITY

    port = free_loopback_port()
    deployment = write_deployment(tmp_path / "authority", port=port, ros2_domains=(0,))
    as_ = lambda name: ZenohConfig(connect=[deployment.endpoint],  # noqa: E731
                                   config_file=str(deployment.client_configs[name]))
    axes, buttons = [0.0, 0.8] + [0.0] * 6, [0, 0, 0, 0, 1] + [0] * 6  # left stick up, LB held

    def joy() -> bytes:
        now = time.time_ns()
        head = b"\x00\x01\x00\x00" + struct.pack("<iII", now // 10**9, now % 10**9, 4) + b"joy\x00"
        return head + struct.pack("<I8fI11i", 8, *axes, 11, *buttons)

    with Router(port=port, config_file=deployment.router_config):
        ros = open_session(as_(ROS2_IDENTITY))
        safety = session_as(deployment, "safety")
        jogs = Recorder(safety, KEYS.desired_jog, m.Jog)
        try:
            for jog_zenoh, heard in ((None, False), (as_("jog"), True)):
                bridge = Ros2BridgeService(Ros2BridgeConfig(zenoh=as_("operator"), jog_zenoh=jog_zenoh)).start()
                try:
                    key = bridge.graph.endpoints[core.JOY].key
                    assert wait_for(lambda: any("/MS/" in str(r.ok.key_expr) and "%joy/" in str(r.ok.key_expr)
                                                for r in ros.liveliness().get("@ros2_lv/0/**", timeout=2.0) if r.ok),
                                    timeout=15)
                    if heard:  # (a publisher drops what no subscriber it knows of matches)
                        assert wait_for(lambda: bridge._jog_publisher.matching, timeout=5)
                    for sequence in range(1, 6):
                        ros.put(key, joy(), attachment=struct.pack("<qq", sequence, time.time_ns()) + b"\x10"
                                + bytes(16))
                        time.sleep(0.02)
                    # the bridge made all five requests either way (the router decides who hears them)
                    assert wait_for(lambda: bridge.counters.get("jog.joy") == 5, timeout=5), bridge.counters.snapshot()
                    if heard:
                        assert wait_for(lambda: len(jogs) == 5, timeout=5), len(jogs)
                        assert all(j.deadman and j.source == "jog/ros-joy" for j in jogs.snapshot())
                    else:
                        time.sleep(1.0)
                        assert len(jogs) == 0
                finally:
                    bridge.stop()
        finally:
            jogs.close()
            safety.close()
            ros.close()
