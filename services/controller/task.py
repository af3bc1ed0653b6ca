"""The controller's task: whether the stack may move the arm at all. Pure rules, no zenoh, no locks.

An assistive arm stays still until someone asks it to move: the controller comes up idle, answering every
features message with a zero output (status ``idle``), and servos only while a task runs. A task starts and stops
by request (``mfvs task start|stop``, or the ``controller/api/*`` queryables); stopping answers the next frames with
zero output, so the robot's DSP brings the arm to rest at its normal deceleration. Starting while running, or
stopping while idle, changes nothing and says so.
"""
from __future__ import annotations

from dataclasses import dataclass

from protocol.messages import TaskRequest, TaskState, TaskStatus


@dataclass
class Task:
    state: TaskState = TaskState.IDLE
    #: tasks started so far
    count: int = 0
    started_ns: int = 0
    by: str = ""
    reason: str = ""

    @property
    def running(self) -> bool:
        return self.state is TaskState.RUNNING

    def start(self, request: TaskRequest, now_ns: int) -> TaskStatus:
        """Start a task; the caller resets its law and iteration count when this says ``started``."""
        if self.running:
            return self.status(True, f"already running (task {self.count}, started by {self.by})")
        self.state, self.count, self.started_ns = TaskState.RUNNING, self.count + 1, now_ns
        self.by, self.reason = request.operator, request.reason
        return self.status(True, f"task {self.count} started")

    def stop(self, request: TaskRequest) -> TaskStatus:
        if not self.running:
            return self.status(True, "no task running")
        self.state, self.started_ns = TaskState.IDLE, 0
        self.by, self.reason = request.operator, request.reason
        return self.status(True, f"task {self.count} stopped")

    def status(self, ok: bool = True, message: str = "") -> TaskStatus:
        return TaskStatus(ok=ok, state=self.state, message=message[:256], task=self.count,
                          started_ns=self.started_ns, by=self.by, reason=self.reason[:256])
