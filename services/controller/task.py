"""The controller's task: whether the stack may move the arm at all. Pure rules, no zenoh, no locks.

An assistive arm stays still until someone asks it to move: the controller comes up idle, answering every
features message with a zero output (status ``idle``), and moves only while a task runs: through its phases
(services/controller/phases.py: the visual servo until stopped; a move, which ends by itself when it arrives). A
task starts and stops by request (``mfvs task start|stop``, or the ``controller/api/*`` queryables); stopping answers the next frames with
zero output, so the robot's DSP brings the arm to rest at its normal deceleration. Starting while running, or
stopping while idle, changes nothing and says so.

The person comes first (services/safety/sources.py): when safety says another source took control (their stick), a
running task is paused: it outputs nothing, and releasing the stick does not move it on. Only a resume
(``mfvs task resume``, the console's button) goes on with it, each phase from where the arm is now
(:meth:`Task.resume`); a start while paused is refused, a stop ends it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from protocol.messages import GraspVerdict, TaskPlan, TaskRequest, TaskState, TaskStatus


@dataclass
class Task:
    state: TaskState = TaskState.IDLE
    #: tasks started so far
    count: int = 0
    started_ns: int = 0
    by: str = ""
    reason: str = ""
    #: the running (or last) task's plan, its phases (services.controller.phases) and the one it is in
    plan: TaskPlan = TaskPlan.SERVO
    phases: list = field(default_factory=list)
    index: int = 0
    #: how the last task ended: done, stopped, failed: why ("" while one runs)
    outcome: str = ""
    #: what the hand holds, by the grasp detector, since the task's phases first watched it (None: they do not)
    grasp: Optional[GraspVerdict] = None

    @property
    def running(self) -> bool:
        return self.state is TaskState.RUNNING

    @property
    def paused(self) -> bool:
        return self.state is TaskState.PAUSED

    @property
    def phase(self) -> Optional[object]:
        """The phase the started task is in, running or paused (None when idle)."""
        started = self.state is not TaskState.IDLE
        return self.phases[self.index] if started and self.index < len(self.phases) else None

    def start(self, request: TaskRequest, now_ns: int, phases: Optional[list] = None) -> TaskStatus:
        """Start a task of ``phases``; the caller resets its law and iteration count when this says ``started``."""
        if self.running:
            return self.status(True, f"already running (task {self.count}, started by {self.by})")
        if self.paused:
            return self.status(False, f"task {self.count} is paused ({self.reason}): resume it or stop it first")
        self.state, self.count, self.started_ns = TaskState.RUNNING, self.count + 1, now_ns
        self.by, self.reason = request.operator, request.reason
        self.plan, self.phases, self.index, self.outcome = request.plan, list(phases or []), 0, ""
        self.grasp = None
        return self.status(True, f"task {self.count} started")

    def replace_rest(self, phases: list, request: TaskRequest) -> None:
        """The running task goes on with ``phases`` instead of what was left of its own (a release during a hold)."""
        self.phases = self.phases[: self.index] + list(phases)
        self.by, self.reason = request.operator, request.reason

    def pause(self, why: str) -> bool:
        """Another source took control: the running task waits (whether it was running)."""
        if not self.running:
            return False
        self.state, self.reason = TaskState.PAUSED, why[:256]
        return True

    def resume(self, request: TaskRequest) -> TaskStatus:
        """Go on with a paused task from where the arm is now: the phase it was in starts again (a move to its
        target, its time allowed anew; a hand phase's time anew), or, for a phase that only makes sense from where
        the previous one ended (a grasp's approach, from the converged pre-grasp view), the previous one. The caller
        resets its law."""
        if not self.paused:
            return self.status(self.running, "already running" if self.running else "no task paused")
        phase = self.phases[self.index]
        if getattr(phase, "needs_previous", False) and self.index > 0:
            phase.restart()
            self.index -= 1
            phase = self.phases[self.index]
        phase.restart()
        self.state, self.by, self.reason = TaskState.RUNNING, request.operator, request.reason
        return self.status(True, f"task {self.count} resumed at its {phase.name} phase")

    def stop(self, request: TaskRequest) -> TaskStatus:
        if self.state is TaskState.IDLE:
            return self.status(True, "no task running")
        self.state, self.started_ns = TaskState.IDLE, 0
        self.by, self.reason, self.outcome = request.operator, request.reason, "stopped"
        return self.status(True, f"task {self.count} stopped")

    def advance(self) -> bool:
        """The phase is done: on to the next; whether the task is now done (its last phase was)."""
        self.index += 1
        if self.index < len(self.phases):
            return False
        self.state, self.started_ns, self.outcome = TaskState.IDLE, 0, "done"
        return True

    def fail(self, why: str) -> None:
        """The phase cannot go on: the task ends, saying why."""
        self.state, self.started_ns, self.outcome = TaskState.IDLE, 0, f"failed: {why}"[:256]

    def status(self, ok: bool = True, message: str = "") -> TaskStatus:
        phase = self.phase
        return TaskStatus(ok=ok, state=self.state, message=message[:256], task=self.count,
                          started_ns=self.started_ns, by=self.by, reason=self.reason[:256], plan=self.plan,
                          phase=phase.name if phase is not None else "", outcome=self.outcome, grasp=self.grasp)
