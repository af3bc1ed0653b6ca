"""bench swap: nudged starts, the approach and realtime against lockstep (its random starts:
tests/services/experiments/test_starts.py)."""
import msgspec
import numpy as np

from bench.swap import NUDGE_M, SCENARIOS, first_below, nudge_offsets, nudged, realtime_against_lockstep, summarize
from services.model.frames import PoseConfig
from services.servo.scenario import load_scenario


def test_nudged_starts_move_the_tag_a_little_along_each_axis_the_same_way_every_time():
    offsets = nudge_offsets(8)
    assert offsets == nudge_offsets(8) and len(set(offsets)) == 8
    assert offsets[:6] == [(NUDGE_M, 0.0, 0.0), (-NUDGE_M, 0.0, 0.0), (0.0, NUDGE_M, 0.0), (0.0, -NUDGE_M, 0.0),
                           (0.0, 0.0, NUDGE_M), (0.0, 0.0, -NUDGE_M)]
    assert offsets[6] == (2 * NUDGE_M, 0.0, 0.0)
    table2 = load_scenario(SCENARIOS / "table2.yaml")
    moved = nudged(table2, (0.0, 0.0, NUDGE_M))
    assert np.allclose(np.subtract(moved.target.pose_in_camera.xyz, table2.target.pose_in_camera.xyz),
                       [0.0, 0.0, NUDGE_M])
    assert moved.target.pose_in_camera.rpy_deg == table2.target.pose_in_camera.rpy_deg
    assert table2 == load_scenario(SCENARIOS / "table2.yaml")  # the original is left as it was
    # a pose given in the base frame is moved there; no pose at all: robot_sim's default one is
    in_base = msgspec.structs.replace(table2, target=msgspec.structs.replace(
        table2.target, pose_in_camera=None, pose_in_base=PoseConfig(xyz=(0.5, 0.1, 0.3))))
    assert nudged(in_base, (NUDGE_M, 0.0, 0.0)).target.pose_in_base.xyz == (0.5 + NUDGE_M, 0.1, 0.3)
    assert nudged(in_base, (NUDGE_M, 0.0, 0.0)).target.pose_in_camera is None
    bare = msgspec.structs.replace(table2, target=msgspec.structs.replace(table2.target, pose_in_camera=None))
    assert nudged(bare, (0.0, NUDGE_M, 0.0)).target.pose_in_camera.xyz == (0.0, NUDGE_M, 0.5)


def test_first_below_is_the_iteration_the_error_first_dipped_under():
    assert first_below([0.3, 0.1, 0.04, 0.06, 0.01], 0.05) == 3
    assert first_below([0.3, 0.1], 0.05) is None


def _row(iterations, approach, converged=True):
    return {"iterations": iterations, "approach": approach, "converged": converged, "peak_speed_mps": 0.2,
            "speed_limit_mps": 0.2}


def test_realtime_is_judged_against_the_median_of_lockstep_s_nudged_starts():
    # lockstep's exact start is a low draw (140) of a spread whose median is 156: realtime's 160 is within 10 %
    lockstep = summarize([_row(140, 100), _row(179, 101), _row(143, 100), _row(156, 99), _row(163, 100)])
    realtime = summarize([_row(150, 99), _row(160, 100), _row(171, 100)])
    assert lockstep["iterations_median"] == 156 and realtime["iterations_median"] == 160
    compared = realtime_against_lockstep(lockstep, realtime)
    assert compared == {"median": round(160 / 156, 3), "worst": round(171 / 156, 3), "approach": 1.0,
                        "lockstep_spread": [round(140 / 156, 3), round(179 / 156, 3)], "within": True}
    # a realtime run that did not converge is not within, whatever the others did
    lost_one = summarize([_row(150, 99), _row(160, 100), _row(0, None, converged=False)])
    assert realtime_against_lockstep(lockstep, lost_one)["within"] is False
    slow = summarize([_row(180, 120), _row(175, 118)])
    assert realtime_against_lockstep(lockstep, slow)["within"] is False
    assert realtime_against_lockstep(lockstep, summarize([_row(0, None, converged=False)])) is None
