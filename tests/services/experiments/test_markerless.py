"""The markerless experiment (services/experiments/markerless.py): its starts, its perturbations, its statistics;
and, marked slow, the experiment itself from the command line."""
import json
import subprocess
import sys

import numpy as np
import pytest

from services.experiments import markerless as mk
from services.experiments.starts import corners_in_image
from services.robot_sim.scene import ObjectKind, target_outline
from services.servo.scenario import stack_config


def test_the_wilson_interval_is_the_textbooks():
    low, high = mk.wilson_interval(95, 100)
    assert low == pytest.approx(0.8882, abs=1e-3) and high == pytest.approx(0.9785, abs=1e-3)
    assert mk.wilson_interval(20, 20)[0] == pytest.approx(0.8389, abs=1e-3) and mk.wilson_interval(0, 0) == (None, None)


@pytest.mark.parametrize("kind", ["plane", "cup"])
def test_starts_keep_the_object_in_view_and_reach_the_goal_pose(kind):
    base = mk.base_scenario(kind, None, None)
    starts = mk.draw_starts(base, 4, seed=3)
    assert [s["index"] for s in starts] == [0, 1, 2, 3] and starts == mk.draw_starts(base, 4, seed=3)
    for start in starts:
        pixels = corners_in_image(mk._pose(start), target_outline(base.target), base.camera)
        assert np.all(pixels >= 10) and np.all(pixels[:, 0] <= 629) and np.all(pixels[:, 1] <= 469)
        teach = mk.teach_scenario(base, start)
        # the arm placed where the camera sees the object as at Table 2's goal
        camera = mk.truth_camera(teach, np.asarray(start["goal_joints"]))
        object_in_base = teach.target.pose_in_base.matrix()
        mm, deg = mk.pose_error(np.linalg.inv(mk.GOAL_IN_CAMERA.matrix()), np.linalg.inv(object_in_base) @ camera)
        assert mm < 1e-3 and deg < 1e-3


def test_the_perturbations_change_the_servos_scene_and_nothing_else(tmp_path):
    base = mk.base_scenario("cup", None, None)
    start = mk.draw_starts(base, 2, seed=1)[1]
    plain = mk.servo_scenario(base, start, tmp_path / "g", ())
    assert plain.objects == [] and plain.light == type(plain.light)() and plain.target.leaves_at_s is None
    all_three = mk.servo_scenario(base, start, tmp_path / "g", ("lighting", "occlusion", "swap"))
    assert all_three.light.intensity == mk.LIGHT_INTENSITIES[1]
    turned = np.degrees(np.arccos(np.dot(np.array(all_three.light.direction), np.array(plain.light.direction))
                                  / np.linalg.norm(all_three.light.direction) / np.linalg.norm(plain.light.direction)))
    assert turned == pytest.approx(mk.LIGHT_TURN_DEG, abs=0.01)
    occluder, swapped = all_three.objects
    assert occluder.kind == ObjectKind.BOX and occluder.size_m[0] == pytest.approx(0.3 * 2 * base.target.cup.radius_m)
    assert swapped.texture_seed != base.target.texture_seed and swapped.arrives_at_s == mk.SWAP_AT_S
    assert all_three.target.leaves_at_s == mk.SWAP_AT_S and swapped.pose_in_base == all_three.target.pose_in_base
    stack_config(all_three)  # every piece of it valid as robot_sim will take it
    tag = mk.tag_scenario(base, start)
    assert tag.target.kind.value == "tag" and tag.goal.camera_in_tag is not None


def test_a_run_succeeds_when_it_converges_or_holds_before_the_swapped_object():
    assert mk.succeeded({"perturb": [], "converged": True})
    assert not mk.succeeded({"perturb": ["swap"], "converged": False, "held": False})
    assert mk.succeeded({"perturb": ["swap"], "converged": False, "held": True})


@pytest.mark.slow
def test_the_experiment_teaches_servos_and_holds_on_a_swap_from_the_command_line(tmp_path):
    out = subprocess.run([sys.executable, "-m", "services.cli", "experiment", "markerless", "--random-starts", "1",
                          "--seed", "2", "--object", "cup", "--json", "--out", str(tmp_path)],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    run = result["runs"][0]
    assert run["converged"] and run["final_position_error_mm"] < 1.0 and run["final_rotation_error_deg"] < 0.5
    assert run["teach"]["planar"] is False and (tmp_path / "report.md").is_file()
    swap = subprocess.run([sys.executable, "-m", "services.cli", "experiment", "markerless", "--random-starts", "1",
                           "--seed", "2", "--perturb", "swap", "--json"], capture_output=True, text=True, timeout=600)
    row = json.loads(swap.stdout)["runs"][0]
    assert row["held"] and row["frames_commanded_after_swap"] <= 1 and row["status"] == "target_lost"
