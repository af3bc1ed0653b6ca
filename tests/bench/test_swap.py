"""bench swap's random starts: scenarios no one has seen, drawn the same way from the same seed."""
import numpy as np

from bench.swap import SCENARIOS, random_scenarios
from services.servo import load_scenario


def test_random_starts_are_loadable_reproducible_and_face_the_camera(tmp_path):
    first = random_scenarios(SCENARIOS / "table2.yaml", 5, seed=7, out_dir=tmp_path / "a")
    again = random_scenarios(SCENARIOS / "table2.yaml", 5, seed=7, out_dir=tmp_path / "b")
    other = random_scenarios(SCENARIOS / "table2.yaml", 5, seed=8, out_dir=tmp_path / "c")
    poses = [load_scenario(p).target.pose_in_camera for p in first]
    assert poses == [load_scenario(p).target.pose_in_camera for p in again]
    assert poses != [load_scenario(p).target.pose_in_camera for p in other]
    assert len({tuple(p.xyz) for p in poses}) == 5
    base = load_scenario(SCENARIOS / "table2.yaml")
    for path, pose in zip(first, poses):
        scenario = load_scenario(path)
        assert scenario.law == base.law and scenario.goal == base.goal  # only the start differs
        assert 0.42 <= pose.xyz[2] <= 0.60 and abs(pose.xyz[0]) <= 0.08 and abs(pose.xyz[1]) <= 0.06
        # the tag's face points back at the camera (its normal within 15° of the optical axis, reversed)
        normal = pose.matrix()[:3, 2]
        assert normal[2] < -np.cos(np.radians(15.0))
