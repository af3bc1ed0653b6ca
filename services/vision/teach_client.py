"""Teach a view over zenoh, step by step (`mfvs teach`, the console's teach button, the markerless experiment): vision
takes the first view, the controller moves the camera by the probe (once the person confirmed), vision takes the
second view and triangulates, the controller moves it back, and vision makes the goal (services/vision/teach.py).
Each step's answer is checked; a step that fails cancels the teach and says why, with the arm where it is.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from protocol import messages as m
from protocol.keys import Keys
from services.controller.task_client import call_task
from services.runtime.service import NoAnswer, ask


class TeachFailed(RuntimeError):
    """The teach stopped at a step, saying why; nothing of it was kept."""


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


def _until_ok(ask: Callable[[], m.TeachReply], timeout_s: float, wait_s: float = 0.2) -> m.TeachReply:
    """A step asked again while it fails only because the arm has not come to rest (or no fresh image yet)."""
    deadline = time.monotonic() + timeout_s
    while True:
        reply = ask()
        waiting = not reply.ok and ("is moving" in reply.message or "old" in reply.message
                                    or "no image yet" in reply.message)
        if reply.ok or not waiting or time.monotonic() >= deadline:
            return reply
        time.sleep(wait_s)


def _move(session, keys: Keys, operator: str, move_m, timeout_s: float) -> m.TaskStatus:
    """The controller's move phase, waited for to its end."""
    request = m.TaskRequest(operator=operator, reason="teach: depth probe", plan=m.TaskPlan.MOVE,
                            move_m=tuple(float(v) for v in move_m), move_frame=m.MoveFrame.CAMERA)
    started = call_task(session, keys, m.START_TASK, request)
    if not started.ok or started.state is not m.TaskState.RUNNING:
        raise TeachFailed(f"the controller did not start the probe motion: {started.message}")
    number = started.task
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        status = call_task(session, keys, m.GET_TASK)
        if status.task != number or status.state is not m.TaskState.RUNNING:
            if status.outcome != "done":
                raise TeachFailed(f"the probe motion did not finish: {status.outcome or status.message}")
            return status
        time.sleep(0.1)
    call_task(session, keys, m.STOP_TASK, m.TaskRequest(operator=operator, reason="teach: probe timed out"))
    raise TeachFailed(f"the probe motion took longer than {timeout_s:g} s; stopped")


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

    region = [tuple(float(v) for v in p) for p in region_px]
    step(_until_ok(lambda: call_teach(session, keys, _request(m.TeachPhase.BEGIN, operator, region_px=region,
                                                               detector=detector)), rest_timeout_s))
    question = (f"The arm will move the camera {np.linalg.norm(probe_m) * 1e2:.1f} cm sideways and back to measure "
                "the object's depth. Is the way clear?")
    if not confirm(question):
        call_teach(session, keys, _request(m.TeachPhase.CANCEL, operator))
        raise TeachFailed("teach cancelled: the probe motion was not confirmed")
    try:
        _move(session, keys, operator, probe_m, move_timeout_s)
        second = step(_until_ok(lambda: call_teach(session, keys, _request(m.TeachPhase.SECOND_VIEW, operator)),
                                rest_timeout_s))
    finally:  # back to the first view whatever the second said (from where the probe ended)
        status = call_task(session, keys, m.GET_TASK)
        if status.outcome == "done" and status.plan is m.TaskPlan.MOVE:
            _move(session, keys, operator, [-v for v in probe_m], move_timeout_s)
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
