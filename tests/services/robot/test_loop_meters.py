"""services/robot/loop_meters.py: the robot loop's health detail starts with the arm (robot_sim splits it off
there) and names the torque-mode setup only where there is one."""
from services.robot.loop_meters import LoopMeters


def test_the_health_detail_starts_with_the_arm_and_ends_with_the_torque_setup_if_any():
    meters = LoopMeters()
    meters.work.add(0.0005)
    detail = meters.health_detail("arm j2n6s300: 6 joints", "Table 5.1: damping 0")
    assert detail.startswith("arm j2n6s300: 6 joints; bus_rate_hz=0.0 late_per_s=0.0 missed_per_s=0.0 "
                             "work_ms=0.50/0.50 ")
    assert detail.endswith("(p50/p99); Table 5.1: damping 0")
    assert meters.health_detail("arm", "").endswith("(p50/p99)")
