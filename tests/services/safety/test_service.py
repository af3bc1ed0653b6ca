"""The safety service with robot_sim over a real zenoh router (lockstep): a stand-in pipeline plays vision and
controller until the controller lands."""
import math
import time

import msgpack
import numpy as np
import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention, ClockMode
from services.runtime.transport import open_session
from services.model.zones import BoxZone, SphereZone
from services.robot.contact_watch import ContactConfig
from services.robot.node import LockstepConfig
from services.robot_sim.service import RobotSimConfig, RobotSimService
from services.safety.checks import SafetyLimits
from services.safety.service import SafetyConfig, SafetyService
from tests.stack import KEYS, FakePipeline, Recorder, ee_speeds, wait_for


@pytest.fixture
def harness(router):
    """Starts safety (lockstep) with the given limits, then robot_sim; yields helpers; stops everything."""
    started = {}

    def start(limits: SafetyLimits | None = None, twist_for=lambda t: ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
              frame_timeout_s: float = 2.0, contact: bool = False, **pipe):
        client = open_session(router.client_config())
        safety = SafetyService(SafetyConfig(clock=ClockMode.LOCKSTEP, zenoh=router.client_config(),
                                            limits=limits or SafetyLimits()))
        safety.start()
        pipeline = FakePipeline(client, twist_for, **pipe)
        states = Recorder(client, KEYS.robot_state, m.RobotState)
        status = Recorder(client, KEYS.safety_status, m.SafetyStatus)
        time.sleep(0.3)
        robot = RobotSimService(RobotSimConfig(clock=ClockMode.LOCKSTEP, zenoh=router.client_config(),
                                               lockstep=LockstepConfig(frame_timeout_s=frame_timeout_s),
                                               contact=ContactConfig(enabled=contact)))
        robot.start()
        started.update(client=client, safety=safety, pipeline=pipeline, robot=robot, states=states, status=status)
        return started

    yield start
    for name in ("robot", "safety"):
        if name in started:
            started[name].stop()
    if "pipeline" in started:
        started["pipeline"].close()
        started["client"].close()


def test_commands_within_limits_are_forwarded(harness):
    h = harness(twist_for=lambda t: ((0.05, 0.0, -0.02), (0.0, 0.0, 0.0)))
    assert wait_for(lambda: len(h["states"]) >= 150, timeout=60)
    speeds, _ = ee_speeds(h["states"].snapshot()[100:150])
    assert np.allclose(speeds, math.hypot(0.05, 0.02), rtol=0.02)
    state = h["states"].last()
    hops = [hop.service for hop in state.applied_command.trace]
    assert hops == ["safety", "robot_sim"]
    assert h["safety"].core.safety_state is m.SafetyState.OK


def test_over_the_speed_limit_is_clamped(harness):
    h = harness(SafetyLimits(max_linear_speed_mps=0.08), twist_for=lambda t: ((0.2, 0.0, 0.0), (0.0, 0.0, 0.0)))
    assert wait_for(lambda: len(h["states"]) >= 150, timeout=60)
    speeds, _ = ee_speeds(h["states"].snapshot()[100:150])
    assert np.allclose(speeds, 0.08, rtol=0.02)
    assert wait_for(lambda: "linear_speed" in h["status"].last().active_limits)
    assert h["status"].last().state is m.SafetyState.LIMITING


def test_over_the_speed_limit_is_refused_when_configured(harness):
    h = harness(SafetyLimits(max_linear_speed_mps=0.08, over_limit="refuse"),
                twist_for=lambda t: ((0.2, 0.0, 0.0), (0.0, 0.0, 0.0)))
    assert wait_for(lambda: len(h["states"]) >= 100, timeout=60)
    q = np.array([s.q for s in h["states"].snapshot()])
    assert np.abs(q - q[0]).max() < 1e-6
    assert h["safety"].counters.get("refused.linear_speed") > 10
    assert wait_for(lambda: h["status"].last().state is m.SafetyState.REFUSING)
    assert "linear_speed" in h["status"].last().last_refusal


def test_a_workspace_zone_is_never_entered(harness):
    head = SphereZone(name="head", centre=(0.0, -0.44, 0.72), radius_m=0.12)  # 0.21 m above the start
    limits = SafetyLimits(zones=[head, BoxZone(name="base", min_xyz=(-0.17, -0.17, -0.05),
                                               max_xyz=(0.17, 0.17, 0.33))])
    h = harness(limits, twist_for=lambda t: ((0.0, 0.0, 0.1), (0.0, 0.0, 0.0)))
    assert wait_for(lambda: len(h["states"]) >= 300, timeout=90)
    distances = [head.signed_distance(np.array([s.pose.X, s.pose.Y, s.pose.Z]))[0] for s in h["states"].snapshot()]
    assert min(distances) >= 0.0
    assert min(distances) < 0.03  # it came up to the zone


def test_estop_stops_within_v0_over_a_stop_and_stays_latched(harness):
    h = harness(twist_for=lambda t: ((0.12, 0.0, 0.0), (0.0, 0.0, 0.0)))
    assert wait_for(lambda: len(h["states"]) >= 80, timeout=60)
    trigger_ns = h["states"].last().header.stamp_ns
    v0 = ee_speeds(h["states"].snapshot()[-5:])[0][-1]
    h["client"].put(KEYS.estop, m.encode(m.EStop(header=m.Header(), operator="test", reason="hand in the way")))
    assert wait_for(lambda: h["safety"].core.estop_latched)
    n = len(h["states"])
    assert wait_for(lambda: len(h["states"]) >= n + 100, timeout=60)
    snapshot = h["states"].snapshot()
    speeds, t = ee_speeds(snapshot)
    # braking starts when the robot applies safety's emergency stop (its DSP says so); in lockstep the simulation
    # may run a few cycles between the trigger and safety's latch, so the two delays are bounded separately
    braking_ns = next(s.header.stamp_ns for s in snapshot
                      if s.header.stamp_ns >= trigger_ns and "emergency_stop" in s.faults)
    assert braking_ns - trigger_ns <= 100_000_000
    after = t * 1e9 >= braking_ns
    a_stop = h["robot"].config.dsp.emergency_linear_decel_mps2  # the robot's braking, not safety's to set
    # at rest from the state after which it stays still (latched): the actuators' servo, settling after the brake,
    # may touch 1 mm/s again a few ms after it first went under (1.0009 mm/s once), which is not motion
    moving = np.flatnonzero(after & (speeds >= 1e-3))
    assert len(moving) and moving[-1] + 1 < len(t), "the arm did not come to rest"
    rest = t[moving[-1] + 1]
    assert rest - braking_ns * 1e-9 <= v0 / a_stop + 0.030
    assert h["status"].last().state is m.SafetyState.ESTOP
    assert h["safety"].counters.get("refused.estop") > 10
    # only an explicit reset releases it; then the next command moves the arm again
    h["client"].put(KEYS.estop, m.encode(m.EStop(header=m.Header(), reset=True, operator="test")))
    n = len(h["states"])
    assert wait_for(lambda: len(h["states"]) >= n + 80, timeout=60)
    assert ee_speeds(h["states"].snapshot()[-5:])[0][-1] == pytest.approx(0.12, rel=0.02)


def test_stale_commands_stop_the_arm_within_budget_plus_stopping(harness):
    # the pipeline falls silent: the simulator then moves on after frame_timeout_s (wall) per frame
    h = harness(twist_for=lambda t: ((0.1, 0.0, 0.0), (0.0, 0.0, 0.0)), frame_timeout_s=0.05)
    assert wait_for(lambda: len(h["states"]) >= 80, timeout=60)
    h["pipeline"].enabled = False  # the controller falls silent but stays alive
    silent_ns = h["states"].last().header.stamp_ns
    v0 = ee_speeds(h["states"].snapshot()[-5:])[0][-1]
    n = len(h["states"])
    assert wait_for(lambda: len(h["states"]) >= n + 100, timeout=90)
    speeds, t = ee_speeds(h["states"].snapshot())
    after = t * 1e9 >= silent_ns
    rest = next(ti for ti, s in zip(t[after], speeds[after], strict=True) if s < 1e-3)
    budget = h["safety"].config.limits.command_budget_s
    assert rest - silent_ns * 1e-9 <= budget + v0 / 0.64 + 0.030
    assert h["safety"].counters.get("refused.freshness") >= 1


def test_losing_the_controller_liveliness_stops_at_once(harness):
    h = harness(twist_for=lambda t: ((0.1, 0.0, 0.0), (0.0, 0.0, 0.0)))
    assert wait_for(lambda: len(h["states"]) >= 80, timeout=60)
    h["pipeline"].drop_liveliness("controller")
    assert wait_for(lambda: "controller" not in h["safety"].core.alive)
    assert wait_for(lambda: h["safety"].counters.get("refused.liveliness") >= 1)
    n = len(h["states"])
    assert wait_for(lambda: len(h["states"]) >= n + 60, timeout=60)
    assert ee_speeds(h["states"].snapshot()[-5:])[0][-1] < 1e-3


def test_wrong_convention_and_bad_payloads_are_refused(harness):
    h = harness(twist_for=lambda t: ((0.05, 0.0, 0.0), (0.0, 0.0, 0.1)), convention=AngularConvention.OMEGA)
    assert wait_for(lambda: len(h["states"]) >= 60, timeout=60)
    bad = m.to_builtins(m.Twist(header=m.Header(), frame="mixed", angular="seed000", linear=(0.1, 0.0, 0.0),
                                rotational=(0.0, 0.0, 0.0)))
    bad["linear"][0] = float("nan")
    for payload in (msgpack.packb(bad), b"\xff\x00", m.encode(m.Header())):
        h["client"].put(KEYS.desired_twist, payload)
    h["client"].put(KEYS.estop, b"\x00")
    assert wait_for(lambda: h["safety"].counters.get("rejected.twist") >= 3
                    and h["safety"].counters.get("rejected.estop") >= 1)
    q = np.array([s.q for s in h["states"].snapshot()])
    assert np.abs(q - q[0]).max() < 1e-6
    assert h["safety"].counters.get("refused.convention") > 5
    assert not h["safety"].core.estop_latched and h["safety"].state == "running"


def test_an_estop_is_confirmed_at_once_not_at_the_next_status_period(router):
    """Safety says its state as soon as an e-stop changes it: with its status every 5 s, the e-stop and its
    release are each confirmed well within a status period, after one request each."""
    from services.safety.estop_client import EStopClient

    safety = SafetyService(SafetyConfig(zenoh=router.client_config(), status_rate_hz=0.2)).start()
    session = open_session(router.client_config())
    estops = Recorder(session, KEYS.estop, m.EStop)
    try:
        time.sleep(0.5)  # past the first status, sent as the loop starts
        with EStopClient(session, KEYS) as client:
            for reset in (False, True):
                started = time.monotonic()
                status = client.send(reset, "tester", "test", timeout_s=4.0)
                assert status is not None and (status.state is m.SafetyState.ESTOP) != reset
                assert time.monotonic() - started < 1.0
        assert wait_for(lambda: len(estops) == 2, timeout=2)  # one put each: none repeated for want of an answer
        time.sleep(0.3)
        assert len(estops) == 2
    finally:
        estops.close()
        session.close()
        safety.stop()


def test_mfvs_estop_command_engages_and_resets(router):
    import subprocess
    import sys
    from pathlib import Path

    mfvs = str(Path(sys.executable).parent / "mfvs")
    safety = SafetyService(SafetyConfig(zenoh=router.client_config()))
    safety.start()
    try:
        out = subprocess.run([mfvs, "estop", "--connect", router.endpoint, "--reason", "test"], capture_output=True,
                             text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        assert "e-stop engaged: safety reports state estop" in out.stdout
        assert safety.core.estop_latched and "mfvs-cli: test" in safety.core.estop_reason
        out = subprocess.run([mfvs, "estop", "--reset", "--connect", router.endpoint], capture_output=True,
                             text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        assert not safety.core.estop_latched
    finally:
        safety.stop()
    out = subprocess.run([mfvs, "estop", "--connect", router.endpoint, "--timeout", "1"], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 1 and "no safety service confirmed" in out.stderr


def test_a_desired_commands_hand_part_closes_the_fingers_and_they_stay_closed_when_the_commands_stop(harness):
    """Over the router, in lockstep: the stand-in controller's zero twists carry a finger target; the robot's states
    show the fingers closing on it. Once the commands stop (safety then sends stops) and after an e-stop, the
    fingers stay where they were sent: nothing but a finger command moves them."""
    closed = 1.2
    h = harness(fingers_for=lambda capture: m.FingerCommand(mode=m.FingerMode.POSITION, values=[closed] * 3),
                frame_timeout_s=0.2)  # (once the stand-in falls silent, each frame waits this for its answer)
    assert wait_for(lambda: len(h["states"]) >= 150, timeout=60)  # 1.5 s: the travel takes about 1 s
    fingers = h["states"].last().fingers
    assert fingers is not None and np.allclose(fingers.target, closed) and np.allclose(fingers.position, closed,
                                                                                        atol=1e-3)
    h["pipeline"].enabled = False
    seen = len(h["states"])
    assert wait_for(lambda: len(h["states"]) >= seen + 50, timeout=60)
    assert np.allclose(h["states"].last().fingers.position, closed, atol=1e-3)
    h["client"].put(KEYS.estop, m.encode(m.EStop(header=m.Header(), operator="test", reason="hold")))
    seen = len(h["states"])
    assert wait_for(lambda: len(h["states"]) >= seen + 50, timeout=60)
    assert np.allclose(h["states"].last().fingers.position, closed, atol=1e-3)


def test_a_push_on_the_moving_arm_is_a_contact_the_robot_names_and_safety_stops_the_arm_for(harness):
    """robot_sim's contact monitor (off as shipped, docs/contact.md) on its own torque sensors, the arm moving at 5 cm/s: quiet
    until a 57 N push on the wrist's link (MuJoCo's applied force, standing in for a body in the arm's way), then a
    contact in the states, a protective stop that names it, and the arm held."""
    import mujoco

    h = harness(twist_for=lambda t: ((0.05, 0.0, 0.0), (0.0, 0.0, 0.0)), contact=True)
    assert wait_for(lambda: len(h["states"]) >= 100, timeout=60)
    quiet = h["states"].last().contact
    assert quiet is not None and quiet.contacts == 0 and quiet.rate_hz == pytest.approx(500.0)
    assert max(s.contact.ratio for s in h["states"].snapshot()[20:]) < 1.0
    robot = h["robot"]
    link = robot.arm.link_names[robot.arm.n_joints - 3]
    body = mujoco.mj_name2id(robot.sim.model, mujoco.mjtObj.mjOBJ_BODY, link)
    robot.sim.data.xfrc_applied[body, :3] = (0.0, 40.0, -40.0)
    try:
        assert wait_for(lambda: h["safety"].core.estop_latched, timeout=30)
        assert "protective stop: contact at joint" in h["safety"].core.estop_reason
        assert h["safety"].counters.get("contact.stops") == 1
        assert robot.counters.get("contact.detected") >= 1
        n = len(h["states"])
        assert wait_for(lambda: len(h["states"]) >= n + 30, timeout=30)
        touched = h["states"].last().contact
        assert touched.contacts >= 1 and 1 <= touched.last_joint <= robot.arm.n_joints - 2
        assert abs(touched.last_residual_nm) > touched.last_threshold_nm
        speeds, _ = ee_speeds(h["states"].snapshot()[-10:])
        assert np.all(speeds < 0.005)  # held where it was pushed, not driven on
    finally:
        robot.sim.data.xfrc_applied[body, :3] = 0.0
