"""robot_sim loop benchmark.

* realtime, rendering 640×480 at 30 Hz for a subscriber: the robot loop's achieved rate and period jitter (its 500 Hz
  bus cycle, |period − 2 ms|: p50, p99, max; every fifth cycle is the DSP's), and the achieved frame and (100 Hz)
  state rates;
* lockstep: the real-time factor (simulated / wall time) with a stand-in pipeline that answers every clock tick
  and every frame at once (the upper bound the real services can approach), and free-running (nobody listening).

``python -m bench.loops [--json] [--seconds S] [--arm NAME]`` or ``mfvs bench loops``.
"""
from __future__ import annotations

import argparse
import json
import threading
import time

from protocol import messages as m
from protocol.conventions import ClockMode
from protocol.keys import Keys
from bench.stack import unknown_arm
from services.cli.options import add_arm_option
from services.model.arm import DEFAULT_ARM
from services.runtime.metrics import LoopTimer
from services.runtime.transport import GuardedPublisher, Router, open_session
from services.robot_sim.service import RobotSimConfig, RobotSimService

KEYS = Keys()


class _StandInPipeline:
    """Answers each clock tick with a stop command stamped at the tick, and each frame with one derived from it."""

    def __init__(self, session) -> None:
        self.publisher = GuardedPublisher.declare(session, KEYS.robot_command)
        self.frame_stamp = 0
        self.seq = 0  # numbered: the robot refuses a repeat
        self.lock = threading.Lock()
        self.subscribers = [
            session.declare_subscriber(KEYS.clock, self._on_tick),
            session.declare_subscriber(KEYS.camera_image, self._on_image),
        ]

    def _answer(self, stamp: int) -> None:
        with self.lock:  # numbered and sent in one step: the tick's and the frame's callbacks run on two threads,
            # and a number sent after a higher one is refused as a replay
            self.seq += 1
            header = m.Header(seq=self.seq, stamp_ns=stamp, source_stamp_ns=self.frame_stamp)
            self.publisher.put(m.encode(m.RobotCommand(header=header, mode=m.CommandMode.STOP)))

    def _on_tick(self, sample) -> None:
        self._answer(m.decode(sample.payload.to_bytes(), m.SimClock).sim_time_ns)

    def _on_image(self, sample) -> None:
        stamp = m.decode(sample.payload.to_bytes(), m.Image).header.source_stamp_ns
        with self.lock:
            self.frame_stamp = stamp
        self._answer(stamp)

    def close(self) -> None:
        for s in self.subscribers:
            s.undeclare()
        self.publisher.undeclare()


def realtime(seconds: float, arm: str = DEFAULT_ARM) -> dict:
    with Router() as router:
        client = open_session(router.client_config())
        frames: list[int] = []
        states: list[int] = []
        client.declare_subscriber(KEYS.camera_image,
                                  lambda s: frames.append(m.decode(s.payload.to_bytes(), m.Image).header.stamp_ns))
        client.declare_subscriber(KEYS.robot_state, lambda s: states.append(time.monotonic_ns()))
        service = RobotSimService(RobotSimConfig(arm=arm, clock=ClockMode.REALTIME, zenoh=router.client_config()))
        service.start()
        try:
            time.sleep(1.0)  # warm-up: renderer context, first frames
            service.loop_timer = LoopTimer(service.loop_timer.nominal_s)
            n_frames, n_states = len(frames), len(states)
            # what the node counts as its loop not keeping up (late and missed cycles, DSP overruns, ...)
            overruns_before = sum(service.counters.get(name) for name in service.OVERRUNS)
            start = time.monotonic()
            time.sleep(seconds)
            elapsed = time.monotonic() - start
            stats = service.loop_timer.stats()
            frame_rate = (len(frames) - n_frames) / elapsed
            state_rate = (len(states) - n_states) / elapsed
            overruns = sum(service.counters.get(name) for name in service.OVERRUNS) - overruns_before
        finally:
            service.stop()
            client.close()
    return {"cycle_rate_hz": round(stats["rate_hz"], 2), "cycle_jitter_ms_p50": round(stats["jitter_ms_p50"], 3),
            "cycle_jitter_ms_p99": round(stats["jitter_ms_p99"], 3),
            "cycle_jitter_ms_max": round(stats["jitter_ms_max"], 3), "cycles": stats["n"],
            "frame_rate_hz": round(frame_rate, 2), "state_rate_hz": round(state_rate, 2), "overruns": overruns,
            "seconds": seconds}


def lockstep(sim_seconds: float, pipeline: bool, arm: str = DEFAULT_ARM) -> dict:
    with Router() as router:
        client = open_session(router.client_config())
        stand_in = _StandInPipeline(client) if pipeline else None
        time.sleep(0.3)
        config = RobotSimConfig(arm=arm, clock=ClockMode.LOCKSTEP, zenoh=router.client_config(),
                                max_sim_time_s=sim_seconds)
        service = RobotSimService(config)
        start = time.monotonic()
        service.start()
        try:
            service.finished.wait(timeout=max(60.0, 30 * sim_seconds))
            wall = time.monotonic() - start
            timeouts = {k: v for k, v in service.counters.snapshot().items() if k.startswith("lockstep.")}
            sim_time = service.sim.time_ns * 1e-9
            n_frames = service.sim.frame_count
        finally:
            service.stop()
            if stand_in is not None:
                stand_in.close()
            client.close()
    return {"real_time_factor": round(sim_time / wall, 3), "sim_seconds": round(sim_time, 3),
            "wall_seconds": round(wall, 3), "frames": n_frames, "timeouts": timeouts}


def run(seconds: float = 10.0, sim_seconds: float = 5.0, arm: str = DEFAULT_ARM) -> dict:
    return {
        "arm": arm,
        "realtime": realtime(seconds, arm),
        "lockstep_with_pipeline": lockstep(sim_seconds, pipeline=True, arm=arm),
        "lockstep_free_running": lockstep(sim_seconds, pipeline=False, arm=arm),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench loops", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=10.0, help="realtime measurement window (s)")
    parser.add_argument("--sim-seconds", type=float, default=5.0, help="simulated time per lockstep run (s)")
    add_arm_option(parser)
    args = parser.parse_args(argv)
    if unknown_arm(parser, args):
        return 2
    result = run(args.seconds, args.sim_seconds, args.arm)
    if args.json:
        print(json.dumps(result))
    else:
        rt = result["realtime"]
        print(f"robot_sim on the {result['arm']}: realtime loop {rt['cycle_rate_hz']:.2f} Hz (nominal 500), "
              f"period jitter p50 {rt['cycle_jitter_ms_p50']:.3f} ms, p99 {rt['cycle_jitter_ms_p99']:.3f} ms, "
              f"max {rt['cycle_jitter_ms_max']:.3f} ms "
              f"({rt['cycles']} cycles, {rt['overruns']} overruns); frames {rt['frame_rate_hz']:.1f} Hz, "
              f"states {rt['state_rate_hz']:.1f} Hz")
        for name in ("lockstep_with_pipeline", "lockstep_free_running"):
            ls = result[name]
            print(f"{name.replace('_', ' ')}: real-time factor {ls['real_time_factor']:.2f} "
                  f"({ls['sim_seconds']} s simulated in {ls['wall_seconds']} s, {ls['frames']} frames, "
                  f"timeouts and retries {ls['timeouts'] or 'none'})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
