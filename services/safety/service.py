"""The safety service: the only publisher of robot commands.

It takes desired twists and joint velocities from the controller, checks each one (services.safety.checks),
holds the latest approved command and resends it every control cycle while it is fresh, and otherwise commands
a stop, saying why. It watches a latched emergency stop (``…/safety/estop``: any operator tool engages it, only
an explicit reset releases it) and the liveliness of the upstream services and of the robot.

Clock modes: in realtime the 100 Hz resend runs on wall time. In lockstep safety answers every robot state (the
robot's DSP tick) with the held command checked against that very state and stamped with its tick, and every new
approved command is forwarded at once, checked against the state of the tick its frame was captured at, which is
the pipeline's answer to that frame.

It also watches what the arm does (:class:`~services.safety.checks.MotionMonitor`): a measured end-effector or
joint speed over its limit by more than the margin, for longer than a state period, latches a protective stop,
released like the e-stop.
"""
from __future__ import annotations

import threading
import time
from typing import Optional

import msgspec
import numpy as np
import zenoh

from protocol.conventions import ClockMode, Frame
from protocol.messages import (
    CommandMode,
    EStop,
    Header,
    JointVelocity,
    RobotCommand,
    RobotState,
    SafetyState,
    SafetyStatus,
    Twist,
)
from services.runtime.service import Service, ServiceConfig
from services.runtime.state_history import StateHistory
from services.robot.pacing import request_realtime
from services.safety.checks import CommandChecker, Decision, MotionMonitor, SafetyLimits


class SafetyConfig(ServiceConfig):
    limits: SafetyLimits = msgspec.field(default_factory=SafetyLimits)
    #: realtime resend rate of the held command (the robot's DSP needs one every 10 ms)
    rate_hz: float = 100.0
    status_rate_hz: float = 10.0
    #: liveliness names whose loss stops the arm at once (the command path)
    upstream: list[str] = msgspec.field(default_factory=lambda: ["vision", "controller"])
    #: liveliness names of which one must be alive (the robot)
    robots: list[str] = msgspec.field(default_factory=lambda: ["robot_sim", "robot_gateway"])
    #: the emergency deceleration the robot applies to an e-stop (documents the robot's setting; m/s²)
    estop_decel_mps2: float = 1.5
    #: SCHED_FIFO priority of the safety process where the OS grants it (0: normal scheduling): its resends feed the
    #: robot's 20 ms watchdog, which must not trip because safety waited behind the rest of the host
    realtime_priority: int = 30


class _Held:
    """The latest approved desired command (as the controller sent it) and where it came from. It is checked
    again at every resend, so clamps ramp and zones and joint limits follow the arm."""

    def __init__(self, twist: Optional[Twist], joint: Optional[JointVelocity], recv_ns: int) -> None:
        self.twist = twist
        self.joint = joint
        self.recv_ns = recv_ns

    @property
    def source(self) -> Header:
        return self.twist.header if self.twist is not None else self.joint.header

    def check(self, checker: CommandChecker, q, dt: float) -> Decision:
        """Check the command against the joint angles ``q``."""
        if self.twist is not None:
            t = self.twist
            return checker.check_twist(t.frame, t.angular, (*t.linear, *t.rotational), q, dt)
        return checker.check_joint_velocity(self.joint.velocities, q, dt)


class SafetyService(Service):
    name = "safety"
    follows_sim_clock = False  # it answers the robot's ticks itself and sets its clock from them

    def __init__(self, config: SafetyConfig | None = None, **kw) -> None:
        config = config or SafetyConfig()
        super().__init__(config, **kw)
        self.config: SafetyConfig = config
        self.lockstep = ClockMode(config.clock) is ClockMode.LOCKSTEP
        self.checker = CommandChecker(config.limits)
        self.monitor = MotionMonitor(config.limits, self.checker.kin)
        self.lock = threading.RLock()
        self.held: Optional[_Held] = None
        self.robot_state: Optional[tuple[RobotState, int]] = None
        self.states: StateHistory[RobotState] = StateHistory()
        #: lockstep: desired commands whose frame's robot state has not arrived yet
        self._waiting: list[_Held] = []
        self.estop_latched = False
        self.estop_reason = ""
        self.alive: set[str] = set()
        self.last_refusal = ""
        self.active_limits: list[str] = []
        self.safety_state = SafetyState.REFUSING
        self._thread: Optional[threading.Thread] = None

    # ------------------------------------------------------------------ lifecycle
    def on_start(self) -> None:
        keys = self.keys
        self.command_pub = self.publisher(keys.robot_command, "command")
        self.status_pub = self.publisher(keys.safety_status, "status")
        self.subscribe(keys.robot_state, RobotState, self._on_state, "robot_state", sim_stamped=True)
        self.subscribe(keys.desired_twist, Twist, self._on_twist, "twist")
        self.subscribe(keys.desired_joint_velocity, JointVelocity, self._on_joint_velocity, "joint_velocity")
        self.subscribe(keys.estop, EStop, self._on_estop, "estop")
        self._declared.append(self.session.liveliness().declare_subscriber(
            keys.liveliness_all, self._on_liveliness, history=True))
        self._thread = threading.Thread(target=self._loop, name="safety-loop", daemon=True)
        self._thread.start()

    def on_stop(self) -> None:
        # leave the arm stopping rather than holding a last command for the watchdog's grace
        try:
            self._send(Decision(refusal="safety service stopping"), None)
        except Exception:
            pass
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def check_health(self) -> tuple[bool, str]:
        alive = self._thread is not None and self._thread.is_alive()
        peaks = " ".join(f"peak_{name}={ratio:.2f}" for name, ratio in self.monitor.peak_ratio.items())
        return alive, (f"state={self.safety_state.value} estop={self.estop_latched} alive={sorted(self.alive)} "
                       f"measured speeds/limits: {peaks}")

    # ------------------------------------------------------------------ inputs
    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(name)
            else:
                self.alive.discard(name)
                if name in self.config.upstream and self.held is not None:
                    self.held = None
                    self._refuse(f"liveliness: {name} is gone")
                    self._send_stop_now()

    def _on_state(self, state: RobotState, recv_ns: int) -> None:
        stamp = state.header.stamp_ns
        with self.lock:
            self.robot_state = (state, recv_ns)
            self.states.add(stamp, state)
            overspeed = self.monitor.observe(state.q, state.dq, stamp)
            if overspeed is not None:
                self._protective_stop(overspeed)
            if not self.lockstep:
                return
            if stamp > self.clock.now_ns():
                self.clock.set_ns(stamp)
            waiting, self._waiting = self._waiting, []
            for candidate in waiting:
                self._on_desired(candidate)
            self._cycle(stamp_ns=stamp, state=state)  # the answer to this tick

    def _protective_stop(self, reason: str) -> None:
        """Latched like the e-stop (and released the same way): the arm does something it was not told to."""
        self.counters.inc("overspeed.trips")
        if not self.estop_latched:
            self._refuse(f"protective_stop: {reason}")
            self.estop_latched = True
            self.estop_reason = f"protective stop: {reason}"
            self.held = None
            self.log.error("PROTECTIVE STOP: %s", reason)
            self._send_stop_now()

    def _on_estop(self, message: EStop, _recv_ns: int) -> None:
        with self.lock:
            if message.reset:
                if self.estop_latched:
                    self.log.warning("e-stop reset by %s", message.operator or "an operator")
                self.estop_latched = False
                self.estop_reason = ""
                self.counters.inc("estop.resets")
            else:
                self.estop_latched = True
                self.estop_reason = f"{message.operator or 'operator'}: {message.reason or 'e-stop'}"
                self.held = None
                self.counters.inc("estop.triggers")
                self.log.warning("E-STOP engaged (%s)", self.estop_reason)
                self._send_stop_now()

    def _on_twist(self, twist: Twist, recv_ns: int) -> None:
        self._on_desired(_Held(twist, None, recv_ns))

    def _on_joint_velocity(self, command: JointVelocity, recv_ns: int) -> None:
        self._on_desired(_Held(None, command, recv_ns))

    def _on_desired(self, candidate: _Held) -> None:
        with self.lock:
            state = None
            if self.lockstep:  # checked against the state of the tick its frame was captured at
                state, ready = self.states.for_input(candidate.source.source_stamp_ns)
                if not ready:
                    self._waiting.append(candidate)
                    return
            if self.estop_latched:
                self._refuse(f"estop: latched ({self.estop_reason})")
                self._send(Decision(refusal=self.last_refusal), candidate)  # answers the frame with the e-stop
                return
            decision, reason = self._evaluate(candidate, state)
            if reason is None:
                self.held = candidate
                self._send(decision, candidate)
                return
            self.held = None
            self._refuse(reason)
            # the stop carries the refused command's source: it is the pipeline's answer to that frame
            self._send(Decision(refusal=reason), candidate)

    def _evaluate(self, held: _Held, state: Optional[RobotState] = None) -> tuple[Optional[Decision], Optional[str]]:
        """(decision, None) when the command may go to the robot now, else (None, reason). ``state``: the robot
        state to check against (default: the latest)."""
        reason = self._input_problem(held.source)
        if reason is not None:
            return None, reason
        q = self._fresh_q(state)
        if q is None:
            return None, "robot_state: no fresh robot state to check the command against"
        decision = held.check(self.checker, q, self._dt())
        if decision.refused:
            self.active_limits = list(decision.limits)
            return None, decision.refusal
        return decision, None

    # ------------------------------------------------------------------ checks of the moment
    def _input_problem(self, header: Header) -> Optional[str]:
        lim = self.config.limits
        now = self.clock.now_ns()
        missing = [name for name in self.config.upstream if name not in self.alive]
        if missing:
            return f"liveliness: {', '.join(missing)} not alive"
        if not any(name in self.alive for name in self.config.robots):
            return "liveliness: no robot alive"
        age = (now - header.stamp_ns) * 1e-9
        if -age > lim.future_skew_s or -(now - header.source_stamp_ns) * 1e-9 > lim.future_skew_s:
            return (f"freshness: stamped {max(-age, (header.source_stamp_ns - now) * 1e-9) * 1e3:.0f} ms in the "
                    f"future (skew at most {lim.future_skew_s * 1e3:.0f} ms)")
        if age > lim.command_budget_s:
            return f"freshness: command is {age * 1e3:.0f} ms old (budget {lim.command_budget_s * 1e3:.0f} ms)"
        if header.source_stamp_ns == 0:
            return "freshness: command does not say which image it derives from"
        image_age = (now - header.source_stamp_ns) * 1e-9
        if image_age > lim.image_budget_s:
            return (f"freshness: image is {image_age * 1e3:.0f} ms old "
                    f"(budget {lim.image_budget_s * 1e3:.0f} ms)")
        state = self.robot_state[0] if self.robot_state is not None else None
        if state is not None and state.angular_convention is not lim.robot_convention:
            return (f"convention: the robot reads '{state.angular_convention.value}', safety is configured for "
                    f"'{lim.robot_convention.value}'")
        return None

    def _fresh_q(self, state: Optional[RobotState] = None) -> Optional[np.ndarray]:
        if state is None:
            if self.robot_state is None:
                return None
            state, _ = self.robot_state
        if (self.clock.now_ns() - state.header.stamp_ns) * 1e-9 > self.config.limits.state_budget_s:
            return None
        return np.asarray(state.q, dtype=float)

    def _dt(self) -> float:
        return 1.0 / self.config.rate_hz

    # ------------------------------------------------------------------ output
    def _refuse(self, reason: str) -> None:
        self.last_refusal = reason
        self.counters.inc(f"refused.{reason.split(':', 1)[0]}")
        self.limited_log.warning(f"refuse:{reason.split(':', 1)[0]}", "safety: stop: %s", reason)

    def _send_stop_now(self) -> None:
        self._send(Decision(refusal=self.last_refusal or "stop"), None)

    def _send(self, decision: Decision, held: Optional[_Held], stamp_ns: Optional[int] = None) -> None:
        """Publish one robot command: the decision's motion, or a stop (an emergency stop when latched). With
        ``held``, the command carries that input's source stamp and trace."""
        now = self.clock.now_ns() if stamp_ns is None else stamp_ns
        if held is not None:
            header = self.header("command", stamp_ns=now, source=held.source, recv_ns=held.recv_ns)
        else:
            header = self.header("command", stamp_ns=now)
        if self.estop_latched:
            command = RobotCommand(header=header, mode=CommandMode.EMERGENCY_STOP, reason=self.estop_reason[:256])
            state = SafetyState.ESTOP
        elif decision.refused or held is None:
            command = RobotCommand(header=header, mode=CommandMode.STOP, reason=(decision.refusal or "")[:256])
            state = SafetyState.REFUSING if self.last_refusal else SafetyState.OK
            self.checker.reset_motion()
        elif decision.twist is not None:
            twist = Twist(header=header, frame=Frame.MIXED, angular=self.config.limits.robot_convention,
                          linear=tuple(decision.twist[:3]), rotational=tuple(decision.twist[3:]))
            command = RobotCommand(header=header, mode=CommandMode.CARTESIAN_VELOCITY, twist=twist)
            state = SafetyState.LIMITING if decision.limits else SafetyState.OK
        else:
            command = RobotCommand(header=header, mode=CommandMode.JOINT_VELOCITY,
                                   joint_velocities=decision.joint_velocities.tolist())
            state = SafetyState.LIMITING if decision.limits else SafetyState.OK
        self.safety_state = state
        self.active_limits = list(decision.limits)
        self.command_pub.put(command)

    def _cycle(self, stamp_ns: Optional[int] = None, state: Optional[RobotState] = None) -> None:
        """One control cycle: resend the held command if it is still fresh and allowed, else stop."""
        with self.lock:
            held = self.held
            if held is not None and not self.estop_latched:
                decision, reason = self._evaluate(held, state)
                if reason is None:
                    self._send(decision, held, stamp_ns)
                    return
                self.held = None
                self._refuse(reason)
            self._send(Decision(refusal=self.last_refusal or "idle: no command"), None, stamp_ns)

    def _loop(self) -> None:
        if not self.lockstep:
            request_realtime(self.config.realtime_priority, "safety resend loop")
            self.declare_loop("pub.command", self.config.rate_hz, ("cycles.late",))
        status_period = 1.0 / self.config.status_rate_hz
        next_status = time.monotonic()
        period = 1.0 / self.config.rate_hz
        next_cycle = time.monotonic()
        while not self.stop_requested:
            now = time.monotonic()
            if not self.lockstep and now >= next_cycle:
                try:
                    self._cycle()
                except Exception:
                    self.counters.inc("errors.cycle")
                    self.limited_log.error("cycle", "safety cycle failed")
                    self.log.debug("cycle failure", exc_info=True)
                next_cycle += period
                if next_cycle < now - period:  # a resend missed its deadline (the robot's watchdog is two)
                    self.counters.inc("cycles.late")
                if next_cycle < now - 5 * period:
                    next_cycle = now + period
            if now >= next_status:
                self.status_pub.put(self.status_message())
                next_status = now + status_period
            wake = next_status if self.lockstep else min(next_cycle, next_status)
            time.sleep(max(0.0, min(wake - time.monotonic(), 0.05)))

    def status_message(self) -> SafetyStatus:
        with self.lock:
            return SafetyStatus(header=self.header("status"), state=self.safety_state,
                                active_limits=list(self.active_limits)[:32], last_refusal=self.last_refusal[:256],
                                counters=self.counters.snapshot())
