"""The soak's judge (bench/soak.py): each unsafe event it must see, and a clean run it must pass."""
import random


import pytest
import yaml

from bench.soak import (ACROSS_HOSTS_KINDS, HOSTS, KIND_WEIGHTS, REST_S, AcrossHosts, Judge, OneHost, StateRecord,
                        Window, applicable_kinds, check_kinds, goal_features, hosts_profile)
from services.stack.launcher import Profile, profile_arm
from services.runtime.authority import write_deployment
from services.runtime.config import load_config
from services.tools import netns
from services.robot.admission import AdmissionConfig
from services.robot.dsp import DSPConfig

MS = 1_000_000


def records(speeds, applied_age_ms=10, start_ns=10**18):
    """States every 10 ms at these end-effector speeds, each applying a command ``applied_age_ms`` old."""
    return [StateRecord(stamp_ns=start_ns + i * 10 * MS, heard_ns=start_ns + i * 10 * MS + MS, linear_mps=v,
                        joint_ratio=0.3, linear_limit_mps=0.2,
                        applied_stamp_ns=start_ns + (i * 10 - applied_age_ms) * MS)
            for i, v in enumerate(speeds)]


def judged(states, **extra):
    judge = Judge.for_robot(AdmissionConfig(), DSPConfig())
    for record in states:
        judge.state(record)
    for name, value in extra.items():
        setattr(judge, name, value)
    return judge.verdict()


def test_a_clean_run_has_no_unsafe_event():
    verdict = judged(records([0.05] * 100 + [0.0] * 100))
    assert verdict["unsafe_events"] == [] and verdict["lost_state_events"] == 0


def test_a_speed_over_the_limit_is_one_event_however_long_it_lasts():
    verdict = judged(records([0.1] * 10 + [0.25] * 5 + [0.1] * 10))
    assert [e["rule"] for e in verdict["unsafe_events"]] == ["speed over the limit"]


def test_a_command_older_than_the_robot_admits_is_a_stale_command_applied():
    verdict = judged(records([0.05] * 20, applied_age_ms=400))
    assert [e["rule"] for e in verdict["unsafe_events"]] == ["stale command applied"]
    # the admission's limit plus the DSP's watchdog hold is not
    assert judged(records([0.05] * 20, applied_age_ms=200 + 20))["unsafe_events"] == []


def test_an_injected_command_applied_is_unsafe():
    states = records([0.05] * 20)
    verdict = judged(states, injected_stamps={states[7].applied_stamp_ns})
    assert [e["rule"] for e in verdict["unsafe_events"]] == ["injected command applied"]


def test_motion_after_the_rest_budget_of_a_cut_is_unsafe_and_braking_within_it_is_not():
    start = 10**18
    braking = records([0.1] * 10 + [0.05] * 20 + [0.0] * 70, start_ns=start)
    cut = Window("safety killed", start + 100 * MS, start + 900 * MS)
    assert judged(braking, rest_windows=[cut])["unsafe_events"] == []
    creeping = records([0.1] * 10 + [0.002] * 90, start_ns=start)
    events = judged(creeping, rest_windows=[cut])["unsafe_events"]
    assert [e["rule"] for e in events] == ["motion after safety killed"]
    # what moves after the window ended (the path is whole again) is not judged by it
    moving_after = records([0.0] * 100 + [0.1] * 50, start_ns=start)
    assert judged(moving_after, rest_windows=[Window("the e-stop", start, start + 990 * MS)])["unsafe_events"] == []
    assert REST_S < 0.9


def test_gaps_in_the_states_heard_are_lost_state_not_unsafe():
    states = records([0.0] * 50)
    del states[20:40]
    verdict = judged(states)
    assert verdict["lost_state_events"] == 1 and verdict["unsafe_events"] == []
    assert abs(verdict["lost_state_longest_s"] - 0.21) < 1e-6


def test_goals_are_the_tag_square_at_a_reachable_depth():
    rng = random.Random(4)
    for _ in range(50):
        corners, depth = goal_features(rng)
        assert 0.25 <= depth <= 0.40 and len(corners) == 4
        side = ((corners[1][0] - corners[0][0]) ** 2 + (corners[1][1] - corners[0][1]) ** 2) ** 0.5
        assert abs(side * depth - 2 * 0.0481) < 1e-9


def test_cables_are_pulled_only_across_hosts():
    assert "cable" not in applicable_kinds(OneHost())
    lab = netns.Lab(list(HOSTS), tag="unit")  # not entered: nothing is created
    across = AcrossHosts(lab, {host: None for host in HOSTS}, {})
    assert applicable_kinds(across) == list(KIND_WEIGHTS) and across.cable_hosts == HOSTS
    with pytest.raises(ValueError, match="--hosts"):
        check_kinds(list(ACROSS_HOSTS_KINDS), hosts=False)
    with pytest.raises(ValueError, match="unknown"):
        check_kinds(["kill", "meteor"], hosts=True)
    check_kinds(["cable", "kill"], hosts=True)


def test_the_hosts_profile_is_the_shipped_one_filled_in(tmp_path):
    lab = netns.Lab(list(HOSTS), tag="unit")
    deployment = write_deployment(tmp_path / "authority", host=lab.address("robot"),
                                  services=("safety", "robot_sim", "vision", "controller", "operator"))
    hosts_of = hosts_profile(tmp_path / "p.yaml", lab, deployment, tmp_path / "faults",
                             ["robot_sim:dsp.watchdog_cycles=500"], arm="j2n6s300")
    assert hosts_of == {"router": "robot", "robot_sim": "robot", "vision": "vision", "controller": "vision",
                        "safety": "safety"}
    profile = yaml.safe_load((tmp_path / "p.yaml").read_text())
    assert profile["router"]["address"] == lab.address("robot")
    robot_sim = next(s for s in profile["services"] if s["name"] == "robot_sim")
    assert robot_sim["set"] == [f"faults_file={tmp_path / 'faults' / 'robot_sim.yaml'}", "dsp.watchdog_cycles=500",
                                "arm=j2n6s300"]
    # the whole stack on the arm asked for (`mfvs up` refuses a profile that mixes arms)
    assert profile_arm(load_config(tmp_path / "p.yaml", Profile)) == "j2n6s300"
    assert robot_sim["zenoh_config"] == str(deployment.client_configs["robot_sim"])
    with pytest.raises(ValueError, match="no service called"):
        hosts_profile(tmp_path / "q.yaml", lab, deployment, tmp_path / "faults", ["camera:x=1"])
