"""vision as a service with robot_sim over a real zenoh router, in lockstep."""
import threading
import time

import numpy as np
import pytest

from protocol import messages as m
from protocol.conventions import ClockMode
from protocol.keys import Keys
from services.runtime.transport import GuardedPublisher, open_session
from services.robot_sim.service import RobotSimConfig, RobotSimService
from services.vision.service import VisionConfig, VisionService
from tests.stack import next_seq, wait_for

KEYS = Keys()




class StopOnFeatures:
    """Stands in for controller + safety: answers each tick, and each frame once its features arrive (alive as
    safety: the robot waits for safety's answers)."""

    def __init__(self, session):
        self.publisher = GuardedPublisher.declare(session, KEYS.robot_command)
        self.features = []
        self.frame_stamp = 0
        self.lock = threading.Lock()
        self.subs = [session.declare_subscriber(KEYS.clock, self._on_tick),
                     session.declare_subscriber(KEYS.features, self._on_features)]
        self.token = session.liveliness().declare_token(KEYS.liveliness("safety"))

    def _send(self, stamp):
        header = m.Header(stamp_ns=stamp, source_stamp_ns=self.frame_stamp, seq=next_seq())
        self.publisher.put(m.encode(m.RobotCommand(header=header, mode=m.CommandMode.STOP)))

    def _on_tick(self, sample):
        self._send(m.decode(sample.payload.to_bytes(), m.SimClock).sim_time_ns)

    def _on_features(self, sample):
        features = m.decode(sample.payload.to_bytes(), m.Features)
        with self.lock:
            self.features.append(features)
            self.frame_stamp = features.header.source_stamp_ns
        self._send(features.header.source_stamp_ns)

    def close(self):
        for s in self.subs:
            s.undeclare()
        self.token.undeclare()


@pytest.fixture
def stack(router):
    client = open_session(router.client_config())
    vision = VisionService(VisionConfig(clock=ClockMode.LOCKSTEP, zenoh=router.client_config()))
    vision.start()
    downstream = StopOnFeatures(client)
    time.sleep(0.3)
    robot = RobotSimService(RobotSimConfig(clock=ClockMode.LOCKSTEP, zenoh=router.client_config()))
    robot.start()
    yield client, vision, robot, downstream
    robot.stop()
    downstream.close()
    vision.stop()
    client.close()


def test_features_for_every_frame_in_lockstep(stack):
    client, vision, robot, downstream = stack
    assert wait_for(lambda: len(downstream.features) >= 10)
    first = downstream.features[:10]
    assert all(f.status is m.FeatureStatus.OK for f in first), [f.detail for f in first]
    stamps = [f.header.source_stamp_ns for f in first]
    assert stamps == sorted(stamps) and len(set(stamps)) == 10
    assert all(f.header.trace[-1].service == "vision" for f in first)
    # vision follows simulated time: it received each frame at its capture time (the simulator waits)
    assert all(f.header.trace[-1].recv_ns >= f.header.source_stamp_ns for f in first)
    assert robot.counters.get("lockstep.timeouts.frame") == 0
    # the default target is 0.5 m ahead, squarely facing the camera
    assert np.allclose(first[0].depths, 0.5, atol=0.01)


def test_goal_queryables_and_bad_inputs(stack):
    client, vision, robot, downstream = stack
    assert wait_for(lambda: len(downstream.features) >= 2)
    goal = m.VisionGoal(header=m.Header(), features=[(-0.1, -0.1), (0.1, -0.1), (0.1, 0.1), (-0.1, 0.1)], depth_m=0.35)
    reply = m.decode(list(client.get(KEYS.vision_api("set_goal"), payload=m.encode(goal), timeout=5))[0]
                     .ok.payload.to_bytes(), m.VisionGoalReply)
    assert reply.ok and reply.goal_depths == [0.35] * 4
    got = m.decode(list(client.get(KEYS.vision_api("get_goal"), timeout=5))[0].ok.payload.to_bytes(),
                   m.VisionGoalReply)
    assert got.goal_points == goal.features
    n = len(downstream.features)
    assert wait_for(lambda: len(downstream.features) > n + 2)
    assert downstream.features[-1].goal_depths == [0.35] * 4
    bad = m.decode(list(client.get(KEYS.vision_api("set_goal"), payload=b"\xc1", timeout=5))[0].ok.payload
                   .to_bytes(), m.VisionGoalReply)
    assert not bad.ok and "VisionGoal" in bad.message
    client.put(KEYS.camera_image, b"not an image")
    client.put(KEYS.camera_info, b"\x80")
    assert wait_for(lambda: vision.counters.get("rejected.image") >= 1
                    and vision.counters.get("rejected.camera_info") >= 1)
    n = len(downstream.features)
    assert wait_for(lambda: len(downstream.features) > n + 3)  # still serving
    assert vision.state == "running"


def test_in_lockstep_a_frame_that_came_before_the_camera_info_waits_for_it(router):
    """The camera info and a frame come on subscribers of their own, in the host's order: in lockstep the frame
    waits for the info (a replay once had its first frame refused for want of it); in realtime it is refused."""
    from services.robot_sim.scene import CameraConfig, camera_info

    camera = CameraConfig()
    for clock, refused in ((ClockMode.LOCKSTEP, False), (ClockMode.REALTIME, True)):
        vision = VisionService(VisionConfig(clock=clock, zenoh=router.client_config()))
        vision.start()
        try:
            vision._info = None  # nobody answered its query: there is no camera on this router
            answers = []
            vision.features_pub.put = answers.append
            stamp = 1_000_000_000 if clock is ClockMode.LOCKSTEP else time.time_ns()
            header = m.Header(stamp_ns=stamp, source_stamp_ns=stamp, seq=next_seq())
            vision._on_image(m.Image(header=header, width=camera.width, height=camera.height,
                                     encoding=camera.encoding,
                                     data=bytes(camera.width * camera.height * m.CHANNELS[camera.encoding])), 0)
            time.sleep(0.2)  # the info comes later, on another thread
            vision._on_camera_info(camera_info(camera, m.Header(stamp_ns=stamp, seq=next_seq())), 0)
            assert wait_for(lambda: answers, timeout=5)
            no_info = answers[0].status is m.FeatureStatus.INVALID_IMAGE and "camera info" in answers[0].detail
            assert no_info is refused, (clock, answers[0].status, answers[0].detail)
        finally:
            vision.stop()
