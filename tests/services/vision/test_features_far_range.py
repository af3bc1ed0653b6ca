"""Vision far away: the tag rendered by the simulator from 0.2 m to 3 m at 640×480, facing the camera and tilted by
30° and 60°; the AprilTag backend's corners against the pinhole projection of MuJoCo's poses, and the tag's pose
from them (IPPE) against MuJoCo's."""
import cv2
import numpy as np
import pytest

from services.model import tag as tags
from services.robot_sim.scene import PoseConfig, SceneConfig, TargetConfig
from services.robot_sim.sim import Simulation
from services.vision.features import TagDetector, tag_pose

DISTANCES = (0.2, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0)
TILTS = (0.0, 30.0, 60.0)


@pytest.fixture(scope="module")
def detector():
    return TagDetector(backend="apriltag")


def rendered(distance: float, tilt_deg: float):
    pose = PoseConfig(xyz=(0.0, 0.0, distance), rpy_deg=(180.0 + tilt_deg, 0.0, 15.0))
    cfg = SceneConfig(floor=False, target=TargetConfig(pose_in_camera=pose))
    sim = Simulation(cfg)
    try:
        gray = cv2.cvtColor(sim.render(), cv2.COLOR_RGB2GRAY)
        T_ct = np.linalg.inv(sim.camera_pose()) @ sim.target_pose()
    finally:
        sim.close()
    corners = (T_ct[:3, :3] @ tags.corners_in_tag(cfg.target.size_m).T).T + T_ct[:3, 3]
    projected = (cfg.camera.matrix() @ (corners / corners[:, 2:3]).T).T[:, :2]
    return gray, projected, T_ct, cfg


@pytest.mark.parametrize("tilt", TILTS)
@pytest.mark.parametrize("distance", DISTANCES)
def test_corners_within_half_a_pixel_and_the_pose_within_one_percent(detector, distance, tilt):
    gray, projected, T_ct, cfg = rendered(distance, tilt)
    found = detector.find(gray, 0)
    assert found is not None, f"tag lost at {distance} m, {tilt}°"
    assert np.linalg.norm(found.corners_px - projected, axis=1).max() < 0.5
    R, t = tag_pose(found.corners_px, cfg.camera.matrix(), None, cfg.target.size_m)
    assert np.linalg.norm(t - T_ct[:3, 3]) < 0.01 * distance
