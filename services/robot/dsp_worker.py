"""Realtime: the robot node's DSP cycle on a thread of its own (``<name>-dsp``, an
:class:`~services.runtime.async_cycle.AsyncCycle`) beside the loop, handed each tick's reading, so that the bus cycle
goes out on time whatever the DSP costs (as a robot's servo loop never waits for its planner).

Each tick goes over with its command window: the DSP may wait for a fresh command up to the node's
``command_window_s`` after the hand-over, never later than :data:`~services.robot.node_config.PLAN_MARGIN_S` before
the next bus exchange, which uses its plan. A tick the thread has not taken when the next comes is skipped and counted
(``dsp.overruns``); a plan taken after another exchange went out is late (``dsp.late_plans``: that exchange went out
on the last plan); a cycle that fails is counted (``errors.dsp``) and logged, and the next tick runs. No zenoh here.
"""
from __future__ import annotations

import logging
import time
from typing import Callable

from services.robot.arm_driver import ArmDriver
from services.robot.hardware import JointReading
from services.robot.node_config import PLAN_MARGIN_S
from services.runtime.async_cycle import AsyncCycle
from services.runtime.logs import RateLimitedLogger
from services.runtime.metrics import Counters, DurationStats

#: one DSP cycle: (tick_ns, reading, wait_until) -> how long it waited for a command (s)
DspTick = Callable[[int, JointReading, float], float]


class DspWorker:
    def __init__(self, name: str, driver: ArmDriver, dsp_tick: DspTick, command_window_s: float,
                 dsp_time: DurationStats, counters: Counters, log: logging.Logger,
                 limited_log: RateLimitedLogger) -> None:
        """``name``: the node's; ``dsp_time``: where each cycle's own time goes (without its wait for a command)."""
        self.name = name
        self.driver = driver
        self.dsp_tick = dsp_tick
        self.command_window_s = command_window_s
        self.dsp_time = dsp_time
        self.counters = counters
        self.log = log
        self.limited_log = limited_log
        self._cycle = AsyncCycle(f"{name}-dsp", on_overrun=lambda: counters.inc("dsp.overruns"))

    def hand_over(self, tick_ns: int, reading: JointReading, exchange_due: float) -> None:
        """The DSP cycle of the tick at ``tick_ns``, on ``reading``, to run on the thread; ``exchange_due``: when the
        next bus exchange is due (monotonic)."""
        wait_until = min(time.monotonic() + self.command_window_s, exchange_due - PLAN_MARGIN_S)
        exchanges = self.driver.cycles
        self._cycle.submit(lambda: self._run(tick_ns, reading, wait_until, exchanges))

    def stop(self) -> None:
        self._cycle.stop()

    def _run(self, tick_ns: int, reading: JointReading, wait_until: float, exchanges: int) -> None:
        """The DSP cycle of a tick on the thread: ``exchanges``, the bus exchanges done when it was handed over (a
        plan taken after another exchange is late)."""
        try:
            start = time.monotonic()
            # a window of 0 ends as it begins
            waited_s = self.driver.run_dsp(lambda: self.dsp_tick(tick_ns, reading, wait_until))
            self.dsp_time.add(time.monotonic() - start - waited_s)
            if self.driver.cycles > exchanges:
                self.counters.inc("dsp.late_plans")  # the next exchange went out on the last cycle's plan
        except Exception:
            self.counters.inc("errors.dsp")
            self.limited_log.error("dsp", "%s: DSP cycle failed", self.name)
            self.log.debug("DSP cycle failure", exc_info=True)
