"""Safety's rules, with no zenoh, no locks and no clock: what to send to the robot for each input.

:class:`SafetyCore` holds the latest approved desired command and checks it again at every resend (so clamps ramp
and zones and joint limits follow the arm), the latched e-stop and protective stop, the liveliness of the command
path and the robot, and the freshness of every input, two-sided (stale, or stamped in the future beyond a small
skew). Each input (a desired command, a robot state, an e-stop, a liveliness change, a resend cycle) is a method
that takes the time and returns what to do, in order: :class:`Send` a robot command, :class:`Refused` an input
(counted ``refused.<kind>``), :class:`Count` an event, :class:`Note` a log line. The service
(:mod:`services.safety.service`) decodes, calls, and carries those out.

Lockstep: a desired command is checked against the state of the tick its frame was captured at, and waits for
that state if it has not arrived; every robot state is answered with the held command checked against it, before
any command that waited for it (the order a state and a command arrive in is the host's, not the run's).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Optional, Union

import numpy as np

from protocol.conventions import AngularConvention, Frame
from protocol.messages import (
    CommandMode,
    EStop,
    FingerCommand,
    FingerMode,
    Header,
    Jog,
    JointVelocity,
    MOTION_MODES,
    RobotCommand,
    RobotState,
    SafetyState,
    Twist,
)
from services.model.arm import ArmDescription, declared_arm
from services.model.kinematics import ArmKinematics
from services.model.limits import declared as declared_limits
from services.runtime.state_history import StateHistory
from services.safety.checks import CommandChecker, Decision, MotionMonitor, SafetyLimits
from services.safety.sources import Claim, CommandSource, Freshness, SourceRegistry, declared_name, default_sources


class HeldCommand:
    """A desired command as its source sent it, the key it came on, and when it arrived.

    ``engaged``: whether its source asks to move at all (a jog's dead-man held; always for the controller's).
    ``conventions``: angular conventions its command type defines beside the robot's (a jog's ω)."""

    def __init__(self, twist: Optional[Twist], joint: Optional[JointVelocity], recv_ns: int, key: str = "",
                 engaged: bool = True, conventions: tuple[AngularConvention, ...] = ()) -> None:
        self.twist = twist
        self.joint = joint
        self.recv_ns = recv_ns
        #: the key it came on (a Keys attribute), and the source it names
        self.key = key or ("desired_twist" if twist is not None else "desired_joint_velocity")
        self.source_name = twist.source if twist is not None else joint.source
        #: the hand's part that goes with it (None: the fingers keep their targets)
        self.fingers = twist.fingers if twist is not None else joint.fingers
        self.engaged = engaged
        self.conventions = conventions

    @classmethod
    def from_jog(cls, jog: Jog, recv_ns: int, n_fingers: Optional[int]) -> "HeldCommand":
        """A person's jog as the mixed twist it asks for (ω about the hand's own axes), with every finger at its
        finger rate (``n_fingers``: the robot's hand's, None before a state declared it: a finger rate is then
        refused by the finger check, not guessed)."""
        fingers = None
        if jog.finger_rate != 0.0 and jog.deadman:
            fingers = FingerCommand(mode=FingerMode.VELOCITY, values=[jog.finger_rate] * (n_fingers or 1))
        twist = Twist(header=jog.header, frame=Frame.MIXED, angular=AngularConvention.OMEGA, linear=jog.linear,
                      rotational=jog.angular, source=jog.source, fingers=fingers)
        return cls(twist, None, recv_ns, key="desired_jog", engaged=jog.deadman,
                   conventions=(AngularConvention.OMEGA,))

    @property
    def at_rest(self) -> bool:
        """It asks for no motion: its source not engaged, or every velocity zero and no finger part."""
        if not self.engaged:
            return True
        if self.fingers is not None:
            return False
        if self.twist is not None:
            return not (any(self.twist.linear) or any(self.twist.rotational))
        return not any(self.joint.velocities)

    @property
    def source(self) -> Header:
        return self.twist.header if self.twist is not None else self.joint.header

    def check(self, checker: CommandChecker, state: RobotState, dt: float, near_singularity: bool = True) -> Decision:
        """Check the command against the robot's ``state``: its joint angles and the limits it declares
        (``near_singularity``: its source's twists slowed and stopped before a singularity)."""
        q, robot = np.asarray(state.q, dtype=float), declared_limits(state, checker.kin.arm)
        if self.twist is not None:
            t = self.twist
            return checker.check_twist(t.frame, t.angular, (*t.linear, *t.rotational), q, dt, robot,
                                       also_accepted=self.conventions, near_singularity=near_singularity)
        return checker.check_joint_velocity(self.joint.velocities, q, dt, robot)


@dataclass
class Send:
    """A robot command to publish: ``command`` (its header is the service's to fill) answering ``held`` (whose
    source and trace the header carries), stamped ``stamp_ns`` (None: now)."""

    command: RobotCommand
    held: Optional[HeldCommand] = None
    stamp_ns: Optional[int] = None


@dataclass
class Refused:
    reason: str

    @property
    def kind(self) -> str:
        return self.reason.split(":", 1)[0]


@dataclass
class Count:
    name: str


@dataclass
class Note:
    level: int
    text: str


Action = Union[Send, Refused, Count, Note]


class SafetyCore:
    def __init__(self, limits: SafetyLimits, upstream: list[str], robots: list[str], rate_hz: float,
                 lockstep: bool, arm: Optional[str] = None, sources: Optional[list[CommandSource]] = None) -> None:
        """``arm``: the arm safety was started for (None: the robot's, as its states declare it); the checks are
        made for the robot's arm once a state declares it, and nothing moves an arm they were not made for.
        ``sources``: the command sources it takes commands from (default: the controller's)."""
        self.registry = SourceRegistry(default_sources() if sources is None else sources)
        self.claim = Claim()
        self.limits = limits
        self.upstream, self.robots = list(upstream), list(robots)
        self.dt = 1.0 / rate_hz
        self.lockstep = lockstep
        self.expected_arm = arm
        self.arm: Optional[ArmDescription] = None
        self.checker: Optional[CommandChecker] = None
        self.monitor: Optional[MotionMonitor] = None
        #: why the robot's arm is not one safety runs for ("" when it is, or none was heard)
        self.wrong_arm = ""
        self._held: Optional[HeldCommand] = None
        self.robot_state: Optional[RobotState] = None
        self.states: StateHistory[RobotState] = StateHistory()
        #: lockstep: desired commands whose frame's robot state has not arrived yet
        self.waiting: list[HeldCommand] = []
        #: lockstep: the last command sent at each tick answered, and the answer to each frame; a repeat of either
        #: (the robot's lockstep retry publishes its state and frame again) is answered the same, not checked again,
        #: since each check moves the ramp on and a run would then depend on when the host made it retry
        self._tick_answers: dict[int, Send] = {}
        self._frame_answers: dict[int, Send] = {}
        self.estop_latched = False
        self.estop_reason = ""
        #: the robot's count of contacts in the last state seen (None: no state with a contact monitor yet)
        self.contacts_seen: Optional[int] = None
        #: device-derived sources: the last sequence number taken from each (by its full name, e.g. jog/pad)
        self.device_seq: dict[str, int] = {}
        self.alive: set[str] = set()
        self.last_refusal = ""
        self.active_limits: list[str] = []
        self.safety_state = SafetyState.REFUSING

    @property
    def held(self) -> Optional[HeldCommand]:
        """The approved command safety resends while it is fresh (None: it stops the arm)."""
        return self._held

    @held.setter
    def held(self, command: Optional[HeldCommand]) -> None:
        self._held = command
        if command is None:  # whoever was in control let go: the next approved command's source takes it
            self.claim.let_go()

    @property
    def in_control(self) -> str:
        """The source whose command safety holds ("" when none)."""
        return self.claim.holder if self._held is not None else ""

    # ------------------------------------------------------------------ inputs
    def liveliness(self, name: str, present: bool) -> list[Action]:
        if present:
            self.alive.add(name)
            return []
        self.alive.discard(name)
        self._forget_answers()
        held = self.held
        if name in self.upstream and held is not None and self.registry.freshness(held.source_name) is Freshness.IMAGE:
            self.held = None
            return [self._refuse(f"liveliness: {name} is gone"), self._stop_now()]
        return []

    def jog(self, jog: Jog, recv_ns: int, now_ns: int) -> list[Action]:
        """A person's jog request: a desired command of its source like any other, taken while its dead-man is
        held (:meth:`desired`)."""
        hand = self.arm.hand if self.arm is not None else None
        return self.desired(HeldCommand.from_jog(jog, recv_ns, hand.n_fingers if hand is not None else None), now_ns)

    def state(self, state: RobotState, now_ns: int) -> list[Action]:
        """A robot state; in lockstep ``now_ns`` is its stamp, and it is answered (then the commands that waited for
        it); a state answered before, with what was last sent at its tick."""
        stamp = state.header.stamp_ns
        if self.lockstep and stamp in self._tick_answers:
            return [Count("repeated.state"), self._tick_answers[stamp]]
        out = self._state(state, stamp, now_ns)
        if self.lockstep:
            self._remember(out, tick_ns=stamp)
        return out

    def _remember(self, actions: list[Action], tick_ns: int, frame_ns: Optional[int] = None) -> None:
        """Lockstep: the last command of ``actions`` as what was sent at ``tick_ns`` (and, with ``frame_ns``, as
        the answer to that frame)."""
        sent = [action for action in actions if isinstance(action, Send)]
        if not sent:
            return
        self._tick_answers[tick_ns] = sent[-1]
        if frame_ns is not None:
            self._frame_answers[frame_ns] = sent[-1]
        for answers in (self._tick_answers, self._frame_answers):
            while len(answers) > 16:
                del answers[next(iter(answers))]

    def _forget_answers(self) -> None:
        """After a stop of safety's own (e-stop, protective stop, liveliness lost): a repeat is answered anew."""
        self._tick_answers.clear()
        self._frame_answers.clear()

    def _state(self, state: RobotState, stamp: int, now_ns: int) -> list[Action]:
        out: list[Action] = []
        arm, self.wrong_arm = declared_arm(state.arm, state.arm_digest, len(state.q), self.expected_arm, self.arm)
        if arm is None:  # not an arm these checks are for: a stop answers, nothing else is done with it
            out.append(self._refuse(f"arm: {self.wrong_arm}"))
            self.held = None
            if self.lockstep:
                out.append(self._send(Decision(refusal=self.last_refusal), None, stamp))
            return out
        if self.checker is None:
            self.arm = arm
            self.checker = CommandChecker(self.limits, ArmKinematics(arm))
            self.monitor = MotionMonitor(self.limits, self.checker.kin)
        self.robot_state = state
        self.states.add(stamp, state)
        overspeed = self.monitor.observe(state.q, state.dq, stamp, declared_limits(state, arm))
        if overspeed is not None:
            out += self._protective_stop(overspeed)
        out += self._contact(state)
        if self.lockstep:
            # the tick's answer first, then the commands derived from its frame, whichever reached safety first:
            # the order in which they arrive depends on the host (each subscriber has its own thread), and each
            # check moves the checker's ramp on, so the other order would answer the same frame differently
            out += self.cycle(now_ns, stamp_ns=stamp, state=state)
            waiting, self.waiting = self.waiting, []
            for candidate in waiting:
                out += self.desired(candidate, now_ns)
        return out

    def estop(self, message: EStop) -> list[Action]:
        if message.reset:
            out: list[Action] = [Count("estop.resets")]
            if self.estop_latched:
                out.append(Note(logging.WARNING, f"e-stop reset by {message.operator or 'an operator'}"))
                # what the next cycle's stop (nothing is held after an e-stop) will say, said now: the release is
                # confirmed by this state
                self.safety_state = SafetyState.REFUSING if self.last_refusal else SafetyState.OK
            self.estop_latched, self.estop_reason = False, ""
            return out
        self.estop_latched = True
        self.estop_reason = f"{message.operator or 'operator'}: {message.reason or 'e-stop'}"
        self.held = None
        self._forget_answers()
        return [Count("estop.triggers"), Note(logging.WARNING, f"E-STOP engaged ({self.estop_reason})"),
                self._stop_now()]

    def desired(self, candidate: HeldCommand, now_ns: int) -> list[Action]:
        """A desired twist or joint velocity from the controller: approved and held, or refused with a stop that
        answers its frame."""
        state = None
        if self.lockstep and self.registry.freshness(candidate.source_name) is Freshness.DEVICE:
            # a person's device runs on wall time, which a lockstep run does not follow: it cannot wait for a tick
            return [self._refuse(f"freshness: {candidate.source_name} is a device's source, and this is a lockstep "
                                 "run (a person's device runs on wall time)")]
        if self.lockstep:  # checked against the state of the tick its frame was captured at
            frame = candidate.source.source_stamp_ns
            if frame in self._frame_answers:
                return [Count("repeated.command"), self._frame_answers[frame]]
            state, ready = self.states.for_input(frame)
            if not ready:
                self.waiting.append(candidate)
                return []
            out = self._desired(candidate, now_ns, state)
            self._remember(out, tick_ns=now_ns, frame_ns=frame)
            return out
        return self._desired(candidate, now_ns, state)

    def _desired(self, candidate: HeldCommand, now_ns: int, state: Optional[RobotState]) -> list[Action]:
        if self.estop_latched:
            refused = self._refuse(f"estop: latched ({self.estop_reason})")
            return [refused, self._send(Decision(refusal=self.last_refusal), candidate)]  # the frame's answer
        declared, why = self.registry.admit(candidate.source_name, candidate.key, candidate.fingers is not None)
        if declared is not None:
            why = self._sequence_problem(declared, candidate) or ""
        if declared is not None and not why and not candidate.engaged:
            return self._disengaged(declared, candidate)
        if declared is not None and not why:
            why = self.claim.refusal(declared, candidate.source_name, holding=self.held is not None,
                                     at_rest=candidate.at_rest) or ""
            if why and candidate.at_rest:  # a source waiting at rest while another is in control: no refusal
                return [Count("claims.waiting")]
        if why:  # not a command for the arm now: refused, and the source in control (if any) keeps it
            refused = self._refuse(why)
            return [refused] if self.held is not None else [refused, self._send(Decision(refusal=why), candidate)]
        decision, reason = self._evaluate(candidate, now_ns, state)
        if reason is None:
            before = self.in_control
            self.held = candidate
            out: list[Action] = []
            if self.claim.take(declared, candidate.source_name):
                out += [Count("claims.switched"),
                        Note(logging.INFO, f"{candidate.source_name} takes control from {before}")]
            return out + [self._send(decision, candidate)]
        self.held = None
        # the stop carries the refused command's source: it is the pipeline's answer to that frame
        return [self._refuse(reason), self._send(Decision(refusal=reason), candidate)]

    def _disengaged(self, declared: CommandSource, candidate: HeldCommand) -> list[Action]:
        """A source that does not ask to move (a jog whose dead-man is released): if it is in control, the arm
        stops now and it lets go; otherwise it changes nothing (a person's stick at rest while the servo runs)."""
        held = self.held
        if held is None or declared_name(held.source_name) != declared.name:
            return [Count("released.idle")]
        self.held = None
        why = f"deadman: {candidate.source_name} released"
        return [Count("released.stops"), self._refuse(why), self._send(Decision(refusal=why), candidate)]

    def cycle(self, now_ns: int, stamp_ns: Optional[int] = None, state: Optional[RobotState] = None) -> list[Action]:
        """One control cycle: resend the held command if it is still fresh and allowed, else stop."""
        out: list[Action] = []
        held = self.held
        if held is not None and not self.estop_latched:
            decision, reason = self._evaluate(held, now_ns, state)
            if reason is None:
                return [self._send(decision, held, stamp_ns)]
            self.held = None
            out.append(self._refuse(reason))
        out.append(self._send(Decision(refusal=self.last_refusal or "idle: no command"), None, stamp_ns))
        return out

    def leaving(self, send: Send, now_ns: int) -> list[Action]:
        """``send`` checked again at ``now_ns``, the moment it leaves: a command that moves the arm goes out only if
        its input is still fresh then. Between the check and the publication the service can be held back (a host
        that cannot keep up: measured 130 ms at half a core), and a motion command stamped when it leaves would
        reach the robot fresh on an image older than the budget; it becomes the stop that refuses it instead."""
        if send.held is None or send.command.mode not in MOTION_MODES:
            return [send]
        problem = self.input_problem(send.held, now_ns)
        if problem is None:
            return [send]
        if self.held is send.held:
            self.held = None
        return [self._refuse(problem), self._send(Decision(refusal=problem), send.held, send.stamp_ns)]

    def stop(self, reason: str) -> list[Action]:
        """A stop now (the service stopping: leave the arm stopping rather than holding a last command)."""
        self._forget_answers()
        return [self._send(Decision(refusal=reason), None)]

    # ------------------------------------------------------------------ checks of the moment
    def _contact(self, state: RobotState) -> list[Action]:
        """A contact the robot's monitor detected since the last state safety saw (its count rose): a protective
        stop that names it. The first state sets where the count starts (a contact before safety ran was not in
        its charge); a count lower than the last seen is a robot that started again, counting from 0 while safety
        ran: each of its contacts is."""
        contact = state.contact
        if contact is None:
            return []
        seen, self.contacts_seen = self.contacts_seen, contact.contacts
        if seen is not None and contact.contacts < seen:
            seen = 0
        if seen is None or contact.contacts <= seen:
            return []
        return self._protective_stop(contact.last_contact(), counter="contact.stops")

    def _protective_stop(self, reason: str, counter: str = "overspeed.trips") -> list[Action]:
        """Latched like the e-stop (and released the same way): the arm does something it was not told to, or
        touched something."""
        out: list[Action] = [Count(counter)]
        self._forget_answers()
        if not self.estop_latched:
            out.append(self._refuse(f"protective_stop: {reason}"))
            self.estop_latched = True
            self.estop_reason = f"protective stop: {reason}"
            self.held = None
            out += [Note(logging.ERROR, f"PROTECTIVE STOP: {reason}"), self._stop_now()]
        return out

    def _evaluate(self, held: HeldCommand, now_ns: int,
                  state: Optional[RobotState] = None) -> tuple[Optional[Decision], Optional[str]]:
        """(decision, None) when the command may go to the robot now, else (None, reason). ``state``: the robot
        state to check against (default: the latest)."""
        reason = self.input_problem(held, now_ns)
        if reason is not None:
            return None, reason
        if self.checker is None:  # no state from an arm these checks are for
            return None, (f"arm: {self.wrong_arm}" if self.wrong_arm
                          else "robot_state: no robot state has declared its arm yet")
        state = self._fresh_state(now_ns, state)
        if state is None:
            return None, "robot_state: no fresh robot state to check the command against"
        problem = self._finger_problem(held, state)
        if problem is not None:
            return None, problem
        decision = held.check(self.checker, state, self.dt, self.registry.stops_near_singularity(held.source_name))
        if decision.refused:
            self.active_limits = list(decision.limits)
            return None, decision.refusal
        return decision, None

    def _finger_problem(self, held: HeldCommand, state: RobotState) -> Optional[str]:
        """Why a command's hand part cannot go to the robot (the command is then refused whole), or None."""
        fingers = held.fingers
        if fingers is None:
            return None
        hand = self.arm.hand
        if hand is None or state.fingers is None:
            return f"fingers: a finger command, and the {self.arm.name}'s robot reports no fingers"
        if len(fingers.values) != hand.n_fingers:
            return f"fingers: the {hand.name} has {hand.n_fingers} fingers, the command {len(fingers.values)} values"
        return None

    def _sequence_problem(self, declared: CommandSource, candidate: HeldCommand) -> Optional[str]:
        """A device-derived command's sequence number must rise from the last taken from its source (a repeated or
        reordered one is not the person's latest input); why not, or None. Taken: it is the last."""
        if declared.freshness is not Freshness.DEVICE:
            return None
        seq, last = candidate.source.seq, self.device_seq.get(candidate.source_name)
        if last is not None and seq <= last:
            return f"sequence: {candidate.source_name}'s command {seq} is not after its last, {last}"
        self.device_seq[candidate.source_name] = seq
        return None

    def input_problem(self, held: HeldCommand, now_ns: int) -> Optional[str]:
        """Why a desired command may not move the arm now (its source's freshness rule, both ways; the robot's
        liveliness and convention), or None."""
        header = held.source
        if self.registry.freshness(held.source_name) is Freshness.DEVICE:
            problem = self._device_problem(header, now_ns)
        else:
            problem = self._image_problem(header, now_ns)
        if problem is not None:
            return problem
        state = self.robot_state
        lim = self.limits
        if state is not None and state.angular_convention is not lim.robot_convention:
            return (f"convention: the robot reads '{state.angular_convention.value}', safety is configured for "
                    f"'{lim.robot_convention.value}'")
        return None

    def _future_problem(self, header: Header, now_ns: int) -> Optional[str]:
        """An input stamped (or its source stamped) further ahead of safety's clock than the skew allows."""
        lim = self.limits
        ahead = max(header.stamp_ns, header.source_stamp_ns) - now_ns
        if ahead * 1e-9 > lim.future_skew_s:
            return (f"freshness: stamped {ahead * 1e-6:.0f} ms in the future (skew at most "
                    f"{lim.future_skew_s * 1e3:.0f} ms)")
        return None

    def _command_problem(self, header: Header, now_ns: int, alive: set[str]) -> Optional[str]:
        """What every source's command needs, whatever its freshness rule: a robot among ``alive``, the command
        not stamped in the future and within its budget."""
        if not any(name in alive for name in self.robots):
            return "liveliness: no robot alive"
        problem = self._future_problem(header, now_ns)
        if problem is not None:
            return problem
        age = (now_ns - header.stamp_ns) * 1e-9
        if age > self.limits.command_budget_s:
            return (f"freshness: command is {age * 1e3:.0f} ms old (budget "
                    f"{self.limits.command_budget_s * 1e3:.0f} ms)")
        return None

    def _device_problem(self, header: Header, now_ns: int) -> Optional[str]:
        """Freshness of a device-derived command: the command within its budget, its device heard within its own
        (``source_stamp_ns``), a robot alive. No image, so no image path's service is needed."""
        lim = self.limits
        problem = self._command_problem(header, now_ns, self.alive)
        if problem is not None:
            return problem
        if header.source_stamp_ns == 0:
            return "freshness: command does not say when its device was last heard"
        device_age = (now_ns - header.source_stamp_ns) * 1e-9
        if device_age > lim.device_budget_s:
            return (f"freshness: its device was last heard {device_age * 1e3:.0f} ms ago (budget "
                    f"{lim.device_budget_s * 1e3:.0f} ms: frozen or gone)")
        return None

    def _image_problem(self, header: Header, now_ns: int) -> Optional[str]:
        """Freshness of an image-derived command: the services on the image's path and a robot alive, the command
        and its image within their budgets."""
        lim = self.limits
        alive = self.alive
        if self.lockstep:
            # a message is proof that what made it was alive when the arm was where it says: the services on its
            # trace, the robot whose state safety holds. Their liveliness tokens reach safety whenever the host
            # delivers them (a first frame could be answered before vision's token was seen, on a busy host); a
            # token withdrawn still stops the arm at once (:meth:`liveliness`)
            alive = alive | {hop.service for hop in header.trace}
            if self.robot_state is not None:
                alive = alive | set(self.robots)
        missing = [name for name in self.upstream if name not in alive]
        if missing:
            return f"liveliness: {', '.join(missing)} not alive"
        problem = self._command_problem(header, now_ns, alive)
        if problem is not None:
            return problem
        if header.source_stamp_ns == 0:
            return "freshness: command does not say which image it derives from"
        image_age = (now_ns - header.source_stamp_ns) * 1e-9
        if image_age > lim.image_budget_s:
            return (f"freshness: image is {image_age * 1e3:.0f} ms old "
                    f"(budget {lim.image_budget_s * 1e3:.0f} ms)")
        return None

    def _fresh_state(self, now_ns: int, state: Optional[RobotState] = None) -> Optional[RobotState]:
        """``state`` (default: the latest) when it is within the state budget, else None."""
        state = state if state is not None else self.robot_state
        if state is None or (now_ns - state.header.stamp_ns) * 1e-9 > self.limits.state_budget_s:
            return None
        return state

    # ------------------------------------------------------------------ output
    def _refuse(self, reason: str) -> Refused:
        self.last_refusal = reason
        return Refused(reason)

    def _stop_now(self) -> Send:
        return self._send(Decision(refusal=self.last_refusal or "stop"), None)

    def _send(self, decision: Decision, held: Optional[HeldCommand], stamp_ns: Optional[int] = None) -> Send:
        """The robot command for a decision: its motion with its hand part, or a stop (an emergency stop when
        latched), which never carries one: safety never moves a finger by itself, and so never opens the hand."""
        header = Header()  # the service fills it (sequence, stamp, source and trace)
        if self.estop_latched:
            command = RobotCommand(header=header, mode=CommandMode.EMERGENCY_STOP, reason=self.estop_reason[:256])
            state = SafetyState.ESTOP
        elif decision.refused or held is None:
            command = RobotCommand(header=header, mode=CommandMode.STOP, reason=(decision.refusal or "")[:256])
            state = SafetyState.REFUSING if self.last_refusal else SafetyState.OK
            if self.checker is not None:
                self.checker.reset_motion()
        elif decision.twist is not None:
            twist = Twist(header=header, frame=Frame.MIXED, angular=self.limits.robot_convention,
                          linear=tuple(decision.twist[:3]), rotational=tuple(decision.twist[3:]),
                          source=held.source_name)
            command = RobotCommand(header=header, mode=CommandMode.CARTESIAN_VELOCITY, twist=twist,
                                   fingers=held.fingers)
            state = SafetyState.LIMITING if decision.limits else SafetyState.OK
        else:
            command = RobotCommand(header=header, mode=CommandMode.JOINT_VELOCITY,
                                   joint_velocities=decision.joint_velocities.tolist(), fingers=held.fingers)
            state = SafetyState.LIMITING if decision.limits else SafetyState.OK
        self.safety_state = state
        self.active_limits = list(decision.limits)
        return Send(command, held, stamp_ns)
