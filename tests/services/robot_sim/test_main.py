"""robot_sim as its own process: `python -m services.robot_sim`, its shipped config, signals, bad config."""
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from protocol import messages as m
from protocol.keys import Keys
from services.runtime.transport import open_session
from services.robot_sim.service import RobotSimConfig, RobotSimService
from tests.helpers import REPO

SHIPPED = REPO / "services" / "robot_sim" / "robot_sim.yaml"
KEYS = Keys()


def start(router, *args):
    env = dict(os.environ, MUJOCO_GL="egl")
    return subprocess.Popen([sys.executable, "-m", "services.robot_sim", "--config", str(SHIPPED),
                             "--connect", router.endpoint, *args], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_runs_as_a_process_and_stops_on_sigterm(router):
    client = open_session(router.client_config())
    states, images = [], []
    client.declare_subscriber(KEYS.robot_state, lambda s: states.append(m.decode(s.payload.to_bytes(), m.RobotState)))
    client.declare_subscriber(KEYS.camera_image, lambda s: images.append(m.decode(s.payload.to_bytes(), m.Image)))
    proc = start(router)
    try:
        deadline = time.monotonic() + 60
        while (len(states) < 200 or len(images) < 10) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        assert len(states) >= 200 and len(images) >= 10, proc.stderr.read() if proc.poll() is not None else ""
        # realtime: wall-clock stamps, states every 10 ms and images every 33 ms. The loops' periods, read off the
        # median step (what a window's count would give depends on what the host gave the process in it: a cycle
        # the host delayed is counted late, not made up)
        stamps = np.array([s.header.stamp_ns for s in states[-150:]])
        assert np.all(np.diff(stamps) > 0)
        assert np.median(np.diff(stamps)) * 1e-9 == pytest.approx(0.010, rel=0.1)
        assert abs(stamps[-1] * 1e-9 - time.time()) < 5.0
        image_stamps = np.array([i.header.source_stamp_ns for i in images[-8:]])
        assert np.all(np.diff(image_stamps) > 0)
        assert np.median(np.diff(image_stamps)) * 1e-9 == pytest.approx(1 / 30, rel=0.1)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        client.close()


def test_bad_config_is_refused_with_the_key_name(router, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("dsp: {max_linear_speed_mps: 0.5}\nscene: {camera: {fx: 615.0}}\n")
    out = subprocess.run([sys.executable, "-m", "services.robot_sim", "--config", str(bad)], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "dsp.max_linear_speed_mps" in out.stderr and "(0.04, 0.2)" in out.stderr
    bad.write_text("scene: {camera: {focal: 615.0}}\n")
    out = subprocess.run([sys.executable, "-m", "services.robot_sim", "--config", str(bad)], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "scene.camera.focal" in out.stderr
    # a deploy profile's override is validated like the file it changes
    out = subprocess.run([sys.executable, "-m", "services.robot_sim", "--config", str(SHIPPED), "--set",
                          "dsp.max_linear_speed_mps=0.5"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "max_linear_speed_mps" in out.stderr
    out = subprocess.run([sys.executable, "-m", "services.robot_sim", "--set", "mode=teleport"], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "mode" in out.stderr


def test_max_sim_time_ends_a_lockstep_run(router):
    config = RobotSimConfig(clock="lockstep", zenoh=router.client_config(), max_sim_time_s=0.5)
    service = RobotSimService(config).start()
    assert service.lockstep
    try:
        assert service.finished.wait(30)
        assert service.sim.time_ns == 500_000_000
    finally:
        service.stop()
