"""The simulated world: MuJoCo physics at 1 kHz, the JACO-2's actuators (their firmware,
:mod:`services.robot_sim.firmware`) on its joints, the target's motion, and eye-in-hand rendering. No zenoh, no
threads, no wall time: the service (and tests, and notebooks) drive it.

Time is the arm's own timeline: integer nanoseconds that advance only by whole bus cycles (:meth:`cycle`, 2 ms),
each a fixed number of physics steps. At a cycle boundary the actuators take the commands that came during the
cycle before and report their values; then physics runs to the next boundary. Camera frames fall on the boundary
at or after their nominal times.
"""
from __future__ import annotations

import collections
import math
from typing import Optional

import mujoco
import numpy as np

from services.model import frames
from services.model.arm import EE_LINK, ArmDescription, load_arm
from services.runtime.metrics import Counters
from services.robot.hardware import CYCLE_NS, ActuatorValues
from services.robot_sim import scene as scene_mod
from services.robot_sim.imaging import expose
from services.robot_sim.finger_firmware import FingerFirmware
from services.robot_sim.firmware import ActuatorConfig, ActuatorFirmware


#: where an object that is not in the scene is kept: far below the floor, out of every view
OUT_OF_SCENE = np.array([0.0, 0.0, -100.0])


class _Mover:
    """A scene object's schedule: its position at time t (s), or out of the scene outside [arrives, leaves)."""

    def __init__(self, mocap: int, start: np.ndarray, velocity: np.ndarray, arrives: Optional[float],
                 leaves: Optional[float]) -> None:
        self.mocap, self.start, self.velocity = mocap, np.array(start, dtype=float), velocity
        self.arrives, self.leaves = arrives, leaves

    def position(self, t: float) -> np.ndarray:
        if (self.arrives is not None and t < self.arrives) or (self.leaves is not None and t >= self.leaves):
            return OUT_OF_SCENE
        return self.start + self.velocity * t


class Simulation:
    def __init__(self, scene: scene_mod.SceneConfig | None = None, actuators: ActuatorConfig | None = None,
                 render: bool = True, counters: Counters | None = None, arm: ArmDescription | None = None) -> None:
        #: the arm simulated (its description; a service passes the one it is configured with, a notebook may
        #: leave it to the default arm)
        self.arm = arm if arm is not None else load_arm()
        self.scene = scene or scene_mod.SceneConfig()
        self.scene.check(self.arm)
        self.n = self.arm.n_joints
        self.model = scene_mod.build_model(self.scene, self.arm)
        self.data = mujoco.MjData(self.model)
        #: the hand's fingers: their hinges follow the arm's joints in MuJoCo's coordinates, the free objects' six
        #: each after them
        self.n_fingers = 0 if self.arm.hand is None else self.arm.hand.n_fingers
        free = self.scene.free_objects
        if self.model.nv != self.n + self.n_fingers + 6 * len(free):
            raise ValueError(f"the model must have exactly {self.n} joints', {self.n_fingers} fingers' and "
                             f"{len(free)} free objects' dofs, it has {self.model.nv}")
        #: each free object's free joint's coordinates in qpos (where it is now: :meth:`object_pose`)
        self._free_qpos = {obj.name: int(self.model.joint(f"{scene_mod.object_body(obj)}_free").qposadr[0])
                           for obj in free}
        self.firmware = ActuatorFirmware(self.model, self.data, self.arm, actuators, counters)
        #: the hand's finger actuators (None: the arm carries no hand)
        self.fingers = FingerFirmware(self.model, self.data, self.arm) if self.n_fingers else None
        self.physics_dt_ns = int(round(self.model.opt.timestep * 1e9))
        self.cycle_ns = CYCLE_NS
        if self.cycle_ns % self.physics_dt_ns:
            raise ValueError("the bus cycle must be a whole number of physics steps")
        self.steps_per_cycle = self.cycle_ns // self.physics_dt_ns
        self.frame_period_ns = int(round(1e9 / self.scene.camera.rate_hz))
        self.time_ns = 0
        self.next_frame_ns = 0
        self.frame_count = 0
        self._mocap = self.model.body(scene_mod.TAG_BODY).mocapid[0]
        self._target_start = self.data.mocap_pos[self._mocap].copy()
        self._target_velocity = np.asarray(self.scene.target.velocity_mps, dtype=float)
        #: the scene's other objects (and the target, when it leaves): where each is at a time, and when it is there
        self._scheduled = [_Mover(self.model.body(scene_mod.object_body(obj)).mocapid[0],
                                  scene_mod.object_in_base(self.scene, self.arm, obj)[:3, 3],
                                  np.asarray(obj.velocity_mps, dtype=float), obj.arrives_at_s, obj.leaves_at_s)
                           for obj in self.scene.objects if not obj.free]
        #: the target stuck on a free object: that object's free joint's coordinates, and where on it the target is
        carrier = self.scene.carrier()
        self._carrier: Optional[tuple[int, np.ndarray]] = None
        if carrier is not None:
            self._carrier = (self._free_qpos[carrier.name], self.scene.target.pose_in_object.matrix())
        self._ee_body = self.model.body(EE_LINK).id
        self._camera_id = self.model.camera(scene_mod.CAMERA_NAME).id
        self._renderer = None
        self._render_enabled = render
        imaging = self.scene.camera.imaging
        #: the world at each of the last cycle boundaries, as long back as the camera's exposure (motion blur)
        self._history: Optional[collections.deque] = None
        if imaging is not None and imaging.exposure_s > 0:
            self._history = collections.deque(maxlen=int(math.ceil(imaging.exposure_s * 1e9 / self.cycle_ns)) + 2)
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self, joints_deg=None) -> None:
        mujoco.mj_resetData(self.model, self.data)
        q = self.firmware.model_from_physical_deg(self.scene.start_deg(self.arm) if joints_deg is None else joints_deg)
        self.data.qpos[: self.n] = q
        self.data.mocap_pos[self._mocap] = self._target_start
        self.time_ns = 0
        self._place_scheduled()
        if self._carrier is not None:
            self._follow_carrier()
        mujoco.mj_forward(self.model, self.data)
        self.firmware.now_s = 0.0
        self.firmware.hold_all()
        if self.fingers is not None:
            self.fingers.hold_all()
        self.next_frame_ns = 0
        self.frame_count = 0

    @property
    def q(self) -> np.ndarray:
        return self.data.qpos[: self.n].copy()

    @property
    def dq(self) -> np.ndarray:
        return self.data.qvel[: self.n].copy()

    @property
    def tau(self) -> np.ndarray:
        return self.data.actuator_force[: self.n].copy()

    def ee_pose(self) -> np.ndarray:
        return frames.homogeneous(self.data.xmat[self._ee_body].reshape(3, 3), self.data.xpos[self._ee_body])

    def ee_twist_base(self) -> np.ndarray:
        """[v; ω] of the end-effector origin in base coordinates, from MuJoCo's own Jacobian."""
        jacp, jacr = np.zeros((3, self.model.nv)), np.zeros((3, self.model.nv))
        mujoco.mj_jacBody(self.model, self.data, jacp, jacr, self._ee_body)
        return np.concatenate([jacp @ self.data.qvel, jacr @ self.data.qvel])

    def camera_pose(self) -> np.ndarray:
        """The camera's optical frame (OpenCV convention) in the base frame."""
        return frames.homogeneous(self.data.cam_xmat[self._camera_id].reshape(3, 3) @ scene_mod.MUJOCO_FROM_OPTICAL.T,
                                  self.data.cam_xpos[self._camera_id])

    def target_pose(self) -> np.ndarray:
        return frames.homogeneous(frames.quat_wxyz_to_matrix(self.data.mocap_quat[self._mocap]),
                                  self.data.mocap_pos[self._mocap])

    @property
    def free_objects(self) -> list[str]:
        """The free objects' names, in the scene's order."""
        return list(self._free_qpos)

    def object_pose(self, name: str) -> np.ndarray:
        """Where a free object is now (base frame): MuJoCo's truth, for what measures a grasp."""
        return self._free_pose(self._free_qpos[name])

    def _free_pose(self, address: int) -> np.ndarray:
        """A free joint's pose from its coordinates (position, then orientation): current after a step, where the
        bodies' poses are the step's start's."""
        coordinates = self.data.qpos[address:address + 7]
        return frames.homogeneous(frames.quat_wxyz_to_matrix(coordinates[3:]), coordinates[:3])

    def set_target_pose(self, T: np.ndarray) -> None:
        if self._carrier is not None:
            raise ValueError("the target is on an object: it goes where the object goes")
        self.data.mocap_pos[self._mocap] = T[:3, 3]
        self.data.mocap_quat[self._mocap] = frames.matrix_to_quat_wxyz(T[:3, :3])
        self._target_start = self.data.mocap_pos[self._mocap] - self._target_velocity * (self.time_ns * 1e-9)
        mujoco.mj_kinematics(self.model, self.data)

    # ------------------------------------------------------------------ stepping
    def begin_cycle(self) -> ActuatorValues:
        """The cycle boundary: the actuators take the commands of the cycle before; returns what they report for
        this cycle (its stamp is the boundary's time)."""
        self.firmware.begin_cycle(self.time_ns * 1e-9)
        if self.fingers is not None:
            self.fingers.begin_cycle()
        if self._history is not None:
            d = self.data
            self._history.append((self.time_ns, d.qpos.copy(), d.mocap_pos.copy(), d.mocap_quat.copy()))
        return self.firmware.values(self.time_ns)

    def world_at(self, time_ns: int) -> Optional[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The joints and the target (qpos, mocap_pos, mocap_quat) at the last cycle boundary at or before
        ``time_ns`` that is still remembered (the camera's exposure back), or None when nothing is."""
        if not self._history:
            return None
        chosen = self._history[0]
        for entry in self._history:
            if entry[0] > time_ns:
                break
            chosen = entry
        return chosen[1], chosen[2], chosen[3]

    def end_cycle(self) -> None:
        """Physics to the next boundary."""
        self.step_physics(self.steps_per_cycle)

    def cycle(self) -> ActuatorValues:
        values = self.begin_cycle()
        self.end_cycle()
        return values

    def step_physics(self, steps: int = 1) -> None:
        """Physics only: the actuators set their torques each step, the target moves."""
        moving = bool(self._target_velocity.any())
        fingers = self.fingers
        for _ in range(steps):
            self.firmware.apply(self.time_ns * 1e-9)
            if fingers is not None:
                fingers.apply()
            mujoco.mj_step(self.model, self.data)
            self.time_ns += self.physics_dt_ns
            if moving:
                self.data.mocap_pos[self._mocap] = self._target_start + self._target_velocity * (self.time_ns * 1e-9)
            if self._scheduled or self.scene.target.leaves_at_s is not None:
                self._place_scheduled()
            if self._carrier is not None:
                self._follow_carrier()

    def _place_scheduled(self) -> None:
        """The scene's other objects where they are now, and out of the scene (far below the floor) when they are
        not in it; the target too, once it has left."""
        t = self.time_ns * 1e-9
        for mover in self._scheduled:
            self.data.mocap_pos[mover.mocap] = mover.position(t)
        leaves = self.scene.target.leaves_at_s
        if leaves is not None and t >= leaves:
            self.data.mocap_pos[self._mocap] = OUT_OF_SCENE

    def _follow_carrier(self) -> None:
        """The target where its object is now (the object's free joint: its position, then its orientation)."""
        address, in_object = self._carrier
        T = self._free_pose(address) @ in_object
        self.data.mocap_pos[self._mocap] = T[:3, 3]
        self.data.mocap_quat[self._mocap] = frames.matrix_to_quat_wxyz(T[:3, :3])

    def frame_due(self) -> bool:
        return self.time_ns >= self.next_frame_ns

    def mark_frame(self) -> None:
        """Record that the frame due now was captured (by :meth:`render` or by a renderer of a snapshot)."""
        self.frame_count += 1
        while self.next_frame_ns <= self.time_ns:
            self.next_frame_ns += self.frame_period_ns

    @property
    def camera_id(self) -> int:
        return self._camera_id

    def render(self) -> np.ndarray:
        """An RGB image (H×W×3 uint8) from the eye-in-hand camera at the current state; advances the frame
        schedule. Must be called from the thread that owns this simulation (the EGL context is per thread)."""
        if not self._render_enabled:
            raise RuntimeError("this simulation was created with render=False")
        if self._renderer is None:
            cam = self.scene.camera
            self._renderer = scene_mod.renderer(self.model, cam.height, cam.width)
        mujoco.mj_forward(self.model, self.data)
        self._renderer.update_scene(self.data, camera=self._camera_id)
        image = self._renderer.render().copy()
        self.mark_frame()
        imaging = self.scene.camera.imaging
        return image if imaging is None else expose(image, imaging, self.time_ns)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
