"""robot_sim as a service over a real zenoh router, in lockstep: the test process plays the safety service."""
import bisect
import threading
import time

import msgpack
import msgspec
import numpy as np
import pytest

from protocol import kinova
from protocol import messages as m
from protocol.conventions import AngularConvention, ClockMode, Frame
from protocol.keys import Keys
from services.robot.dsp import DSPConfig, motion_limits
from services.robot.lockstep_gate import LockstepConfig
from services.runtime.transport import GuardedPublisher, open_session
from services.robot_sim.service import RobotSimConfig, RobotSimService
from tests.stack import next_seq, wait_for
from services.model.arm import load_arm

ARM = load_arm("j2s7s300")

KEYS = Keys()




class FakeSafety:
    """Answers every clock tick with a robot command stamped at the tick and derived from the latest frame (what
    the safety service does with the pipeline's output), alive under safety's name (the robot waits for its
    answers while safety is alive)."""

    def __init__(self, session, make_command, watch_frames=False):
        self.session = session
        self.make_command = make_command
        self.publisher = GuardedPublisher.declare(session, KEYS.robot_command)
        self.ticks = 0
        self.frame_stamp = 0
        self.lock = threading.Lock()
        self.subscribers = [session.declare_subscriber(KEYS.clock, self._on_tick)]
        if watch_frames:
            self.subscribers.append(session.declare_subscriber(KEYS.camera_image, self._on_image))
        # alive once it listens, as a service declares its liveliness after its subscriptions
        self.token = session.liveliness().declare_token(KEYS.liveliness("safety"))

    def _on_image(self, sample):
        with self.lock:
            self.frame_stamp = m.decode(sample.payload.to_bytes(), m.Image).header.source_stamp_ns
        self._answer(self.frame_stamp)

    def _on_tick(self, sample):
        tick = m.decode(sample.payload.to_bytes(), m.SimClock)
        with self.lock:
            self.ticks += 1
        self._answer(tick.sim_time_ns)

    def _answer(self, stamp):
        payloads = self.make_command(stamp, self.frame_stamp)
        for payload in payloads if isinstance(payloads, list) else [payloads]:
            self.publisher.put(payload)

    def close(self):
        for subscriber in self.subscribers:
            subscriber.undeclare()
        self.publisher.undeclare()
        self.token.undeclare()


def twist_payload(stamp, source_stamp=0, linear=(0.05, 0.0, 0.0), convention=AngularConvention.SEED000):
    header = m.Header(stamp_ns=stamp, source_stamp_ns=source_stamp, seq=next_seq())
    twist = m.Twist(header=header, frame=Frame.MIXED, angular=convention, linear=linear, rotational=(0.0, 0.0, 0.0))
    return m.encode(m.RobotCommand(header=header, mode=m.CommandMode.CARTESIAN_VELOCITY, twist=twist))


@pytest.fixture
def client(router):
    session = open_session(router.client_config())
    yield session
    session.close()


@pytest.fixture
def start_robot(router):
    """Starts robot_sim in lockstep when called (so a test can subscribe first)."""
    started = []

    def start():
        config = RobotSimConfig(clock=ClockMode.LOCKSTEP, zenoh=router.client_config(), health_period_s=0.2)
        service = RobotSimService(config)
        service.start()
        started.append(service)
        return service

    yield start
    for service in started:
        service.stop()


@pytest.fixture
def robot(start_robot):
    return start_robot()


def collect(session, key, message_type):
    out = []
    session.declare_subscriber(key, lambda s: out.append(m.decode(s.payload.to_bytes(), message_type)))
    return out


def test_lockstep_velocity_command_moves_as_declared(robot, client):
    states = collect(client, KEYS.robot_state, m.RobotState)
    safety = FakeSafety(client, lambda t, f: twist_payload(t, f))
    try:
        assert wait_for(lambda: len(states) >= 150, timeout=60)
    finally:
        safety.close()
    window = states[80:150]
    stamps = np.array([s.header.stamp_ns for s in window])
    assert np.all(np.diff(stamps) == 10_000_000)  # exactly one 10 ms cycle per state in lockstep
    xyz = np.array([[s.pose.X, s.pose.Y, s.pose.Z] for s in window])
    velocity = np.diff(xyz, axis=0) / 0.01
    assert np.allclose(velocity.mean(axis=0), [0.05, 0.0, 0.0], atol=0.001)
    applied = [s.applied_command for s in window]
    assert all(a is not None and a.trace[-1].service == "robot_sim" for a in applied)
    assert all(s.angular_convention is AngularConvention.SEED000 for s in window)
    # the limits its DSP applies, declared in every state (the controller and safety read them there)
    assert all(s.limits == motion_limits(DSPConfig(), ARM) for s in window)


def test_lockstep_publishes_frames_with_capture_stamps(start_robot, client):
    images = collect(client, KEYS.camera_image, m.Image)
    safety = FakeSafety(client, lambda t, f: twist_payload(t, f, linear=(0.0, 0.0, 0.0)), watch_frames=True)
    time.sleep(0.3)  # let the subscriptions reach the router before the first frame
    robot = start_robot()
    try:
        assert wait_for(lambda: len(images) >= 4, timeout=60)
        frame_timeouts = robot.counters.get("lockstep.timeouts.frame")  # before the fake safety goes away
    finally:
        safety.close()
    stamps = [i.header.source_stamp_ns for i in images[:4]]
    assert all(i.header.stamp_ns == i.header.source_stamp_ns for i in images[:4])
    periods = np.diff(stamps)
    assert np.all(np.abs(periods - 1e9 / 30) <= 10_000_000)  # frames fall on the cycle at or after 1/30 s
    assert frame_timeouts == 0
    assert images[0].width == 640 and images[0].height == 480 and images[0].encoding is m.ImageEncoding.MONO8  # robot_sim.yaml default
    replies = list(client.get(KEYS.camera_info))
    info = m.decode(replies[0].ok.payload.to_bytes(), m.CameraInfo)
    assert (info.fx, info.fy, info.cx, info.cy) == (615.0, 615.0, 319.5, 239.5)


def test_bad_and_refused_commands_leave_the_arm_at_rest(robot, client):
    states = collect(client, KEYS.robot_state, m.RobotState)
    plain = msgpack.unpackb(twist_payload(0))
    plain["twist"]["linear"][0] = float("nan")
    nan_payload = msgpack.packb(plain)
    bad = [b"\x93garbage", twist_payload(0)[:-4], nan_payload]
    counter = {"n": 0}

    def make(t, _frame):
        counter["n"] += 1
        # garbage first, then a valid command in a convention this arm does not read (it answers the tick)
        return [bad[counter["n"] % 3], twist_payload(t, convention=AngularConvention.OMEGA)]

    safety = FakeSafety(client, make)
    try:
        assert wait_for(lambda: len(states) >= 100, timeout=60)
    finally:
        safety.close()
    q = np.array([s.q for s in states])
    assert np.abs(q - q[0]).max() < 1e-6
    errors = robot.counters.snapshot()
    assert errors.get("rejected.command", 0) >= 60
    assert errors.get("refused.convention", 0) >= 60
    assert any(f.startswith("refused: this arm reads angular velocity as 'seed000'") for f in states[-1].faults)
    assert robot.state == "running"


def api(client, function, argument=None, reply_type=kinova.ApiReply):
    payload = m.encode(argument) if argument is not None else None
    replies = list(client.get(KEYS.robot_api(function), payload=payload, timeout=10.0))
    assert len(replies) == 1
    return m.decode(replies[0].ok.payload.to_bytes(), reply_type)


def test_kinova_api_queryables(robot, client):
    position = api(client, "GetAngularPosition", reply_type=kinova.AngularPositionReply)
    assert position.code == kinova.ErrorCode.NO_ERROR_KINOVA
    # the arm holding at home, as the DSP holds it: within a thousandth of a degree (it settles by micro-degrees
    # under gravity for as long as the service has run, which a loaded host makes longer)
    assert position.result.Actuators.as_list() == pytest.approx(ARM.home_deg.tolist(), abs=1e-3)
    cartesian = api(client, "GetCartesianPosition", reply_type=kinova.CartesianPositionReply)
    T = ARM.dh_forward_kinematics(ARM.home)
    assert [cartesian.result.Coordinates.X, cartesian.result.Coordinates.Y, cartesian.result.Coordinates.Z] == \
        pytest.approx(T[:3, 3].tolist(), abs=1e-5)

    target = ARM.home_deg + np.array([5.0, -5.0, 0.0, 5.0, 0.0, -5.0, 10.0])
    point = kinova.TrajectoryPoint(Position=kinova.UserPosition(
        Type=kinova.POSITION_TYPE.ANGULAR_POSITION, Actuators=kinova.AngularInfo.from_list(target)))
    assert api(client, "SendBasicTrajectory", point).code == kinova.ErrorCode.NO_ERROR_KINOVA
    info = api(client, "GetGlobalTrajectoryInfo", reply_type=kinova.TrajectoryFIFOReply)
    assert info.result.MaxSize == 2000

    def reached():
        now = api(client, "GetAngularPosition", reply_type=kinova.AngularPositionReply).result.Actuators.as_list()
        return np.abs(np.array(now) - target).max() < 0.1

    assert wait_for(reached, timeout=60)
    assert wait_for(lambda: api(client, "GetGlobalTrajectoryInfo",
                                reply_type=kinova.TrajectoryFIFOReply).result.TrajectoryCount == 0)

    corners = [kinova.CartesianInfo(X=x, Y=y, Z=0.0) for x, y in ((0.3, -0.3), (0.6, -0.3), (0.6, 0.3), (0.3, 0.3))]
    top = [kinova.CartesianInfo(X=c.X, Y=c.Y, Z=0.8) for c in corners]
    zone = kinova.Zone(ID=1, zoneShape=kinova.ZoneShape(Points=corners + top))
    assert api(client, "SetProtectionZone", kinova.ZoneList(NbZones=1, Zones=[zone])).code == 1
    zones = api(client, "GetProtectionZone", reply_type=kinova.ZoneListReply).result
    assert zones.NbZones == 1 and zones.Zones[0].zoneShape.Points[2].X == pytest.approx(0.6)
    assert api(client, "EraseAllProtectionZones").code == 1
    assert api(client, "GetProtectionZone", reply_type=kinova.ZoneListReply).result.NbZones == 0

    conf = api(client, "GetClientConfigurations", reply_type=kinova.ClientConfigurationsReply).result
    assert conf.MaxTranslationVelocity == pytest.approx(0.2)
    bad_conf = kinova.ClientConfigurations(MaxTranslationVelocity=0.5)
    assert api(client, "SetClientConfigurations", bad_conf).code == kinova.ErrorCode.ERROR_INVALID_PARAM


def test_kinova_api_refuses_unknown_functions_and_bad_arguments(robot, client):
    replies = list(client.get(KEYS.robot_api("SelfDestruct"), timeout=5.0))
    reply = m.decode(replies[0].ok.payload.to_bytes(), kinova.ApiReply)
    assert reply.code == kinova.ErrorCode.ERROR_INVALID_PARAM and "unknown function" in reply.message
    replies = list(client.get(KEYS.robot_api("SendBasicTrajectory"), payload=b"\x01\x02", timeout=5.0))
    reply = m.decode(replies[0].ok.payload.to_bytes(), kinova.ApiReply)
    assert reply.code == kinova.ErrorCode.ERROR_INVALID_PARAM and "TrajectoryPoint" in reply.message
    zone = kinova.Zone(ID=2, zoneShape=kinova.ZoneShape(shapeType=kinova.ShapeType.Pyramid))
    reply = api(client, "SetProtectionZone", kinova.ZoneList(NbZones=1, Zones=[zone]))
    assert reply.code == kinova.ErrorCode.ERROR_INVALID_PARAM and "PrismSquareBase_Z" in reply.message
    assert robot.counters.get("rejected.api") == 2


def raw_api(client, function, payload: bytes) -> kinova.ApiReply:
    replies = list(client.get(KEYS.robot_api(function), payload=payload, timeout=10.0))
    assert len(replies) == 1  # every query is answered
    return m.decode(replies[0].ok.payload.to_bytes(), kinova.ApiReply)


def test_kinova_api_refuses_what_a_request_does_not_say(robot, client):
    """A request that changes the arm must spell out every field (``{}`` must not erase the zones or send the arm
    to zero angles); a function without an argument refuses a payload (garbage must not run MoveHome); a payload
    that is not MessagePack at all (an invalid UTF-8 key) gets an error reply, not silence."""
    corners = [kinova.CartesianInfo(X=x, Y=y, Z=z) for z in (0.0, 0.8) for x, y in
               ((0.3, -0.3), (0.6, -0.3), (0.6, 0.3), (0.3, 0.3))]
    zone = kinova.Zone(ID=1, zoneShape=kinova.ZoneShape(Points=corners))
    assert api(client, "SetProtectionZone", kinova.ZoneList(NbZones=1, Zones=[zone])).code == 1
    before = api(client, "GetAngularPosition", reply_type=kinova.AngularPositionReply).result.Actuators.as_list()
    probes = [("SetProtectionZone", msgpack.packb({})), ("SetProtectionZone", msgpack.packb({"NbZones": 0})),
              ("SendBasicTrajectory", msgpack.packb({"Position": {"Type": 2}})),
              ("SetClientConfigurations", msgpack.packb({"MaxTranslationVelocity": 0.1})),
              ("MoveHome", b"\x01\x02garbage"), ("EraseAllProtectionZones", msgpack.packb({})),
              ("SendBasicTrajectory", bytes.fromhex("81a1ff00"))]
    for function, payload in probes:
        reply = raw_api(client, function, payload)
        assert reply.code == kinova.ErrorCode.ERROR_INVALID_PARAM, (function, payload, reply)
    assert robot.counters.get("rejected.api") == len(probes)
    assert api(client, "GetProtectionZone", reply_type=kinova.ZoneListReply).result.NbZones == 1
    time.sleep(0.3)
    after = api(client, "GetAngularPosition", reply_type=kinova.AngularPositionReply).result.Actuators.as_list()
    assert np.abs(np.array(after) - np.array(before)).max() < 0.05
    # the explicit forms still work: every field said, and the empty zone list is its own request
    assert api(client, "SetProtectionZone", kinova.ZoneList(NbZones=0, Zones=[])).code == 1
    assert api(client, "EraseAllProtectionZones").code == 1


def test_lockstep_retries_a_tick_whose_answer_was_lost(robot, client):
    seen = set()

    def make(t, _frame):
        if t not in seen:  # the first time each tick arrives, the answer is "lost"
            seen.add(t)
            return []
        return twist_payload(t)

    states = collect(client, KEYS.robot_state, m.RobotState)
    safety = FakeSafety(client, make)
    try:
        assert wait_for(lambda: len(states) >= 30, timeout=60)
        counters = robot.counters.snapshot()
    finally:
        safety.close()
    assert counters.get("lockstep.retries", 0) >= 5
    assert counters.get("lockstep.timeouts.cycle", 0) == 0
    assert states[-1].applied_command is not None


def test_realtime_camera_trigger_moves_to_where_slow_commands_are_applied_soonest(router, client):
    """robot_sim (realtime, ``trigger_offset_ms: auto``, starting at its mode's default, the tick) told by the robot
    states that every command reaches the robot 9.5 ms after its frame's capture and is applied 18.8 ms after it (a
    DSP that takes its commands 8.8 ms after its tick): it moves the camera to 8 ms after the tick (10.8 ms), and
    its frames follow."""
    ticks, images, own_states = collect(client, KEYS.clock, m.SimClock), [], collect(client, KEYS.robot_state,
                                                                                       m.RobotState)
    state_pub = GuardedPublisher.declare(client, KEYS.robot_state)

    def on_image(sample):
        image = m.decode(sample.payload.to_bytes(), m.Image)
        images.append(image.header.stamp_ns)
        if not own_states:
            return
        capture = image.header.stamp_ns
        hop = m.Hop(service="robot_gateway", recv_ns=capture + 9_500_000, pub_ns=capture + 18_800_000)
        applied = m.Header(stamp_ns=capture, source_stamp_ns=capture, trace=[hop])
        state_pub.put(m.encode(msgspec.structs.replace(own_states[-1], applied_command=applied)))

    client.declare_subscriber(KEYS.camera_image, on_image)
    config = RobotSimConfig(clock=ClockMode.REALTIME, zenoh=router.client_config(), health_period_s=0.2)
    config.scene.camera.trigger_offset_ms = "auto"
    service = RobotSimService(config)
    service.start()
    try:
        assert wait_for(lambda: len(images) >= 10 and ticks, timeout=30.0)

        def phases_ms(stamps):
            """Each frame's capture after the last DSP tick before it. Against that tick, not the first one: a
            cycle the host made robot_sim drop moves its stamps on by 2 ms (services/robot_sim/service.py
            cycles_dropped), and a CI run measured against the first tick saw every frame after the move at 0."""
            tick_stamps = sorted(t.header.stamp_ns for t in ticks)
            phases = []
            for stamp in stamps:
                before = bisect.bisect_right(tick_stamps, stamp) - 1
                if before >= 0 and stamp - tick_stamps[before] < 10_000_000:
                    phases.append(round((stamp - tick_stamps[before]) / 1e6, 1))
            return phases

        assert set(phases_ms(images[:5])) == {0.0}
        assert wait_for(lambda: "camera_trigger_ms=8 (auto, moved 1x," in service.health().detail, timeout=30.0)
        moved_at = len(images)
        assert wait_for(lambda: len(images) >= moved_at + 5, timeout=10.0)
        after = phases_ms(images[moved_at + 1:])
        why = (service.health().detail, service.counters.get("cycles.missed"), after)
        # a frame whose tick and capture straddle a dropped cycle reads 2 ms off: at most one of them
        assert len(after) >= 4 and sum(phase == 8.0 for phase in after) >= len(after) - 1, why
        assert service.counters.get("camera.trigger_moves") == 1, why
    finally:
        service.stop()
        state_pub.undeclare()


@pytest.mark.parametrize("late", ["safety", "image subscriber"])
def test_lockstep_waits_for_its_answerers_before_its_first_tick(router, client, late):
    """Who is alive and who subscribes reach the robot's new session on zenoh's thread some time after it opens: a
    loop that did not wait ran its first ticks unanswered, or skipped its first frame for nobody subscribed yet,
    and a run differed from the next. Told to (as the stack tells it), the robot waits for safety and for vision's
    subscription before its first cycle; here one of them comes late."""
    declare_safety = lambda: client.liveliness().declare_token(KEYS.liveliness("safety"))  # noqa: E731
    declare_vision = lambda: client.declare_subscriber(KEYS.camera_image, lambda sample: None)  # noqa: E731
    declared = [declare_vision() if late == "safety" else declare_safety()]
    config = RobotSimConfig(clock=ClockMode.LOCKSTEP, zenoh=router.client_config(),
                            lockstep=LockstepConfig(await_answerers_s=30.0))
    robot = RobotSimService(config)
    robot.start()
    try:
        time.sleep(LockstepConfig().cycle_timeout_s + 0.1)  # longer than a tick's wait for its answer: nothing ran
        assert robot.sim.time_ns == 0 and robot.counters.get("lockstep.timeouts.cycle") == 0
        declared.append(declare_safety() if late == "safety" else declare_vision())
        # nobody answers: the first tick waits its cycle_timeout_s, then the arm goes on; its frame was taken
        assert wait_for(lambda: robot.counters.get("lockstep.timeouts.frame") >= 1, timeout=10)
        assert robot.counters.get("lockstep.timeouts.answerers") == 0
        assert robot.counters.get("frames.unobserved") == 0
    finally:
        robot.stop()
        for declaration in declared:
            declaration.undeclare()


def test_lockstep_without_its_answerers_runs_on_and_counts_it(router):
    robot = RobotSimService(RobotSimConfig(clock=ClockMode.LOCKSTEP, zenoh=router.client_config(),
                                           lockstep=LockstepConfig(await_answerers_s=0.2)))
    robot.start()
    try:
        assert wait_for(lambda: robot.sim.time_ns > 0, timeout=10)
        assert robot.counters.get("lockstep.timeouts.answerers") == 1
    finally:
        robot.stop()
