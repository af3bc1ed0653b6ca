"""bench/stack.py and the benchmarks on an arm: `mfvs bench NAME --arm ARM`: every benchmark on an arm takes it as every command does (an unknown arm: one line,
exit 2, nothing started), and the helpers they share (bench/stack.py)."""
import importlib
import json
import subprocess
import sys

import pytest

from bench.stack import detail_fields, measured_arm, profile_on_arm
from bench.swap import SCENARIOS, shipped_for
from services.cli.commands import BENCHMARKS
from services.model.arm import arm_names
from services.stack.launcher import profile_arm
from services.paths import REPO

#: the benchmarks whose figures do not depend on the arm: vision times detection on rendered frames of the tag
ARMLESS = {"vision"}
ON_AN_ARM = sorted(set(BENCHMARKS) - ARMLESS)
#: the arms described (services/model/arms): an unknown arm's refusal lists them, whichever there are
KNOWN = ", ".join(arm_names())


@pytest.mark.parametrize("name", ON_AN_ARM)
def test_an_unknown_arm_is_one_line_and_exit_2_before_anything_starts(name, capsys):
    module = importlib.import_module(BENCHMARKS[name])
    assert module.main(["--arm", "j2n9s300"]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == f"mfvs bench {name}: unknown arm 'j2n9s300'; known: {KNOWN}\n"


def test_the_command_line_passes_the_arm_to_the_benchmark():
    out = subprocess.run([sys.executable, "-m", "services.cli", "bench", "lowlevel", "--arm", "j2n9s300"],
                         capture_output=True, text=True, cwd=REPO, timeout=60)
    assert out.returncode == 2 and out.stderr.strip().splitlines() == [
        f"mfvs bench lowlevel: unknown arm 'j2n9s300'; known: {KNOWN}"]


def test_a_benchmark_s_stack_runs_the_arm_asked_for():
    for name in ("sim", "gateway"):
        assert profile_arm(profile_on_arm(name, "j2n6s300")) == "j2n6s300"
        assert profile_arm(profile_on_arm(name, "j2s7s300")) == "j2s7s300"


def test_the_arm_measured_is_the_one_the_robot_declared():
    assert measured_arm("j2n6s300", ["j2n6s300", "j2n6s300"]) == "j2n6s300"
    with pytest.raises(RuntimeError, match="declared the j2s7s300, not the j2n6s300"):
        measured_arm("j2n6s300", {"j2s7s300"})


def test_detail_fields_read_a_robot_s_health_detail():
    # shapes of a robot node's and of robot_sim's actuators' details (words and parentheses between the fields)
    node = ("arm j2n6s300: 6 actuators on the bus 0x10-0x15; bus_rate_hz=499.8 late_per_s=0.0 missed_per_s=0.0 "
            "work_ms=0.25/0.60 wake_lag_ms=0.03/0.31 (p50/p99)")
    assert detail_fields(node) == {"bus_rate_hz": "499.8", "late_per_s": "0.0", "missed_per_s": "0.0",
                                   "work_ms": "0.25/0.60", "wake_lag_ms": "0.03/0.31"}
    actuators = ("sim_time_s=12.000 bus_cycle_rate_hz=499.7 jitter_ms_p99=0.13 host_phase_error_ms_p50=0.02 "
                 "p99=0.30 camera_trigger_ms=2 (auto, from 0-8)")
    assert detail_fields(actuators)["bus_cycle_rate_hz"] == "499.7"
    assert detail_fields(None) == {}


def test_swap_on_an_arm_takes_the_shipped_scenarios_that_fit_it(capsys):
    fit, left = shipped_for("j2n6s300")
    assert SCENARIOS / "table2.yaml" in fit and SCENARIOS / "part_b_j2n6s300.yaml" in fit
    assert SCENARIOS / "part_b.yaml" in left  # it starts the 7-DoF at seven angles of its own
    assert shipped_for(None)[1] == []
    swap = importlib.import_module("bench.swap")
    assert swap.main(["--arm", "j2n6s300", "--scenario", str(SCENARIOS / "part_b.yaml")]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith("mfvs bench swap: ") and "not a start for the j2n6s300" in err


def test_laws_report_the_arm_they_ran_on(capsys):
    laws = importlib.import_module("bench.laws")
    assert laws.main(["--json", "--arm", "j2n6s300", "--iterations", "5", "--rounds", "1"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["arm"] == "j2n6s300" and set(result["laws"]) >= {"adaptive-pd-mixed", "smc"}
