"""The grasp experiment (services/experiments/grasp.py): its placements and their geometry; a whole reach, grasp,
lift, hold and shake through the real services, composed, in lockstep, from the command line; and, marked slow, the
objects that must not be held (nothing, a slippery box) and an emergency stop during the hold."""
import json
import subprocess
import sys

import numpy as np
import pytest

from services.controller.phases import GraspConfig
from services.experiments import grasp
from services.model import frames
from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics
from services.robot_sim.scene import TableConfig
from services.servo.scenario import Scenario, stack_config


@pytest.mark.parametrize("arm_name", ["j2s7s300", "j2n6s300"])
def test_placements_are_seeded_on_the_table_and_reachable_and_the_taught_view_sees_the_card_ahead(arm_name):
    table, config = TableConfig(), GraspConfig()
    drawn = grasp.draw_placements(arm_name, 5, 4, "cup", config, table)
    assert drawn == grasp.draw_placements(arm_name, 5, 4, "cup", config, table)
    assert drawn != grasp.draw_placements(arm_name, 5, 5, "cup", config, table)
    for p in drawn:
        assert grasp.PLACE_X_M[0] <= p["x_m"] <= grasp.PLACE_X_M[1] and abs(p["turn_deg"]) <= grasp.PLACE_TURN_DEG
        scenario = grasp.grasp_scenario(msgspec_replace_arm(Scenario(), arm_name), p, "cup")
        scene = stack_config(scenario).robot.scene
        scene.check(load_arm(arm_name))  # the card on the cup, the arm at its ready pose within its limits
        T_obj = grasp.object_in_base(p, "cup", table)
        assert T_obj[2, 3] == pytest.approx(table.top_z_m + grasp.CUP.height_m / 2)
        assert T_obj[:3, 1] == pytest.approx([0.0, 0.0, 1.0])  # standing
    # the goal: the card straight ahead of the camera, in the middle of the image, at the approach's distance
    view = grasp.taught_view("cup", config, grasp.grasp_camera(config)).matrix()
    card_in_camera = np.linalg.inv(view)
    assert np.linalg.norm(card_in_camera[:2, 3]) < 1e-3
    assert card_in_camera[2, 3] == pytest.approx(config.approach_m + grasp.HOLD_AHEAD_M - grasp.CUP.radius_m
                                                 - grasp.CARD_OFFSET_M + 0.02, abs=0.01)


def msgspec_replace_arm(scenario, arm_name):
    import msgspec

    return msgspec.structs.replace(scenario, robot=msgspec.structs.replace(scenario.robot, arm=arm_name))


def test_the_ready_pose_and_the_grasp_keep_the_joints_well_inside_their_limits():
    for arm_name in ("j2s7s300", "j2n6s300"):
        arm = load_arm(arm_name)
        q = grasp.ready_joints(arm_name, GraspConfig(), TableConfig())
        assert np.min(arm.limit_margins_deg(q), initial=np.inf) > 20.0
        R, p = ArmKinematics(arm).pose(q)
        assert R[:3, 1] @ [0.0, 0.0, 1.0] > 0.999  # the hand upright beside the object: its y up


def run_cli(*args, timeout=600):
    out = subprocess.run([sys.executable, "-m", "services.cli", "experiment", "grasp", "--json", *args],
                         capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


def test_the_arm_reaches_grasps_lifts_holds_and_shakes_a_cup_from_the_command_line(tmp_path):
    result = run_cli("--placements", "1", "--seed", "9", "--object", "cup", "--out", str(tmp_path))
    row = result["runs"][0]
    assert row["grasped"] and row["verdict"] == "grasped" and row["verdict_after_hold"] == "grasped"
    assert row["lifted_m"] >= grasp.LIFTED_M and row["held_s"] >= grasp.HOLD_S - 0.05
    assert row["slip_mm"] < 10.0 and not row["dropped"] and row["shake"]["moves"] == ["done"] * 3
    assert list(row["phases_s"]) == ["servo", "approach", "grasp", "lift", "hold"]
    assert result["summary"]["lifted_and_held"] == 1 and (tmp_path / "grasp.json").is_file()


def test_the_command_line_refuses_what_the_grasp_does_not_take():
    out = subprocess.run([sys.executable, "-m", "services.cli", "experiment", "grasp", "--object", "plane"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "grasp takes --object cup, box, slippery, none" in out.stderr
    out = subprocess.run([sys.executable, "-m", "services.cli", "experiment", "grasp", "--perturb", "swap"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "one --perturb of estop" in out.stderr
    out = subprocess.run([sys.executable, "-m", "services.cli", "experiment", "table3", "--placements", "3"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and "--placements is for grasp" in out.stderr


@pytest.mark.slow
def test_nothing_between_the_fingers_is_empty_and_a_slippery_box_is_caught_slipping():
    empty = run_cli("--placements", "1", "--seed", "9", "--object", "none")["runs"][0]
    assert empty["verdict"] == "empty" and "closed on nothing" in empty["failure"]
    slippery = run_cli("--placements", "1", "--seed", "9", "--object", "slippery")["runs"][0]
    assert slippery["verdict"] == "slipping" and "slipping" in slippery["failure"]


@pytest.mark.slow
def test_an_emergency_stop_during_the_hold_does_not_drop_the_cup():
    row = run_cli("--placements", "1", "--seed", "9", "--object", "cup", "--perturb", "estop")["runs"][0]
    assert row["grasped"] and row["dropped"] is False and row["lifted_m"] >= grasp.LIFTED_M
