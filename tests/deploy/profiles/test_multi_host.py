"""The shipped multi-host profile across three computers: Linux network namespaces joined by veth pairs and a
bridge (robot + router, vision + controller, safety), each host started by `mfvs up --host NAME` in its own
namespace and run directory, reaching the router over TCP at its address; the operator, in a fourth, starts a
task and the arm converges onto the tag across hosts, and through a cable pulled out of safety's computer
mid-motion and plugged back in."""
import contextlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from services.tools import netns
from services.tools.netns import MFVS, REPO

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


#: run in the robot's namespace: every robot state until its standard input closes (or for at most argv[2] s), one
#: JSON line each (the arm as the robot sees it)
#: listens to the robot's states on the robot's computer, at realtime priority as the services there run (its
#: threads, zenoh's, inherit it): what it measures is the router's delivery, not its own wait for a CPU (at normal
#: priority, on a host slowed to 0.8 of a core, it once heard a state 2.3 s late)
OBSERVER = """
import json, os, select, sys, time
import numpy as np
from protocol import messages as m
from protocol.keys import Keys
from services.runtime.transport import ZenohConfig, open_session

os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
session = open_session(ZenohConfig(connect=[sys.argv[1]]))
heard = []
def on_state(sample):  # what arrived when, and nothing more: decoding and writing each state here made the observer
    heard.append((time.time_ns(), sample.payload.to_bytes()))  # itself late, 2.4 s behind at 0.65 of a core
session.declare_subscriber(Keys().robot_state, on_state)
select.select([sys.stdin], [], [], float(sys.argv[2]))
session.close()
for wall, payload in heard:
    s = m.decode(payload, m.RobotState)
    a = s.applied_command
    print(json.dumps({"stamp": s.header.stamp_ns, "wall": wall, "xyz": [s.pose.X, s.pose.Y, s.pose.Z],
                      "dq": float(np.abs(s.dq).max()), "faults": s.faults[:4],
                      "applied_stamp": a.stamp_ns if a else 0, "applied_source": a.source_stamp_ns if a else 0,
                      "applied_at": a.trace[-1].pub_ns if a else 0}))
"""


def _profile(tmp_path: Path, router_address: str) -> Path:
    """The shipped profile as a lab copies it: the robot computer's address edited in, nothing else."""
    profile = yaml.safe_load((REPO / "deploy" / "profiles" / "multi-host.yaml").read_text())
    profile["router"]["address"] = router_address
    path = tmp_path / "multi-host.yaml"
    path.write_text(yaml.safe_dump(profile))
    return path


@contextlib.contextmanager
def _stack_across(lab: netns.Lab, tmp_path: Path):
    """The shipped profile up on robot, vision and safety (the router's computer first); down at the end. Yields
    a function giving each computer's environment (its own run directory)."""
    profile = _profile(tmp_path, lab.address("robot"))
    env = lambda host: dict(os.environ, MFVS_RUN_DIR=str(tmp_path / host))  # noqa: E731 (one per computer)
    run_dirs = {host: tmp_path / host for host in ("robot", "vision", "safety")}
    with netns.stack_across(lab, profile, run_dirs, f"tcp/{lab.address('robot')}:7447"):
        yield env


def _operator(lab: netns.Lab, env, wait_s: float) -> subprocess.Popen:
    return subprocess.Popen(lab.command("operator", [sys.executable, "-c", OPERATOR,
                                                     f"tcp/{lab.address('robot')}:7447", str(wait_s)]),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env("operator"),
                            cwd=REPO)


def test_a_task_converges_across_three_hosts(tmp_path):
    with netns.Lab(HOSTS) as lab, _stack_across(lab, tmp_path) as env:
        stacks = {h: json.loads((tmp_path / h / "stack.json").read_text()) for h in ("robot", "vision", "safety")}
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
        out, err = _operator(lab, env, 90).communicate(timeout=150)
        assert out, err
        result = json.loads(out)
        assert result["started"] and result["converged"], result


#: the robot's DSP stops a velocity command after this many 10-ms cycles without one (robot_sim.yaml), and brakes
#: at its emergency deceleration from at most 0.2 m/s; the state is published every 10 ms
REST_BUDGET_S = 0.5
#: an observer on the robot's computer hears every state within this of its stamp, whatever happens to safety's link
HEARD_WITHIN_S = 1.0
#: a command older than this is never applied (services/robot/admission.py)
MAX_COMMAND_AGE_S = 0.2


def test_a_cable_pulled_mid_motion_stops_the_arm_and_nothing_stale_moves_it_after(tmp_path):
    with netns.Lab(HOSTS) as lab, _stack_across(lab, tmp_path) as env:
        endpoint = f"tcp/{lab.address('robot')}:7447"
        # to a file, not a pipe: a pipe nobody reads until the end fills in ~2.5 s and blocks the observer's
        # callbacks, which then hears everything seconds late (it once passed for the router holding traffic back)
        heard = tmp_path / "observer.jsonl"
        with open(heard, "w") as out_file:
            observer = subprocess.Popen(lab.command("robot", [sys.executable, "-c", OBSERVER, endpoint, "120"]),
                                        stdin=subprocess.PIPE, stdout=out_file, stderr=subprocess.PIPE, text=True,
                                        env=env("robot"), cwd=REPO)
        operator = _operator(lab, env, 35)
        time.sleep(2.5)  # the task is under way: the arm moves
        cut_ns = time.time_ns()
        lab.link("safety", up=False)
        time.sleep(2.0)
        heal_ns = time.time_ns()
        lab.link("safety", up=True)
        out, err = operator.communicate(timeout=90)
        observer.communicate(timeout=30)  # it heard the whole task: its input closes, it leaves
        states = [json.loads(line) for line in heard.read_text().splitlines()]
    assert out, err
    result = json.loads(out)
    # the router holds nobody's traffic behind the dead link: on the robot's computer the states are heard as they
    # are published, cable out or not (7 ms at most in one run; a generous bound for a busy 2-core host)
    assert max((s["wall"] - s["stamp"]) * 1e-9 for s in states) < HEARD_WITHIN_S
    # judged on the arm's own clock (the states' stamps)
    moving = [s for s in states if s["stamp"] < cut_ns and s["dq"] > 0.02]
    assert moving, "the arm was not moving when the cable was pulled"
    during = [s for s in states if cut_ns + REST_BUDGET_S * 1e9 <= s["stamp"] < heal_ns]
    assert during and max(s["dq"] for s in during) < 1e-3, "the arm kept moving without safety"
    rest = next(s for s in states if s["stamp"] >= cut_ns and s["dq"] < 1e-3)
    assert (rest["stamp"] - cut_ns) * 1e-9 < REST_BUDGET_S
    # nothing the link held back moves the arm after it heals: every command applied is fresh at the tick that
    # applied it (the robot's hop; the state reporting it is stamped up to a DSP cycle later)
    applied = [s for s in states if s["applied_stamp"]]
    assert max((s["applied_at"] - s["applied_stamp"]) * 1e-9 for s in applied) <= MAX_COMMAND_AGE_S
    # what safety sent into the dead link arrives when TCP gets through again: only the last of it, stamped within the
    # admission's age of the heal, may be fresh enough to apply then (a CI run applied one, a stop, arm at rest)
    held = [s for s in applied if cut_ns + 0.1e9 < s["applied_stamp"] < heal_ns - MAX_COMMAND_AGE_S * 1e9]
    assert not held, "a command held back by the dead link applied after it healed"
    # no jump: the end effector's speed stays within the DSP's limit (0.2 m/s) all along
    xyz = np.array([s["xyz"] for s in states])
    t = np.array([s["stamp"] for s in states]) * 1e-9
    assert (np.linalg.norm(np.diff(xyz, axis=0), axis=1) / np.maximum(np.diff(t), 1e-3)).max() < 0.2 * 1.1
    # and the task goes on once safety is back: it converges, or the controller says why not
    assert result["started"] and (result["converged"] or result["last_status"] != "converging"), result
