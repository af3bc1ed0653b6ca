"""The simulation: MuJoCo physics at 1 kHz, the emulated DSP at 100 Hz on the joint actuator interface, the
target's motion, and eye-in-hand rendering. No zenoh here: the service (and tests, and notebooks) drive it.

Time is simulated and integer: ``time_ns`` advances by whole physics steps; DSP cycles and camera frames fall on
the physics step at or after their nominal times.
"""
from __future__ import annotations

import mujoco
import numpy as np

from services.common import frames, jaco2
from services.common.actuators import SimActuators
from services.common.dsp import DSPConfig, KinovaDSP
from services.robot_sim import scene as scene_mod


class Simulation:
    def __init__(self, scene: scene_mod.SceneConfig | None = None, dsp: DSPConfig | None = None,
                 render: bool = True) -> None:
        self.scene = scene or scene_mod.SceneConfig()
        self.model = scene_mod.build_model(self.scene)
        self.data = mujoco.MjData(self.model)
        self.dsp = KinovaDSP(dsp)
        self.actuators = SimActuators(self.model, self.data, self.dsp.config.cycle_s)
        self.physics_dt_ns = int(round(self.model.opt.timestep * 1e9))
        self.cycle_ns = int(round(self.dsp.config.cycle_s * 1e9))
        if self.cycle_ns % self.physics_dt_ns:
            raise ValueError("the DSP cycle must be a whole number of physics steps")
        self.steps_per_cycle = self.cycle_ns // self.physics_dt_ns
        self.frame_period_ns = int(round(1e9 / self.scene.camera.rate_hz))
        self.time_ns = 0
        self.next_frame_ns = 0
        self.frame_count = 0
        self._mocap = self.model.body(scene_mod.TAG_BODY).mocapid[0]
        self._target_start = self.data.mocap_pos[self._mocap].copy()
        self._ee_body = self.model.body(jaco2.EE_LINK).id
        self._camera_id = self.model.camera(scene_mod.CAMERA_NAME).id
        self._renderer = None
        self._render_enabled = render
        self.reset()

    # ------------------------------------------------------------------ state
    def reset(self, joints_deg=None) -> None:
        mujoco.mj_resetData(self.model, self.data)
        q = jaco2.physical_deg_to_model(self.scene.initial_joints_deg if joints_deg is None else joints_deg)
        self.data.qpos[: jaco2.N_JOINTS] = q
        self.data.mocap_pos[self._mocap] = self._target_start
        mujoco.mj_forward(self.model, self.data)
        self.actuators.hold()
        self.time_ns = 0
        self.next_frame_ns = 0
        self.frame_count = 0

    @property
    def q(self) -> np.ndarray:
        return self.data.qpos[: jaco2.N_JOINTS].copy()

    @property
    def dq(self) -> np.ndarray:
        return self.data.qvel[: jaco2.N_JOINTS].copy()

    @property
    def tau(self) -> np.ndarray:
        return self.actuators.read().tau

    @property
    def q_ref(self) -> np.ndarray:
        """The joint angles the actuators are servoing to (what GetAngularCommand reports)."""
        return self.actuators.q_ref.copy()

    def ee_pose(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = self.data.xmat[self._ee_body].reshape(3, 3)
        T[:3, 3] = self.data.xpos[self._ee_body]
        return T

    def ee_twist_base(self) -> np.ndarray:
        """[v; ω] of the end-effector origin in base coordinates, from MuJoCo's own Jacobian."""
        jacp, jacr = np.zeros((3, self.model.nv)), np.zeros((3, self.model.nv))
        mujoco.mj_jacBody(self.model, self.data, jacp, jacr, self._ee_body)
        return np.concatenate([jacp @ self.data.qvel, jacr @ self.data.qvel])

    def camera_pose(self) -> np.ndarray:
        """The camera's optical frame (OpenCV convention) in the base frame."""
        T = np.eye(4)
        T[:3, :3] = self.data.cam_xmat[self._camera_id].reshape(3, 3) @ scene_mod.MUJOCO_FROM_OPTICAL.T
        T[:3, 3] = self.data.cam_xpos[self._camera_id]
        return T

    def target_pose(self) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = frames.quat_wxyz_to_matrix(self.data.mocap_quat[self._mocap])
        T[:3, 3] = self.data.mocap_pos[self._mocap]
        return T

    def set_target_pose(self, T: np.ndarray) -> None:
        self.data.mocap_pos[self._mocap] = T[:3, 3]
        self.data.mocap_quat[self._mocap] = frames.matrix_to_quat_wxyz(T[:3, :3])
        self._target_start = self.data.mocap_pos[self._mocap] - np.asarray(self.scene.target.velocity_mps) * (
            self.time_ns * 1e-9)
        mujoco.mj_kinematics(self.model, self.data)

    # ------------------------------------------------------------------ stepping
    def step_cycle(self) -> np.ndarray:
        """One DSP cycle (10 ms): the DSP reads the joints and writes references; physics runs to the next cycle.
        Returns the references written."""
        dq_ref = self.dsp_cycle()
        self.step_physics(self.steps_per_cycle)
        return dq_ref

    def dsp_cycle(self) -> np.ndarray:
        """The DSP's part of a cycle only (physics is the caller's, e.g. in 2 ms steps)."""
        dq_ref = self.dsp.cycle(self.actuators.read())
        self.actuators.write(dq_ref)
        return dq_ref

    def step_physics(self, steps: int = 1) -> None:
        """Physics only (no DSP cycle): the actuators apply their torques each step. For the actuator-bus mode,
        where the DSP runs in a gateway on the other side of the RS-485 bus."""
        dt = self.model.opt.timestep
        velocity = np.asarray(self.scene.target.velocity_mps, dtype=float)
        for _ in range(steps):
            self.actuators.apply(dt)
            mujoco.mj_step(self.model, self.data)
            self.time_ns += self.physics_dt_ns
            if velocity.any():
                self.data.mocap_pos[self._mocap] = self._target_start + velocity * (self.time_ns * 1e-9)

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
            self._renderer = mujoco.Renderer(self.model, cam.height, cam.width)
        mujoco.mj_forward(self.model, self.data)
        self._renderer.update_scene(self.data, camera=self._camera_id)
        image = self._renderer.render().copy()
        self.mark_frame()
        return image

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
