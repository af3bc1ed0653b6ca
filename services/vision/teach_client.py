"""Teach a view over zenoh, step by step (`mfvs teach`, the console's teach button, the markerless experiment): vision
takes the first view, the controller moves the camera by the probe (once the person confirmed), vision takes the
second view and triangulates, the controller moves it back, and vision makes the goal (services/vision/teach.py).
Each step's answer is checked; a step that fails cancels the teach and says why, with the arm where it is.

Every wait (the arm to come to rest, the probe to end) is measured on the arm's clock, the stamps of its states: in
lockstep the arm's time runs only as fast as the host lets the services answer, so a wall-clock timeout would fail a
teach on a busy host that an idle one passes (a markerless run failed its probe "after 30 s" while a browser and a
benchmark shared its two cores). The wall clock bounds only silence: no state from the arm for ARM_SILENT_S.
"""
from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from protocol import messages as m
from protocol.keys import Keys
from services.controller.task_client import call_task
from services.runtime.service import NoAnswer, ask


#: the arm is taken to have stopped when no state of it arrived for this long (wall s): five times the longest a
#: lockstep arm waits at a DSP tick for the pipeline before it goes on without it (LockstepGate.cycle_timeout_s, 2 s);
#: a realtime arm sends its state at 100 Hz
ARM_SILENT_S = 10.0


class TeachFailed(RuntimeError):
    """The teach stopped at a step, saying why; nothing of it was kept."""


class ArmSilent(TeachFailed):
    """No state from the arm for too long: its loop stopped, or the stack is gone."""


class ArmClock:
    """The arm's time as its states stamp it (ns; simulated in lockstep, the wall's in realtime), for the teach's
    waits: ``timer(s)`` expires once ``s`` seconds of the arm's time passed (counted from its first state when none
    came yet), and raises :class:`ArmSilent` once the arm has been silent for ``silent_s`` of the wall's."""

    def __init__(self, session, keys: Keys, silent_s: float = ARM_SILENT_S) -> None:
        self.silent_s = silent_s
        self._lock = threading.Lock()
        self._stamp_ns = 0
        self._heard = time.monotonic()  # from the start, the arm has as long to be heard as to go silent
        self._subscriber = session.declare_subscriber(keys.robot_state, self._on_state)

    def _on_state(self, sample) -> None:
        try:
            stamp = m.decode(sample.payload.to_bytes(), m.RobotState).header.stamp_ns
        except m.ProtocolError:
            return
        with self._lock:
            if stamp > self._stamp_ns:
                self._stamp_ns, self._heard = stamp, time.monotonic()

    def now_ns(self) -> int:
        """The arm's last stamp (0: none yet); raises once the arm has been silent too long."""
        with self._lock:
            stamp, silent = self._stamp_ns, time.monotonic() - self._heard
        if silent > self.silent_s:
            raise ArmSilent(f"no state from the arm for {silent:.0f} s: its loop stopped")
        return stamp

    def timer(self, seconds: float) -> Callable[[], bool]:
        deadline = 0

        def expired() -> bool:
            nonlocal deadline
            now = self.now_ns()
            if not deadline and now:
                deadline = now + int(seconds * 1e9)
            return bool(deadline) and now >= deadline
        return expired

    def close(self) -> None:
        self._subscriber.undeclare()


@dataclass
class TeachResult:
    goal: str
    digest: str
    file: bytes
    #: what each step said, in order
    steps: list[str] = field(default_factory=list)
    keypoints: int = 0
    planar: Optional[bool] = None
    triangulation_error_px: float = 0.0
    probe_m: Optional[tuple] = None


def call_teach(session, keys: Keys, request: m.TeachRequest, timeout_s: float = 10.0) -> m.TeachReply:
    try:
        return ask(session, keys.vision_api("teach"), m.encode(request), m.TeachReply, timeout_s)
    except NoAnswer:
        raise TeachFailed(f"vision did not answer {keys.vision_api('teach')} within {timeout_s:g} s") from None


def _request(phase: m.TeachPhase, operator: str, **kw) -> m.TeachRequest:
    return m.TeachRequest(header=m.Header(), phase=phase, operator=operator, **kw)


def _until_ok(ask: Callable[[], m.TeachReply], clock: ArmClock, timeout_s: float, wait_s: float = 0.2
              ) -> m.TeachReply:
    """A step asked again while it fails only because the arm has not come to rest (or no fresh image yet), for
    ``timeout_s`` of the arm's time."""
    expired = clock.timer(timeout_s)
    while True:
        reply = ask()
        waiting = not reply.ok and ("is moving" in reply.message or "old" in reply.message
                                    or "no image yet" in reply.message)
        if reply.ok or not waiting or expired():
            return reply
        time.sleep(wait_s)


def _move(session, keys: Keys, operator: str, move_m, clock: ArmClock, timeout_s: float) -> m.TaskStatus:
    """The controller's move phase, waited for to its end."""
    request = m.TaskRequest(operator=operator, reason="teach: depth probe", plan=m.TaskPlan.MOVE,
                            move_m=tuple(float(v) for v in move_m), move_frame=m.MoveFrame.CAMERA)
    started = call_task(session, keys, m.START_TASK, request)
    if not started.ok or started.state is not m.TaskState.RUNNING:
        raise TeachFailed(f"the controller did not start the probe motion: {started.message}")
    number = started.task
    expired = clock.timer(timeout_s)
    try:
        while not expired():
            status = call_task(session, keys, m.GET_TASK)
            if status.task != number or status.state is not m.TaskState.RUNNING:
                if status.outcome != "done":
                    raise TeachFailed(f"the probe motion did not finish: {status.outcome or status.message}")
                return status
            time.sleep(0.1)
        failure = TeachFailed(f"the probe motion took longer than {timeout_s:g} s of the arm's time; stopped")
    except ArmSilent as silent:  # the probe is stopped all the same
        failure = silent
    call_task(session, keys, m.STOP_TASK, m.TaskRequest(operator=operator, reason="teach: probe stopped"))
    raise failure


def teach(session, keys: Keys, name: str, operator: str, region_px=(), probe_m=(0.03, 0.0, 0.0),
          detector: str = "", confirm: Callable[[str], bool] = lambda _: True, move_timeout_s: float = 30.0,
          rest_timeout_s: float = 5.0, say: Callable[[str], None] = lambda _: None) -> TeachResult:
    """Teach the current view as goal ``name``: the whole procedure (module doc). ``confirm(question)`` is asked
    before the arm moves (the person says yes); ``say`` hears each step's answer."""
    steps: list[str] = []

    def step(reply: m.TeachReply) -> m.TeachReply:
        steps.append(f"{reply.phase.value}: {reply.message}")
        say(steps[-1])
        if not reply.ok:
            call_teach(session, keys, _request(m.TeachPhase.CANCEL, operator))
            raise TeachFailed(f"teach {reply.phase.value}: {reply.message}")
        return reply

    clock = ArmClock(session, keys)
    try:
        return _teach(session, keys, name, operator, region_px, probe_m, detector, confirm, move_timeout_s,
                      rest_timeout_s, clock, step, steps)
    except ArmSilent:
        with contextlib.suppress(TeachFailed):  # vision may be gone with the arm
            call_teach(session, keys, _request(m.TeachPhase.CANCEL, operator))
        raise
    finally:
        clock.close()


def _teach(session, keys: Keys, name: str, operator: str, region_px, probe_m, detector: str,
           confirm: Callable[[str], bool], move_timeout_s: float, rest_timeout_s: float, clock: ArmClock,
           step: Callable[[m.TeachReply], m.TeachReply], steps: list[str]) -> TeachResult:
    region = [tuple(float(v) for v in p) for p in region_px]
    step(_until_ok(lambda: call_teach(session, keys, _request(m.TeachPhase.BEGIN, operator, region_px=region,
                                                               detector=detector)), clock, rest_timeout_s))
    question = (f"The arm will move the camera {np.linalg.norm(probe_m) * 1e2:.1f} cm sideways and back to measure "
                "the object's depth. Is the way clear?")
    if not confirm(question):
        call_teach(session, keys, _request(m.TeachPhase.CANCEL, operator))
        raise TeachFailed("teach cancelled: the probe motion was not confirmed")
    try:
        _move(session, keys, operator, probe_m, clock, move_timeout_s)
        second = step(_until_ok(lambda: call_teach(session, keys, _request(m.TeachPhase.SECOND_VIEW, operator)),
                                clock, rest_timeout_s))
    finally:  # back to the first view whatever the second said (from where the probe ended)
        status = call_task(session, keys, m.GET_TASK)
        if status.outcome == "done" and status.plan is m.TaskPlan.MOVE:
            _move(session, keys, operator, [-v for v in probe_m], clock, move_timeout_s)
    final = step(call_teach(session, keys, _request(m.TeachPhase.FINISH, operator, name=name)))
    return TeachResult(goal=final.goal, digest=final.goal_digest, file=final.goal_file, steps=steps,
                       keypoints=second.keypoints, planar=second.planar,
                       triangulation_error_px=second.triangulation_error_px, probe_m=second.probe_m)


def set_taught_goal(session, keys: Keys, payload: bytes, timeout_s: float = 10.0) -> m.VisionGoalReply:
    """Give vision a taught goal's file (``mfvs task start --goal FILE``): its reply (refused in one line when the
    camera, resolution or arm differ)."""
    goal = m.VisionGoal(header=m.Header(), taught_file=payload)
    try:
        return ask(session, keys.vision_api("set_goal"), m.encode(goal), m.VisionGoalReply, timeout_s)
    except NoAnswer:
        raise TeachFailed(f"vision did not answer {keys.vision_api('set_goal')} within {timeout_s:g} s") from None
