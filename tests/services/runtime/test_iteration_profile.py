"""The lockstep profile's timers: nothing wrapped unless asked, and one thread's timed calls nest exactly."""
import json
import time

from services.runtime import iteration_profile as ip


class _Work:
    def outer(self):
        time.sleep(0.002)
        self.inner()
        return 1

    def inner(self):
        time.sleep(0.003)


def test_off_the_functions_are_the_ones_written(monkeypatch):
    monkeypatch.delenv(ip.PROFILE_DIR_ENV, raising=False)
    from services.robot.node import RobotNode

    before = RobotNode.bus_cycle
    assert ip.install("robot_sim") is False
    assert RobotNode.bus_cycle is before and not hasattr(before, "__wrapped_by_profile__")


def test_nested_timers_split_the_outer_call_exactly():
    timers = ip._Timers()
    work = _Work()
    work.outer, work.inner = timers.wrap("outer", work.outer), timers.wrap("inner", work.inner)
    for _ in range(3):
        assert work.outer() == 1
    (outer,) = [v for (_, label), v in timers.totals.items() if label == "outer"]
    (inner,) = [v for (_, label), v in timers.totals.items() if label == "inner"]
    assert outer[2] == inner[2] == 3 and outer[3] == 3 and inner[3] == 0  # calls, and calls that returned a value
    assert inner[0] == inner[1] >= 9_000_000  # 3 × 3 ms, nothing timed inside
    assert outer[1] + inner[1] == outer[0] and outer[1] >= 6_000_000  # exclusive times add up to the outer call


def test_every_timed_function_exists():
    """A renamed function would silently drop out of the profile: each name resolves, to a function."""
    for process, timed in ip.TIMED.items():
        for name in timed:
            owner, attribute, function = ip._resolve(name)
            assert callable(function), f"{process}: {name}"


def test_a_profile_is_written_at_exit_and_read_back(tmp_path):
    timers = ip._Timers()
    timers.wrap("frame_wait", lambda: 5)()
    ip._timers, saved = timers, ip._timers
    try:
        ip._write(tmp_path, "robot_sim")
    finally:
        ip._timers = saved
    profile = ip.read_profiles(tmp_path)["robot_sim"]
    assert profile["cpu_s"] > 0 and ip.calls(profile, "frame_wait", returned=True) == 1
    assert json.loads(next(tmp_path.glob("robot_sim-*.json")).read_text())["timers"][0]["label"] == "frame_wait"
