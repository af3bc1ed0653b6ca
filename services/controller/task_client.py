"""Start, stop and read the controller's task over zenoh (``…/controller/api/*``), as `mfvs task`, `mfvs servo`
and the benchmarks do."""
from __future__ import annotations

from typing import Optional

from protocol import messages as m
from protocol.keys import Keys
from services.runtime.service import NoAnswer, ask


class TaskUnavailable(RuntimeError):
    """No controller answered (none running, or this identity may not ask)."""


def call_task(session, keys: Keys, function: str, request: Optional[m.TaskRequest] = None,
              timeout_s: float = 5.0) -> m.TaskStatus:
    """The controller's answer to one task function (``m.START_TASK``, ``m.STOP_TASK``, ``m.GET_TASK``); a
    refused request comes back with ``ok`` false and the reason in ``message``."""
    if function not in m.TASK_FUNCTIONS:
        raise ValueError(f"unknown task function {function!r}: one of {', '.join(m.TASK_FUNCTIONS)}")
    if (request is None) != (function == m.GET_TASK):
        raise ValueError(f"{function} takes {'no request' if function == m.GET_TASK else 'a TaskRequest'}")
    payload = m.encode(request) if request is not None else None
    try:
        return ask(session, keys.controller_api(function), payload, m.TaskStatus, timeout_s)
    except NoAnswer:
        raise TaskUnavailable(f"no controller answered {keys.controller_api(function)} within {timeout_s:g} s") from None


def start_task(session, keys: Keys, operator: str, reason: str = "", timeout_s: float = 5.0) -> m.TaskStatus:
    return call_task(session, keys, m.START_TASK, m.TaskRequest(operator=operator, reason=reason), timeout_s)


def stop_task(session, keys: Keys, operator: str, reason: str = "", timeout_s: float = 5.0) -> m.TaskStatus:
    return call_task(session, keys, m.STOP_TASK, m.TaskRequest(operator=operator, reason=reason), timeout_s)


def describe_task(status: m.TaskStatus) -> str:
    """The controller's answer to a task request in a sentence (`mfvs task`, the console)."""
    by = f", by {status.by}" + (f": {status.reason}" if status.reason else "") if status.by else ""
    # a servo task says nothing more (its one phase is the servo); another plan says itself and the phase it is in
    running_other = status.state is m.TaskState.RUNNING and status.plan is not m.TaskPlan.SERVO
    doing = f", {status.plan.value}" + (f" in {status.phase}" if status.phase else "") if running_other else ""
    hand = f", the hand {status.grasp.value}" if status.grasp is not None else ""
    ended = f", last {status.outcome}" if status.outcome and status.state is not m.TaskState.RUNNING else ""
    return (f"task {status.state.value} (task {status.task}{by}{doing}{hand}{ended})"
            f"{': ' + status.message if status.message else ''}")
