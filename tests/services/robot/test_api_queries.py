"""services/robot/api_queries.py, its worker's side without zenoh: the calls waiting are run on what drives the arm
and answered; a motion is refused while low-level torque control owns the arm, and a call that fails is answered
with its failure and counted."""
import logging
from types import SimpleNamespace

from protocol import kinova
from services.robot.api_queries import ApiQueries
from services.runtime.logs import RateLimitedLogger
from services.runtime.metrics import Counters


class Arm:
    """What drives the arm, as the worker calls it: the calls it ran, and GetAngularPosition failing."""

    def __init__(self):
        self.ran = []

    def call(self, function, argument):
        self.ran.append(function)
        if function == "GetAngularPosition":
            raise OSError("the comm layer answered 1015")
        return kinova.ApiReply()


def queries():
    counters, refused = Counters(), []
    api = ApiQueries("robot", counters, RateLimitedLogger(logging.getLogger("test")),
                     refuse=lambda stream, reason: refused.append((stream, reason)), wake=lambda: None,
                     stopping=lambda: True)
    return api, counters, refused


def submit(api, function, answers):
    assert api.calls.submit(function, None, lambda reply: answers.append((function, reply))) == ""


def test_the_calls_waiting_run_on_the_arm_in_order_and_each_is_answered():
    api, counters, refused = queries()
    arm, answers = Arm(), []
    for function in ("MoveHome", "GetAngularPosition", "StartForceControl"):
        submit(api, function, answers)
    api.run_waiting(arm, SimpleNamespace(torque_mode=False))
    assert arm.ran == ["MoveHome", "GetAngularPosition", "StartForceControl"] and not refused
    assert [(function, reply.code) for function, reply in answers] == [
        ("MoveHome", kinova.ErrorCode.NO_ERROR_KINOVA), ("GetAngularPosition", kinova.ErrorCode.UNKNOWN_ERROR),
        ("StartForceControl", kinova.ErrorCode.NO_ERROR_KINOVA)]
    assert "1015" in answers[1][1].message and counters.get("errors.api") == 1


def test_a_motion_is_refused_while_torque_control_owns_the_arm_and_a_reading_is_not():
    api, _, refused = queries()
    arm, answers = Arm(), []
    submit(api, "SendBasicTrajectory", answers)
    submit(api, "GetCartesianPosition", answers)
    api.run_waiting(arm, SimpleNamespace(torque_mode=True))
    assert arm.ran == ["GetCartesianPosition"]
    assert answers[0][1].code == kinova.ErrorCode.ERROR_INVALID_PARAM
    assert refused == [("api", "SendBasicTrajectory: low-level torque control is active")]
