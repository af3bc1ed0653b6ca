"""robot_sim in actuator-bus mode, in realtime: physics at 1 kHz and the actuators' 500 Hz bus cycle on wall
time, in a thread. (The DSP is not here: a gateway drives the actuators over the bus.)"""
from __future__ import annotations

import threading

from protocol import rs485
from services.common.clock import PeriodicSchedule
from services.common.metrics import LoopTimer
from services.common.rs485_bus import BusConfig, RS485Bus
from services.robot_sim.actuator_bus import ActuatorBusConfig, ActuatorBusEmulator
from services.robot_sim.sim import Simulation

CYCLE_S = rs485.CYCLE_S


class BusRunner:
    def __init__(self, sim: Simulation, bus: BusConfig, actuators: ActuatorBusConfig | None = None) -> None:
        self.sim = sim
        self.bus = RS485Bus(bus)
        self.emulator = ActuatorBusEmulator(sim.model, sim.data, self.bus, actuators)
        sim.actuators = self.emulator
        self.loop_timer = LoopTimer(CYCLE_S)
        self.lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="robot_sim-bus", daemon=True)

    def start(self) -> "BusRunner":
        self._thread.start()
        return self

    def _run(self) -> None:
        schedule = PeriodicSchedule(CYCLE_S, max_lag_periods=None)
        steps = max(1, round(CYCLE_S / self.sim.model.opt.timestep))
        while not self._stop.is_set():
            schedule.wait()
            self.loop_timer.tick()
            with self.lock:
                self.emulator.process(schedule.elapsed_s())
                self.sim.step_physics(steps)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.bus.close()
