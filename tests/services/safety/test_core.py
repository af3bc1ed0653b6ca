"""Safety's rules without zenoh, locks or a clock (services.safety.core): what each input makes safety send."""
import pytest
import numpy as np

from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from services.safety.checks import SafetyLimits
from services.safety.core import Count, HeldCommand, Note, Refused, SafetyCore, Send
from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics
from tests.helpers import ARM_DECLARED

ARM = load_arm("j2s7s300")

S = 1_000_000_000  # ns


def core(lockstep=False, **limits) -> SafetyCore:
    safety = SafetyCore(SafetyLimits(**limits), upstream=["vision", "controller"], robots=["robot_sim"],
                        rate_hz=100.0, lockstep=lockstep)
    for name in ("vision", "controller", "robot_sim"):
        safety.liveliness(name, True)
    return safety


def state(stamp_ns, q=None) -> m.RobotState:
    return m.RobotState(**ARM_DECLARED, header=m.Header(stamp_ns=stamp_ns), q=(ARM.home if q is None else q).tolist(),
                        dq=[0.0] * 7, tau=[0.0] * 7,
                        pose=m.KinovaPose(X=0, Y=0, Z=0, ThetaX=0, ThetaY=0, ThetaZ=0),
                        control_mode=m.ControlMode.CARTESIAN_VELOCITY)


def twist(stamp_ns, capture_ns=None, linear=(0.05, 0.0, 0.0)) -> HeldCommand:
    header = m.Header(stamp_ns=stamp_ns, source_stamp_ns=stamp_ns if capture_ns is None else capture_ns)
    return HeldCommand(m.Twist(header=header, frame=Frame.MIXED, angular=AngularConvention.SEED000, linear=linear,
                               rotational=(0.0, 0.0, 0.0)), None, stamp_ns)


def sends(actions) -> list[m.RobotCommand]:
    return [a.command for a in actions if isinstance(a, Send)]


def refusals(actions) -> list[str]:
    return [a.reason for a in actions if isinstance(a, Refused)]


def test_idle_is_a_stop_and_an_approved_command_is_held_and_resent_while_fresh():
    safety = core()
    assert [c.mode for c in sends(safety.cycle(10 * S))] == [m.CommandMode.STOP]
    safety.state(state(10 * S), 10 * S)
    approved = safety.desired(twist(10 * S), 10 * S + 5_000_000)
    assert [c.mode for c in sends(approved)] == [m.CommandMode.CARTESIAN_VELOCITY]
    assert sends(approved)[0].twist.linear[0] > 0 and approved[0].held is safety.held
    resent = sends(safety.cycle(10 * S + 50_000_000))
    assert resent[0].mode is m.CommandMode.CARTESIAN_VELOCITY
    stale = safety.cycle(10 * S + 150_000_000)  # the command is 150 ms old: budget 100 ms
    assert refusals(stale) == ["freshness: command is 150 ms old (budget 100 ms)"]
    assert [c.mode for c in sends(stale)] == [m.CommandMode.STOP] and safety.held is None


def test_a_motion_command_held_back_before_it_leaves_goes_out_as_a_stop_once_its_image_aged_past_the_budget():
    """A service held back between the check and the publication (an overloaded host) must not send motion on an
    image that aged past the budget meanwhile: checked again as it leaves, it is the stop that refuses it."""
    safety = core()
    checked = 10 * S + 200_000_000  # the image captured at 10 s, 200 ms old when checked: within 250 ms
    safety.state(state(checked - 5_000_000), checked - 5_000_000)
    approved = safety.desired(twist(checked - 5_000_000, capture_ns=10 * S), checked)
    send = next(a for a in approved if isinstance(a, Send))
    assert send.command.mode is m.CommandMode.CARTESIAN_VELOCITY and safety.held is send.held
    assert safety.leaving(send, checked + 10_000_000) == [send]  # 210 ms: still within the budget
    late = safety.leaving(send, checked + 60_000_000)  # held back 60 ms: the image is 260 ms old
    assert refusals(late) == ["freshness: image is 260 ms old (budget 250 ms)"]
    assert [c.mode for c in sends(late)] == [m.CommandMode.STOP] and safety.held is None
    assert sends(late)[0].reason == refusals(late)[0]
    stop = next(a for a in late if isinstance(a, Send))
    assert safety.leaving(stop, checked + 500_000_000) == [stop]  # a stop leaves whenever it can


def test_freshness_is_two_sided_and_liveliness_is_required():
    safety = core()
    safety.state(state(10 * S), 10 * S)
    future = safety.desired(twist(10 * S + 60_000_000), 10 * S)
    assert "in the future" in refusals(future)[0]
    assert [c.mode for c in sends(future)] == [m.CommandMode.STOP]
    assert "image is 300 ms old" in refusals(safety.desired(twist(10 * S, capture_ns=10 * S - 300_000_000),
                                                           10 * S))[0]
    safety.liveliness("vision", False)
    assert refusals(safety.desired(twist(10 * S), 10 * S)) == ["liveliness: vision not alive"]


def test_losing_the_command_path_while_a_command_is_held_stops_at_once():
    safety = core()
    safety.state(state(10 * S), 10 * S)
    safety.desired(twist(10 * S), 10 * S)
    actions = safety.liveliness("controller", False)
    assert refusals(actions) == ["liveliness: controller is gone"]
    assert [c.mode for c in sends(actions)] == [m.CommandMode.STOP] and safety.held is None


def test_the_estop_latches_answers_every_frame_with_an_emergency_stop_and_only_a_reset_releases_it():
    safety = core()
    safety.state(state(10 * S), 10 * S)
    safety.desired(twist(10 * S), 10 * S)
    engaged = safety.estop(m.EStop(header=m.Header(), operator="alice", reason="spill"))
    assert [a.name for a in engaged if isinstance(a, Count)] == ["estop.triggers"]
    assert any(isinstance(a, Note) and "alice: spill" in a.text for a in engaged)
    assert [c.mode for c in sends(engaged)] == [m.CommandMode.EMERGENCY_STOP] and safety.held is None
    answer = safety.desired(twist(10 * S + 10_000_000), 10 * S + 10_000_000)
    assert refusals(answer) == ["estop: latched (alice: spill)"]
    assert [c.mode for c in sends(answer)] == [m.CommandMode.EMERGENCY_STOP]
    assert sends(safety.cycle(10 * S + 20_000_000))[0].mode is m.CommandMode.EMERGENCY_STOP
    released = safety.estop(m.EStop(header=m.Header(), reset=True, operator="alice"))
    assert [a.name for a in released if isinstance(a, Count)] == ["estop.resets"] and not safety.estop_latched
    assert sends(safety.desired(twist(10 * S + 30_000_000), 10 * S + 30_000_000))[0].mode is \
        m.CommandMode.CARTESIAN_VELOCITY


def test_measured_overspeed_latches_a_protective_stop():
    safety = core()
    J = ArmKinematics(ARM).jacobian_base(ARM.home)
    actions = []
    for k in range(3):  # the end effector at 0.3 m/s (limit 0.15) for longer than a state period
        moving = state(10 * S + k * 10_000_000)
        moving.dq = (np.linalg.pinv(J) @ np.array([0.3, 0, 0, 0, 0, 0])).tolist()
        actions += safety.state(moving, moving.header.stamp_ns)
    assert safety.estop_latched and "protective stop" in safety.estop_reason
    assert [a.name for a in actions if isinstance(a, Count)] == ["overspeed.trips"]
    assert [c.mode for c in sends(actions)] == [m.CommandMode.EMERGENCY_STOP]


def with_contacts(stamp_ns, contacts, last=(0, 0.0, 0.0)) -> m.RobotState:
    out = state(stamp_ns)
    out.contact = m.ContactState(residual_nm=[0.0] * 7, threshold_nm=[2.0] * 7, ratio=0.5, joint=0, rate_hz=500.0,
                                 contacts=contacts, last_joint=last[0], last_residual_nm=last[1],
                                 last_threshold_nm=last[2])
    return out


def test_a_contact_the_robot_detected_latches_a_protective_stop_that_names_it_and_only_a_reset_releases_it():
    safety = core()
    # contacts before safety saw the robot are not its charge: the first state sets where the count starts
    assert not refusals(safety.state(with_contacts(10 * S, 2), 10 * S)) and not safety.estop_latched
    safety.desired(twist(10 * S), 10 * S)
    assert safety.held is not None
    quiet = safety.state(with_contacts(10 * S + 10_000_000, 2), 10 * S + 10_000_000)
    assert not safety.estop_latched and not [a for a in quiet if isinstance(a, Count)]
    # a state missed, the next one's count two higher: one stop, naming the last contact
    touched = safety.state(with_contacts(10 * S + 30_000_000, 4, (3, -5.25, 3.2)), 10 * S + 30_000_000)
    assert safety.estop_latched and safety.held is None
    assert [a.name for a in touched if isinstance(a, Count)] == ["contact.stops"]
    assert refusals(touched) == ["protective_stop: contact at joint 3: residual -5.25 N·m beyond its 3.20 N·m "
                                 "threshold"]
    assert [c.mode for c in sends(touched)] == [m.CommandMode.EMERGENCY_STOP]
    assert all(c.fingers is None for c in sends(touched))  # the hand is never opened by it
    # it holds while the robot says the same count; an operator's reset releases it as an e-stop's
    later = safety.desired(twist(10 * S + 40_000_000), 10 * S + 40_000_000)
    assert refusals(later)[0].startswith("estop: latched (protective stop: contact at joint 3")
    safety.state(with_contacts(10 * S + 50_000_000, 4), 10 * S + 50_000_000)
    safety.estop(m.EStop(header=m.Header(), reset=True, operator="alice"))
    assert not safety.estop_latched
    assert sends(safety.desired(twist(10 * S + 60_000_000), 10 * S + 60_000_000))[0].mode is \
        m.CommandMode.CARTESIAN_VELOCITY


def test_a_robot_that_started_again_counts_from_zero_and_its_first_contact_still_stops_the_arm():
    safety = core()
    safety.state(with_contacts(10 * S, 3), 10 * S)
    restarted = safety.state(with_contacts(10 * S + 10_000_000, 0), 10 * S + 10_000_000)
    assert not safety.estop_latched and not [a for a in restarted if isinstance(a, Count)]
    touched = safety.state(with_contacts(10 * S + 20_000_000, 1, (2, 4.5, 4.4)), 10 * S + 20_000_000)
    assert safety.estop_latched and [a.name for a in touched if isinstance(a, Count)] == ["contact.stops"]
    # a restart whose first state already counts one: that contact happened while safety ran
    again = core()
    again.state(with_contacts(10 * S, 3), 10 * S)
    again.state(with_contacts(10 * S + 10_000_000, 1, (2, 4.5, 4.4)), 10 * S + 10_000_000)
    assert again.estop_latched and "contact at joint 2" in again.estop_reason


def test_lockstep_checks_a_command_against_its_frame_s_state_and_answers_every_tick():
    safety = core(lockstep=True)
    frame = 10 * S
    waiting = safety.desired(twist(frame), frame)  # its frame's state has not arrived yet
    assert waiting == [] and len(safety.waiting) == 1
    actions = safety.state(state(frame), frame)  # the tick's answer (nothing held yet: a stop), then the command
    modes = [c.mode for c in sends(actions)]
    assert modes == [m.CommandMode.STOP, m.CommandMode.CARTESIAN_VELOCITY]
    assert [a.stamp_ns for a in actions if isinstance(a, Send)] == [frame, None]


def test_lockstep_answers_a_frame_the_same_whichever_of_its_state_and_command_arrives_first():
    """Each subscriber has its own thread, so the host decides whether a tick's state or the command derived from
    that tick's frame reaches safety first; each check moves the ramp on (the checker remembers the last command),
    so the answers must not depend on it."""
    def run(command_first: bool) -> list:
        safety = core(lockstep=True)
        out = []
        for k in range(4):  # a held command that grows each frame: the ramp limits every step
            tick = 10 * S + k * 10_000_000
            command = twist(tick, linear=(0.04 * (k + 1), 0.0, 0.0))
            inputs = [lambda: safety.desired(command, tick), lambda: safety.state(state(tick), tick)]
            for give in (inputs if command_first else inputs[::-1]):
                out += [(c.mode, c.twist.linear if c.twist is not None else None, c.header.source_stamp_ns)
                        for c in sends(give())]
        return out

    assert run(command_first=True) == run(command_first=False)


def test_lockstep_answers_a_repeated_state_or_command_as_before_without_checking_it_again():
    """The robot's lockstep retry publishes a tick's state and frame again when an answer is slow (wall time): safety
    answers them with what it sent, so that the ramp (which each check moves on) and every later answer are what
    they are without the retry. After an e-stop a repeat is answered anew: never motion again."""
    def run(repeat: bool):
        safety = core(lockstep=True)
        out = []
        for k in range(4):
            tick = 10 * S + k * 10_000_000
            command = twist(tick, linear=(0.05 * (k + 1), 0.0, 0.0))
            steps = [lambda: safety.state(state(tick), tick), lambda: safety.desired(command, tick)]
            if repeat:
                steps += steps
            for step in steps:
                actions = step()
                out.append([(c.mode, c.twist.linear if c.twist is not None else None) for c in sends(actions)])
        return safety, out

    once, answers = run(repeat=False)
    twice, repeated = run(repeat=True)
    assert [a for k, a in enumerate(repeated) if k % 4 < 2] == answers  # the first of each, as without repeats
    # a repeat of the tick's state or of its frame's command: the last command sent at that tick (the frame's)
    assert [a for k, a in enumerate(repeated) if k % 4 >= 2] == [a for k, a in enumerate(answers) for _ in (0, 1)
                                                                 if k % 2 == 1]
    assert np.allclose(twice.checker.last_twist_base, once.checker.last_twist_base)
    last = 10 * S + 30_000_000
    twice.estop(m.EStop(header=m.Header(), reason="test"))
    assert [c.mode for c in sends(twice.state(state(last), last))] == [m.CommandMode.EMERGENCY_STOP]


def test_lockstep_takes_a_command_s_trace_and_a_robot_state_as_proof_of_life_before_their_tokens_arrive():
    """Liveliness tokens reach safety in wall time: on a busy host a lockstep run's first frame could come before
    vision's token was seen, and the run would differ from the next. In lockstep the services on a command's trace,
    and the robot whose state safety holds, are alive; in realtime only their tokens say so. A token withdrawn
    stops the arm in both."""
    def fresh(lockstep: bool) -> SafetyCore:
        return SafetyCore(SafetyLimits(), upstream=["vision", "controller"], robots=["robot_sim"], rate_hz=100.0,
                          lockstep=lockstep)

    frame = 10 * S
    command = twist(frame)
    command.twist.header.trace = [m.Hop(service="vision", recv_ns=frame, pub_ns=frame),
                                  m.Hop(service="controller", recv_ns=frame, pub_ns=frame)]
    lockstep = fresh(True)
    lockstep.state(state(frame), frame)
    assert [c.mode for c in sends(lockstep.desired(command, frame))] == [m.CommandMode.CARTESIAN_VELOCITY]
    untraced = fresh(True)
    untraced.state(state(frame), frame)
    assert refusals(untraced.desired(twist(frame), frame)) == ["liveliness: vision, controller not alive"]
    realtime = fresh(False)
    realtime.state(state(frame), frame)
    assert refusals(realtime.desired(command, frame)) == ["liveliness: vision, controller not alive"]
    lockstep.liveliness("vision", True)
    withdrawn = lockstep.liveliness("vision", False)
    assert refusals(withdrawn) == ["liveliness: vision is gone"] and lockstep.held is None


def test_safety_started_for_another_arm_than_the_robots_sends_only_stops():
    """Safety started for the 6-DoF, the robot declaring the 7-DoF: the state is refused (``arm``), a desired
    command gets a stop, nothing moves (issue 32); safety left to the robot's arm checks for the robot's."""
    for_6dof = SafetyCore(SafetyLimits(), upstream=["vision", "controller"], robots=["robot_sim"], rate_hz=100.0,
                          lockstep=False, arm="j2n6s300")
    for name in ("vision", "controller", "robot_sim"):
        for_6dof.liveliness(name, True)
    actions = for_6dof.state(state(10 * S), 10 * S)
    assert [a.reason for a in actions if isinstance(a, Refused)] == [
        "arm: started for the j2n6s300, the robot runs the j2s7s300: nothing is done for it"]
    answer = sends(for_6dof.desired(twist(10 * S), 10 * S))
    assert [c.mode for c in answer] == [m.CommandMode.STOP] and for_6dof.checker is None
    follows = core()
    follows.state(state(10 * S), 10 * S)
    assert sends(follows.desired(twist(10 * S), 10 * S))[0].mode is m.CommandMode.CARTESIAN_VELOCITY
    assert follows.arm.name == "j2s7s300"


def test_joint_velocities_for_another_arm_are_refused():
    safety = core()
    safety.state(state(10 * S), 10 * S)
    six = HeldCommand(None, m.JointVelocity(header=m.Header(stamp_ns=10 * S, source_stamp_ns=10 * S),
                                            velocities=[0.01] * 6), 10 * S)
    actions = safety.desired(six, 10 * S)
    assert [c.mode for c in sends(actions)] == [m.CommandMode.STOP]
    assert any(isinstance(a, Refused) and a.reason.startswith("joint_count: 6 joint velocities") for a in actions)


# ------------------------------------------------------------------ command sources
def sourced(stamp_ns, source, linear=(0.05, 0.0, 0.0)) -> HeldCommand:
    header = m.Header(stamp_ns=stamp_ns, source_stamp_ns=stamp_ns)
    return HeldCommand(m.Twist(header=header, frame=Frame.MIXED, angular=AngularConvention.SEED000, linear=linear,
                               rotational=(0.0, 0.0, 0.0), source=source), None, stamp_ns)


def two_sources() -> SafetyCore:
    """The controller (priority 10) and a second image-derived source above it (priority 20)."""
    from services.safety.sources import CommandSource, default_sources

    safety = SafetyCore(SafetyLimits(), upstream=["vision", "controller"], robots=["robot_sim"], rate_hz=100.0,
                        lockstep=False, sources=default_sources() + [CommandSource(
                            name="helper", keys=["desired_twist"], drives=["twist"], priority=20)])
    for name in ("vision", "controller", "robot_sim"):
        safety.liveliness(name, True)
    safety.state(state(10 * S), 10 * S)
    return safety


def test_the_source_in_control_is_the_one_whose_command_is_held():
    safety = core()
    safety.state(state(10 * S), 10 * S)
    assert safety.in_control == ""
    approved = safety.desired(twist(10 * S), 10 * S)
    assert safety.in_control == "controller/servo" and sends(approved)[0].twist.source == "controller/servo"
    safety.desired(sourced(10 * S + 20_000_000, "controller/probe"), 10 * S + 20_000_000)
    assert safety.in_control == "controller/probe"  # the same source doing something else: no switch
    assert safety.claim.switches == 0
    safety.cycle(10 * S + 200_000_000)  # stale: nothing held, nobody in control
    assert safety.held is None and safety.in_control == ""


def test_a_command_from_an_undeclared_source_is_refused_before_any_check_and_moves_nothing():
    safety = core()
    safety.state(state(10 * S), 10 * S)
    out = safety.desired(sourced(10 * S, "intruder"), 10 * S)
    assert refusals(out) == ["source: 'intruder' is not a declared command source (controller, jog)"]
    assert [c.mode for c in sends(out)] == [m.CommandMode.STOP] and safety.in_control == ""
    joint = HeldCommand(None, m.JointVelocity(header=m.Header(stamp_ns=10 * S, source_stamp_ns=10 * S),
                                              velocities=[0.0] * 7, source="helper"), 10 * S)
    assert refusals(two_sources().desired(joint, 10 * S)) == ["source: helper may not command on "
                                                             "desired_joint_velocity"]


def test_a_higher_priority_source_takes_control_and_a_lower_one_is_refused_without_stopping_it():
    safety = two_sources()
    t = 10 * S
    safety.desired(sourced(t, "controller/servo"), t)
    assert safety.in_control == "controller/servo"
    taken = safety.desired(sourced(t + 10_000_000, "helper/hold", linear=(0.0, 0.02, 0.0)), t + 10_000_000)
    assert safety.in_control == "helper/hold" and safety.claim.switches == 1
    assert any(isinstance(a, Count) and a.name == "claims.switched" for a in taken)
    assert sends(taken)[-1].twist.linear[1] > 0
    refused = safety.desired(sourced(t + 20_000_000, "controller/servo"), t + 20_000_000)
    assert refusals(refused) == ["claim: helper/hold is in control (priority 20 ≥ 10)"]
    assert sends(refused) == [] and safety.in_control == "helper/hold"  # the holder's motion goes on
    assert sends(safety.cycle(t + 30_000_000))[0].twist.linear[1] > 0
    # the holder lets go (its command goes stale): the displaced controller takes control again only from rest
    # (its task pauses when it hears who took control: the person letting go never resumes what they interrupted),
    # no switch counted as a take-over (nobody held it)
    safety.cycle(t + 200_000_000)
    assert safety.in_control == ""
    safety.state(state(t + 200_000_000), t + 200_000_000)
    refused = safety.desired(sourced(t + 210_000_000, "controller/servo"), t + 210_000_000)
    assert refusals(refused) == ["claim: controller was displaced by helper/hold and takes control again only from "
                                 "rest (its task pauses)"]
    assert [c.mode for c in sends(refused)] == [m.CommandMode.STOP] and safety.in_control == ""
    safety.desired(sourced(t + 220_000_000, "controller/servo", linear=(0.0, 0.0, 0.0)), t + 220_000_000)
    assert safety.in_control == "controller/servo" and safety.claim.switches == 1
    moving = safety.desired(sourced(t + 230_000_000, "controller/servo"), t + 230_000_000)
    assert sends(moving)[-1].twist.linear[0] > 0


def test_sources_are_declared_once_on_keys_that_exist():
    from services.safety.sources import CommandSource, SourceRegistry

    with pytest.raises(ValueError, match="declared twice"):
        SourceRegistry([CommandSource(name="a", keys=["desired_twist"], drives=["twist"])] * 2)
    with pytest.raises(ValueError, match="unknown keys"):
        SourceRegistry([CommandSource(name="a", keys=["robot_command"], drives=["twist"])])
    with pytest.raises(ValueError, match="must be 1-32"):
        CommandSource(name="Jog Pad", keys=["desired_twist"], drives=["twist"])


# ------------------------------------------------------------------------------------------------ the hand
def hand_state(stamp_ns, fingers=True) -> m.RobotState:
    s = state(stamp_ns)
    if not fingers:
        return s
    return m.RobotState(**{f: getattr(s, f) for f in s.__struct_fields__ if f != "fingers"},
                        fingers=m.FingerState(position=[0.1] * 3, velocity=[0.0] * 3, current_a=[0.0] * 3,
                                              target=[0.1] * 3))


def twist_with_fingers(stamp_ns, values, mode=m.FingerMode.POSITION) -> HeldCommand:
    header = m.Header(stamp_ns=stamp_ns, source_stamp_ns=stamp_ns)
    return HeldCommand(m.Twist(header=header, frame=Frame.MIXED, angular=AngularConvention.SEED000,
                               linear=(0.0, 0.0, 0.0), rotational=(0.0, 0.0, 0.0),
                               fingers=m.FingerCommand(mode=mode, values=values)), None, stamp_ns)


def test_a_commands_hand_part_goes_with_its_approved_motion_and_with_every_resend_while_it_is_fresh():
    safety = core()
    safety.state(hand_state(10 * S), 10 * S)
    approved = sends(safety.desired(twist_with_fingers(10 * S, [1.2] * 3), 10 * S + 5_000_000))
    assert approved[0].mode is m.CommandMode.CARTESIAN_VELOCITY
    assert approved[0].fingers == m.FingerCommand(mode=m.FingerMode.POSITION, values=[1.2] * 3)
    assert approved[0].twist.fingers is None  # the robot command's own field carries it
    assert sends(safety.cycle(10 * S + 50_000_000))[0].fingers is not None
    stale = sends(safety.cycle(10 * S + 150_000_000))
    assert stale[0].mode is m.CommandMode.STOP and stale[0].fingers is None  # the fingers keep their targets


def test_safety_never_moves_a_finger_by_itself_an_estop_or_a_refusal_carries_no_hand_part():
    safety = core()
    safety.state(hand_state(10 * S), 10 * S)
    safety.desired(twist_with_fingers(10 * S, [1.2] * 3), 10 * S + 5_000_000)
    engaged = sends(safety.estop(m.EStop(header=m.Header(), operator="caregiver")))
    assert [(c.mode, c.fingers) for c in engaged] == [(m.CommandMode.EMERGENCY_STOP, None)]
    while_latched = safety.desired(twist_with_fingers(10 * S + 20_000_000, [0.0] * 3), 10 * S + 25_000_000)
    assert all(c.fingers is None for c in sends(while_latched))  # opening the hand refused like any motion
    safety.estop(m.EStop(header=m.Header(), operator="caregiver", reset=True))
    assert all(c.fingers is None for c in sends(safety.cycle(10 * S + 30_000_000)))
    gone = safety.liveliness("controller", False)
    assert all(c.fingers is None for c in sends(gone))


def test_a_hand_part_that_does_not_fit_refuses_the_whole_command():
    safety = core()
    safety.state(hand_state(10 * S), 10 * S)
    wrong = safety.desired(twist_with_fingers(10 * S, [1.0, 1.0]), 10 * S + 5_000_000)
    assert refusals(wrong) == ["fingers: the kg3 has 3 fingers, the command 2 values"]
    assert [(c.mode, c.fingers) for c in sends(wrong)] == [(m.CommandMode.STOP, None)]
    safety = core()
    safety.state(hand_state(10 * S, fingers=False), 10 * S)  # a robot that reports no fingers (the RS-485 link)
    none = safety.desired(twist_with_fingers(10 * S, [1.0] * 3), 10 * S + 5_000_000)
    assert refusals(none) == ["fingers: a finger command, and the j2s7s300's robot reports no fingers"]


def test_a_source_not_declared_to_drive_the_fingers_has_a_command_with_a_hand_part_refused():
    from services.safety.sources import CommandSource

    safety = SafetyCore(SafetyLimits(), upstream=["vision", "controller"], robots=["robot_sim"], rate_hz=100.0,
                        lockstep=False, sources=[CommandSource(name="controller", keys=["desired_twist"], drives=["twist"])])
    for name in ("vision", "controller", "robot_sim"):
        safety.liveliness(name, True)
    safety.state(hand_state(10 * S), 10 * S)
    refused = safety.desired(twist_with_fingers(10 * S, [1.2] * 3), 10 * S + 5_000_000)
    assert refusals(refused) == ["source: controller may not drive fingers"]
    assert all(c.fingers is None for c in sends(refused))


# ------------------------------------------------------------------ device-derived sources (a person's joystick)
def device_sourced(stamp_ns, seq, device_ns=None, linear=(0.0, 0.03, 0.0), source="person/stick") -> HeldCommand:
    header = m.Header(seq=seq, stamp_ns=stamp_ns, source_stamp_ns=stamp_ns if device_ns is None else device_ns)
    return HeldCommand(m.Twist(header=header, frame=Frame.MIXED, angular=AngularConvention.SEED000, linear=linear,
                               rotational=(0.0, 0.0, 0.0), source=source), None, stamp_ns)


def with_device_source(lockstep=False) -> SafetyCore:
    """The controller (image-derived, priority 10) and a person's device (device-derived, priority 20)."""
    from services.safety.sources import CommandSource, default_sources

    safety = SafetyCore(SafetyLimits(), upstream=["vision", "controller"], robots=["robot_sim"], rate_hz=100.0,
                        lockstep=lockstep, sources=default_sources() + [CommandSource(
                            name="person", keys=["desired_twist"], drives=["twist"], priority=20,
                            freshness="device")])
    safety.liveliness("robot_sim", True)
    safety.state(state(10 * S), 10 * S)
    return safety


def test_a_device_derived_command_needs_no_image_path_only_its_budget_and_a_device_heard_lately():
    safety = with_device_source()  # neither vision nor the controller is alive: a joystick needs neither
    t = 10 * S
    moved = safety.desired(device_sourced(t, seq=1), t + 2_000_000)
    assert [c.mode for c in sends(moved)] == [m.CommandMode.CARTESIAN_VELOCITY] and safety.in_control == "person/stick"
    stale = safety.cycle(t + 120_000_000)  # no command for 120 ms: budget 100 ms
    assert refusals(stale) == ["freshness: command is 120 ms old (budget 100 ms)"] and safety.held is None
    frozen = safety.desired(device_sourced(t + 300_000_000, seq=2, device_ns=t), t + 300_000_000)
    assert refusals(frozen) == ["freshness: its device was last heard 300 ms ago (budget 250 ms: frozen or gone)"]
    assert [c.mode for c in sends(frozen)] == [m.CommandMode.STOP]
    unheard = safety.desired(device_sourced(t + 310_000_000, seq=3, device_ns=0), t + 310_000_000)
    assert refusals(unheard) == ["freshness: command does not say when its device was last heard"]


def test_a_device_derived_command_must_come_after_the_last_one_taken_from_its_device():
    safety = with_device_source()
    t = 10 * S
    safety.state(state(t + 10_000_000), t + 10_000_000)
    assert sends(safety.desired(device_sourced(t + 10_000_000, seq=7), t + 10_000_000))[0].mode is \
        m.CommandMode.CARTESIAN_VELOCITY
    replayed = safety.desired(device_sourced(t + 20_000_000, seq=7), t + 20_000_000)
    assert refusals(replayed) == ["sequence: person/stick's command 7 is not after its last, 7"]
    # not the person's latest input: refused, and the latest (seq 7, still fresh) keeps its motion
    assert sends(replayed) == [] and safety.held.source.seq == 7
    assert sends(safety.desired(device_sourced(t + 30_000_000, seq=8), t + 30_000_000))[0].mode is \
        m.CommandMode.CARTESIAN_VELOCITY
    # another device of the same source counts its own sequence
    other = safety.desired(device_sourced(t + 40_000_000, seq=1, source="person/console"), t + 40_000_000)
    assert refusals(other) == [] and safety.in_control == "person/console"


def test_losing_the_image_path_does_not_stop_a_device_in_control_and_lockstep_runs_refuse_devices():
    safety = with_device_source()
    t = 10 * S
    for name in ("vision", "controller"):
        safety.liveliness(name, True)
    safety.desired(device_sourced(t, seq=1), t)
    assert safety.liveliness("vision", False) == [] and safety.in_control == "person/stick"
    assert safety.liveliness("robot_sim", False) == [] and safety.cycle(t + 10_000_000)[0].reason == \
        "liveliness: no robot alive"
    lockstep = with_device_source(lockstep=True)
    refused = lockstep.desired(device_sourced(t, seq=1), t)
    assert refusals(refused) == ["freshness: person/stick is a device's source, and this is a lockstep run (a "
                                 "person's device runs on wall time)"]
    assert lockstep.waiting == []


# ------------------------------------------------------------------ a person's jog (services/jog)
def jog(stamp_ns, seq, deadman=True, mode=m.JogMode.TRANSLATION, linear=(0.0, 0.0, 0.0), angular=(0.0, 0.0, 0.0),
        finger_rate=0.0, device_ns=None) -> m.Jog:
    return m.Jog(header=m.Header(seq=seq, stamp_ns=stamp_ns, source_stamp_ns=stamp_ns if device_ns is None
                                 else device_ns), mode=mode, deadman=deadman, linear=linear, angular=angular,
                 finger_rate=finger_rate)


def jogging(lockstep=False) -> SafetyCore:
    """Safety as shipped (the controller and the jog), a JACO-2 with its hand, every service alive."""
    safety = core(lockstep)
    safety.state(hand_state(10 * S), 10 * S)
    return safety


def test_a_jog_moves_the_hand_along_the_base_and_turns_it_about_its_own_axes_only_while_its_deadman_is_held():
    safety = jogging()
    t = 10 * S
    moved = sends(safety.jog(jog(t, 1, linear=(0.0, 0.03, 0.0)), t, t))
    assert [c.mode for c in moved] == [m.CommandMode.CARTESIAN_VELOCITY] and safety.in_control == "jog/stick"
    assert moved[0].twist.angular is SafetyLimits().robot_convention and moved[0].twist.linear[1] > 0
    assert moved[0].twist.linear[0] == 0.0 and moved[0].twist.linear[2] == 0.0  # its direction kept
    released = safety.jog(jog(t + 10_000_000, 2, deadman=False, linear=(0.0, 0.03, 0.0)), t + 10_000_000,
                          t + 10_000_000)
    assert refusals(released) == ["deadman: jog/stick released"]
    assert [c.mode for c in sends(released)] == [m.CommandMode.STOP] and safety.held is None
    assert Count("released.stops") in released
    # released and not in control: nothing happens, nothing is refused
    assert safety.jog(jog(t + 20_000_000, 3, deadman=False), t + 20_000_000, t + 20_000_000) == \
        [Count("released.idle")]
    # ω about the hand's own z: at the home pose the hand's z is not the base's, and what the robot gets turns the
    # hand about its own z
    wrist = sends(safety.jog(jog(t + 30_000_000, 4, mode=m.JogMode.WRIST, angular=(0.0, 0.0, 0.2)),
                             t + 30_000_000, t + 30_000_000))[0]
    from services.model import frames

    R, _ = ArmKinematics(ARM).pose(ARM.home)
    omega_ee = frames.omega_ee_from_angular(np.array(wrist.twist.rotational), R, SafetyLimits().robot_convention)
    assert omega_ee[2] > 0 and abs(omega_ee[0]) < 1e-9 and abs(omega_ee[1]) < 1e-9


def test_a_jog_in_fingers_mode_moves_every_finger_at_its_rate_and_its_release_leaves_them_where_they_are():
    safety = jogging()
    t = 10 * S
    closing = sends(safety.jog(jog(t, 1, mode=m.JogMode.FINGERS, finger_rate=0.5), t, t))[0]
    assert closing.fingers == m.FingerCommand(mode=m.FingerMode.VELOCITY, values=[0.5] * ARM.hand.n_fingers)
    assert not any(closing.twist.linear) and not any(closing.twist.rotational)
    released = sends(safety.jog(jog(t + 10_000_000, 2, deadman=False, mode=m.JogMode.FINGERS, finger_rate=0.5),
                                t + 10_000_000, t + 10_000_000))
    assert [c.fingers for c in released] == [None]


def test_a_jog_takes_control_from_the_servo_which_retakes_it_only_from_rest():
    safety = jogging()
    t = 10 * S
    safety.desired(twist(t), t)
    assert safety.in_control == "controller/servo"
    safety.jog(jog(t + 10_000_000, 1), t + 10_000_000, t + 10_000_000)  # a touch: the dead-man, the stick centred
    assert safety.in_control == "jog/stick" and safety.claim.switches == 1
    assert not any(sends(safety.cycle(t + 20_000_000))[0].twist.linear)  # the servo's motion does not go on
    waiting = safety.desired(twist(t + 30_000_000, linear=(0.0, 0.0, 0.0)), t + 30_000_000)
    assert waiting == [Count("claims.waiting")]  # at rest, waiting: no refusal
    assert refusals(safety.desired(twist(t + 40_000_000), t + 40_000_000)) == [
        "claim: jog/stick is in control (priority 20 ≥ 10)"]
    safety.jog(jog(t + 50_000_000, 2, deadman=False), t + 50_000_000, t + 50_000_000)  # let go
    refused = safety.desired(twist(t + 60_000_000), t + 60_000_000)
    assert refusals(refused) == ["claim: controller was displaced by jog/stick and takes control again only from "
                                 "rest (its task pauses)"]
    assert [c.mode for c in sends(refused)] == [m.CommandMode.STOP]
    safety.desired(twist(t + 70_000_000, linear=(0.0, 0.0, 0.0)), t + 70_000_000)
    assert safety.in_control == "controller/servo"


def test_a_stale_or_frozen_jog_stops_and_one_from_another_source_name_or_in_lockstep_moves_nothing():
    safety = jogging()
    t = 10 * S
    safety.jog(jog(t, 1, linear=(0.03, 0.0, 0.0)), t, t)
    stale = safety.cycle(t + 110_000_000)
    assert refusals(stale) == ["freshness: command is 110 ms old (budget 100 ms)"] and safety.held is None
    safety.state(hand_state(t + 200_000_000), t + 200_000_000)
    frozen = safety.jog(jog(t + 300_000_000, 2, linear=(0.03, 0.0, 0.0), device_ns=t), t + 300_000_000,
                        t + 300_000_000)
    assert [c.mode for c in sends(frozen)] == [m.CommandMode.STOP] and refusals(frozen)[0].startswith(
        "freshness: its device was last heard 300 ms ago")
    forged = m.Jog(header=m.Header(seq=3, stamp_ns=t + 300_000_000, source_stamp_ns=t + 300_000_000),
                   mode=m.JogMode.TRANSLATION, deadman=True, linear=(0.03, 0.0, 0.0), source="controller/servo")
    assert refusals(safety.jog(forged, t + 300_000_000, t + 300_000_000)) == [
        "source: controller may not command on desired_jog"]
    lockstep = jogging(lockstep=True)
    assert refusals(lockstep.jog(jog(t, 1, linear=(0.03, 0.0, 0.0)), t, t))[0].startswith(
        "freshness: jog/stick is a device's source, and this is a lockstep run")


def test_a_jog_message_moves_only_its_own_modes_part():
    with pytest.raises(ValueError, match="a translation jog moves only its own mode's part"):
        jog(1, 1, linear=(0.1, 0.0, 0.0), angular=(0.0, 0.1, 0.0))
    assert jog(1, 1, deadman=False, linear=(0.1, 0.0, 0.0)).at_rest
    with pytest.raises(m.ProtocolError, match="linear"):  # beyond the wire's bound
        m.decode(m.encode(jog(1, 1, linear=(3.0, 0.0, 0.0))), m.Jog)
