"""Shared test helpers: random configurations and reference kinematics through Pinocchio."""
import ctypes
import ctypes.util
import os
from pathlib import Path

import numpy as np

from services import paths
from services.model.kinematics import ArmKinematics
from services.model.arm import load_arm

ARM = load_arm("j2s7s300")
#: a robot state's declaration of that arm (RobotState's arm and arm_digest)
ARM_DECLARED = {"arm": ARM.name, "arm_digest": ARM.digest}


def computed_torque_options_for_the_emulated_arm(arm=ARM, **options):
    """The options of the JACO thesis's computed torque (the ``computed-torque`` controller) with gains that hold the
    emulated arm's joints through their torque-mode friction: the K-58 wrist joints, light behind their friction,
    nine times stiffer (JACO thesis §5.4 likewise needed a far higher gain on joint 6 than on the others)."""
    from services.controller.torque_controllers import ControllerOptions

    wrist = np.array([j.actuator == "K-58" for j in arm.joints])
    kp = np.where(wrist, 900.0, 100.0)
    return ControllerOptions(kp=kp.tolist(), kd=(2.0 * np.sqrt(kp)).tolist(), **options)


def emulated_arm_gravity(arm):
    """The emulated arm's own gravity torque (N·m) as a function of model angles: robot_sim's MuJoCo model at rest,
    built once (a host's torque loop can call it every cycle)."""
    import mujoco

    from services.robot_sim.scene import CameraConfig, SceneConfig, build_model

    true_model = build_model(SceneConfig(camera=CameraConfig(enabled=False)), arm)
    data = mujoco.MjData(true_model)

    def gravity(q) -> np.ndarray:
        data.qpos[: arm.n_joints] = q
        mujoco.mj_forward(true_model, data)
        return data.qfrc_bias[: arm.n_joints].copy()

    return gravity


def gravity_the_description_misses(arm, q) -> np.ndarray:
    """The emulated arm's gravity torque less its description's at model angles ``q`` (N·m): mostly the hand's
    extra 30 % (services/model/arm.py's emulation). The truth is robot_sim's own MuJoCo model at rest."""
    return emulated_arm_gravity(arm)(q) - ArmKinematics(arm).gravity(q)


#: the repository's root
REPO = paths.REPO


def random_q(rng, margin_deg: float = 2.0) -> np.ndarray:
    """Model angles: limited joints uniformly inside their limits, continuous joints over ±2 turns."""
    lower, upper = ARM.model_limits()
    q = rng.uniform(-4 * np.pi, 4 * np.pi, ARM.n_joints)
    limited = np.isfinite(lower)
    m = np.radians(margin_deg)
    q[limited] = rng.uniform(lower[limited] + m, upper[limited] - m)
    return q


class PinArm(ArmKinematics):
    """Reference kinematics for tests: the product's Pinocchio wrapper (checked against MuJoCo and the DH table
    in test_arm), of the default arm unless told another."""

    def __init__(self, arm=ARM) -> None:
        super().__init__(arm)


#: Sensors 2022 Table 2's goal: the square ±0.1666 (normalised) at 0.2888 m
GOAL_SQUARE = np.array([[-0.1666, -0.1666], [0.1666, -0.1666], [0.1666, 0.1666], [-0.1666, 0.1666]])


def tag_corners_seen(q, tag_in_base: np.ndarray, camera_in_ee: np.ndarray, kin: ArmKinematics | None = None,
                     size_m: float = 0.0962) -> tuple[np.ndarray, np.ndarray]:
    """Normalised corners and depths of the tag at ``tag_in_base`` from the camera at configuration q (the model's
    kinematics, exact projection)."""
    from services.model import frames
    from services.model import tag as tags

    camera = frames.homogeneous(*(kin or ArmKinematics(ARM)).pose(q)) @ camera_in_ee
    T = np.linalg.inv(camera) @ tag_in_base
    corners = (T[:3, :3] @ tags.corners_in_tag(size_m).T).T + T[:3, 3]
    return corners[:, :2] / corners[:, 2:3], corners[:, 2]


def iterations_in_a_late_loop(law, tag_in_camera: np.ndarray, camera_in_ee: np.ndarray, *, seed: int,
                              image_delay_s: float = 0.0, command_delay_s: tuple[float, float] = (0.04, 0.04),
                              frame_gaps: dict[float, float] | None = None, noise: float = 1e-5, carry=None,
                              max_iterations: int = 400) -> int | None:
    """A joint-velocity law in a realtime-like loop without services: from HOME, the tag at ``tag_in_camera``;
    frames taken ``frame_gaps`` apart (gap: probability), each answered ``image_delay_s`` after its capture
    (detection and transport) with the arm's state then, the command moving the arm ``command_delay_s`` (a
    uniform range) after the answer, corners with ``noise``. ``carry(points, depths, q_capture, q_now)`` is
    applied to the frame before the law when given. The iterations to ‖e‖ < 5e-5, or None within
    ``max_iterations``."""
    from services.controller.law import ServoInput
    from services.model import frames

    gaps = frame_gaps or {0.03: 0.5, 0.04: 0.4, 0.07: 0.1}
    rng = np.random.default_rng(seed)
    kin = ArmKinematics(ARM)
    tag_in_base = frames.homogeneous(*kin.pose(ARM.home)) @ camera_in_ee @ tag_in_camera
    q, t = ARM.home.copy(), 0.0
    commands = [(0.0, np.zeros(ARM.n_joints))]  # (moving the arm from, joint velocities)

    def in_effect(at: float) -> np.ndarray:
        return [dq for start, dq in commands if start <= at][-1]

    events, capture_t = [], 0.0  # (time, 0 capture | 1 answer, frame)
    for k in range(max_iterations):
        events += [(capture_t, 0, k), (capture_t + image_delay_s, 1, k)]
        capture_t += rng.choice(list(gaps), p=list(gaps.values()))
    taken, iteration = {}, 0
    for when, kind, k in sorted(events):
        while t < when - 1e-12:
            step = min(0.002, when - t)
            q, t = q + in_effect(t) * step, t + step
        if kind == 0:
            points, depths = tag_corners_seen(q, tag_in_base, camera_in_ee, kin)
            taken[k] = (points + rng.normal(scale=noise, size=points.shape), depths, q.copy())
            continue
        points, depths, q_capture = taken.pop(k)
        if np.linalg.norm(points - GOAL_SQUARE) < 5e-5:
            return iteration + 1
        iteration += 1
        if carry is not None:
            points, depths = carry(points, depths, q_capture, q)
        dq = law.step(ServoInput(t_s=t, points=points, depths=depths, goal_points=GOAL_SQUARE,
                                 goal_depths=np.full(4, 0.2888), q=q.copy(), camera_in_ee=camera_in_ee,
                                 dq=in_effect(t).copy())).joint_velocities
        dq = dq / max(1.0, float(np.max(np.abs(dq) / (ARM.max_speed * 0.8))))
        commands.append((t + rng.uniform(*command_delay_s), dq))
    return None


def signal_a_thread_not_the_main(pid: int, sig: int) -> str:
    """Send ``sig`` to one thread of process ``pid`` other than its main thread (as the kernel may deliver a signal
    sent to the process: to any thread not blocking it); that thread's kernel name."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    others = sorted(int(tid) for tid in os.listdir(f"/proc/{pid}/task") if int(tid) != pid)
    assert others, f"process {pid} has no thread besides its main one"
    tid = others[0]
    if libc.tgkill(pid, tid, sig) != 0:
        raise OSError(ctypes.get_errno(), f"tgkill({pid}, {tid}) failed")
    return Path(f"/proc/{pid}/task/{tid}/comm").read_text().strip()
