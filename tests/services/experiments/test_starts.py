"""Random starts (services/experiments/starts.py): Table-2-like tag poses no one has seen, every corner in the image,
the same from the same seed, written as scenarios that load and run again."""
import random

import numpy as np
import pytest

from services.experiments.random_starts import random_starts_summary, shaped_by, start_summary
from services.paths import SCENARIOS
from services.model import tag as tags
from services.robot_sim.scene import CameraConfig, TargetConfig, TargetKind, target_outline
from services.model.frames import PoseConfig
from services.servo.scenario import load_scenario
from services.experiments.starts import (TABLE2_LIKE, Start, all_corners_visible, corners_in_image, quartiles,
                                         random_start, write_starts)

TABLE2 = SCENARIOS / "table2.yaml"
TAG = tags.corners_in_tag(0.0962)


def test_starts_are_loadable_reproducible_and_within_the_ranges(tmp_path):
    first = write_starts(TABLE2, 12, seed=7, out_dir=tmp_path / "a")
    again = write_starts(TABLE2, 12, seed=7, out_dir=tmp_path / "b")
    other = write_starts(TABLE2, 12, seed=8, out_dir=tmp_path / "c")
    assert [s.pose_in_camera for s in first] == [s.pose_in_camera for s in again]
    assert [s.pose_in_camera for s in first] != [s.pose_in_camera for s in other]
    base = load_scenario(TABLE2)
    r = TABLE2_LIKE
    for start in first:
        scenario = load_scenario(start.scenario)
        pose = scenario.target.pose_in_camera
        assert pose == start.pose_in_camera
        assert scenario.law == base.law and scenario.goal == base.goal and scenario.gains == base.gains
        assert scenario.robot == base.robot and scenario.camera == base.camera  # only the start differs
        x, y, z = pose.xyz
        roll, pitch, yaw = pose.rpy_deg
        assert r.ahead_m[0] <= z <= r.ahead_m[1] and abs(x) <= r.off_centre_m and abs(y) <= r.off_centre_m
        assert abs(roll - 180.0) <= r.roll_deg and abs(pitch) <= r.pitch_deg and abs(yaw) <= r.yaw_deg
        pixels = corners_in_image(pose, target_outline(scenario.target), scenario.camera)
        assert np.all(pixels >= r.margin_px) and np.all(pixels[:, 0] <= 639 - r.margin_px)
        assert np.all(pixels[:, 1] <= 479 - r.margin_px)
        assert f"--seed 7: start {start.index}" in start.scenario.read_text()


def test_a_pose_with_a_corner_outside_the_image_is_drawn_again():
    camera = CameraConfig()
    assert all_corners_visible(PoseConfig(xyz=(0.0, 0.0, 0.5), rpy_deg=(180.0, 0.0, 0.0)), TAG, camera, 10.0)
    # 0.26 m off the axis at 0.5 m: the tag's centre at pixel 639.5 + 319.5, half of it beyond the right edge
    assert not all_corners_visible(PoseConfig(xyz=(0.26, 0.0, 0.5), rpy_deg=(180.0, 0.0, 0.0)), TAG, camera,
                                   10.0)
    assert not all_corners_visible(PoseConfig(xyz=(0.0, 0.0, -0.5), rpy_deg=(180.0, 0.0, 0.0)), TAG, camera,
                                   10.0)  # behind the camera
    tiny = CameraConfig(width=64, height=48, fx=615.0, fy=615.0)
    with pytest.raises(ValueError, match="keeps its whole outline"):
        random_start(random.Random(0), TABLE2_LIKE, TAG, tiny)


@pytest.mark.parametrize("kind", [TargetKind.PLANE, TargetKind.CUP])
def test_starts_over_any_target_keep_its_whole_outline_in_view(kind):
    """The same draws for a markerless object: every point of its outline (a plane's corners, a cup's silhouette)
    in the image; the cup's outline holds its rim, its base and its handle."""
    target = TargetConfig(kind=kind)
    outline = target_outline(target)
    assert len(outline) == (4 if kind == TargetKind.PLANE else 25)
    rng, camera = random.Random(3), CameraConfig()
    for _ in range(20):
        pose = random_start(rng, TABLE2_LIKE, outline, camera)
        pixels = corners_in_image(pose, outline, camera)
        assert np.all(pixels >= TABLE2_LIKE.margin_px) and np.all(pixels[:, 0] <= 639 - TABLE2_LIKE.margin_px)


def test_quartiles():
    assert quartiles([]) == {"n": 0, "q1": None, "median": None, "q3": None, "min": None, "max": None}
    q = quartiles([1, 2, 3, 4, 5])
    assert (q["q1"], q["median"], q["q3"], q["min"], q["max"], q["n"]) == (2.0, 3.0, 4.0, 1, 5, 5)


def _row(law, iterations, converged=True, failure=None, limits=None, saturated=0):
    return {"label": law, "law": law, "iterations": iterations, "converged": converged, "failure": failure,
            "limits_met": limits or {}, "saturated_iterations": saturated}


def test_the_summary_counts_order_improvement_and_names_what_shaped_a_start_that_is_not_clearly_faster():
    start = Start(seed=1, index=0, pose_in_camera=PoseConfig(), scenario=TABLE2)
    fast = {"p-joint": _row("p-joint", 400), "adaptive-p-joint": _row("adaptive-p-joint", 250),
            "adaptive-pd-joint": _row("adaptive-pd-joint", 200), "adaptive-pd-mixed": _row("adaptive-pd-mixed", 120)}
    slow = dict(fast, **{"adaptive-pd-mixed": _row("adaptive-pd-mixed", 190, limits={"singularity": 88, "speed": 3,
                                                                                      "dead_band": 40},
                                                   saturated=100)})
    failed = dict(fast, **{"adaptive-pd-mixed": _row("adaptive-pd-mixed", 1000, converged=False,
                                                     failure="max_iterations")})
    starts = [start_summary(start, rows) for rows in (fast, slow, failed)]
    assert starts[0]["improvement_pct"] == 40.0 and starts[0]["clearly_faster"] and starts[0]["in_paper_order"]
    assert "shaped_by" not in starts[0]
    assert starts[1]["improvement_pct"] == 5.0 and not starts[1]["clearly_faster"]
    assert starts[1]["shaped_by"]["adaptive-pd-mixed"] == {"speed": 3, "singularity": 88, "dead_band": 40,
                                                            "controller_saturation": 100}
    assert starts[2]["improvement_pct"] is None and not starts[2]["in_paper_order"]
    assert starts[2]["failures"] == {"adaptive-pd-mixed": "max_iterations"}
    runs = [row for rows in (fast, slow, failed) for row in rows.values()]
    summary = random_starts_summary(starts, runs)
    assert summary["starts"] == 3 and summary["proposed_failures"] == 1
    assert summary["fraction_in_paper_order"] == round(2 / 3, 3)
    assert summary["fraction_clearly_faster"] == round(1 / 3, 3)
    assert summary["median_improvement_pct"] == 22.5
    assert summary["laws"]["adaptive-pd-mixed"]["iterations"]["median"] == 155.0
    assert summary["laws"]["adaptive-pd-mixed"]["failures"] == {"max_iterations": 1}
    assert [s["index"] for s in summary["not_clearly_faster"]] == [0, 0]
    assert shaped_by(_row("x", 1, limits={"zone": 2, "acceleration": 0})) == {"zone": 2}
