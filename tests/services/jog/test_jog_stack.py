"""`mfvs jog --script FILE` against real services (a router, safety and the simulated arm in realtime): the arm
moves in the mixed frame as Kinova's joystick moves it, and stops on a release, a silent stream and a frozen device.
The figures (latency, stop times, the direction on both arms) are the benchmark's (`mfvs bench latency --source jog
--arm NAME`, bench/latency.py); here a stop must come within the budget that defines it, with room for a late host.
The CI runs each check on one arm (the 6-DoF, whose singularities no redundancy takes it round); the other arm's
runs are ``slow``."""
import json
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import yaml

from protocol import messages as m
from protocol.conventions import ClockMode
from services.jog.mapping import apply_dead_band
from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics, normalized_jacobian
from services.model.singularity import condition_number
from services.robot_sim.scene import CameraConfig, SceneConfig
from services.robot_sim.service import RobotSimConfig, RobotSimService
from services.runtime.transport import open_session
from services.safety.service import SafetyConfig, SafetyService
from tests.stack import KEYS, Recorder, wait_for

MFVS = str(Path(sys.executable).parent / "mfvs")

TRANSLATION = (0.6, -0.4, 0.3)
WRIST = (0.3, 0.0, -0.7)
SCRIPT = {"rate_hz": 50, "speed_level": 2, "steps": [
    {"for_s": 0.4, "deadman": False},
    {"for_s": 1.6, "mode": "translation", "axes": list(TRANSLATION), "deadman": True},
    {"for_s": 0.6, "deadman": False, "axes": list(TRANSLATION)},       # released, the stick still pushed
    {"for_s": 1.6, "mode": "wrist", "axes": list(WRIST), "deadman": True},
    {"for_s": 0.6, "deadman": False},
    {"for_s": 1.0, "mode": "translation", "axes": [0.0, 0.7, 0.0], "deadman": True},
    {"for_s": 0.8, "axes": [0.0, 0.7, 0.0], "deadman": True, "device": "silent"},   # nothing sent: stale
    {"for_s": 1.0, "axes": [0.0, -0.7, 0.0], "deadman": True},
    {"for_s": 0.8, "axes": [0.0, -0.7, 0.0], "deadman": True, "device": "frozen"},  # sent, the device unheard
]}


def motions(states, arm):
    """(stamp s, base linear velocity, angular velocity in the hand's frame) of each state, by the arm's
    kinematics on its measured q and dq."""
    kin = ArmKinematics(arm)
    out = []
    for s in states:
        R, _, J = kin.pose_and_jacobian(np.array(s.q))
        twist = J @ np.array(s.dq)
        out.append((s.header.stamp_ns * 1e-9, twist[:3], R.T @ twist[3:]))
    return out


def direction_error(measured, commanded):
    """The distance between two unit directions (0: the same; 0.05: about 2.9°)."""
    return float(np.linalg.norm(measured / np.linalg.norm(measured) - commanded / np.linalg.norm(commanded)))


@pytest.fixture
def realtime_arm(router, tmp_path):
    started = {}

    def start(arm: str, initial_joints_deg=None):
        client = open_session(router.client_config())
        safety = SafetyService(SafetyConfig(zenoh=router.client_config()))
        safety.start()
        scene = SceneConfig(camera=CameraConfig(enabled=False), initial_joints_deg=initial_joints_deg)
        robot = RobotSimService(RobotSimConfig(arm=arm, zenoh=router.client_config(), clock=ClockMode.REALTIME,
                                               scene=scene))
        robot.start()
        started.update(client=client, safety=safety, robot=robot,
                       states=Recorder(client, KEYS.robot_state, m.RobotState),
                       jogs=Recorder(client, KEYS.desired_jog, m.Jog),
                       safety_status=Recorder(client, KEYS.safety_status, m.SafetyStatus),
                       commands=Recorder(client, KEYS.robot_command, m.RobotCommand))
        assert wait_for(lambda: len(started["states"]) > 20, timeout=30)
        return started

    yield start
    for name in ("robot", "safety"):
        if name in started:
            started[name].stop()
    if "client" in started:
        for name in ("states", "jogs", "safety_status", "commands"):
            started[name].close()
        started["client"].close()


@pytest.mark.parametrize("arm_name", [pytest.param("j2s7s300", marks=pytest.mark.slow), "j2n6s300"])
def test_a_scripted_stick_moves_the_arm_in_the_mixed_frame_and_it_stops_on_release_silence_and_a_frozen_device(
        realtime_arm, router, tmp_path, arm_name):
    h = realtime_arm(arm_name)
    arm = load_arm(arm_name)
    script = tmp_path / "stick.yaml"
    script.write_text(yaml.safe_dump(SCRIPT))
    out = subprocess.run([MFVS, "jog", "--script", str(script), "--json", "--connect", router.endpoint],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    sent = json.loads(out.stdout)
    jogs = h["jogs"].snapshot()
    seqs = [j.header.seq for j in jogs]
    assert seqs == sorted(set(seqs)) and seqs[-1] <= sent["last_seq"] == sent["sent"]
    # in realtime zenoh drops a sample rather than make a publisher wait on a starved host (publisher_options:
    # none lost here unloaded, 1 in 70 at 0.6 of a core and a hog, 4 % at 0.3): the next request, 20 ms later,
    # stands for it; most of the stream arrives
    assert len(jogs) >= 0.5 * sent["sent"], (len(jogs), sent["sent"])
    wait_for(lambda: False, timeout=0.5)  # the arm at rest after the last step
    # each step's time by the requests themselves (their stamps, on the clock the states are stamped by)
    stamp = {id(j): j.header.stamp_ns * 1e-9 for j in jogs}
    translating = [j for j in jogs if j.mode is m.JogMode.TRANSLATION and j.deadman and j.linear[0] > 0]
    turning = [j for j in jogs if j.mode is m.JogMode.WRIST and j.deadman]
    t0 = stamp[id(jogs[0])]
    moving = motions([s for s in h["states"].snapshot() if s.header.stamp_ns * 1e-9 >= t0], arm)

    stops = [c.header.stamp_ns * 1e-9 for c in h["commands"].snapshot() if c.mode is m.CommandMode.STOP]

    def during(held, speed_of, full_speed, settle_s=0.6, end_s=0.15):
        """The motion in the steady part of a step (after the spasm filter's ramp and the arm's acceleration, before
        the next step's request reaches the arm), and whether the host kept time in it. A host too starved to keep
        the requests, the commands or the arm's states fresh has safety or the arm stop (by design: lateness never
        becomes motion): then the arm's braking and its acceleration again after each such stop (its settling, a
        state under 30 % of the step's speed: a stopped arm has no direction) are left out, and the speed is not
        judged."""
        first, last = stamp[id(held[0])], stamp[id(held[-1])]
        late = [t for t in stops if first < t <= last]
        window = [(t, v, w) for t, v, w in moving if first + settle_s <= t <= last - end_s]
        assert window, "no state during a held step"
        kept_time = not late and not h["robot"].counters.get("refused.stale")
        if not kept_time:
            print(f"the host was late: {len(late)} stops in a held step, safety {h['safety'].counters.snapshot()}, "
                  f"the arm refused {h['robot'].counters.get('refused.stale')} stale commands")
            window = [(t, v, w) for t, v, w in window if speed_of(v, w) >= 0.3 * full_speed
                      and not any(stop <= t <= stop + settle_s for stop in late)]
        return window, kept_time

    # translation: the hand along the base's axes, in the commanded direction within 5 %
    commanded = apply_dead_band(TRANSLATION, 0.1)
    full = 0.5 * 0.2 * np.linalg.norm(commanded)  # level 2 of 3: half of 0.2 m/s
    steady, kept_time = during(translating, lambda v, w: np.linalg.norm(v), full)
    for _, v, w in steady:
        assert direction_error(v, commanded) < 0.05, (v, commanded)
        assert np.linalg.norm(w) < 0.02
    if kept_time:
        assert np.mean([np.linalg.norm(v) for _, v, _ in steady]) == pytest.approx(full, rel=0.1)
    # wrist: the hand about its own axes, the commanded direction within 5 %, the hand's position still
    commanded = apply_dead_band(WRIST, 0.1)
    turning_steady, turning_kept_time = during(turning, lambda v, w: np.linalg.norm(w),
                                               0.5 * 0.6 * np.linalg.norm(commanded))
    for _, v, w in turning_steady:
        assert direction_error(w, commanded) < 0.05, (w, commanded)
        assert np.linalg.norm(v) < 0.01

    def rest_after(t_stop, within_s):
        """The first state at rest after ``t_stop``; that it is within ``within_s``."""
        after = [(t, v, w) for t, v, w in moving if t >= t_stop]
        at_rest = next(t for t, v, w in after if np.linalg.norm(v) < 2e-3 and np.linalg.norm(w) < 1e-2)
        assert at_rest - t_stop <= within_s, (at_rest - t_stop, within_s)
        return at_rest - t_stop

    def first_after(held, condition):
        return next(stamp[id(j)] for j in jogs if stamp[id(j)] > stamp[id(held[-1])] and condition(j))

    # a late host's slack on top of each budget: the scheduler's, not the design's
    slack_s = 0.15
    braking_s = 0.1 / 0.64 + 0.6 / 2.75  # from the jog's speed at the DSP's decelerations (docs/robot.md)
    rest_after(first_after(translating, lambda j: not j.deadman), 0.1 + braking_s + slack_s)  # released: at once
    rest_after(first_after(turning, lambda j: not j.deadman), 0.1 + braking_s + slack_s)
    before_silence = [j for j in jogs if j.deadman and j.linear[1] > 0]
    rest_after(stamp[id(before_silence[-1])], 0.1 + braking_s + slack_s)  # no request for 100 ms: stale
    frozen = [j for j in jogs if j.deadman and j.linear[1] < 0 and j.header.source_stamp_ns < j.header.stamp_ns]
    assert frozen, "no request from a frozen device"
    rest_after(frozen[0].header.source_stamp_ns * 1e-9, 0.25 + braking_s + slack_s)  # unheard for 250 ms: frozen
    counters = h["safety"].counters
    assert counters.get("refused.freshness") >= 2
    if kept_time and turning_kept_time:  # a late host's stop may come first: the release then stops nothing
        assert counters.get("released.stops") >= 2


def straight_out(kin, q):
    """The stick's axes for the hand straight out from the base, horizontally (the elbow stretching)."""
    _, p = kin.pose(q)
    out = np.array([p[0], p[1], 0.0])
    return "translation", out / np.abs(out).max()


def turning_joint_5(kin, q):
    """The stick's axes for the wrist turn that the 5th joint alone would make, toward its singular angle."""
    R, _, J = kin.pose_and_jacobian(q)
    omega = R.T @ J[3:, 4] * -1.0
    return "wrist", omega / np.abs(omega).max()


#: (the arm, its start (None: its home), the person's push toward a singularity, the speed level, for how long)
TOWARD_A_SINGULARITY = {
    "j2n6s300 reaching out at the top speed": ("j2n6s300", None, straight_out, 3, 8.0),
    "j2n6s300 turning its wrist": ("j2n6s300", {4: -140.0}, turning_joint_5, 3, 4.0),
    "j2s7s300 reaching out": ("j2s7s300", None, straight_out, 2, 11.0),
}


@pytest.mark.parametrize("case", [pytest.param(case, marks=pytest.mark.slow) if "wrist" not in case else case
                                  for case in sorted(TOWARD_A_SINGULARITY)])
def test_a_stick_pushed_toward_a_singularity_stops_the_arm_before_it_on_the_simulated_arm(realtime_arm, tmp_path,
                                                                                           router, case):
    """Held toward a singularity until the arm stops, through the emulated DSP in realtime: the arm, which follows
    a cycle late and brakes at its joints' and hand's decelerations, stops before the bound, not past it (safety
    plans the stop from κ's growth ahead and the arm's braking: services/model/singularity.py)."""
    arm_name, joints, push, level, seconds = TOWARD_A_SINGULARITY[case]
    arm = load_arm(arm_name)
    kin = ArmKinematics(arm)
    initial = None
    if joints:  # the home pose with these joints at these angles (model degrees), as the arm's own (physical)
        q = arm.home.copy()
        for joint, degrees in joints.items():
            q[joint] = np.radians(degrees)
        initial = [float(d) for d in arm.model_to_physical_deg(q)]
    h = realtime_arm(arm_name, initial)
    q = np.array(h["states"].last().q)
    mode, axes = push(kin, q)
    script = tmp_path / "toward.yaml"
    script.write_text(yaml.safe_dump({"rate_hz": 50, "speed_level": level, "steps": [
        {"for_s": 0.2, "deadman": False},
        {"for_s": seconds, "mode": mode, "axes": [float(a) for a in axes], "deadman": True},
        {"for_s": 0.2, "deadman": False}]}))
    out = subprocess.run([MFVS, "jog", "--script", str(script), "--json", "--connect", router.endpoint],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    bounds = SafetyConfig().limits.singularity
    conditions = [condition_number(normalized_jacobian(kin.jacobian_base(np.array(s.q)), kin.characteristic_length_m))
                  for s in h["states"].snapshot()]
    assert conditions[0] < bounds.slow_from
    kept_time = not (h["safety"].counters.get("refused.robot_state") or h["safety"].counters.get("refused.freshness")
                     or h["robot"].counters.get("refused.stale"))
    if kept_time:
        assert max(conditions) > bounds.slow_from + 10, (max(conditions), h["safety"].counters.snapshot())
    elif max(conditions) <= bounds.slow_from + 10:
        # safety stopped the arm on stale requests or states all along (lateness never becomes motion): it never
        # got near enough to judge the stop, and it never moved unsafely
        print(f"the host was late (safety {h['safety'].counters.snapshot()}): the arm got to κ "
              f"{max(conditions):.1f} only, the stop not judged")
        return
    # stopped before the bound; a host late on top of the planned lag lets a few more through (measured under a
    # full test run's load: 80.2 to 85.1), still short of the DSP's damping (κ ≈ 95), where the arm no longer moves
    # as commanded
    assert max(conditions) < bounds.stop_at * 1.1, max(conditions)
    assert any("singularity_stop" in st.active_limits or "singularity" in st.active_limits
               for st in h["safety_status"].snapshot())
    last = h["states"].last()
    assert np.linalg.norm(np.array(last.dq)) < 1e-3  # at rest
