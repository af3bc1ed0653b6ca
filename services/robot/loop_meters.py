"""The robot loop's meters and what the node says of them: the loop's timing in every state and the detail of its
health. No zenoh and no thread here; each meter is thread-safe of its own (the loop, the DSP worker and the health's
thread use them at once).
"""
from __future__ import annotations

from protocol.messages import LoopTiming
from services.runtime.metrics import DurationStats, RateMeter


class LoopMeters:
    def __init__(self) -> None:
        #: the loop's work per cycle (without its sleep), and the exchanges' share of it
        self.work = DurationStats()
        self.exchange_time = DurationStats()
        #: how late the loop woke for its slots, and how long the DSP cycles took (realtime)
        self.wake_lag = DurationStats()
        self.dsp_time = DurationStats()
        #: how long the DSP waited in its command window (realtime), apart from its own time above
        self.command_wait = DurationStats()
        #: the rates of the loop's cycles, of its late cycles and of the cycles it missed
        self.cycles = RateMeter()
        self.late = RateMeter()
        self.missed = RateMeter()

    def timing(self) -> LoopTiming:
        """The loop's rate, and how often it is late or misses a cycle (said in every state)."""
        return LoopTiming(rate_hz=self.cycles.rate_hz(), late_per_s=self.late.rate_hz(),
                          missed_per_s=self.missed.rate_hz())

    def health_detail(self, arm_summary: str, torque_setup: str) -> str:
        """The detail of a healthy node: ``arm_summary`` first (robot_sim's health splits it off there), the loop's
        rates and durations (p50/p99), then ``torque_setup`` where there is one."""
        timing = self.timing()
        work, exchange, lag, dsp, wait = (self.work.stats(), self.exchange_time.stats(), self.wake_lag.stats(),
                                          self.dsp_time.stats(), self.command_wait.stats())
        return (f"{arm_summary}; bus_rate_hz={timing.rate_hz:.1f} late_per_s={timing.late_per_s:.1f} "
                f"missed_per_s={timing.missed_per_s:.1f} work_ms={work['p50_ms']:.2f}/{work['p99_ms']:.2f} "
                f"exchange_ms={exchange['p50_ms']:.2f}/{exchange['p99_ms']:.2f} "
                f"wake_lag_ms={lag['p50_ms']:.2f}/{lag['p99_ms']:.2f} dsp_ms={dsp['p50_ms']:.2f}/"
                f"{dsp['p99_ms']:.2f} command_wait_ms={wait['p50_ms']:.2f}/{wait['p99_ms']:.2f} (p50/p99)"
                + (f"; {torque_setup}" if torque_setup else ""))
