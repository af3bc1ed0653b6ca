"""Start a whole mfvs stack in this process: a zenoh router on a free loopback port and the services, each a
separate zenoh client of the router (they talk only over zenoh, exactly as when deployed as processes)."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

from protocol.conventions import ClockMode
from services.common.rs485_bus import BusConfig
from services.common.transport import Router
from services.controller.service import ControllerConfig, ControllerService
from services.robot_gateway.service import GatewayConfig, RobotGatewayService
from services.robot_sim.service import RobotSimConfig, RobotSimService
from services.safety.service import SafetyConfig, SafetyService
from services.vision.service import VisionConfig, VisionService


@dataclass
class StackConfig:
    clock: ClockMode = ClockMode.LOCKSTEP
    #: sim: robot_sim with its emulated DSP; gateway: robot_sim's actuators on an RS-485 bus (python-can's
    #: virtual interface, this process) driven by robot_gateway — realtime only
    profile: str = "sim"
    robot: RobotSimConfig = field(default_factory=RobotSimConfig)
    vision: VisionConfig = field(default_factory=VisionConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)


class LocalStack:
    """Router + safety + vision + controller + robot_sim (+ robot_gateway with the gateway profile). Use as a
    context manager."""

    def __init__(self, config: StackConfig) -> None:
        self.config = config
        self.router = Router(port=0)
        self.services: list = []

    def __enter__(self) -> "LocalStack":
        self.router.start()
        client = self.router.client_config()
        cfg = self.config
        if cfg.profile not in ("sim", "gateway"):
            raise ValueError(f"unknown profile {cfg.profile!r}: sim or gateway")
        gateway = cfg.profile == "gateway"
        if gateway:
            cfg.clock = ClockMode.REALTIME
            cfg.robot.mode = "actuator_bus"
            cfg.robot.bus = BusConfig(channel=f"mfvs-stack-{id(self)}")
        for service_cfg in (cfg.safety, cfg.vision, cfg.controller, cfg.robot):
            service_cfg.zenoh = client
            service_cfg.clock = cfg.clock
        try:
            # the pipeline first, so that it is listening when the robot publishes its first frame
            self.safety = SafetyService(cfg.safety).start()
            self.services.append(self.safety)
            self.vision = VisionService(cfg.vision).start()
            self.services.append(self.vision)
            self.controller = ControllerService(cfg.controller).start()
            self.services.append(self.controller)
            time.sleep(0.3)  # let the declarations reach the router before the robot starts the clock
            self.robot = RobotSimService(cfg.robot).start()
            self.services.append(self.robot)
            if gateway:  # after the simulated actuators, which must answer its first exchange
                self.gateway = RobotGatewayService(GatewayConfig(
                    zenoh=client, bus=cfg.robot.bus, dsp=cfg.robot.dsp, link_timeout_s=0.05)).start()
                self.services.append(self.gateway)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    @property
    def endpoint(self) -> str:
        return self.router.endpoint

    def __exit__(self, *exc) -> None:
        for service in reversed(self.services):
            try:
                service.stop()
            except Exception:
                pass
        self.services.clear()
        self.router.close()
