"""Sensors 2022's experiments by command (services/experiments/registry.py, ``mfvs experiment``): each through the real
services in lockstep, reported in one JSON shape beside the paper. Table 3 runs whole in the default run (its ordering and
the mixed law's advantage are the point); the slow tests rerun experiments to check they repeat to the bit."""
import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from bench.hogs import cpu_hogs
from services.experiments.mixed_frame import TABLE3_PAPER
from services.experiments.registry import EXPERIMENTS, run_experiment
from services.experiments.spec import improvement_pct, straightness
from services.paths import SCENARIOS

MFVS = str(Path(sys.executable).parent / "mfvs")
ROW_KEYS = {"label", "law", "converged", "iterations", "status", "final_error_norm", "failure", "limits_met",
            "min_zone_distance_m", "straightness", "detail"}


def shortened(scenario_file: str, tmp_path: Path, max_iterations: int) -> Path:
    """A copy of a shipped scenario that stops after ``max_iterations`` (the default test run's quick checks)."""
    scenario = yaml.safe_load((SCENARIOS / scenario_file).read_text())
    scenario["convergence"]["max_iterations"] = max_iterations
    path = tmp_path / f"short_{scenario_file}"
    path.write_text(yaml.safe_dump(scenario))
    return path


def check_shape(output: dict, name: str) -> None:
    assert output["experiment"] == name and isinstance(output["summary"], dict)
    assert output["repeatable"] and all(row["lockstep_timeouts"] == 0 for row in output["runs"])
    assert [row["label"] for row in output["runs"]] == [spec.label for spec in EXPERIMENTS[name].runs]
    for row in output["runs"]:
        assert ROW_KEYS <= set(row)


def test_table3_in_the_papers_order_with_the_mixed_law_a_quarter_faster(tmp_path):
    """`mfvs experiment table3 --json`: the four laws with Table 3's gains from one start, in the paper's order
    (446 > 189 > 114 > 79) and the proposed law at least 25 % fewer iterations than the joint PD law (paper 31 %);
    the report and figures are written."""
    out = subprocess.run([MFVS, "experiment", "table3", "--json", "--out", str(tmp_path)], capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    output = json.loads(out.stdout.strip().splitlines()[-1])
    check_shape(output, "table3")
    summary = output["summary"]
    assert all(row["converged"] for row in output["runs"])
    assert summary["in_paper_order"], summary["iterations"]
    assert summary["improvement_pct"] >= 25.0, summary
    assert summary["paper_iterations"] == TABLE3_PAPER and summary["paper_improvement_pct"] == 30.7
    report = (tmp_path / "report.md").read_text()
    assert "| adaptive-pd-mixed |" in report and "![errors](errors.png)" in report
    assert (tmp_path / "errors.png").stat().st_size > 1000
    assert all((tmp_path / law / "error.png").exists() for law in TABLE3_PAPER)
    assert "adaptive-pd-mixed" in out.stderr  # a line per run, on stderr with --json


def part_a_by_command(jobs: int, out: Path) -> dict:
    done = subprocess.run([MFVS, "experiment", "part-a", "--json", "--jobs", str(jobs), "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def part_a_alone(tmp_path_factory) -> tuple[dict, Path]:
    """`mfvs experiment part-a --json --jobs 1` on a quiet host: one run the tests below share."""
    out = tmp_path_factory.mktemp("part-a-alone")
    return part_a_by_command(1, out), out


def _side_by_side_logs_exactly_what_one_run_at_a_time_logs(part_a_alone, tmp_path, hogs: int) -> None:
    """`--jobs 2` (each run on a stack of its own, two at a time) with ``hogs`` CPU hogs beside them against
    `--jobs 1` on a quiet host: every trajectory log the same byte for byte, the runs in the experiment's order
    (issue 35)."""
    alone, alone_dir = part_a_alone
    with cpu_hogs(hogs):
        side_by_side = part_a_by_command(2, tmp_path / "side_by_side")
    check_shape(side_by_side, "part-a")
    labels = [spec.label for spec in EXPERIMENTS["part-a"].runs]
    for label in labels:
        assert (alone_dir / label / "trajectory.jsonl").read_bytes() == \
            (tmp_path / "side_by_side" / label / "trajectory.jsonl").read_bytes(), label

    def numbers(output: dict) -> list:
        return [{k: v for k, v in row.items() if k != "plots"} for row in output["runs"]]
    assert numbers(side_by_side) == numbers(alone) and side_by_side["summary"] == alone["summary"]


def test_runs_side_by_side_log_exactly_what_one_run_at_a_time_logs(part_a_alone, tmp_path):
    _side_by_side_logs_exactly_what_one_run_at_a_time_logs(part_a_alone, tmp_path, hogs=0)


@pytest.mark.slow
def test_runs_side_by_side_and_beside_cpu_hogs_log_exactly_what_one_run_at_a_time_logs(part_a_alone, tmp_path):
    """The same beside two CPU hogs: slow (a run shares its core with a hog: 37 s at 0.65 of a core); the lockstep
    runs' independence of the host's load is also checked run to run by
    tests/services/servo/test_run.py::test_lockstep_is_bit_identical_run_to_run_composed_as_processes_and_through_the_gateway."""
    _side_by_side_logs_exactly_what_one_run_at_a_time_logs(part_a_alone, tmp_path, hogs=2)


def test_part_a_the_end_effector_twist_fails_where_the_mixed_one_converges(part_a_alone):
    output, _ = part_a_alone
    check_shape(output, "part-a")
    summary = output["summary"]
    assert summary["as_in_paper"] and summary["ee_frame_tag_left_image"] and summary["ee_frame_error_growth"] > 1.0
    ee = output["runs"][0]
    assert ee["failure"] in ("target_lost", "diverged") and "target was lost" in ee["detail"]


def test_part_d_the_joint_space_realisation_converges_and_is_reported_beside_the_mixed_twist():
    """Part D converges; whether it is slower than the mixed twist (the paper: 154 against 79) is reported, not
    asserted: on the emulated arm the two take about as many iterations (122 and 118 on one machine, 122 and 125
    on another: the SIMD paths of OpenCV and MuJoCo differ between CPUs), and the summary says which."""
    output = run_experiment("part-d")
    check_shape(output, "part-d")
    summary = output["summary"]
    assert summary["converged"] and summary["straightness"] >= 1.0
    assert summary["slower_than_mixed"] == (summary["iterations"] > summary["mixed_iterations"])
    assert abs(summary["iterations"] - summary["mixed_iterations"]) <= 0.2 * summary["mixed_iterations"]


def test_part_c_the_mixed_law_glides_along_the_zone_the_joint_law_is_stopped_at():
    """Near the base the corners' straight image paths pull the camera back into the protection zone: the mixed law
    converges along the zone's face (the DSP removes the motion into it; the end effector never enters), the joint
    law's motion into the zone is refused by safety, and the run reports the zone as its failure."""
    output = run_experiment("part-c")
    check_shape(output, "part-c")
    joint, mixed = output["runs"]
    assert output["summary"]["as_in_paper"]
    assert joint["failure"] == "zone" and "zone" in joint["detail"]
    assert mixed["converged"] and mixed["limits_met"].get("zone", 0) > 0
    assert 0.0 <= mixed["min_zone_distance_m"] < 0.05 and joint["min_zone_distance_m"] >= 0.0
    assert mixed["straightness"] > 1.1  # the corners take a curved route (from table2.yaml: 1.02)


def test_part_b_near_the_edge_of_the_workspace_the_mixed_law_converges_smoothly():
    """The outstretched start: the goal lies near the end of the arm's reach (manipulability under 0.01). As seed
    000 saw on the real arm, the mixed law's error decays smoothly there: the arm's DSP keeps the law's direction
    (issue 34) and, the arm not truly at a singularity, resolves the motion without damping; its redundancy leans
    away from the singularity meanwhile. The joint law's failure on the real arm is not reproduced
    (docs/robot.md); the summary says whether it was."""
    errors: list[float] = []
    output = run_experiment("part-b", on_iteration=lambda label, scenario, record: errors.append(record.error_norm)
                            if label == "adaptive-pd-mixed" else None)
    check_shape(output, "part-b")
    joint, mixed = output["runs"]
    assert mixed["converged"] and "singularity" not in mixed["limits_met"]
    assert mixed["limits_met"].get("singularity_avoidance", 0) > 0
    assert max(joint["min_manipulability"], mixed["min_manipulability"]) < 0.01
    assert output["summary"]["as_in_paper"] is (mixed["converged"] and not joint["converged"])
    approach = [e for e in errors if e > 10 * 5e-5]  # before the creep under the dead-band at the noise floor
    assert all(later <= 1.02 * earlier for earlier, later in zip(approach, approach[1:])), approach


def test_table3_over_random_starts_runs_every_law_on_each_start_and_writes_the_starts(tmp_path):
    """`mfvs experiment table3 --random-starts N --json`: each run carries its start, the summary has each law's
    quartiles and failures and per start the mixed law's improvement; each start is a scenario file that runs
    again with --scenario."""
    base = shortened("table2.yaml", tmp_path, 25)
    out = subprocess.run([MFVS, "experiment", "table3", "--random-starts", "1", "--seed", "5", "--scenario",
                          str(base), "--json", "--out", str(tmp_path / "out")], capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    output = json.loads(out.stdout.strip().splitlines()[-1])
    assert [row["law"] for row in output["runs"]] == list(TABLE3_PAPER)
    start = output["runs"][0]["start"]
    assert all(row["start"] == start for row in output["runs"]) and start["seed"] == 5 and start["index"] == 0
    summary = output["summary"]
    assert summary["starts"] == 1 and set(summary["laws"]) == set(TABLE3_PAPER)
    assert summary["proposed_failures"] == 1 and summary["laws"]["p-joint"]["failures"] == {"max_iterations": 1}
    assert summary["not_clearly_faster"][0]["index"] == 0  # none converged in 25 iterations: what shaped them
    assert (tmp_path / "out" / "random_starts.png").stat().st_size > 1000
    assert "| start |" in (tmp_path / "out" / "report.md").read_text()
    again = run_experiment("table3", start["scenario"])
    assert [row["iterations"] for row in again["runs"]] == [row["iterations"] for row in output["runs"]]
    refused = subprocess.run([MFVS, "experiment", "part-b", "--random-starts", "2"], capture_output=True, text=True,
                             timeout=60)
    assert refused.returncode == 2 and "--random-starts is for table3" in refused.stderr


def test_a_start_where_the_tag_is_never_seen_reports_no_error_and_says_why(tmp_path):
    """final_error_norm is null, not 0.0; the detail names the cause; no empty figures are written."""
    scenario = tmp_path / "unseen.yaml"
    scenario.write_text("target: {pose_in_camera: {xyz: [2.0, 0.0, 0.5], rpy_deg: [180, 0, 0]}}\n"
                        "convergence: {max_iterations: 30}\ntarget_lost_iterations: 5\n")
    output = run_experiment("part-d", scenario, tmp_path / "out")
    for row in output["runs"]:
        assert row["final_error_norm"] is None and not row["converged"]
        assert "never seen" in row["detail"] and "target.pose_in_camera" in row["detail"]
        assert row["plots"] == []
    assert output["plots"] == [] and (tmp_path / "out" / "report.md").exists()


def test_experiment_arguments_are_checked():
    out = subprocess.run([MFVS, "experiment", "table4"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "unknown experiment 'table4'" in out.stderr
    out = subprocess.run([MFVS, "experiment", "table3", "--scenario", "/nonexistent.yaml"], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 2 and "nonexistent" in out.stderr
    for command in (["experiment", "table3"], ["demo"]):
        out = subprocess.run([MFVS, *command, "--jobs", "0"], capture_output=True, text=True, timeout=60)
        assert out.returncode == 2 and "--jobs must be at least 1, not 0" in out.stderr


def test_the_summary_figures():
    assert improvement_pct(79, 114) == 30.7 and improvement_pct(None, 114) is None
    line = [{"points": [[0.1 * k, 0.0]] * 4} for k in range(5)]
    assert straightness(line) == 1.0
    detour = [{"points": [[x, y]] * 4} for x, y in ((0, 0), (1, 1), (2, 0))]
    assert straightness(detour) == pytest.approx(2 ** 0.5, rel=1e-3)


@pytest.mark.slow
def test_mfvs_demo_runs_part_a_and_table3_and_says_where_to_look(tmp_path):
    out = subprocess.run([MFVS, "demo", "--out", str(tmp_path)], capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    assert (tmp_path / "part-a" / "report.md").exists() and (tmp_path / "table3" / "report.md").exists()
    assert str(tmp_path / "table3" / "report.md") in out.stdout and out.stdout.count("iterations") >= 6


@pytest.mark.slow
@pytest.mark.parametrize("name", list(EXPERIMENTS))
def test_every_experiment_repeats_to_the_bit(name):
    first, again = run_experiment(name), run_experiment(name)
    assert first["runs"] == again["runs"] and first["summary"] == again["summary"]
