"""Teach by showing: the current view kept as a goal, each keypoint's depth measured by the arm itself (pure: no
zenoh, no clock; :class:`TeachSession` is vision's, the steps are driven by services/vision/teach_client.py).

1. **begin**: with the arm at rest, the object's keypoints in its region of the image (SIFT or ORB), refused when the
   region has too little texture, with the camera's pose (the arm's forward kinematics and the camera's mount);
2. the arm moves the camera a few centimetres sideways (the controller's move phase, after the person confirms;
   safety checks it as any command);
3. **second view**, at rest again: the first view's keypoints matched in this one (ratio test, then the epipolar
   constraint by MAGSAC), and triangulated from the camera's measured motion between the two views (a known
   baseline: the points' depths in metres, not up to scale); points whose reprojection error in either view is over
   ``max_triangulation_error_px``, or seen under less than ``min_parallax_deg``, are dropped. A plane fitted to the
   rest (least squares, twice, the second time without the points beyond 3σ) says whether the object is planar:
   then each point's depth is the plane's along its ray (Malis and Rives: IBVS tolerates a wrong depth less than
   one hopes, and the plane averages the triangulation's noise out), and the plane's normal is kept;
4. **finish**: the goal file (services/vision/taught.py), which vision then servos to.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np

from protocol.messages import CameraInfo, RobotState
from services.model import frames
from services.model.kinematics import ArmKinematics
from services.runtime.config import ConfigStruct
from services.vision import features as F
from services.vision.keypoints import KeypointConfig, epipolar_inliers, equalized, make_detector, matcher_for, ratio_matches
from services.vision.taught import FILE_FORMAT, FILE_VERSION, MAX_GOAL_KEYPOINTS, TaughtCamera, TaughtGoalFile


class TeachConfig(ConfigStruct):
    """How a view is taught (each number's source, or why it is ours)."""

    #: the default region: the frame less this fraction of its width and height on every side
    border_fraction: float = 0.1
    #: the fewest keypoints a region must have: fewer is a teach with no texture in it (our choice: enough that a
    #: third of them survives the second view, the triangulation and the servo's 12-inlier bound with room)
    min_keypoints: int = 60
    #: the most keypoints kept (the detector's strongest, at most a sixteenth of them in any cell of a 4×4 grid over
    #: the region, so that the pose is not held by one corner of the object)
    max_keypoints: int = 600
    #: the fewest points triangulated into the goal
    min_triangulated: int = 30
    #: the arm is at rest when no joint turns faster than this (rad/s): both views are taken at rest
    rest_speed_rps: float = 0.005
    #: a point whose reprojection error in either view is over this is not kept (px)
    max_triangulation_error_px: float = 1.0
    #: ... nor one seen from the two views under less than this angle (deg): its depth would be noise
    min_parallax_deg: float = 0.5
    #: the object is planar when a plane fits its points within this fraction of their median depth (RMS): 0.5 % is
    #: 1.4 mm at 0.29 m, the triangulation's own noise at a 3-cm baseline and 0.3 px; a cup's wall bulges 10 mm
    planar_rms_fraction: float = 0.005
    #: the probe motion's size (m, in the camera's frame): sideways, a few centimetres (the issue's; 3 cm is a tenth
    #: of Table 2's goal depth, a 6° baseline)
    probe_m: tuple[float, float, float] = (0.03, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not 0.0 <= self.border_fraction < 0.45:
            raise ValueError("teach.border_fraction must be within 0..0.45")
        if not (8 <= self.min_triangulated <= self.min_keypoints <= self.max_keypoints <= MAX_GOAL_KEYPOINTS):
            raise ValueError(f"teach needs 8 <= min_triangulated <= min_keypoints <= max_keypoints <= "
                             f"{MAX_GOAL_KEYPOINTS}")
        if not 0.005 <= float(np.linalg.norm(self.probe_m)) <= 0.1:
            raise ValueError("teach.probe_m must be 5 mm to 10 cm long")


def default_region(width: int, height: int, border_fraction: float) -> np.ndarray:
    """The frame less a border (a polygon, px)."""
    bx, by = border_fraction * (width - 1), border_fraction * (height - 1)
    return np.array([[bx, by], [width - 1 - bx, by], [width - 1 - bx, height - 1 - by], [bx, height - 1 - by]])


def region_problem(region: np.ndarray, width: int, height: int) -> str:
    """Why ``region`` cannot be taught from a width × height image, or ""."""
    if len(region) < 3 or not np.all(np.isfinite(region)):
        return "the region needs 3 or more finite corners"
    if np.any(region < -0.5) or np.any(region[:, 0] > width - 0.5) or np.any(region[:, 1] > height - 0.5):
        return f"the region is not inside the {width}x{height} image"
    area = abs(cv2.contourArea(region.astype(np.float32)))
    if area < 0.01 * width * height:
        return f"the region covers {100 * area / (width * height):.1f} % of the image (at least 1 %)"
    return ""


def keypoints_in_region(gray: np.ndarray, region: np.ndarray, detector, max_keypoints: int, equalization: str = "none"
                        ) -> tuple[np.ndarray, np.ndarray]:
    """(pixels n×2, descriptors) of the detector's strongest keypoints inside ``region``, spread over it."""
    mask = np.zeros(gray.shape[:2], np.uint8)
    cv2.fillPoly(mask, [np.round(region).astype(np.int32)], 255)
    keypoints, descriptors = detector.detectAndCompute(equalized(gray, equalization), mask)
    if descriptors is None or not keypoints:
        return np.zeros((0, 2)), np.zeros((0, 1), np.float32)
    order = sorted(range(len(keypoints)), key=lambda i: -keypoints[i].response)
    lo, hi = region.min(axis=0), region.max(axis=0)
    cell_cap = max(1, max_keypoints // 16)
    counts: dict[tuple[int, int], int] = {}
    chosen = []
    for i in order:
        x, y = keypoints[i].pt
        cell = (min(3, int(4 * (x - lo[0]) / max(hi[0] - lo[0], 1.0))), min(3, int(4 * (y - lo[1]) / max(hi[1] - lo[1], 1.0))))
        if counts.get(cell, 0) < cell_cap:
            counts[cell] = counts.get(cell, 0) + 1
            chosen.append(i)
        if len(chosen) >= max_keypoints:
            break
    return np.array([keypoints[i].pt for i in chosen], dtype=float), descriptors[chosen]


def camera_in_base(kin: ArmKinematics, q, camera_in_ee: np.ndarray) -> np.ndarray:
    """The camera's optical frame in the base frame at configuration ``q`` (the description's kinematics)."""
    return frames.homogeneous(*kin.pose(q)) @ camera_in_ee


def triangulate(n1: np.ndarray, n2: np.ndarray, second_in_first: np.ndarray) -> np.ndarray:
    """The 3D points (first camera's frame, n×3) seen at normalized ``n1`` in the first view and ``n2`` in the
    second, the second camera's pose in the first's frame ``second_in_first`` (DLT, cv2.triangulatePoints)."""
    first_to_second = np.linalg.inv(second_in_first)
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = first_to_second[:3, :]
    X = cv2.triangulatePoints(P1, P2, n1.T.astype(np.float64), n2.T.astype(np.float64))
    return (X[:3] / X[3]).T


def reprojection_px(points: np.ndarray, normalized: np.ndarray, camera_in_first: np.ndarray, f: float) -> np.ndarray:
    """Each point's reprojection error (px, at focal length ``f``) in the view whose camera is at ``camera_in_first``."""
    inv = np.linalg.inv(camera_in_first)
    P = points @ inv[:3, :3].T + inv[:3, 3]
    return f * np.linalg.norm(P[:, :2] / P[:, 2:3] - normalized, axis=1)


def parallax_deg(points: np.ndarray, second_in_first: np.ndarray) -> np.ndarray:
    """The angle under which each point sees the two camera centres (deg)."""
    a = points
    b = points - second_in_first[:3, 3]
    cos = np.sum(a * b, axis=1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, float, float, np.ndarray]:
    """(unit normal toward the camera, distance from the camera, RMS residual, the points used) of the plane that
    fits ``points`` best (least squares), fitted again without the points beyond 3σ of the first fit."""
    keep = np.ones(len(points), bool)
    for _ in range(2):
        centre = points[keep].mean(axis=0)
        _, _, vt = np.linalg.svd(points[keep] - centre)
        normal = vt[2]
        if normal @ centre > 0:  # toward the camera (its centre is the origin)
            normal = -normal
        residual = (points - centre) @ normal
        rms = float(np.sqrt(np.mean(residual[keep] ** 2)))
        keep = np.abs(residual) <= max(3.0 * rms, 1e-6)
    return normal, float(-normal @ centre), rms, keep


def depths_on_plane(normalized: np.ndarray, normal: np.ndarray, distance: float) -> np.ndarray:
    """Each ray's point on the plane {X: n·X = −d} (its ray through the normalized point)."""
    rays = np.column_stack([normalized, np.ones(len(normalized))])
    scale = distance / np.maximum(-(rays @ normal), 1e-9)
    return rays * scale[:, None]


def at_rest(state: RobotState, rest_speed_rps: float) -> bool:
    return float(np.max(np.abs(state.dq))) <= rest_speed_rps


@dataclass
class FirstView:
    gray: np.ndarray
    region: np.ndarray
    detector: str
    equalization: str
    pixels: np.ndarray
    descriptors: np.ndarray
    camera: np.ndarray  # the camera's pose in the base frame
    state: RobotState
    info: CameraInfo
    operator: str


@dataclass
class Triangulated:
    pixels: np.ndarray
    descriptors: np.ndarray
    points: np.ndarray
    planar: bool
    normal: Optional[np.ndarray]
    distance: Optional[float]
    error_px: float
    probe_m: np.ndarray


class TeachError(ValueError):
    """A step of the teach that cannot be done, and why (in one line)."""


class TeachSession:
    """One teach, step by step; each step raises TeachError with the reason when it cannot be done."""

    def __init__(self, config: TeachConfig) -> None:
        self.config = config
        self.first: Optional[FirstView] = None
        self.triangulated: Optional[Triangulated] = None

    def begin(self, gray: np.ndarray, info: CameraInfo, state: Optional[RobotState], kin: Optional[ArmKinematics],
              region: Optional[np.ndarray], detector: str, operator: str, equalization: Optional[str] = None) -> int:
        """The first view; the number of keypoints in the region (``equalization``: the keypoint front end's by
        default)."""
        cfg = self.config
        equalization = equalization or KeypointConfig().equalization
        height, width = gray.shape[:2]
        region = default_region(width, height, cfg.border_fraction) if region is None or not len(region) else \
            np.asarray(region, dtype=float)
        problem = region_problem(region, width, height)
        if problem:
            raise TeachError(problem)
        if state is None or kin is None:
            raise TeachError("no robot state: the teach needs the arm's pose")
        if not at_rest(state, cfg.rest_speed_rps):
            raise TeachError(f"the arm is moving ({np.max(np.abs(state.dq)):.3f} rad/s): teach it at rest")
        pixels, descriptors = keypoints_in_region(gray, region, make_detector(detector), cfg.max_keypoints,
                                                  equalization)
        if len(pixels) < cfg.min_keypoints:
            raise TeachError(f"the region has too little texture: {len(pixels)} keypoints (at least "
                             f"{cfg.min_keypoints}); show the object closer, or another side of it")
        camera_in_ee = frames.homogeneous(frames.quat_wxyz_to_matrix(info.camera_in_ee.quat_wxyz), info.camera_in_ee.xyz)
        self.first = FirstView(gray, region, detector, equalization, pixels, descriptors,
                               camera_in_base(kin, state.q, camera_in_ee),
                               state, info, operator)
        self.triangulated = None
        return len(pixels)

    def second_view(self, gray: np.ndarray, state: Optional[RobotState], kin: Optional[ArmKinematics]) -> Triangulated:
        """The second view, after the probe motion: the first view's keypoints triangulated."""
        cfg, first = self.config, self.first
        if first is None:
            raise TeachError("no first view: begin the teach first")
        if state is None or kin is None:
            raise TeachError("no robot state: the teach needs the arm's pose")
        if not at_rest(state, cfg.rest_speed_rps):
            raise TeachError(f"the arm is moving ({np.max(np.abs(state.dq)):.3f} rad/s): the second view is taken "
                             "at rest")
        info = first.info
        camera_in_ee = frames.homogeneous(frames.quat_wxyz_to_matrix(info.camera_in_ee.quat_wxyz), info.camera_in_ee.xyz)
        second_camera = camera_in_base(kin, state.q, camera_in_ee)
        second_in_first = np.linalg.inv(first.camera) @ second_camera
        baseline = float(np.linalg.norm(second_in_first[:3, 3]))
        if baseline < 0.005:
            raise TeachError(f"the camera moved {baseline * 1e3:.1f} mm between the views (at least 5 mm)")
        detector = make_detector(first.detector)
        keypoints, descriptors = detector.detectAndCompute(equalized(gray, first.equalization), None)
        if descriptors is None or len(keypoints) < cfg.min_triangulated:
            raise TeachError("the second view shows too little of the object")
        matches = ratio_matches(first.descriptors, descriptors, matcher_for(first.detector), 0.75)
        if len(matches) < cfg.min_triangulated:
            raise TeachError(f"only {len(matches)} keypoints found again in the second view (at least "
                             f"{cfg.min_triangulated}): did the object move?")
        ids = np.array([m[0] for m in matches])
        px1 = first.pixels[ids]
        px2 = np.array([keypoints[m[1]].pt for m in matches], dtype=float)
        mask = epipolar_inliers(px1, px2, 1.5)
        if mask is not None:  # (a planar object's epipolar geometry may be degenerate: the triangulation's checks)
            ids, px1, px2 = ids[mask], px1[mask], px2[mask]
        K = F.camera_matrix(info.fx, info.fy, info.cx, info.cy)
        dist = np.asarray(info.distortion, dtype=float)
        n1, n2 = F.normalize(px1, K, dist), F.normalize(px2, K, dist)
        points = triangulate(n1, n2, second_in_first)
        f = 0.5 * (info.fx + info.fy)
        err1 = reprojection_px(points, n1, np.eye(4), f)
        err2 = reprojection_px(points, n2, second_in_first, f)
        keep = ((points[:, 2] > 0.02) & (err1 <= cfg.max_triangulation_error_px)
                & (err2 <= cfg.max_triangulation_error_px) & (parallax_deg(points, second_in_first) >= cfg.min_parallax_deg))
        if keep.sum() < cfg.min_triangulated:
            raise TeachError(f"only {int(keep.sum())} keypoints triangulated within "
                             f"{cfg.max_triangulation_error_px:g} px (at least {cfg.min_triangulated}): did the "
                             "object move, or the arm's pose not match its description?")
        ids, n1, points = ids[keep], n1[keep], points[keep]
        error = float(np.median(np.maximum(err1[keep], err2[keep])))
        normal, distance, rms, on_plane = fit_plane(points)
        planar = rms <= cfg.planar_rms_fraction * float(np.median(points[:, 2])) and on_plane.mean() >= 0.8
        if planar:
            ids, n1 = ids[on_plane], n1[on_plane]
            points = depths_on_plane(n1, normal, distance)
        self.triangulated = Triangulated(first.pixels[ids], first.descriptors[ids], points, planar,
                                         normal if planar else None, distance if planar else None, error,
                                         second_in_first[:3, 3])
        return self.triangulated

    def finish(self, name: str, taught_ns: int) -> TaughtGoalFile:
        first, t = self.first, self.triangulated
        if first is None or t is None:
            raise TeachError("the teach has no second view yet: the depths are not measured")
        info = first.info
        ok, png = cv2.imencode(".png", first.gray)
        state = first.state
        dtype = "float32" if first.detector == "sift" else "uint8"
        descriptors = np.ascontiguousarray(t.descriptors.astype(dtype))
        return TaughtGoalFile(
            format=FILE_FORMAT, version=FILE_VERSION, name=name, taught_ns=taught_ns, operator=first.operator,
            detector=first.detector, equalization=first.equalization,
            camera=TaughtCamera(width=info.width, height=info.height, fx=info.fx, fy=info.fy, cx=info.cx, cy=info.cy,
                                distortion=list(info.distortion)),
            arm=state.arm, arm_digest=state.arm_digest, joints=[float(v) for v in state.q],
            camera_in_base=[float(v) for v in first.camera.reshape(-1)],
            region_px=[(float(x), float(y)) for x, y in first.region],
            keypoints_px=[(float(x), float(y)) for x, y in t.pixels],
            points_camera=[(float(x), float(y), float(z)) for x, y, z in t.points],
            descriptors=descriptors.tobytes(), descriptor_dtype=dtype, descriptor_size=int(descriptors.shape[1]),
            planar=bool(t.planar), plane_normal=None if t.normal is None else tuple(float(v) for v in t.normal),
            plane_distance_m=None if t.distance is None else float(t.distance),
            probe_m=tuple(float(v) for v in t.probe_m), triangulation_error_px=float(t.error_px),
            image_png=png.tobytes() if ok else b"")

