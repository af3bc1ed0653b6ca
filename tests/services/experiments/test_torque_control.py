"""``mfvs experiment torque-control`` (services/experiments/torque_control.py): the JACO thesis's chapter 5 in realtime,
each controller a process of its own against a real robot process (robot_sim, real MuJoCo) on a real router.

The CI runs the quick form (a 3 s reference over 3/16 of the thesis's motion: the same speeds) on one controller
of each kind (``--runs``: the task-space PID, the joint PD, the joint-velocity law; about 22 s) and checks its JSON
and each one's tracking against a bound stated here; the quick form of all five (the two null-space variants of
the task-space law added, about 35 s) and the whole experiment (about 3.5 minutes an arm) are ``slow``."""
import json
import subprocess
import sys

import pytest

from services.experiments.torque_control import NAME, kept_time
from services.model.arm import arm_names
from tests.helpers import REPO

#: the arms described (services/model/arms): an unknown arm's refusal lists them, whichever there are
KNOWN = ", ".join(arm_names())

#: each controller's bound on the quick run (position and orientation: the worst over the run; joint-pd: the
#: worst and RMS error of the big joints 1-3 and of the wrist 4-6 on ±20° of eq. 5.3, which its PD without
#: feed-forward follows with a lag). The wrist barely tracks: Table 5.3's gains through the links-only M̂ against
#: its Coulomb friction, and, since the arm's gravity is off after Table 5.1, the hand's extra weight the model
#: misses (0.9 N·m at joint 4): a joint that did not move at all would be 20° off at worst and 14.1° RMS, so its
#: bound says only that it stays bounded. Measured with the data sheets' actuators after Table 5.1's setup on the
#: 2-core machine: jt-pid 6.8-9.0 mm / 3.1°, null-space 2.2-4.7 mm / 3.1-3.9°, null-space-mass 8.9 mm / 3.1°,
#: joint-pd joints 1-3 15.8° worst and 8.5° RMS, wrist 20.9° worst and 13.4° RMS, joint-velocity 0.65-0.69 mm /
#: 10.9°; the bounds leave room for a host that is late
QUICK_BOUNDS = {
    "jt-pid": {"position_mm": 15.0, "orientation_deg": 6.0},
    "null-space": {"position_mm": 8.0, "orientation_deg": 6.0},
    "null-space-mass": {"position_mm": 15.0, "orientation_deg": 6.0},
    "joint-pd": {"joint_deg": (18.0, 25.0), "joint_rms_deg": (10.0, 15.0)},  # (joints 1-3, the wrist)
    "joint-velocity": {"position_mm": 3.0, "orientation_deg": 16.0},
}


#: the quick runs the CI makes: one of each kind of law (task space, joint space, joint velocity)
QUICK_IN_CI = ["jt-pid", "joint-pd", "joint-velocity"]


def mfvs(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "services.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=timeout)


def quick_run(out, labels: list[str]):
    done = mfvs("experiment", NAME, "--quick", "--runs", ",".join(labels), "--json", "--out", str(out))
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout), out, done.stderr


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    return quick_run(tmp_path_factory.mktemp("torque-quick"), QUICK_IN_CI)


def test_the_quick_experiment_prints_one_json_object_with_every_run(quick):
    output, out, progress = quick
    assert output["experiment"] == NAME and output["seed"] == "003" and output["arm"] == "j2n6s300"
    assert [row["label"] for row in output["runs"]] == QUICK_IN_CI
    for row in output["runs"]:
        for key in ("label", "law", "letter", "status", "converged", "iterations", "final_error_norm", "failure",
                    "position_mm", "orientation_deg", "saturation_s", "saturation_robot_s", "missed_cycles",
                    "robot_watchdog", "safety_stops", "torque_setup", "timing", "plots"):
            assert key in row, (row["label"], key)
        assert set(row["position_mm"]) == {"rms", "max", "final"}
        timing = row["timing"]
        assert timing["missed"] == timing["late"] + timing["superseded"] + timing["unseen"]
        assert row["robot_counters"] and row["robot_bus_hz"] > 0  # the robot's own counters, from its health
        assert row["plots"] and all((out / p).is_file() for p in row["plots"])
    summary = output["summary"]
    assert summary["target"]["kind"] == "thesis" and summary["target"]["reachable"]  # 3/16 of the motion
    assert {obs["verdict"] for obs in summary["observations"]} <= {"agrees", "does not", "cannot tell"}
    assert summary["model"]["model_over_arm"][-1] < 0.1  # the links alone: joint 6's rotor inertia unknown
    report = (out / "report.md").read_text()
    assert "## The thesis beside the measurements" in report and "jt-pid" in report
    assert all((out / p).is_file() for p in output["plots"])
    assert "joint-velocity" in progress  # a line per run on stderr with --json


@pytest.mark.parametrize("label", QUICK_IN_CI)
def test_each_controller_tracks_within_its_bound(quick, label):
    """Each controller, a process answering the 500 Hz low-level states, runs to its end (no abort, no torque at
    a limit) and tracks within its bound; late and missed cycles are counted, not turned into motion.

    Where the host did not keep the loop's time (more than MAX_MISSED_FRACTION of the cycles missed: a slower
    host, or one busy with other programs), the figures measure the host as much as the controller (the
    joint-velocity law's high-gain velocity loop saturates its torques then): the report must say so, and the
    bounds, which are the controller's, are not judged on them."""
    check_tracking(*quick[:2], label)


@pytest.mark.slow
def test_the_quick_form_of_all_five_tracks_within_their_bounds(tmp_path):
    output, out, _ = quick_run(tmp_path, list(QUICK_BOUNDS))
    assert [row["label"] for row in output["runs"]] == list(QUICK_BOUNDS)
    for label in QUICK_BOUNDS:
        check_tracking(output, out, label)


def check_tracking(output: dict, out, label: str) -> None:
    row = next(r for r in output["runs"] if r["label"] == label)
    bound = QUICK_BOUNDS[label]
    assert row["host_kept_time"] == kept_time(row["timing"], row["robot_counters"])
    assert row["torque_setup"] and len(row["torque_setup"]["applied"]) == 6  # each run made Table 5.1's setup
    if not row["host_kept_time"]:
        assert "this host did not keep the loop's time" in (out / "report.md").read_text().lower()
        print(f"{label}: the host missed {row['missed_cycles']} of {row['timing']['received']} cycles, the emulated "
              f"arm {row['robot_counters'].get('cycles.missed')} of its own: its bounds not judged (saturated "
              f"{row['saturation_s']} s)")
        return
    assert row["status"] == "completed", row["failure"]
    assert row["iterations"] > 1000  # about 2000 states in 4 s at 500 Hz; a loaded host answers fewer
    assert row["saturation_s"] == 0.0
    assert row["safety_stops"] == 0  # Table 5.1's safety factor 1: the arm never left torque control
    if "joint_deg" in bound:
        errors = row["joint_error_deg"]
        for part, joints in enumerate((slice(0, 3), slice(3, None))):
            assert max(errors["max"][joints]) < bound["joint_deg"][part], errors
            assert max(errors["rms"][joints]) < bound["joint_rms_deg"][part], errors
    else:
        assert row["position_mm"]["max"] < bound["position_mm"], row["position_mm"]
        assert row["orientation_deg"]["max"] < bound["orientation_deg"], row["orientation_deg"]
    print(f"{label}: position {row['position_mm']} mm, orientation {row['orientation_deg']}°, missed "
          f"{row['missed_cycles']} of {row['timing']['answered']}, robot watchdog {row['robot_watchdog']}")


@pytest.mark.parametrize("args, message", [
    (["--arm", "j2x9"], f"unknown arm 'j2x9'; known: {KNOWN}"),
    (["--scenario", "examples/scenarios/table2.yaml"], "torque-control takes no --scenario"),
    (["--profile", "hardware"], "unknown profile 'hardware'"),
    (["--quick", "--runs", "jt-pid,nope"], "torque-control --quick has no run 'nope'; its runs: jt-pid, "),
])
def test_bad_input_is_one_line_and_exit_2(args, message):
    done = mfvs("experiment", NAME, *args, timeout=60)
    assert done.returncode == 2 and message in done.stderr and len(done.stderr.strip().splitlines()) == 1


@pytest.mark.slow
@pytest.mark.parametrize("arm", ["j2n6s300", "j2s7s300"])
def test_the_whole_experiment_on_each_arm(tmp_path, arm):
    """The experiment as the issue runs it: every run completes after Table 5.1's setup, never stopped by the
    safety factor; on the thesis's arm the null space improves the position over the transpose, as the thesis
    found, and joint 6 follows better at Table 5.3's far higher gain than at joint 1's, best with the rotors'
    inertia in M̂ (the wrist's Coulomb friction keeps it from following well at either: docs/torque.md)."""
    done = mfvs("experiment", NAME, "--arm", arm, "--json", "--out", str(tmp_path), timeout=900)
    assert done.returncode == 0, done.stderr[-2000:]
    output = json.loads(done.stdout)
    assert all(row["status"] == "completed" for row in output["runs"]), [r["failure"] for r in output["runs"]]
    assert all(row["safety_stops"] == 0 and row["torque_setup"] for row in output["runs"])
    verdicts = {obs["id"]: obs["verdict"] for obs in output["summary"]["observations"]}
    if arm == "j2n6s300":
        assert verdicts["null_space_improves_position"] == "agrees"
        rows = {row["label"]: row for row in output["runs"]}
        last = {label: rows[label]["joint_error_deg"]["rms"][-1]
                for label in ("joint-pd", "joint-pd-last-low", "joint-pd-last-low-rotors")}
        assert last["joint-pd-last-low-rotors"] < last["joint-pd"] < last["joint-pd-last-low"], last
        assert not output["summary"]["target"]["reachable"]  # eq. 5.2's Xf: a few mm out of reach
    assert (tmp_path / "report.md").is_file()
