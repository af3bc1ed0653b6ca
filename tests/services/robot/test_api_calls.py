"""services/robot/api_calls.py: Kinova API calls between the queryable and the robot's worker, each answered once:
run by the worker, or timed out while waiting (not run), or refused when too many wait or the node stops."""
import threading

from protocol import kinova
from services.robot.api_calls import ApiCallQueue


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def queue_with(clock, **kw):
    answers, timeouts = [], []
    calls = ApiCallQueue(5.0, clock=clock, on_timeout=timeouts.append, **kw)
    return calls, answers, timeouts


def test_the_worker_runs_calls_in_order_and_answers_each_once():
    clock = Clock()
    calls, answers, _ = queue_with(clock)
    for name in ("MoveHome", "GetAngularPosition"):
        assert calls.submit(name, None, lambda reply, name=name: answers.append((name, reply.code))) == ""
    first = calls.take()
    assert first.function == "MoveHome" and first.state == "running"
    calls.finish(first, kinova.ApiReply())
    second = calls.take()
    calls.finish(second, kinova.ApiReply(code=1015))
    assert calls.take() is None
    assert answers == [("MoveHome", 1), ("GetAngularPosition", 1015)]


def test_a_call_still_waiting_at_its_deadline_is_answered_as_timed_out_and_not_run():
    clock = Clock()
    calls, answers, timeouts = queue_with(clock)
    calls.submit("MoveHome", None, answers.append)
    running = calls.take()
    calls.submit("GetAngularPosition", None, answers.append)
    clock.now = 4.9
    assert calls.expire() == 0
    clock.now = 5.0  # the worker is still in MoveHome: the one waiting behind it is due
    assert calls.expire() == 1
    assert answers[0].code == kinova.ErrorCode.ERROR_COMM_TIMEOUT and "GetAngularPosition not run" in answers[0].message
    assert [c.function for c in timeouts] == ["GetAngularPosition"]
    assert calls.expire() == 0 and calls.take() is None  # gone: never run
    calls.finish(running, kinova.ApiReply())  # the running one is answered when it ends, late or not
    assert [a.code for a in answers] == [kinova.ErrorCode.ERROR_COMM_TIMEOUT, 1]
    # a call the worker reaches after its deadline is answered on the way, not run
    calls.submit("MoveHome", None, answers.append)
    clock.now = 11.0
    assert calls.take() is None and answers[-1].code == kinova.ErrorCode.ERROR_COMM_TIMEOUT and len(timeouts) == 2


def test_too_many_waiting_and_a_stopping_node_are_refused_and_the_waiting_answered():
    clock = Clock()
    calls, answers, _ = queue_with(clock, capacity=2)
    assert calls.submit("A", None, answers.append) == "" and calls.submit("B", None, answers.append) == ""
    assert "2 Kinova API calls are waiting" in calls.submit("C", None, answers.append)
    calls.close("robot_gateway is stopping")
    assert [a.message for a in answers] == ["not run: robot_gateway is stopping"] * 2
    assert calls.submit("D", None, answers.append) == "robot_gateway is stopping" and calls.take() is None


def test_the_timeout_thread_wakes_at_the_deadline():
    calls = ApiCallQueue(0.2)
    answers, done = [], threading.Event()
    calls.submit("MoveHome", None, lambda reply: (answers.append(reply), done.set()))

    def expire_when_due():
        while not done.is_set():
            calls.wait_for_deadline(5.0)
            calls.expire()

    thread = threading.Thread(target=expire_when_due)
    thread.start()
    assert done.wait(3.0) and answers[0].code == kinova.ErrorCode.ERROR_COMM_TIMEOUT
    thread.join(3.0)
