"""The robot on the simulated arm with no zenoh and no threads: the robot node's rules (services.robot.core) over
the in-process hardware, one DSP cycle (five bus cycles) per :meth:`SimulatedRobot.step_cycle`. What robot_sim
does in lockstep, for tests and notebooks."""
from __future__ import annotations

from typing import Optional

import numpy as np

from protocol.messages import RobotCommand
from services.model.arm import ArmDescription
from services.model.kinematics import ArmKinematics
from services.robot.dsp import DSPConfig, KinovaDSP
from services.robot.core import Refusal, RobotCore
from services.robot.hardware import CYCLES_PER_DSP
from services.robot_sim.firmware import ActuatorConfig
from services.robot_sim.hardware import SimulatedHardware
from services.robot_sim.scene import SceneConfig
from services.robot_sim.sim import Simulation


class SimulatedRobot:
    def __init__(self, scene: SceneConfig | None = None, dsp: DSPConfig | None = None,
                 actuators: ActuatorConfig | None = None, arm: ArmDescription | None = None) -> None:
        """``arm``: the arm simulated (default: the default arm)."""
        self.sim = Simulation(scene, actuators, render=False, arm=arm)
        self.arm = self.sim.arm
        self.hardware = SimulatedHardware(self.sim)
        self._dsp_config = dsp or DSPConfig()
        self.reset()

    def reset(self, joints_deg=None) -> None:
        """Back to the scene's start (or ``joints_deg``), at rest, with a fresh DSP."""
        self.sim.reset(joints_deg)
        self.core = RobotCore(KinovaDSP(self._dsp_config, ArmKinematics(self.arm)), self.hardware.read())
        self.dsp = self.core.dsp

    def step_cycle(self, command: Optional[RobotCommand] = None) -> Optional[Refusal]:
        """One DSP cycle on the latest reading (with ``command``, if any), then the bus cycles until the next."""
        refusal = self.core.dsp_cycle(command)
        for _ in range(CYCLES_PER_DSP):
            self.core.observe(self.hardware.exchange(self.core.targets()))
        return refusal

    @property
    def q(self) -> np.ndarray:
        return self.sim.q

    @property
    def dq(self) -> np.ndarray:
        return self.sim.dq

    def ee_pose(self) -> np.ndarray:
        return self.sim.ee_pose()

    def ee_twist_base(self) -> np.ndarray:
        return self.sim.ee_twist_base()
