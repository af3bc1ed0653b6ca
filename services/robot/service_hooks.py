"""What a robot service gives the robot node (:class:`~services.robot.node.RobotNode`, which calls these): the joints'
hardware, its further outputs, the camera frame taken at a tick, what it publishes again for a late answer in
lockstep, and what it does as the loop starts and ends. Each has its default here; robot_sim and robot_gateway
override what they have. (What drives the arm, the health's first words and the cycles a stall dropped are the
node's own hooks: they have its state to work on.)
"""
from __future__ import annotations

from typing import Optional

from services.robot.hardware import JointReading, RobotHardware


class RobotServiceHooks:
    def open_hardware(self) -> tuple[RobotHardware, JointReading]:
        """The joints' hardware and its first reading (the arm's joints before the first cycle)."""
        raise NotImplementedError

    def declare_outputs(self) -> None:
        """Further publishers and queryables of a robot service (robot_sim: camera and clock)."""

    def frame_at_tick(self, tick_ns: int) -> Optional[int]:
        """At a DSP tick (after its state went out): the capture stamp of the camera frame taken at this tick, if
        any (robot_sim takes and publishes it here)."""
        return None

    def on_lockstep_retry(self, tick_ns: int) -> None:
        """The answer to a tick is late: publish what it answers again (robot_sim: the frame and the tick)."""

    def lockstep_outputs_matched(self) -> bool:
        """Whether what the pipeline answers (robot_sim: its camera's images) has its subscribers."""
        return True

    def on_loop_start(self) -> None:
        """The realtime loop is about to run its first cycle (robot_sim starts its arm's time now)."""

    def on_lockstep_end(self) -> None:
        """The lockstep loop's thread is about to end (robot_sim frees the renderer that thread rendered with)."""
