"""One controller's run against the low-level API without zenoh (services/torque_controller/core.py): its time base,
its end, its timing accounting, its refusals and its log."""
import math

import numpy as np
import pytest

from protocol import messages as m
from services.controller.torque_controllers import ControllerOptions, make_controller
from services.model.arm import load_arm
from services.torque_controller.core import ClientTiming, TorqueRun, load_log

ARM6 = load_arm("j2n6s300")
MS = 1_000_000


def state(stamp_ns: int, q, n: int = 6) -> m.LowLevelState:
    return m.LowLevelState(header=m.Header(stamp_ns=stamp_ns), mode=m.ActuatorMode.TORQUE, q=list(q),
                           dq=[0.0] * n, tau=[0.0] * n, current_a=[0.0] * n, temperature_c=[30.0] * n)


def test_timing_counts_late_superseded_and_unseen_cycles():
    timing = ClientTiming()
    start = 10**12
    for k in (0, 1, 2, 5, 6):  # cycles 3 and 4 never arrived
        timing.received_state(start + 2 * k * MS, start + 2 * k * MS + MS // 2)
    timing.superseded += 1
    # the robot's pipeline: a state arrives 0.5 ms after its stamp at the earliest
    timing.answered_state(start, start + MS // 2, start + MS)  # answered 0.5 ms after it could be: in time
    timing.answered_state(start + 2 * MS, start + 2 * MS + MS // 2, start + 5 * MS)  # 2.5 ms: missed its cycle
    timing.answered_state(start + 4 * MS, start + 6 * MS, start + 7 * MS)  # it came 2 ms late, answered at 2.5
    summary = timing.summary()
    assert (summary["unseen"], summary["late"], summary["superseded"], summary["missed"]) == (2, 2, 1, 5)
    assert summary["latency_ms"]["max"] == pytest.approx(3.0)
    assert summary["response_ms"]["max"] == pytest.approx(2.5)
    assert summary["arrival_delay_ms"]["max"] == pytest.approx(2.0)
    assert summary["cycle_rate_hz"] == pytest.approx(4 / 0.012, abs=0.1)


def test_the_run_evaluates_the_reference_at_each_state_stamp_and_ends_on_time():
    controller = make_controller("joint-pd", ARM6)
    run = TorqueRun(controller, duration_s=0.1)
    start = 10**12
    q0 = ARM6.home
    run.begin(state(start, q0), None)
    assert run.answer(state(start, q0)) is not None
    # a state 50 ms later (whatever the wall clock says): the reference there, eq. 5.3 at t = 0.05 s
    tau = run.answer(state(start + 50 * MS, q0))
    assert tau is not None and run.arrays()["t"][-1] == pytest.approx(0.05)
    expected_q_d = q0 + math.radians(20) * math.sin(2 * math.pi * 0.05 / 8)
    assert run.arrays()["q_d"][-1] == pytest.approx(expected_q_d)
    assert run.answer(state(start + 101 * MS, q0)) is None and run.finished and not run.abort


def test_the_run_gives_up_beyond_its_abort_threshold_and_refuses_another_arms_state():
    controller = make_controller("joint-pd", ARM6, ControllerOptions(abort_joint_deg=5.0))
    run = TorqueRun(controller, duration_s=10.0)
    start = 10**12
    run.begin(state(start, ARM6.home), None)
    assert not run.fits(state(start, [0.0] * 7, n=7)) and run.timing.refused == 1
    assert run.answer(state(start + 2 * MS, ARM6.home + math.radians(10))) is None
    assert run.finished and "joint error" in run.abort


def test_the_log_holds_the_run_and_what_it_was(tmp_path):
    controller = make_controller("jt-pid", ARM6, ControllerOptions(tf_s=1.0))
    run = TorqueRun(controller, duration_s=1.0)
    start = 10**12
    run.begin(state(start, ARM6.home), None)
    for k in range(5):
        run.answer(state(start + 2 * k * MS, ARM6.home))
    path = run.save(tmp_path / "run.npz", robot={"service": "robot_sim"})
    meta, arrays = load_log(path)
    assert meta["controller"] == "jt-pid" and meta["arm"] == "j2n6s300" and meta["robot"]["service"] == "robot_sim"
    assert meta["target"] == "thesis" and meta["xf"] == pytest.approx(list(controller.start.xf))
    assert arrays["x"].shape == (5, 6) and arrays["tau_command"].shape == (5, 6)
    assert np.isnan(arrays["q_d"]).all()  # a task run tracks no joint reference
