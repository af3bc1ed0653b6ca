"""vision on frames rendered by robot_sim at known poses (real MuJoCo EGL rendering, real OpenCV detection)."""
import math
import subprocess
import sys
import time

import cv2
import msgpack
import msgspec
import numpy as np
import pytest

from protocol import messages as m
from services.model import frames
from services.model import tag as tags
from services.model.frames import PoseConfig
from services.robot_sim.scene import CameraConfig, SceneConfig, TargetConfig, camera_info
from services.robot_sim.sim import Simulation
from services.vision import features as F
from services.vision.service import TABLE2_DEPTH, TABLE2_GOAL, VisionConfig, VisionService
from tests.helpers import REPO


def render(pose_in_camera: PoseConfig, camera: CameraConfig | None = None, tag_id: int = 0, floor: bool = False):
    """(rgb image, true corner projections px, true tag-in-camera pose, scene config)."""
    cfg = SceneConfig(camera=camera or CameraConfig(), floor=floor,
                      target=TargetConfig(id=tag_id, pose_in_camera=pose_in_camera))
    sim = Simulation(cfg)
    try:
        image = sim.render()
        T_ct = np.linalg.inv(sim.camera_pose()) @ sim.target_pose()
    finally:
        sim.close()
    corners = F.corners_in_camera(T_ct, cfg.target.size_m)
    uv = (cfg.camera.matrix() @ (corners / corners[:, 2:3]).T).T[:, :2]
    return image, uv, T_ct, cfg


def image_message(pixels, stamp_ns=None):
    stamp = time.time_ns() if stamp_ns is None else stamp_ns
    h, w = pixels.shape[:2]
    return m.Image(header=m.Header(stamp_ns=stamp, source_stamp_ns=stamp), width=w, height=h,
                   encoding=m.ImageEncoding.RGB8, data=np.ascontiguousarray(pixels).tobytes())


def vision_for(cfg: SceneConfig, **overrides) -> VisionService:
    service = VisionService(VisionConfig(**overrides))
    service._on_camera_info(camera_info(cfg.camera, m.Header()), 0)
    return service


POSES = [
    PoseConfig(xyz=(0.0, 0.0, 0.3), rpy_deg=(180.0, 0.0, 0.0)),
    PoseConfig(xyz=(0.03, -0.02, 0.45), rpy_deg=(165.0, 15.0, 25.0)),
    PoseConfig(xyz=(-0.05, 0.04, 0.6), rpy_deg=(195.0, -20.0, -70.0)),
    PoseConfig(xyz=(0.06, 0.05, 0.8), rpy_deg=(170.0, 10.0, 140.0)),
    PoseConfig(xyz=(-0.04, -0.06, 1.0), rpy_deg=(185.0, 12.0, 200.0)),
]


@pytest.mark.parametrize("pose", POSES, ids=lambda p: f"z{p.xyz[2]}")
def test_corners_depth_and_pose_from_rendered_frames(pose):
    image, expected_px, T_ct, cfg = render(pose)
    service = vision_for(cfg)
    features = service.process(image_message(image), time.time_ns())
    assert features.status is m.FeatureStatus.OK, features.detail
    corners = np.array(features.pixels)
    assert np.linalg.norm(corners - expected_px, axis=1).max() < 0.5
    true_depths = F.corners_in_camera(T_ct, cfg.target.size_m)[:, 2]
    assert np.allclose(features.depths, true_depths, rtol=0.01)
    true_points = F.project(F.corners_in_camera(T_ct, cfg.target.size_m))[0]
    assert np.abs(np.array(features.points) - true_points).max() < 1.0 / 615.0  # half a pixel, normalized
    assert np.allclose(features.tag.pose_in_camera.xyz, T_ct[:3, 3], rtol=0.01, atol=2e-3)
    assert features.header.source_stamp_ns > 0 and features.header.trace[-1].service == "vision"


def test_corners_on_a_1280x720_camera_with_an_offset_principal_point():
    camera = CameraConfig(width=1280, height=720, fx=920.0, fy=925.0, cx=650.0, cy=350.0)
    image, expected_px, _, cfg = render(POSES[1], camera)
    features = vision_for(cfg).process(image_message(image), time.time_ns())
    assert features.status is m.FeatureStatus.OK
    assert np.linalg.norm(np.array(features.pixels) - expected_px, axis=1).max() < 0.5


@pytest.mark.parametrize("camera_in_tag", [
    PoseConfig(xyz=(0.0, 0.0, 0.2888), rpy_deg=(180.0, 0.0, 0.0)),
    PoseConfig(xyz=(0.03, -0.02, 0.4), rpy_deg=(170.0, 8.0, 30.0)),
    PoseConfig(xyz=(-0.05, 0.03, 0.55), rpy_deg=(175.0, -6.0, -45.0)),
])
def test_goal_from_camera_in_tag_equals_what_the_camera_sees_there(camera_in_tag):
    goal_points, goal_depths = F.goal_from_camera_in_tag(camera_in_tag.matrix(), 0.0962)
    # place the simulated camera at that pose: the tag is then at the inverse pose in the camera frame
    T_ct = np.linalg.inv(camera_in_tag.matrix())
    rpy = np.degrees(frames.matrix_to_euler_xyz(T_ct[:3, :3]))
    image, _, _, cfg = render(PoseConfig(xyz=tuple(T_ct[:3, 3]), rpy_deg=tuple(rpy)))
    features = vision_for(cfg).process(image_message(image), time.time_ns())
    assert features.status is m.FeatureStatus.OK
    assert np.abs(np.array(features.points) - goal_points).max() < 1e-3
    assert np.allclose(features.depths, goal_depths, rtol=0.01)


def test_table2_goal_is_the_camera_0_2888_m_in_front_of_the_tag():
    points, depths = F.goal_from_camera_in_tag(PoseConfig(xyz=(0, 0, TABLE2_DEPTH), rpy_deg=(180, 0, 0)).matrix(),
                                               0.0962)
    assert np.allclose(points, TABLE2_GOAL, atol=1e-4) and np.allclose(depths, TABLE2_DEPTH)


def test_error_is_features_minus_goal():
    image, _, _, cfg = render(POSES[1])
    features = vision_for(cfg).process(image_message(image), time.time_ns())
    e = np.array(features.points) - np.array(TABLE2_GOAL)
    assert np.allclose(features.error, e.reshape(-1)) and features.error_norm == pytest.approx(np.linalg.norm(e))
    assert features.goal_depths == [TABLE2_DEPTH] * 4


def test_target_lost_is_reported_immediately_and_teach_needs_a_target():
    image, _, _, cfg = render(POSES[0])
    service = vision_for(cfg)
    assert service.process(image_message(image), time.time_ns()).status is m.FeatureStatus.OK
    lost, _, _, _ = render(PoseConfig(xyz=(0.6, -0.2, 0.4), rpy_deg=(180.0, 0.0, 0.0)), floor=True)  # out of view
    features = service.process(image_message(lost), time.time_ns())
    assert features.status is m.FeatureStatus.TARGET_LOST and features.points == [] and features.error == []
    reply = service.set_goal(m.VisionGoal(header=m.Header(), teach=True))
    assert not reply.ok and "target in view" in reply.message


def test_other_tag_ids_are_ignored():
    image, _, _, cfg = render(POSES[0], tag_id=7)
    features = vision_for(cfg).process(image_message(image), time.time_ns())
    assert features.status is m.FeatureStatus.TARGET_LOST


def test_partial_when_the_tag_comes_within_the_border_margin():
    image, expected_px, _, cfg = render(PoseConfig(xyz=(0.11, 0.0, 0.35), rpy_deg=(180.0, 0.0, 0.0)))
    right_gap = cfg.camera.width - 1 - expected_px[:, 0].max()
    assert 10 < right_gap < 60
    assert vision_for(cfg).process(image_message(image), time.time_ns()).status is m.FeatureStatus.OK
    features = vision_for(cfg, border_margin_px=right_gap + 1).process(image_message(image), time.time_ns())
    assert features.status is m.FeatureStatus.PARTIAL and "border" in features.detail
    assert len(features.points) == 4 and len(features.error) == 8


def test_bad_images_are_refused_and_counted():
    image, _, _, cfg = render(POSES[0])
    service = vision_for(cfg)
    black = service.process(image_message(np.zeros_like(image)), time.time_ns())
    assert black.status is m.FeatureStatus.INVALID_IMAGE and "all-black" in black.detail
    small = service.process(image_message(image[:240, :320]), time.time_ns())
    assert small.status is m.FeatureStatus.INVALID_IMAGE and "320x240" in small.detail
    no_info = VisionService(VisionConfig()).process(image_message(image), time.time_ns())
    assert no_info.status is m.FeatureStatus.INVALID_IMAGE and "camera info" in no_info.detail
    stale = vision_for(cfg).process(image_message(image, stamp_ns=time.time_ns() - 2_000_000_000), time.time_ns())
    assert stale.status is m.FeatureStatus.STALE and stale.points == [] and "ms old" in stale.detail
    t = time.time_ns()
    assert service.process(image_message(image, t), t).status is m.FeatureStatus.OK
    old = service.process(image_message(image, t - 1000), t)
    assert old.status is m.FeatureStatus.STALE and "out-of-order" in old.detail
    assert service.counters.get("rejected.image") == 3  # black, wrong size, out of order


def test_the_same_image_again_gets_the_same_answer():
    """robot_sim's lockstep retry publishes a frame again while an answer is late: vision answers it with what it
    answered the first time (not "out-of-order"), whichever of the two deliveries it happened to process."""
    image, _, _, cfg = render(POSES[1])
    service = vision_for(cfg)
    t = time.time_ns()
    first = service.process(image_message(image, t), t)
    again = service.process(image_message(image, t), t + 5_000_000)
    assert first.status is m.FeatureStatus.OK and again == first
    assert service.counters.get("frames.repeated") == 1 and service.counters.get("rejected.image") == 0
    assert service.process(image_message(image, t - 1000), t).status is m.FeatureStatus.STALE  # older: refused
    newer = service.process(image_message(image, t + 1000), t + 1000)
    assert newer.status is m.FeatureStatus.OK and newer.header.source_stamp_ns == t + 1000


def test_goal_changes_at_run_time():
    image, _, T_ct, cfg = render(POSES[1])
    service = vision_for(cfg)
    square = [(-0.1, -0.1), (0.1, -0.1), (0.1, 0.1), (-0.1, 0.1)]
    assert service.set_goal(m.VisionGoal(header=m.Header(), features=square, depth_m=0.4)).ok
    features = service.process(image_message(image), time.time_ns())
    assert features.goal_points == square and features.goal_depths == [0.4] * 4
    # teach: the current view becomes the goal, so the error vanishes
    assert service.set_goal(m.VisionGoal(header=m.Header(), teach=True)).ok
    features = service.process(image_message(image), time.time_ns())
    assert features.error_norm < 1e-12
    pose = m.Pose(xyz=(0.0, 0.0, 0.3), quat_wxyz=tuple(frames.matrix_to_quat_wxyz(frames.rot_x(math.pi))))
    reply = service.set_goal(m.VisionGoal(header=m.Header(), camera_in_tag=pose))
    assert reply.ok and np.allclose(reply.goal_depths, 0.3)
    assert not service.set_goal(m.VisionGoal(header=m.Header(), features=square[:3], depth_m=0.3)).ok


def test_vision_goal_message_needs_exactly_one_goal():
    with pytest.raises(m.ProtocolError):
        m.decode(msgpack.packb({"header": m.to_builtins(m.Header()), "teach": True, "depth_m": 0.3,
                                "features": [[0, 0]]}), m.VisionGoal)
    with pytest.raises(m.ProtocolError, match="depth_m"):
        m.decode(msgpack.packb({"header": m.to_builtins(m.Header()), "features": [[0, 0]]}), m.VisionGoal)


def test_normalize_undistorts():
    K = F.camera_matrix(600.0, 610.0, 320.0, 240.0)
    dist = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])
    truth = np.array([[0.1, -0.05], [-0.2, 0.15], [0.25, 0.2], [-0.05, -0.22]])
    pts3 = np.hstack([truth, np.ones((4, 1))])
    px, _ = cv2.projectPoints(pts3, np.zeros(3), np.zeros(3), K, dist)
    assert np.abs(F.normalize(px.reshape(-1, 2), K, dist) - truth).max() < 1e-6
    assert np.abs(F.normalize(px.reshape(-1, 2), K, None) - truth).max() > 1e-3  # ignoring it would be wrong


def test_detector_refinement_options():
    image, expected_px, _, _ = render(POSES[1])
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    for refinement in F.Refinement:
        detection = F.TagDetector(refinement=refinement).find(gray, 0)
        assert detection is not None and np.linalg.norm(detection.corners_px - expected_px, axis=1).max() < 1.5
    with pytest.raises(ValueError):
        F.TagDetector(refinement="magic")
    with pytest.raises(ValueError):
        tags.dictionary("tag25h9")


def test_measure_is_vision_without_the_service():
    """The pure pipeline (detect → normalise → pose → error) on a rendered frame, an all-black one and an empty
    one: the same figures the service publishes, with no zenoh, clock or lock."""
    image, expected_px, T_ct, cfg = render(POSES[1])
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    K, goal = cfg.camera.matrix(), np.array(TABLE2_GOAL)
    config = VisionConfig()
    detector = F.TagDetector(refinement=config.refinement, backend=config.detector)
    result = F.measure(gray, detector, 0, cfg.target.size_m, K, None, goal, min_peak_brightness=20)
    assert result.status == "ok" and not result.rejected
    assert np.linalg.norm(result.corners_px - expected_px, axis=1).max() < 0.5
    assert np.allclose(result.error, (result.points - goal).reshape(-1)) and result.error_norm > 0
    assert np.allclose(result.depths, F.corners_in_camera(T_ct, cfg.target.size_m)[:, 2], rtol=0.01)
    published = vision_for(cfg).process(image_message(image), time.time_ns())
    assert np.allclose(published.points, result.points) and published.error_norm == pytest.approx(result.error_norm)
    black = F.measure(np.zeros_like(gray), detector, 0, cfg.target.size_m, K, None, goal, min_peak_brightness=20)
    assert black.status == "invalid_image" and black.rejected and black.points is None
    empty = F.measure(np.full_like(gray, 200), detector, 0, cfg.target.size_m, K, None, goal)
    assert empty.status == "target_lost" and not empty.rejected and "not in view" in empty.detail
    assert F.measure(gray, detector, 7, cfg.target.size_m, K, None, goal).status == "target_lost"  # another id


def _frames_along_a_motion(n: int, rate_rad: float = 0.02):
    """Grayscale frames of the camera turning and moving as the arm does between frames (a joint step each)."""
    cfg = SceneConfig(target=TargetConfig(pose_in_camera=PoseConfig(xyz=(0.03, -0.02, 0.45), rpy_deg=(170, 8, 25))))
    sim = Simulation(cfg)
    out = []
    try:
        for k in range(n):
            sim.data.qpos[:6] += rate_rad * np.array([1.0, -0.5, 0.5, 1.0, -1.0, 1.5]) * (1 if k else 0)
            out.append(cv2.cvtColor(sim.render(), cv2.COLOR_RGB2GRAY))
    finally:
        sim.close()
    return out


@pytest.mark.parametrize("backend, refinement, tolerance_px", [
    ("aruco", "apriltag_subpix", 0.0), ("apriltag", "none", 0.1), ("apriltag", "apriltag_subpix", 0.002)])
def test_window_search_finds_the_full_frame_corners_along_a_motion(backend, refinement, tolerance_px):
    """aruco's corners in the window are the full frame's to the bit; the AprilTag library's thresholds in tiles
    of the image it is given, so its raw corners may move, within 0.1 px, and the sub-pixel search (vision's
    default) brings them back together; the tag's pose follows its corners."""
    detector = F.TagDetector(backend=backend, refinement=refinement)
    tracker = F.TagTracker(detector, F.RoiConfig(full_frame_every=1000))
    frames_ = _frames_along_a_motion(10)
    K = SceneConfig().camera.matrix()
    moved = []
    for gray in frames_:
        full = detector.find(gray, 0)
        tracked = tracker.find(gray, 0)
        assert full is not None and tracked is not None
        assert np.abs(tracked.corners_px - full.corners_px).max() <= tolerance_px
        (R_full, t_full), (R_window, t_window) = (F.tag_pose(c, K, None, 0.0962)
                                                  for c in (full.corners_px, tracked.corners_px))
        assert np.linalg.norm(t_window - t_full) <= 0.01 * tolerance_px * np.linalg.norm(t_full) + 1e-12
        moved.append(full.corners_px)
    assert tracker.searches == {"window": 9, "full": 1, "fallback": 0}
    steps = np.abs(np.diff(np.array(moved), axis=0)).max(axis=(1, 2))
    assert steps.min() > 2.0  # the tag really moved between frames (px): the window followed it


def test_vision_default_detector_finds_aruco_corners_in_a_quarter_of_the_time():
    """The default (the AprilTag library's quads, then OpenCV's sub-pixel search) lands where aruco's default
    lands, so the experiments' figures hold (its speed is the benchmark's: `mfvs bench vision`)."""
    config = VisionConfig()
    default = F.TagDetector(backend=config.detector, refinement=config.refinement)
    aruco = F.TagDetector(backend="aruco", refinement="apriltag_subpix")
    for gray in _frames_along_a_motion(6, rate_rad=0.05):
        ours, theirs = default.find(gray, 0), aruco.find(gray, 0)
        assert np.abs(ours.corners_px - theirs.corners_px).max() < 0.002


def test_window_search_falls_back_and_re_detects_on_the_full_frame():
    detector = F.TagDetector()
    gray = _frames_along_a_motion(1)[0]
    full = detector.find(gray, 0).corners_px
    tracker = F.TagTracker(detector, F.RoiConfig(full_frame_every=3))
    tracker.last_corners_px = full + np.array([300.0, 200.0])  # the tag "was" far from where it is now
    assert np.array_equal(tracker.find(gray, 0).corners_px, full)
    assert tracker.take_last_search() == "fallback" and tracker.take_last_search() == ""
    searches = []
    for _ in range(7):
        tracker.find(gray, 0)
        searches.append(tracker.take_last_search())
    assert searches == ["window", "window", "window", "full", "window", "window", "window"]
    assert tracker.find(np.zeros_like(gray), 0) is None and tracker.last_corners_px is None
    assert tracker.window(gray.shape) is None  # lost: the next search is the full frame


def test_window_is_the_last_box_with_its_margin_clipped_to_the_image():
    tracker = F.TagTracker(F.TagDetector(), F.RoiConfig(margin_fraction=0.25, min_margin_px=48))
    tracker.last_corners_px = np.array([[100.0, 100.0], [300.0, 100.0], [300.0, 300.0], [100.0, 300.0]])
    assert tracker.window((480, 640)) == (50, 50, 351, 351)
    tracker.last_corners_px = np.array([[10.0, 20.0], [40.0, 20.0], [40.0, 50.0], [10.0, 50.0]])
    assert tracker.window((480, 640)) == (0, 0, 89, 99)
    tracker.last_corners_px = np.array([[0.0, 0.0], [639.0, 0.0], [639.0, 479.0], [0.0, 479.0]])
    assert tracker.window((480, 640)) is None  # the window would be the whole image
    assert F.TagTracker(F.TagDetector(), F.RoiConfig(enabled=False)).window((480, 640)) is None
    with pytest.raises(ValueError):
        F.RoiConfig(full_frame_every=0)


@pytest.mark.parametrize("backend", ["aruco", "apriltag"])
def test_the_vision_core_needs_no_service_and_takes_time_from_its_caller(backend):
    from services.vision.core import VisionCore

    image, _, _, cfg = render(POSES[1])
    core = VisionCore(VisionConfig(detector=backend))
    info = camera_info(cfg.camera, m.Header())
    captured = 5_000_000_000  # any clock: the core reads none of its own
    fresh = core.process(image_message(image, captured), info, now_ns=captured + 100_000_000)
    assert fresh.status is m.FeatureStatus.OK and fresh.counts == ["detect.full"] and not fresh.refusal
    assert np.allclose(core.last_points, fresh.seen.points)
    late = core.process(image_message(image, captured + 1), info, now_ns=captured + 1 + 260_000_000)
    assert late.status is m.FeatureStatus.STALE and late.counts == ["frames.stale"] and late.seen is None
    again = core.process(image_message(image, captured), info, now_ns=captured)
    assert again.status is m.FeatureStatus.STALE and "not newer" in again.refusal
    assert core.goal_from(m.VisionGoal(header=m.Header(), teach=True)).description == "teach"


def _official_tag_with_cells_misread(*cells: tuple[int, int]) -> np.ndarray:
    """The official tag36h11 id 0, 20 px a cell, with these data cells (row, column of its 6×6) inverted: what a
    camera reads when those cells come out wrong."""
    from pathlib import Path

    image = cv2.imread(str(Path(__file__).parents[1] / "model" / "data" / "tag36_11_00000.png"), cv2.IMREAD_GRAYSCALE)
    for row, column in cells:  # 10×10: a white ring, the black border, then the 6×6 data cells
        image[2 + row, 2 + column] = 255 - image[2 + row, 2 + column]
    big = cv2.resize(image, (200, 200), interpolation=cv2.INTER_NEAREST)
    return cv2.copyMakeBorder(big, 60, 60, 60, 60, cv2.BORDER_CONSTANT, value=255)


def _detector_table_mb(corrected_bits: int) -> float:
    """What building the apriltag detector adds to a fresh process's resident memory (MB): in this process, memory
    an earlier detector freed is reused without showing."""
    script = ("from services.vision.features import TagDetector\n"
              "def rss():\n"
              "    with open('/proc/self/status') as f:\n"
              "        return next(int(l.split()[1]) for l in f if l.startswith('VmRSS:')) / 1024\n"
              "before = rss()\n"
              f"detector = TagDetector(backend='apriltag', apriltag_corrected_bits={corrected_bits})\n"
              "print(rss() - before)\n")
    return float(subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                                cwd=REPO, timeout=120).stdout)


def test_the_apriltag_detector_corrects_as_many_wrong_cells_as_configured():
    """AprilTag's default corrects two misread cells; one bit corrected loses a tag with two, keeps one with one;
    and its decode table shrinks from tens of MB to about one."""
    with_two, with_one = _detector_table_mb(2), _detector_table_mb(1)
    assert with_two > 25 and with_one < 5, (with_two, with_one)
    library_default = F.TagDetector(backend="apriltag")
    one_bit = F.TagDetector(backend="apriltag", apriltag_corrected_bits=1)
    none = F.TagDetector(backend="apriltag", apriltag_corrected_bits=0)
    clean, one_wrong, two_wrong = (_official_tag_with_cells_misread(*cells)
                                   for cells in ((), ((1, 1),), ((1, 1), (4, 3))))
    assert all(d.find(clean, 0) is not None for d in (library_default, one_bit, none))
    assert library_default.find(one_wrong, 0) is not None and one_bit.find(one_wrong, 0) is not None
    assert none.find(one_wrong, 0) is None
    assert library_default.find(two_wrong, 0) is not None
    assert one_bit.find(two_wrong, 0) is None
    with pytest.raises(ValueError, match="corrected bits"):
        F.TagDetector(backend="apriltag", apriltag_corrected_bits=3)
    with pytest.raises(msgspec.ValidationError):
        msgspec.convert({"apriltag_corrected_bits": 3}, VisionConfig)
