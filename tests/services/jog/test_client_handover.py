"""The hand-over between the person and the servo, on a stack as `mfvs up` starts it (realtime): a running servo
task, a touch of the stick (`mfvs jog --script`) takes control and pauses it, the arm stays still once the stick is
released, `mfvs status` says who is in control, and `mfvs task resume` goes on with it."""
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from protocol import messages as m
from services.runtime.transport import ZenohConfig, free_loopback_port, open_session
from tests.stack import Recorder, wait_for
from protocol.keys import Keys

MFVS = str(Path(sys.executable).parent / "mfvs")


def mfvs(*args, env, timeout=120):
    return subprocess.run([MFVS, *args], capture_output=True, text=True, timeout=timeout, env=env)


def safety_detail(env) -> str:
    report = json.loads(mfvs("status", "--json", env=env).stdout)
    return next((s["detail"] for s in report["services"] if s["name"] == "safety"), "")


def test_a_touch_of_the_stick_pauses_the_servo_task_and_a_resume_goes_on_with_it(tmp_path):
    env = dict(os.environ, MFVS_RUN_DIR=str(tmp_path))
    port = free_loopback_port()
    up = mfvs("up", "--port", str(port), "--clock", "realtime", env=env)
    assert up.returncode == 0, up.stderr
    session = open_session(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"]))
    states = Recorder(session, Keys().robot_state, m.RobotState)
    try:
        assert wait_for(lambda: "in control:" in safety_detail(env), timeout=30)
        started = mfvs("task", "start", "--operator", "alice", env=env)
        assert started.returncode == 0, started.stdout + started.stderr
        assert wait_for(lambda: "in control: controller/servo" in safety_detail(env), timeout=20)
        jogs = Recorder(session, Keys().desired_jog, m.Jog)
        # the person touches the stick and lifts the hand (level 1: 5 cm/s for 1.2 s), then lets go
        script = tmp_path / "touch.yaml"
        script.write_text(yaml.safe_dump({"rate_hz": 50, "speed_level": 1, "steps": [
            {"for_s": 1.2, "mode": "translation", "axes": [0, 0, 1.0], "deadman": True},
            {"for_s": 0.4, "deadman": False}]}))
        jog = mfvs("jog", "--script", str(script), "--json", env=env)
        assert jog.returncode == 0, jog.stderr
        status = json.loads(mfvs("task", "status", "--json", env=env).stdout)
        assert status["state"] == "paused" and "jog/stick took control" in status["reason"], status
        # paused: released, the stick hands nothing back; the arm comes to rest and stays there
        time.sleep(0.5)
        still_from = len(states)
        time.sleep(1.0)
        q = np.array([s.q for s in states.snapshot()[still_from:]])
        assert len(q) > 20 and np.abs(q - q[0]).max() < 2e-3, np.abs(q - q[0]).max()
        assert "paused" in mfvs("status", env=env).stdout
        touched_ns = jogs.snapshot()[0].header.stamp_ns
        # from the lowest the hand went after the touch: the servo's motion, up to 0.2 m/s in any direction, is
        # braked at the arm's deceleration before the lift begins
        lowest_z = min(s.pose.Z for s in states.snapshot() if s.header.stamp_ns >= touched_ns)
        lifted_z = states.last().pose.Z
        assert lifted_z - lowest_z > 0.02, (lowest_z, lifted_z)  # the person's lift, which the paused servo kept
        resumed = mfvs("task", "resume", "--operator", "alice", env=env)
        assert resumed.returncode == 0 and "resumed at its servo phase" in resumed.stdout, resumed.stdout
        assert wait_for(lambda: "in control: controller/servo" in safety_detail(env), timeout=10)
        # the servo goes back toward its goal from where the person left the arm: down again by a centimetre or more
        assert wait_for(lambda: lifted_z - states.last().pose.Z > 0.01, timeout=20), states.last().pose.Z
    finally:
        if "jogs" in locals():
            jogs.close()
        states.close()
        session.close()
        mfvs("down", env=env)
