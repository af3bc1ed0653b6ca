"""bench lowlevel: a short run on each arm and profile gives every figure (timing is the benchmark's to print, not
the test's to bound)."""
import json
import math

import pytest

from bench.lowlevel import COUNTERS, main


def _stats_complete(figures: dict) -> bool:
    return figures["n"] > 0 and all(math.isfinite(figures[k]) for k in ("p50", "p99", "max"))


@pytest.mark.parametrize("profile, arm, joints", [("sim", "j2n6s300", 6), ("gateway", "j2s7s300", 7)])
def test_a_short_run_reports_every_figure_of_the_loop(profile, arm, joints, capsys):
    assert main(["--json", "--seconds", "1.5", "--profile", profile, "--arm", arm]) == 0
    result = json.loads(capsys.readouterr().out)
    assert (result["arm"], result["joints"], result["profile"]) == (arm, joints, profile)
    states, client, loop = result["states"], result["client"], result["loop"]
    assert states["n"] > 100 and states["rate_hz"] > 0
    assert _stats_complete(states["period_ms"]) and _stats_complete(states["jitter_ms"])
    assert states["lost"] >= 0 and states["arm_cycles_without_exchange"] >= 0
    assert states["torque_mode_share"] > 0.5  # the client's torques put the joints in torque mode
    assert states["drift_deg_max"] < 5.0  # and the arm held (the robot's gravity and the client's light hold)
    assert client["commands"] > 100 and client["slots_skipped"] >= 0 and _stats_complete(client["send_jitter_ms"])
    assert _stats_complete(client["command_to_state_ms"]) and client["command_to_state_ms"]["p50"] > 0
    assert loop["bus_rate_hz"] > 0 and loop["lowlevel_state_hz"] > 0
    assert loop["wake_lag_ms"]["p99"] is not None and loop["work_ms"]["p99"] is not None
    assert set(loop["counters"]) >= set(COUNTERS) and all(v >= 0 for v in loop["counters"].values())
    if profile == "gateway":
        assert result["robot"] == "robot_gateway" and result["actuators"]["cycle_rate_hz"] > 0
    else:
        assert result["robot"] == "robot_sim" and result["actuators"] is None
