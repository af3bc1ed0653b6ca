"""The bridge relays a ROS 2 stick as jog requests, on a real zenoh router: samples put on rmw_zenoh's data keys as
a ROS publisher puts them (the CDR written by hand below and the rclpy fixture's bytes, with the 33-byte attachment;
the keys read off the bridge's liveliness tokens) become Jog messages on jog/request with rising sequence numbers and
the dead-man; bad ones are counted and nothing goes out. With jog_zenoh the requests leave on a second session."""
import math
import struct
import time
from pathlib import Path

import pytest

from protocol import messages as m
from protocol.messages import JogMode
from services.ros2_bridge.service import Ros2BridgeConfig, Ros2BridgeService
from services.runtime.transport import open_session
from services.controller.service import ControllerConfig, ControllerService
from tests.services.ros2_bridge.test_service import attachment, data_key, token_parts, trigger
from tests.stack import KEYS, Recorder, wait_for

FIXTURES = Path(__file__).resolve().parents[2] / "protocol" / "ros2" / "fixtures"
GID = bytes(range(40, 56))


def _header(stamp_ns: int, frame: str) -> bytes:
    text = frame.encode() + b"\x00"
    return b"\x00\x01\x00\x00" + struct.pack("<iII", stamp_ns // 10**9, stamp_ns % 10**9, len(text)) + text


def joy_cdr(axes, buttons, stamp_ns: int) -> bytes:
    """sensor_msgs/Joy: header, float32[] axes, int32[] buttons (each a count and 4-aligned elements)."""
    out = _header(stamp_ns, "joy")
    out += bytes(-(len(out) - 4) % 4)
    out += struct.pack(f"<I{len(axes)}f", len(axes), *axes)
    return out + struct.pack(f"<I{len(buttons)}i", len(buttons), *buttons)


def twist_cdr(frame: str, linear, angular, stamp_ns: int) -> bytes:
    """geometry_msgs/TwistStamped: header, then linear and angular, six 8-aligned doubles."""
    out = _header(stamp_ns, frame)
    return out + bytes(-(len(out) - 4) % 8) + struct.pack("<6d", *linear, *angular)


def pad(up: float, lb: bool, a: bool = False, start: bool = False):
    """An Xbox 360 pad as the joy driver reports it: 8 axes (left stick 0, 1; right 3, 4), 11 buttons (A 0, LB 4,
    Start 7)."""
    axes = [0.0, up, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    buttons = [0] * 11
    buttons[4], buttons[0], buttons[7] = int(lb), int(a), int(start)
    return axes, buttons


def bridge_endpoints(session, wanted: set) -> dict:
    """The bridge's subscriptions and services by their ROS names: each one's data key, and its QoS as ``NAME qos``,
    read off its liveliness tokens once all of ``wanted`` are declared."""
    keys = {}

    def found() -> bool:
        for reply in session.liveliness().get("@ros2_lv/0/**", timeout=2.0):
            if reply.ok is not None:
                parts = token_parts(str(reply.ok.key_expr))
                if parts["kind"] in ("MS", "SS"):
                    keys[parts["topic"]] = data_key(parts)
                    keys[parts["topic"] + " qos"] = parts["qos"]
        return wanted <= set(keys)
    assert wait_for(found, timeout=15, period=0.2), keys
    return keys


@pytest.fixture(params=["own session", "jog identity's session"])
def bridge(router, request):
    jog_zenoh = router.client_config() if request.param != "own session" else None
    service = Ros2BridgeService(Ros2BridgeConfig(zenoh=router.client_config(), jog_zenoh=jog_zenoh,
                                                 diagnostics_period_s=5.0))
    session = open_session(router.client_config())
    service.start()
    try:
        keys = bridge_endpoints(session, {"/joy", "/mfvs/delta_twist_cmds", "/mfvs/resume_task"})
        yield service, session, keys
    finally:
        service.stop()
        session.close()


def test_a_ros_joy_stream_becomes_jog_requests_with_the_dead_man_and_bad_input_sends_nothing(bridge):
    service, session, keys = bridge
    jogs = Recorder(session, KEYS.desired_jog, m.Jog)
    # (a zenoh publisher drops what no subscriber it knows of matches: wait until the jog publisher knows this one)
    assert wait_for(lambda: service._jog_publisher.matching, timeout=5)
    joy_key, twist_key = keys["/joy"], keys["/mfvs/delta_twist_cmds"]
    # both subscriptions as joy_node publishes and MoveIt Servo subscribes: reliable, volatile, keep last 10
    assert keys["/joy qos"] == keys["/mfvs/delta_twist_cmds qos"] == "::,10:,:,:,,"

    # the rclpy fixture's bytes (stamped 2026-01-01: far off this clock) go through, heard at their receipt
    before = time.time_ns()
    session.put(joy_key, (FIXTURES / "joy.rclpy.cdr").read_bytes(), attachment=attachment(1, GID))
    assert wait_for(lambda: len(jogs) == 1, timeout=5)
    first = jogs.last()
    assert first.deadman and first.source == "jog/ros-joy" and first.header.seq == 1
    assert before <= first.header.source_stamp_ns <= time.time_ns()
    assert service.counters.get("ros.joy.stamp_not_used") == 1

    # a stick pushed up with LB held, at 50 Hz, then A (the mode: wrist) and LB let go
    stamps = []
    for i in range(12):
        stamps.append(time.time_ns())
        session.put(joy_key, joy_cdr(*pad(0.8, lb=True), stamps[-1]), attachment=attachment(2 + i, GID))
        time.sleep(0.02)
    session.put(joy_key, joy_cdr(*pad(0.8, lb=True, a=True), time.time_ns()), attachment=attachment(20, GID))
    session.put(joy_key, joy_cdr(*pad(0.8, lb=False), time.time_ns()), attachment=attachment(21, GID))
    assert wait_for(lambda: len(jogs) == 15, timeout=5), len(jogs)
    sent = jogs.snapshot()
    assert [j.header.seq for j in sent] == list(range(1, 16))
    pushed = sent[1:13]
    assert all(j.deadman and j.mode is JogMode.TRANSLATION and j.speed_level == 1 for j in pushed)
    assert [j.header.source_stamp_ns for j in pushed] == stamps  # their own stamps: this clock's
    assert all(j.header.stamp_ns >= j.header.source_stamp_ns for j in pushed)
    speeds = [j.linear[0] for j in pushed]  # +X, ramped by the spasm filter, at most level 1's quarter speed
    assert speeds == sorted(speeds) and 0.0 < speeds[-1] <= 0.2 * 0.25 + 1e-12
    assert all(j.linear[1] == j.linear[2] == 0.0 for j in pushed)
    assert sent[13].mode is JogMode.WRIST and sent[13].deadman
    assert not sent[14].deadman and sent[14].at_rest

    # a twist: a translation in the base frame, its own source and sequence; an all-zero one a release
    session.put(twist_key, twist_cdr("base_link", (0.0, 0.05, 0.0), (0.0, 0.0, 0.0), time.time_ns()),
                attachment=attachment(1, GID))
    session.put(twist_key, twist_cdr("base_link", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), time.time_ns()),
                attachment=attachment(2, GID))
    assert wait_for(lambda: len(jogs) == 17, timeout=5)
    moved, released = jogs.snapshot()[15:]
    assert (moved.source, moved.header.seq, moved.deadman, moved.linear) == ("jog/ros-twist", 1, True,
                                                                             (0.0, 0.05, 0.0))
    assert (released.header.seq, released.deadman) == (2, False)

    # bad input: each counted by its reason, nothing sent
    now = time.time_ns
    bad = [
        (joy_key, joy_cdr([0.0, math.nan] + [0.0] * 6, [0, 0, 0, 0, 1] + [0] * 6, now()), "joy.not_finite"),
        (joy_key, joy_cdr([0.0, 0.5], [0, 0, 0, 0, 1], now()), "joy.size"),
        (joy_key, b"\x00\x01\x00\x00garbage", "joy.cdr"),
        (twist_key, twist_cdr("world", (0.1, 0.0, 0.0), (0.0, 0.0, 0.0), now()), "twist.frame"),
        (twist_key, twist_cdr("base_link", (0.1, 0.0, 0.0), (0.0, 0.0, 0.3), now()), "twist.mixed"),
        (twist_key, twist_cdr("end_effector", (0.0, 0.0, 0.0), (0.0, math.inf, 0.0), now()), "twist.not_finite"),
    ]
    for key, payload, _ in bad:
        session.put(key, payload, attachment=attachment(99, GID))
    session.put(joy_key, joy_cdr(*pad(0.8, lb=True), now()))  # no attachment: no ROS publisher's
    reasons = {f"rejected.ros.{reason}" for _, _, reason in bad} | {"rejected.ros.joy.attachment"}
    assert wait_for(lambda: all(service.counters.get(r) == 1 for r in reasons), timeout=5), \
        service.counters.snapshot()
    time.sleep(0.3)
    assert len(jogs) == 17
    assert not any(k.startswith("errors.ros") for k in service.counters.snapshot())


def test_the_sticks_resume_button_and_the_resume_service_ask_the_real_controller(bridge, router):
    """Start on the pad (a press: not held in the message before) and the resume_task Trigger each reach the
    controller's resume_task and carry its answer: an idle controller has no task paused, so both say so; the jog
    request of the press moves nothing (no dead-man)."""
    service, session, keys = bridge
    controller = ControllerService(ControllerConfig(zenoh=router.client_config()))
    controller.start()
    try:
        jogs = Recorder(session, KEYS.desired_jog, m.Jog)
        assert wait_for(lambda: service._jog_publisher.matching, timeout=5)
        session.put(keys["/joy"], joy_cdr(*pad(0.0, lb=False), time.time_ns()), attachment=attachment(1, GID))
        session.put(keys["/joy"], joy_cdr(*pad(0.0, lb=False, start=True), time.time_ns()),
                    attachment=attachment(2, GID))
        assert wait_for(lambda: service.counters.get("jog.resume.refused") == 1, timeout=10), \
            service.counters.snapshot()
        assert service.counters.get("actions.resume_task") == 1
        assert wait_for(lambda: len(jogs) == 2, timeout=5)
        assert not any(j.deadman for j in jogs.snapshot())
        session.put(keys["/joy"], joy_cdr(*pad(0.0, lb=False, start=True), time.time_ns()),
                    attachment=attachment(3, GID))  # still held: not asked again
        success, message, _ = trigger(session, keys["/mfvs/resume_task"], 1, GID)
        assert not success and "no task paused" in message, message
        assert service.counters.get("actions.resume_task") == 2 and service.counters.get("jog.resume.refused") == 1
    finally:
        controller.stop()


def test_a_ros_stick_drives_the_simulated_arm_along_the_base_and_its_release_stops_it(router):
    """End to end: the joy driver's messages through the bridge, safety and the simulated arm in realtime. LB held
    and the left stick up move the hand along the base's +X; LB let go, it comes to rest."""
    import numpy as np

    from protocol.conventions import ClockMode
    from services.model.arm import load_arm
    from services.model.kinematics import ArmKinematics
    from services.robot_sim.scene import CameraConfig, SceneConfig
    from services.robot_sim.service import RobotSimConfig, RobotSimService
    from services.safety.service import SafetyConfig, SafetyService

    safety = SafetyService(SafetyConfig(zenoh=router.client_config()))
    robot = RobotSimService(RobotSimConfig(arm="j2n6s300", zenoh=router.client_config(), clock=ClockMode.REALTIME,
                                           scene=SceneConfig(camera=CameraConfig(enabled=False))))
    service = Ros2BridgeService(Ros2BridgeConfig(zenoh=router.client_config(), diagnostics_period_s=5.0))
    session = open_session(router.client_config())
    kin = ArmKinematics(load_arm("j2n6s300"))
    states = Recorder(session, KEYS.robot_state, m.RobotState)
    for started in (safety, robot, service):
        started.start()
    try:
        keys = bridge_endpoints(session, {"/joy"})
        assert wait_for(lambda: len(states) > 20, timeout=30)
        assert wait_for(lambda: service._jog_publisher.matching, timeout=5)
        start = kin.pose(np.array(states.last().q))[1]
        sequence = 0

        def joy_for(seconds: float, up: float, lb: bool) -> None:
            nonlocal sequence
            end = time.monotonic() + seconds
            while time.monotonic() < end:  # the joy driver's 20 Hz autorepeat, a little faster
                sequence += 1
                session.put(keys["/joy"], joy_cdr(*pad(up, lb=lb), time.time_ns()), attachment=attachment(sequence, GID))
                time.sleep(0.02)

        joy_for(0.3, 0.0, lb=False)
        joy_for(2.0, 1.0, lb=True)  # level 1: a quarter of 0.2 m/s, ramped in by the spasm filter
        moved = kin.pose(np.array(states.last().q))[1] - start
        joy_for(0.6, 1.0, lb=False)  # LB let go, the stick still up
        assert moved[0] > 0.02 and np.linalg.norm(moved[1:]) < 0.2 * moved[0], moved
        last = states.last()
        assert kin.ee_speed(last.q, last.dq) < 2e-3  # at rest
        assert safety.counters.get("released.stops") >= 1
    finally:
        for started in (service, robot, safety):
            started.stop()
        states.close()
        session.close()
