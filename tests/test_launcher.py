"""`mfvs up`, `mfvs status`, `mfvs down`: the stack as background processes."""
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from services.common.transport import free_loopback_port

MFVS = str(Path(sys.executable).parent / "mfvs")


def mfvs(*args, env, timeout=120):
    return subprocess.run([MFVS, *args], capture_output=True, text=True, timeout=timeout, env=env)


def test_up_status_down(tmp_path):
    env = dict(os.environ, MFVS_RUN_DIR=str(tmp_path))
    port = str(free_loopback_port())
    out = mfvs("up", "--port", port, "--clock", "realtime", env=env)
    try:
        assert out.returncode == 0, out.stderr
        assert "stack up" in out.stdout
        again = mfvs("up", "--port", port, env=env)
        assert again.returncode == 1 and "already up" in again.stderr
        time.sleep(3.0)
        status = mfvs("status", "--json", env=env)
        assert status.returncode == 0, status.stderr
        report = json.loads(status.stdout)
        assert report["router"]["reachable"] and report["router"]["endpoint"].endswith(port)
        services = {s["name"]: s for s in report["services"]}
        assert set(services) == {"robot_sim", "vision", "controller", "safety"}
        stack = json.loads((tmp_path / "stack.json").read_text())
        pids = {p["name"]: p["pid"] for p in stack["processes"]}
        for name, service in services.items():
            assert service["healthy"], (name, service)
            assert service["pid"] == pids[name]
            assert isinstance(service["errors"], dict) and service["rates_hz"]
        assert services["robot_sim"]["rates_hz"]["pub.state"] > 50  # generous: 100 Hz nominal
        assert services["vision"]["rates_hz"]["pub.features"] > 10  # 30 Hz nominal
    finally:
        down = mfvs("down", env=env)
    assert down.returncode == 0 and "stopped 5 processes" in down.stdout
    for pid in pids.values():
        assert not Path(f"/proc/{pid}").exists() or "zombie" in Path(f"/proc/{pid}/status").read_text().lower()
    gone = mfvs("status", "--json", "--connect", f"tcp/127.0.0.1:{port}", env=env)
    assert gone.returncode == 1 and not json.loads(gone.stdout)["router"]["reachable"]


def test_unknown_profile_is_refused(tmp_path):
    env = dict(os.environ, MFVS_RUN_DIR=str(tmp_path))
    bad = tmp_path / "profile.yaml"
    bad.write_text("services: [{name: teleporter}]\n")
    out = mfvs("up", "--profile", str(bad), env=env)
    assert out.returncode == 2 and "teleporter" in out.stderr
    out = mfvs("up", "--profile", "gateway", env=env)
    assert out.returncode == 2 and "robot_gateway" in out.stderr
