"""The console's rules without zenoh or a web server: the page's requests, who may make them, which go out, and
what the page shows."""
import json
import math

import numpy as np
import pytest

from protocol import messages as m
from services.console.core import (ANONYMOUS, Access, Action, ActionMessage, AuthMessage, ConsoleModel, Refused,
                                   Situation, decide, frame_packet, is_loopback, parse_page_message, read_frame_packet)
from services.model.arm import load_arm
from services.model.limits import arm_limits

TOKEN = "correct horse battery"


def action(name, **fields):
    return ActionMessage(action=Action(name), **fields)


def refused(call) -> str:
    with pytest.raises(Refused) as caught:
        call()
    assert caught.value.message  # a sentence for the page
    return caught.value.reason


# ------------------------------------------------------------------------------------------------ parsing
def test_the_page_sends_an_auth_or_an_action_and_nothing_else():
    assert parse_page_message('{"type": "auth", "token": "x"}') == AuthMessage(token="x")
    request = parse_page_message('{"type": "action", "action": "task_start", "id": 3, "operator": "alice", '
                                 '"reason": "a drink", "token": "t"}')
    assert request == ActionMessage(action=Action.TASK_START, id=3, operator="alice", reason="a drink", token="t")
    for bad, reason in [(b'{"type": "auth", "token": "x"}', "malformed"),  # binary
                        ("not json", "malformed"), ("[1, 2]", "malformed"), ('{"type": "move", "joint": 1}', "malformed"),
                        ('{"type": "action", "action": "move_joint"}', "unknown_action"),
                        ('{"type": "action", "action": "task_start", "speed": 9}', "malformed"),
                        ('{"type": "action", "action": "task_start", "id": -1}', "malformed"),
                        ('{"type": "action", "action": "task_start", "operator": "eve\\nroot"}', "malformed"),
                        ('{"type": "action", "action": "task_start", "operator": "' + "x" * 65 + '"}', "malformed"),
                        ('{"type": "action", "action": "task_start", "reason": "' + "x" * 5000 + '"}', "malformed")]:
        assert refused(lambda: parse_page_message(bad)) == reason, bad


# ------------------------------------------------------------------------------------------------ who
def test_loopback_needs_no_token_and_anything_beyond_it_does():
    assert Access("127.0.0.1").token_ok("")
    assert Access("::1").loopback and Access("localhost").loopback and not Access("0.0.0.0", TOKEN).loopback
    with pytest.raises(ValueError, match="needs a token"):
        Access("0.0.0.0")
    with pytest.raises(ValueError, match="needs a token"):
        Access("192.168.1.20")
    with pytest.raises(ValueError, match="at least 8"):
        Access("0.0.0.0", token="short")
    access = Access("0.0.0.0", TOKEN)
    assert access.token_required and access.token_ok(TOKEN)
    assert not access.token_ok("") and not access.token_ok(TOKEN + "x") and not access.token_ok(TOKEN[:-1])
    assert is_loopback("127.3.0.1") and is_loopback("[::1]") and not is_loopback("10.0.0.1")


def test_only_the_consoles_own_page_may_open_its_stream():
    loopback = Access("127.0.0.1")
    loopback.check_origin("http://127.0.0.1:8080", "127.0.0.1:8080", "http")
    loopback.check_origin("http://localhost:8080", "localhost:8080", "http")
    loopback.check_origin("http://[::1]:8080", "[::1]:8080", "http")
    assert refused(lambda: loopback.check_origin(None, "127.0.0.1:8080", "http")) == "origin"
    assert refused(lambda: loopback.check_origin("http://evil.example", "127.0.0.1:8080", "http")) == "origin"
    assert refused(lambda: loopback.check_origin("http://127.0.0.1:9999", "127.0.0.1:8080", "http")) == "origin"
    assert refused(lambda: loopback.check_origin("https://127.0.0.1:8080", "127.0.0.1:8080", "http")) == "origin"
    # DNS rebinding: a site whose name now points at 127.0.0.1 is its own origin, but not a loopback host
    assert refused(lambda: loopback.check_origin("http://evil.example:8080", "evil.example:8080", "http")) == "host"
    wide = Access("0.0.0.0", TOKEN)  # beyond loopback the page is reached by the machine's name
    wide.check_origin("https://arm-pc.local:8080", "arm-pc.local:8080", "https")
    assert refused(lambda: wide.check_origin("https://evil.example", "arm-pc.local:8080", "https")) == "origin"


# ------------------------------------------------------------------------------------------------ what goes out
FREE, ENGAGED, SILENT = Situation(False), Situation(True), Situation(None)


@pytest.mark.parametrize("request_, situation, reason", [
    (action("task_start", operator="alice"), ENGAGED, "estop_engaged"),
    (action("task_start", operator="alice"), SILENT, "safety_silent"),
    (action("task_start", operator="  "), FREE, "operator"),
    (action("estop_engage"), ENGAGED, "already_engaged"),
    (action("estop_release", operator="alice"), ENGAGED, "unconfirmed"),
    (action("estop_release", confirm=True), ENGAGED, "operator"),
    (action("estop_release", operator="alice", confirm=True), FREE, "not_engaged"),
    (action("estop_release", operator="alice", confirm=True), SILENT, "safety_silent"),
    (action("grasp", operator=""), FREE, "operator"),
    (action("grasp", operator="alice"), ENGAGED, "estop_engaged"),
    (action("open_hand", operator="alice"), FREE, "unconfirmed"),
    (action("open_hand", confirm=True), FREE, "operator"),
    (action("open_hand", operator="alice", confirm=True), SILENT, "safety_silent"),
])
def test_requests_the_rules_refuse(request_, situation, reason):
    assert refused(lambda: decide(request_, Access("127.0.0.1"), situation)) == reason


def test_requests_that_go_out_and_stopping_never_waits_for_a_name():
    loopback = Access("127.0.0.1")
    assert decide(action("task_start", operator=" alice ", reason="a drink"), loopback, FREE) == \
        decide(action("task_start", operator="alice", reason="a drink"), loopback, FREE)
    assert decide(action("task_stop"), loopback, ENGAGED).operator == ANONYMOUS
    assert decide(action("estop_engage"), loopback, FREE).action is Action.ESTOP_ENGAGE
    assert decide(action("estop_engage"), loopback, SILENT).action is Action.ESTOP_ENGAGE  # in doubt: sent
    release = decide(action("estop_release", operator="bob", confirm=True, reason="clear"), loopback, ENGAGED)
    assert (release.action, release.operator, release.reason) == (Action.ESTOP_RELEASE, "bob", "clear")
    assert decide(action("grasp", operator="alice", reason="my cup"), loopback, FREE).action is Action.GRASP
    assert decide(action("open_hand", operator="alice", confirm=True), loopback, FREE).action is Action.OPEN_HAND


def test_the_page_asks_the_controller_for_the_plan_each_task_action_names():
    from services.console.service import TASK_ACTIONS

    assert TASK_ACTIONS[Action.GRASP] == (m.START_TASK, m.TaskPlan.GRASP)
    assert TASK_ACTIONS[Action.OPEN_HAND] == (m.START_TASK, m.TaskPlan.RELEASE)
    assert set(TASK_ACTIONS) | {Action.ESTOP_ENGAGE, Action.ESTOP_RELEASE, Action.TEACH} == set(Action)


def test_beyond_loopback_every_action_needs_the_token():
    wide = Access("0.0.0.0", TOKEN)
    for name in Action:
        fields = {"operator": "alice", "confirm": True}
        assert refused(lambda: decide(action(name.value, **fields), wide, ENGAGED)) == "token"
        assert refused(lambda: decide(action(name.value, token="guess", **fields), wide, ENGAGED)) == "token"
    assert decide(action("estop_engage", token=TOKEN), wide, FREE).action is Action.ESTOP_ENGAGE


# ------------------------------------------------------------------------------------------------ what it shows
def header(t_s, source_s=None):
    return m.Header(stamp_ns=int(t_s * 1e9), source_stamp_ns=int((source_s if source_s is not None else t_s) * 1e9))


INFO = m.CameraInfo(header=header(0), width=640, height=480, fx=600.0, fy=600.0, cx=320.0, cy=240.0)
GOAL = [(-0.1, -0.1), (0.1, -0.1), (0.1, 0.1), (-0.1, 0.1)]


def features(t_s, shift_px=0.0, status=m.FeatureStatus.OK):
    corners = [(300.0 + shift_px, 220.0), (340.0 + shift_px, 220.0), (340.0 + shift_px, 260.0), (300.0 + shift_px, 260.0)]
    usable = status in m.USABLE_FEATURE_STATUSES
    return m.Features(header=header(t_s), status=status, points=GOAL if usable else [],
                      depths=[0.3] * 4 if usable else [], ids=[0, 1, 2, 3] if usable else [],
                      weights=[1.0] * 4 if usable else [], goal_points=GOAL if usable else [],
                      goal_depths=[0.3] * 4 if usable else [], error=[0.01 * t_s] * 8 if usable else [],
                      error_norm=0.01 * t_s * math.sqrt(8) if usable else 0.0,
                      pixels=corners if usable else [])


SEVEN, SIX = load_arm("j2s7s300"), load_arm("j2n6s300")


def state(t_s, x=0.4, dq=0.0, faults=(), arm=SEVEN, q=None, digest=None, name=None):
    """A state of the robot running ``arm`` (at its home unless ``q``); ``digest`` and ``name`` declare another."""
    n = len(q) if q is not None else arm.n_joints
    return m.RobotState(header=header(t_s), arm=name or arm.name, arm_digest=digest or arm.digest,
                        q=list(arm.home if q is None else q), dq=[dq] + [0.0] * (n - 1), tau=[0.0] * n,
                        pose=m.KinovaPose(X=x, Y=0.0, Z=0.5, ThetaX=0.0, ThetaY=0.0, ThetaZ=0.0),
                        control_mode=m.ControlMode.CARTESIAN_VELOCITY, faults=list(faults))


def test_the_overlay_puts_the_goal_where_the_lens_does_and_keeps_each_corners_recent_path():
    model = ConsoleModel(path_s=1.0)
    overlay = model.on_features(features(1.0), now=0.0)
    assert overlay["goal"] == [] and overlay["capture_ns"] == 1_000_000_000  # no intrinsics yet
    model.on_camera_info(INFO)
    overlay = model.on_features(features(1.1, shift_px=2.0), now=0.0)
    np.testing.assert_allclose(overlay["goal"], [[260, 180], [380, 180], [380, 300], [260, 300]])
    assert overlay["points"][0] == [302.0, 220.0] and overlay["status"] == "ok"
    for i in range(2, 30):
        model.on_features(features(1.0 + 0.1 * i, shift_px=2.0 * i), now=0.0)
    paths = model.paths()
    assert len(paths) == 4 and len(paths[0]) == 11  # the last second, at 10 frames a second
    assert paths[0][-1] == [358.0, 220.0] and paths[0][0] == [338.0, 220.0]
    model.on_features(features(4.0, status=m.FeatureStatus.TARGET_LOST), now=0.0)  # no corners: the path ages
    assert len(model.paths()[0]) == 10
    model.on_features(features(5.0, status=m.FeatureStatus.TARGET_LOST), now=0.0)
    assert model.paths() == []
    error = model.snapshot(0.0)["error"]
    assert error["t"][-1] == 0.0 and error["t"][0] < 0 and error["v"][-1] == pytest.approx(0.039 * math.sqrt(8))  # the last usable frame


@pytest.mark.parametrize("arm", [SEVEN, SIX], ids=lambda a: a.name)
def test_the_arms_speed_is_its_travel_against_the_limit_it_declares(arm):
    model = ConsoleModel()
    for i in range(40):  # 0.1 m/s along x, a state every 10 ms
        assert model.on_state(state(i * 0.01, x=0.4 + 0.001 * i, dq=0.5, arm=arm), now=0.0) == ""
    snapshot = model.snapshot(0.0)
    assert snapshot["speed"]["now"] == pytest.approx(0.1, rel=1e-6)
    assert snapshot["speed"]["limit"] == arm.max_linear_speed_mps  # declared none: its arm's maximum
    assert snapshot["speed"]["joint_ratio"] == pytest.approx(0.5 / arm.max_speed[0])
    declared = arm_limits(arm, linear_speed_mps=0.05, joint_speed_scale=0.5)
    moving = state(0.5, x=0.45, dq=0.5, arm=arm)
    moving.limits = declared
    model.on_state(moving, now=0.0)
    assert model.snapshot(0.0)["speed"]["limit"] == 0.05
    assert model.joint_speed_ratio == pytest.approx(0.5 / (0.5 * arm.max_speed[0]))


@pytest.mark.parametrize("arm", [SEVEN, SIX], ids=lambda a: a.name)
def test_each_joint_against_its_range_in_the_degrees_the_arm_reports_for_the_arm_the_robot_declares(arm):
    model = ConsoleModel()
    q = arm.home.copy()
    limited = np.flatnonzero(~arm.continuous)
    lower, upper = arm.model_limits()
    q[limited[0]] = lower[limited[0]] + np.radians(4.0)  # 4° from a limit
    model.on_state(state(0.0, arm=arm, q=q), now=0.0)
    snapshot = model.snapshot(0.0)
    assert snapshot["arm"] == {"name": arm.name, "title": arm.title, "joints": arm.n_joints, "described": True,
                               "problem": "", "angles": "physical"}
    joints = snapshot["joints"]
    assert [j["label"] for j in joints] == list(arm.joint_names) and len(joints) == arm.n_joints
    physical = arm.model_to_physical_deg(q)
    for joint, spec, deg in zip(joints, arm.joints, physical):
        assert joint["deg"] == round(deg, 2)  # as GetAngularPosition reports it
        if spec.continuous:
            assert joint["lower_deg"] is None and joint["upper_deg"] is None and joint["margin_deg"] is None
        else:
            assert (joint["lower_deg"], joint["upper_deg"]) == (spec.lower_deg, spec.upper_deg)
            assert spec.lower_deg <= joint["deg"] <= spec.upper_deg
            assert joint["margin_deg"] == pytest.approx(min(deg - spec.lower_deg, spec.upper_deg - deg), abs=0.01)
    assert joints[limited[0]]["margin_deg"] == pytest.approx(4.0, abs=0.01)
    assert [e["text"] for e in snapshot["events"]] == [f"arm {arm.name}: {arm.title}, {arm.n_joints} joints"]


def test_the_6_dof_arms_home_in_the_degrees_its_own_tools_show():
    model = ConsoleModel()
    model.on_state(state(0.0, arm=SIX), now=0.0)
    # kinova-ros's HOME of the j2n6s300, in GetAngularPosition's degrees
    assert [j["deg"] for j in model.snapshot(0.0)["joints"]] == pytest.approx(list(SIX.home_deg), abs=0.01)
    assert [(j["lower_deg"], j["upper_deg"]) for j in model.snapshot(0.0)["joints"]][1:3] == [(47.0, 313.0),
                                                                                            (19.0, 341.0)]


@pytest.mark.parametrize("declared, why", [
    (dict(name="j2x9s999"), "does not describe"),  # an arm this host has no file for
    (dict(digest="0123456789abcdef"), "differs from this host's"),  # the same name, another version of its file
    (dict(q=[0.1] * 5), "5 joints"),  # a state that is not that arm's length
], ids=["unknown", "other_version", "joint_count"])
def test_an_arm_this_host_does_not_describe_is_shown_as_such_and_nothing_breaks(declared, why):
    model = ConsoleModel()
    for i in range(10):
        problem = model.on_state(state(i * 0.01, x=0.4 + 0.001 * i, dq=0.5, **declared), now=i * 0.01)
        assert why in problem  # the service counts it
    snapshot = model.snapshot(0.1)
    assert snapshot["arm"]["described"] is False and snapshot["arm"]["angles"] == "model"
    assert why in snapshot["arm"]["problem"] and snapshot["arm"]["title"] is None
    n = len(declared.get("q", SEVEN.home))
    assert [j["label"] for j in snapshot["joints"]] == [f"J{i}" for i in range(1, n + 1)]
    assert all(j["lower_deg"] is None and j["margin_deg"] is None for j in snapshot["joints"])
    assert snapshot["joints"][0]["deg"] == round(math.degrees(state(0.0, **declared).q[0]), 2)  # model angles
    assert snapshot["speed"]["limit"] is None and snapshot["speed"]["joint_ratio"] is None  # none declared
    assert snapshot["speed"]["now"] == pytest.approx(0.1, rel=1e-6)  # what it does is still shown
    said = [e["text"] for e in snapshot["events"]]
    assert len(said) == 1 and said[0].startswith("arm: ") and why in said[0]  # said once, not every state
    json.dumps(snapshot, allow_nan=False)
    limited = state(0.2, dq=0.5, **declared)  # limits it declares itself are shown, arm or not
    limited.limits = m.MotionLimits(linear_speed_mps=0.05, angular_speed_rps=0.5, joint_speed_rps=[1.0] * n,
                                    linear_accel_mps2=1.0, angular_accel_rps2=1.0, joint_accel_rps2=1.0)
    model.on_state(limited, now=0.2)
    assert model.snapshot(0.2)["speed"]["limit"] == 0.05 and model.joint_speed_ratio == pytest.approx(0.5)


def test_a_robot_restarted_on_another_arm_is_followed():
    model = ConsoleModel()
    model.on_state(state(0.0, name="j2x9s999"), now=0.0)
    assert model.snapshot(0.0)["arm"]["described"] is False
    model.on_state(state(0.0, arm=SIX), now=1.0)
    snapshot = model.snapshot(1.0)
    assert snapshot["arm"]["name"] == "j2n6s300" and snapshot["arm"]["described"]
    assert len(snapshot["joints"]) == 6 and snapshot["speed"]["limit"] == SIX.max_linear_speed_mps
    model.on_state(state(0.0, arm=SEVEN), now=2.0)
    assert [j["label"] for j in model.snapshot(2.0)["joints"]] == list(SEVEN.joint_names)


def test_health_task_estop_and_refusals_make_the_log_and_the_estop_state_goes_stale():
    model = ConsoleModel()
    health = m.ServiceHealth(header=m.Header(), service="vision", pid=1, healthy=True, state="running", uptime_s=1.0)
    model.on_health({"vision": health}, now=1.0)
    slow = m.ServiceHealth(header=m.Header(), service="vision", pid=1, healthy=True, state="running", uptime_s=2.0,
                           degraded=["image at 20.0 Hz (nominal 30)"])
    model.on_health({"vision": slow}, now=2.0)
    model.on_health({}, now=3.0)
    assert [h["condition"] for h in model.snapshot(3.0)["health"]] == ["gone"]
    model.on_safety(m.SafetyStatus(header=m.Header(), state=m.SafetyState.ESTOP, last_refusal="estop: latched"), 4.0)
    assert model.situation(4.5) == Situation(True) and model.situation(5.5) == Situation(None)
    model.on_task(m.TaskStatus(ok=True, state=m.TaskState.RUNNING, task=2, by="alice", reason="a drink"), 6.0)
    model.on_task(m.TaskStatus(ok=True, state=m.TaskState.RUNNING, task=2, by="alice", reason="a drink"), 7.0)
    model.on_estop(m.EStop(header=m.Header(), operator="bob", reason="spill"), 8.0)
    model.on_state(state(0.0, faults=["joint 3 over its limit"]), now=9.0)
    for t in (9.01, 9.02, 9.5):  # a fault that comes and goes with the states: logged once
        model.on_state(state(t - 9.0, faults=["joint 3 over its limit"] if t != 9.02 else []), now=t)
    model.on_estop(m.EStop(header=m.Header(), operator="bob", reason="spill"), 9.6)  # sent again: logged once
    model.note("console", "warning", "refused: the e-stop is already engaged", 10.0)
    texts = [e["text"] for e in model.snapshot(10.0)["events"]]
    assert texts == ["refused: the e-stop is already engaged", "faults: joint 3 over its limit",
                     f"arm j2s7s300: {SEVEN.title}, 7 joints", "e-stop engaged by bob: spill", "task 2 running by alice: a drink",
                     "refused: estop: latched", "state estop", "gone",
                     "degraded (image at 20.0 Hz (nominal 30))"]
    assert model.snapshot(10.0)["task"]["by"] == "alice"
    json.dumps(model.snapshot(10.0), allow_nan=False)  # JSON as the page takes it


def test_a_frame_packet_carries_its_header_and_jpeg():
    packet = frame_packet(b"\xff\xd8jpeg", {"capture_ns": 12, "wall_stamps": True})
    assert read_frame_packet(packet) == ({"capture_ns": 12, "wall_stamps": True}, b"\xff\xd8jpeg")


def test_frames_are_halved_while_the_pages_draw_slower_than_the_camera_and_whole_again_once_they_keep_up():
    from services.console.core import FrameSize

    period = 1 / 30
    size = FrameSize()
    assert [size.on_drawn(0.004, 0.010, period) for _ in range(20)] == [1] * 20  # 14 ms a frame: it keeps up
    # a page taking 60 ms a frame: halved once the smoothed time passes the period, not at the first slow frame
    slow = [size.on_drawn(0.006, 0.054, period) for _ in range(20)]
    assert slow[0] == 1 and slow[-1] == 2 and slow.index(2) >= 2
    # halved frames at 20 ms: above a third of the period, it stays halved (no switching at every frame)
    assert all(size.on_drawn(0.002, 0.018, period) == 2 for _ in range(40))
    # at 6 ms it is whole again
    back = [size.on_drawn(0.001, 0.005, period) for _ in range(40)]
    assert back[-1] == 1 and back.count(1) == len(back) - back.index(1)
    # what cannot be a time changes nothing
    assert size.on_drawn(float("nan"), 1.0, period) == 1 and size.on_drawn(0.1, float("inf"), period) == 1
    assert size.on_drawn(1.0, 1.0, 0.0) == 1


def test_a_halved_frame_is_the_area_average_at_half_its_size_for_every_encoding():
    import numpy as np

    from services.console.service import halved

    rng = np.random.default_rng(3)
    for encoding, channels in ((m.ImageEncoding.MONO8, 1), (m.ImageEncoding.RGB8, 3)):
        pixels = rng.integers(0, 256, (48, 64, channels), dtype=np.uint8)
        image = m.Image(header=m.Header(seq=5), width=64, height=48, encoding=encoding, data=pixels.tobytes())
        small = halved(image)
        assert (small.width, small.height, small.encoding, small.header.seq) == (32, 24, encoding, 5)
        expected = pixels.reshape(24, 2, 32, 2, channels).astype(float).mean(axis=(1, 3))
        got = np.frombuffer(small.data, dtype=np.uint8).reshape(24, 32, channels)
        assert np.abs(got - expected).max() <= 0.5 + 1e-9


def test_the_fingers_are_shown_where_the_robot_reports_them_with_the_targets_they_hold():
    import msgspec

    model = ConsoleModel()
    model.on_state(state(0.0), now=0.0)
    assert model.snapshot(0.0)["fingers"] == []  # a robot that reports none (the RS-485 link)
    closed = SEVEN.hand.closed_angle
    held = m.FingerState(position=[closed / 2] * 3, velocity=[0.0] * 3, current_a=[1.0, 0.5, 0.25],
                         target=[closed] * 3)
    model.on_state(msgspec.structs.replace(state(0.01), fingers=held), now=0.01)
    fingers = model.snapshot(0.01)["fingers"]
    assert [f["label"] for f in fingers] == list(SEVEN.hand.finger_names)
    assert [(f["deg"], f["target_deg"], f["units"], f["closed_deg"]) for f in fingers] == [(40.0, 80.0, 3400, 80.0)] * 3
    assert [f["current_a"] for f in fingers] == [1.0, 0.5, 0.25]


def test_the_page_shows_the_tasks_plan_its_phase_and_what_the_hand_holds():
    model = ConsoleModel()
    model.on_task(m.TaskStatus(ok=True, state=m.TaskState.RUNNING, task=3, by="alice", plan=m.TaskPlan.GRASP,
                               phase="lift", grasp=m.GraspVerdict.GRASPED), 1.0)
    task = model.snapshot(1.0)["task"]
    assert (task["plan"], task["phase"], task["grasp"]) == ("grasp", "lift", "grasped")
    model.on_task(m.TaskStatus(ok=True, state=m.TaskState.IDLE, task=3, outcome="failed: the object is slipping",
                               grasp=m.GraspVerdict.SLIPPING), 2.0)
    task = model.snapshot(2.0)["task"]
    assert task["outcome"].startswith("failed") and task["grasp"] == "slipping"
