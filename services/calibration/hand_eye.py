"""Where the camera sits on the end effector (eye-in-hand): from arm poses and the board's pose in the camera at
each, solve A·X = X·B for X, the camera frame in the end-effector frame.

A recording is a folder of images and ``arm_poses.yaml``: ``arm: NAME`` and ``poses: [{image: NAME, joints_deg: [one angle per joint]}, ...]``,
the arm's physical joint angles (as GetAngularPosition reports them) when each image was taken, with the arm at
rest. The end effector's pose is the arm description's forward kinematics of those angles: the same kinematics the
controller servos with, so the mounting found is the one that makes the controller's camera Jacobian right.

Two steps, as ViSP's and most labs' tools do it:

1. a closed form from the board's pose in each view: OpenCV's ``calibrateHandEye`` (Park-Martin) where the installed
   OpenCV exposes it. OpenCV 5.0.0's Python package does not (opencv/opencv#29565, fixed by #29584 after that
   release), so the same method (Park and Martin 1994: rotation from the motions' rotation axes, then translation by
   least squares) is here as :func:`park_martin` and used in its place; a test checks the two agree where both exist;
2. a refinement of the mounting and the board's place in the base frame together, to the corners' reprojection
   error over every view (``scipy.optimize.least_squares``). A planar board's pose from one view is good to a tenth
   of a millimetre across the image but only to a few tenths of a degree in its tilt; the closed form takes those
   tilts as exact and its translation came out 4-6 mm off in the simulator, where the refinement, which weighs each
   corner as the image measured it, lands within a millimetre.
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from services.model import frames
from services.model.arm import DEFAULT_ARM, load_arm
from services.model.board import BoardConfig, BoardDetector
from services.runtime.config import ConfigError, ConfigStruct, config_from_mapping, read_yaml

#: fewer arm poses than this leave the mounting's rotation poorly determined
MIN_POSES = 5
#: a view with fewer board corners than this gives no pose
MIN_CORNERS = 12
POSES_FILE = "arm_poses.yaml"


class HandEyeFailed(RuntimeError):
    """The recording cannot give a mounting: the reason, and what to do."""


class RecordedPose(ConfigStruct):
    image: str
    joints_deg: list[float]


class Recording(ConfigStruct):
    #: the arm the poses were recorded on (its description: the forward kinematics of the joint angles)
    arm: str = DEFAULT_ARM
    poses: list[RecordedPose] = []

    def __post_init__(self) -> None:
        arm = load_arm(self.arm)
        for pose in self.poses:
            if len(pose.joints_deg) != arm.n_joints:
                raise ValueError(f"{pose.image}: joints_deg has {len(pose.joints_deg)} angles; the {arm.name} has "
                                 f"{arm.n_joints} joints")


def read_recording(directory: Path) -> Recording:
    path = Path(directory) / POSES_FILE
    return config_from_mapping(read_yaml(path), Recording, str(path))


def _pose(params: np.ndarray) -> np.ndarray:
    return frames.homogeneous(cv2.Rodrigues(params[:3])[0], params[3:6])


def _params(T: np.ndarray) -> np.ndarray:
    return np.concatenate([cv2.Rodrigues(T[:3, :3])[0].reshape(3), T[:3, 3]])


def refine_by_reprojection(T_base_ee: list[np.ndarray], views: list, camera_matrix: np.ndarray,
                           distortion: np.ndarray, T_ee_camera: np.ndarray,
                           T_base_board: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """The mounting and the board's pose in the base frame that best reproject every view's board corners
    (Levenberg-Marquardt from the closed form's answer); with the RMS reprojection error (px)."""
    from scipy.optimize import least_squares

    def residuals(x: np.ndarray) -> np.ndarray:
        X_inv, T_bb = np.linalg.inv(_pose(x[:6])), _pose(x[6:])
        out = []
        for T_be, view in zip(T_base_ee, views):
            T_cb = X_inv @ np.linalg.inv(T_be) @ T_bb
            projected, _ = cv2.projectPoints(view.object_points, cv2.Rodrigues(T_cb[:3, :3])[0], T_cb[:3, 3],
                                             camera_matrix, distortion)
            out.append((projected.reshape(-1, 2) - view.image_points).ravel())
        return np.concatenate(out)

    fit = least_squares(residuals, np.concatenate([_params(T_ee_camera), _params(T_base_board)]), method="lm")
    rms = float(np.sqrt(np.mean(fit.fun ** 2) * 2))  # per corner: two residuals each
    return _pose(fit.x[:6]), _pose(fit.x[6:]), rms


@dataclass
class HandEyeResult:
    #: the camera frame in the end-effector frame (4×4)
    T_ee_camera: np.ndarray
    #: how far the board's pose in the base frame, through each arm pose and the mounting found, strays from its
    #: mean (a constant board gives zero): RMS translation (mm) and rotation (deg)
    board_spread_mm: float
    board_spread_deg: float
    poses_used: int
    skipped: dict[str, str]
    solver: str
    #: RMS reprojection error of the board's corners through the mounting found (px)
    reprojection_rms_px: float = float("nan")
    #: how far the closed form's mounting was from the refined one (mm, deg): a large step says the views were poor
    refinement_step_mm: float = 0.0
    refinement_step_deg: float = 0.0

    def summary(self) -> dict:
        rpy = np.degrees(frames.matrix_to_euler_xyz(self.T_ee_camera[:3, :3]))
        return {"camera_in_ee": {"xyz": self.T_ee_camera[:3, 3].tolist(), "rpy_deg": rpy.tolist()},
                "board_spread_mm": self.board_spread_mm, "board_spread_deg": self.board_spread_deg,
                "poses_used": self.poses_used, "skipped": self.skipped, "solver": self.solver,
                "reprojection_rms_px": self.reprojection_rms_px, "refinement_step_mm": self.refinement_step_mm,
                "refinement_step_deg": self.refinement_step_deg}


def park_martin(T_base_ee: list[np.ndarray], T_camera_target: list[np.ndarray]) -> np.ndarray:
    """X = T_ee_camera from A·X = X·B over every pair of poses (i, j): A = T_base_ee[j]⁻¹·T_base_ee[i] (the end
    effector's motion), B = T_camera_target[j]·T_camera_target[i]⁻¹ (the camera's). The rotation maps the camera
    motions' rotation vectors onto the end effector's (least squares, by SVD); the translation solves
    (R_A − I)·t_X = R_X·t_B − t_A stacked over the pairs."""
    alphas, betas, rows, rhs = [], [], [], []
    pairs = list(combinations(range(len(T_base_ee)), 2))
    motions = []
    for i, j in pairs:
        A = np.linalg.inv(T_base_ee[j]) @ T_base_ee[i]
        B = T_camera_target[j] @ np.linalg.inv(T_camera_target[i])
        motions.append((A, B))
        alphas.append(frames.rotation_log(A[:3, :3]))
        betas.append(frames.rotation_log(B[:3, :3]))
    H = np.array(betas).T @ np.array(alphas)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R_X = Vt.T @ D @ U.T
    for A, B in motions:
        rows.append(A[:3, :3] - np.eye(3))
        rhs.append(R_X @ B[:3, 3] - A[:3, 3])
    t_X = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    return frames.homogeneous(R_X, t_X)


def solve_hand_eye(T_base_ee: list[np.ndarray], T_camera_target: list[np.ndarray]) -> tuple[np.ndarray, str]:
    """The mounting, by OpenCV's Park-Martin where the installed OpenCV has it, else by :func:`park_martin`."""
    if hasattr(cv2, "calibrateHandEye"):
        R, t = cv2.calibrateHandEye([T[:3, :3] for T in T_base_ee], [T[:3, 3] for T in T_base_ee],
                                    [T[:3, :3] for T in T_camera_target], [T[:3, 3] for T in T_camera_target],
                                    method=cv2.CALIB_HAND_EYE_PARK)
        return frames.homogeneous(R, np.asarray(t).reshape(3)), "opencv park"
    return park_martin(T_base_ee, T_camera_target), "park-martin (OpenCV's binding is missing)"


def mean_pose(poses: list[np.ndarray]) -> np.ndarray:
    """The mean position and the rotation nearest the mean of the rotation matrices."""
    U, _, Vt = np.linalg.svd(sum(T[:3, :3] for T in poses))
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return frames.homogeneous(R, np.mean([T[:3, 3] for T in poses], axis=0))


def board_spread(T_base_ee, T_camera_target, T_ee_camera) -> tuple[float, float]:
    """RMS distance (mm) and angle (deg) of the board's pose in the base frame, pose by pose, from their mean."""
    boards = [Tb @ T_ee_camera @ Tc for Tb, Tc in zip(T_base_ee, T_camera_target)]
    mean = mean_pose(boards)
    distances = [np.linalg.norm(B[:3, 3] - mean[:3, 3]) * 1e3 for B in boards]
    angles = [np.degrees(np.linalg.norm(frames.rotation_log(mean[:3, :3].T @ B[:3, :3]))) for B in boards]
    return float(np.sqrt(np.mean(np.square(distances)))), float(np.sqrt(np.mean(np.square(angles))))


def board_pose(view, camera_matrix: np.ndarray, distortion: np.ndarray) -> Optional[np.ndarray]:
    """The board's frame in the camera from its corners (OpenCV's iterative PnP, from IPPE's planar start)."""
    ok, rvec, tvec = cv2.solvePnP(view.object_points, view.image_points, camera_matrix, distortion,
                                  flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(view.object_points, view.image_points, camera_matrix, distortion, rvec, tvec)
    return frames.homogeneous(cv2.Rodrigues(rvec)[0], tvec.reshape(3))


def calibrate_hand_eye(directory: Path, board: BoardConfig, camera_matrix: np.ndarray,
                       distortion: np.ndarray) -> HandEyeResult:
    """Solve a recording (``directory``: images and ``arm_poses.yaml``) taken with a calibrated camera."""
    try:
        recording = read_recording(directory)
    except ConfigError as exc:
        raise HandEyeFailed(str(exc)) from None
    detector = BoardDetector(board)
    arm = load_arm(recording.arm)
    T_base_ee, T_camera_target, views, skipped = [], [], [], {}
    for pose in recording.poses:
        gray = cv2.imread(str(Path(directory) / pose.image), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            skipped[pose.image] = "no such image (or not one OpenCV reads)"
            continue
        view = detector.find(gray, MIN_CORNERS)
        T_ct = board_pose(view, camera_matrix, distortion) if view is not None else None
        if T_ct is None:
            skipped[pose.image] = f"fewer than {MIN_CORNERS} board corners found"
            continue
        T_base_ee.append(arm.dh_forward_kinematics(arm.physical_deg_to_model(pose.joints_deg)))
        T_camera_target.append(T_ct)
        views.append(view)
    if len(T_base_ee) < MIN_POSES:
        raise HandEyeFailed(f"the board was found at {len(T_base_ee)} of {len(recording.poses)} arm poses; at least "
                            f"{MIN_POSES} needed, with the wrist turned about different axes")
    X0, solver = solve_hand_eye(T_base_ee, T_camera_target)
    T_base_board0 = mean_pose([Tb @ X0 @ Tc for Tb, Tc in zip(T_base_ee, T_camera_target)])
    X, _, rms = refine_by_reprojection(T_base_ee, views, camera_matrix, distortion, X0, T_base_board0)
    step = np.linalg.inv(X0) @ X
    spread_mm, spread_deg = board_spread(T_base_ee, T_camera_target, X)
    return HandEyeResult(X, spread_mm, spread_deg, len(T_base_ee), skipped, f"{solver}, refined by reprojection",
                         rms, float(np.linalg.norm(step[:3, 3]) * 1e3),
                         float(np.degrees(np.linalg.norm(frames.rotation_log(step[:3, :3])))))
