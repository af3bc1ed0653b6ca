"""The torque controller as a service (services/torque_controller/service.py): what it refuses. Its runs against a
real robot are in tests/services/robot/test_lowlevel.py (computed torque, both robot profiles) and
tests/services/experiments/test_torque_control.py (the JACO thesis's five controllers, each a process)."""
import math
import time

import msgpack
import msgspec

from protocol import messages as m
from protocol.conventions import ClockMode
from services.robot_sim.service import RobotSimConfig, robot_sim_service
from services.runtime.transport import open_session
from services.torque_controller.service import TorqueControllerConfig, TorqueControllerService
from tests.stack import KEYS, wait_for


def test_bad_states_are_counted_and_a_robot_of_another_arm_is_refused(router):
    """Garbage and NaN on robot/lowlevel/state are rejected and counted; a controller started for the j2n6s300
    against a robot running the j2s7s300 says so, commands nothing and ends (failed)."""
    service = TorqueControllerService(TorqueControllerConfig(
        controller="joint-pd", arm="j2n6s300", realtime_priority=0, robot_timeout_s=20.0,
        zenoh=router.client_config())).start()
    client = open_session(router.client_config())
    commands = []
    subscriber = client.declare_subscriber(KEYS.lowlevel_command, lambda sample: commands.append(sample))
    robot = None
    try:
        nan = m.LowLevelState(header=m.Header(stamp_ns=time.time_ns()), mode=m.ActuatorMode.TORQUE, q=[0.0] * 6,
                              dq=[0.0] * 6, tau=[0.0] * 6, current_a=[0.0] * 6, temperature_c=[0.0] * 6)
        fields = msgspec.to_builtins(nan)
        fields["q"][2] = math.nan
        client.put(KEYS.lowlevel_state, b"\x00garbage")
        client.put(KEYS.lowlevel_state, msgpack.packb(fields))
        assert wait_for(lambda: service.counters.get("rejected.lowlevel_state") == 2, timeout=10)
        robot = robot_sim_service(RobotSimConfig(clock=ClockMode.LOCKSTEP, zenoh=router.client_config())).start()
        assert wait_for(lambda: service.failure != "", timeout=20)
        assert not service.finished.is_set()
        assert "started for the j2n6s300, the robot runs the j2s7s300" in service.failure
        assert service.counters.get("refused.wrong_arm") == 1
        assert not commands
    finally:
        subscriber.undeclare()
        client.close()
        service.stop()
        if robot is not None:
            robot.stop()
