"""The shipped multi-host profile across three computers: Linux network namespaces joined by veth pairs and a
bridge (robot + router, vision + controller, safety), each host started by `mfvs up --host NAME` in its own
namespace and run directory, reaching the router over TCP at its address; the operator, in a fourth, starts a
task and the arm converges onto the tag across hosts."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests import netns

REPO = Path(__file__).resolve().parents[3]
MFVS = str(Path(sys.executable).parent / "mfvs")
HOSTS = ["robot", "vision", "safety", "operator"]

WHY = netns.unavailable()
pytestmark = pytest.mark.skipif(bool(WHY), reason=f"no network namespaces here: {WHY}")

#: run in the operator's namespace: start the task, then wait for the controller to say converged
OPERATOR = """
import json, sys, time
from protocol import messages as m
from protocol.keys import Keys
from services.controller.task_client import call_task
from services.runtime.transport import ZenohConfig, open_session

session = open_session(ZenohConfig(connect=[sys.argv[1]]))
statuses = []
session.declare_subscriber(Keys().controller_status,
                           lambda s: statuses.append(m.decode(s.payload.to_bytes(), m.ControllerStatus)))
started = call_task(session, Keys(), m.START_TASK, m.TaskRequest(operator="netns test", reason="across hosts"))
deadline = time.monotonic() + float(sys.argv[2])
while time.monotonic() < deadline and not any(s.status is m.ControllerState.CONVERGED for s in statuses):
    time.sleep(0.2)
last = statuses[-1] if statuses else None
print(json.dumps({"started": started.ok, "statuses": len(statuses),
                  "converged": any(s.status is m.ControllerState.CONVERGED for s in statuses),
                  "iteration": last.iteration if last else 0, "error_norm": last.error_norm if last else None,
                  "last_status": last.status.value if last else None}))
session.close()
"""


def _profile(tmp_path: Path, router_address: str) -> Path:
    """The shipped profile as a lab copies it: the robot computer's address edited in, nothing else."""
    profile = yaml.safe_load((REPO / "deploy" / "profiles" / "multi-host.yaml").read_text())
    profile["router"]["address"] = router_address
    path = tmp_path / "multi-host.yaml"
    path.write_text(yaml.safe_dump(profile))
    return path


def test_a_task_converges_across_three_hosts(tmp_path):
    with netns.Lab(HOSTS) as lab:
        profile = _profile(tmp_path, lab.address("robot"))
        env = lambda host: dict(os.environ, MFVS_RUN_DIR=str(tmp_path / host))  # noqa: E731 (one per computer)
        started = []
        try:
            for host in ("robot", "vision", "safety"):  # the router's computer first
                out = subprocess.run(lab.command(host, [MFVS, "up", "--profile", str(profile), "--host", host,
                                                        "--clock", "realtime"]),
                                     capture_output=True, text=True, timeout=180, env=env(host), cwd=REPO)
                started.append(host)
                assert out.returncode == 0, (host, out.stdout, out.stderr)
                assert f"host {host}: stack up: router tcp/{lab.address('robot')}:7447" in out.stdout
            stacks = {h: json.loads((tmp_path / h / "stack.json").read_text()) for h in started}
            assert [p["name"] for p in stacks["robot"]["processes"]] == ["router", "robot_sim"]
            assert [p["name"] for p in stacks["vision"]["processes"]] == ["vision", "controller"]
            assert [p["name"] for p in stacks["safety"]["processes"]] == ["safety"]
            # the operator's computer sees every service through the router
            status = subprocess.run(lab.command("operator", [MFVS, "status", "--json", "--connect",
                                                             f"tcp/{lab.address('robot')}:7447"]),
                                    capture_output=True, text=True, timeout=60, env=env("operator"), cwd=REPO)
            assert status.returncode == 0, status.stderr
            assert {s["name"] for s in json.loads(status.stdout)["services"]} == \
                {"robot_sim", "vision", "controller", "safety"}
            run = subprocess.run(lab.command("operator", [sys.executable, "-c", OPERATOR,
                                                          f"tcp/{lab.address('robot')}:7447", "90"]),
                                 capture_output=True, text=True, timeout=150, env=env("operator"), cwd=REPO)
            assert run.returncode == 0, run.stderr
            result = json.loads(run.stdout)
            assert result["started"] and result["converged"], result
        finally:
            for host in reversed(started):
                subprocess.run(lab.command(host, [MFVS, "down"]), capture_output=True, timeout=60,
                               env=env(host), cwd=REPO)
