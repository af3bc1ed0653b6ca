"""The safety service: the only publisher of robot commands. Its rules are :class:`~services.safety.core.SafetyCore`
(no zenoh, no locks, no clock); this service decodes, hands each input to the core with the time, and carries out
what the core returns (publish, count, log).

It takes desired twists and joint velocities from the controller, checks each one (services.safety.checks),
holds the latest approved command and resends it one control period after the last command went out while it is
fresh, and otherwise commands a stop, saying why. (A resend is due a period after any send, not on a free-running
grid: a resend between a new command and the robot's next tick would stand in for it there, its trace saying the
command waited in safety.) It watches a latched emergency stop (``…/safety/estop``: any operator tool engages it, only
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
import zenoh

from protocol.conventions import ClockMode
from protocol.messages import EStop, Jog, JointVelocity, RobotCommand, RobotState, SafetyStatus, Twist
from protocol.keys import PIPELINE_SERVICES, last_chunk
from services.runtime.pacing import request_realtime
from services.model.arm import check_arm_name
from services.runtime.service import Service, ServiceConfig
from services.runtime.threads import start_thread
from services.safety.checks import SafetyLimits
from services.safety.core import Action, Count, HeldCommand, Refused, SafetyCore, Send
from services.safety.sources import CommandSource, SourceRegistry, default_sources
from services.runtime.ports import Port, Ports


class SafetyConfig(ServiceConfig):
    #: the arm it guards (services/model/arms/<arm>.yaml); null: the robot's, as its states declare it. Named, a
    #: robot that declares another arm gets only stops from safety
    arm: Optional[str] = None
    limits: SafetyLimits = msgspec.field(default_factory=SafetyLimits)
    #: realtime resend rate of the held command (the robot's DSP needs one every 10 ms)
    rate_hz: float = 100.0
    status_rate_hz: float = 10.0
    #: liveliness names whose loss stops the arm at once (the command path)
    upstream: list[str] = msgspec.field(default_factory=lambda: [s for s in PIPELINE_SERVICES if s != "safety"])
    #: liveliness names of which one must be alive (the robot)
    robots: list[str] = msgspec.field(default_factory=lambda: ["robot_sim", "robot_gateway"])
    #: who may command the arm, on which keys, driving what, with which priority and freshness rule
    #: (services/safety/sources.py); one of them is in control at a time
    sources: list[CommandSource] = msgspec.field(default_factory=default_sources)
    #: SCHED_FIFO priority of the safety process where the OS grants it (0: normal scheduling): its resends feed the
    #: robot's 20 ms watchdog, which must not trip because safety waited behind the rest of the host
    realtime_priority: int = 30

    def __post_init__(self) -> None:
        if self.arm is not None:
            check_arm_name(self.arm)
        SourceRegistry(self.sources)  # two sources of one name, or an unknown key: refused here


class SafetyService(Service):
    name = "safety"
    PORTS = Ports(consumes=(Port("robot_state", RobotState), Port("desired_twist", Twist),
                            Port("desired_joint_velocity", JointVelocity), Port("desired_jog", Jog),
                            Port("estop", EStop)),
                  produces=(Port("robot_command", RobotCommand), Port("safety_status", SafetyStatus)))
    follows_sim_clock = False  # it answers the robot's ticks itself and sets its clock from them

    def __init__(self, config: SafetyConfig | None = None, **kw) -> None:
        config = config or SafetyConfig()
        super().__init__(config, **kw)
        self.config: SafetyConfig = config
        self.lockstep = ClockMode(config.clock) is ClockMode.LOCKSTEP
        self.core = SafetyCore(config.limits, config.upstream, config.robots, config.rate_hz, self.lockstep,
                               arm=config.arm, sources=config.sources)
        #: one input at a time through the core (zenoh's threads, and the resend loop)
        self.lock = threading.Lock()
        self._thread: Optional[threading.Thread] = None
        #: realtime: when the next resend is due (time.monotonic(); each command sent moves it a period on)
        self._resend_due = 0.0

    # ------------------------------------------------------------------ lifecycle
    def on_start(self) -> None:
        keys = self.keys
        self.command_pub = self.publisher(keys.robot_command, "command")
        self.status_pub = self.publisher(keys.safety_status, "status")
        self.subscribe(keys.robot_state, RobotState, self._on_state, "robot_state", sim_stamped=True)
        self.subscribe(keys.desired_twist, Twist, self._on_twist, "twist")
        self.subscribe(keys.desired_joint_velocity, JointVelocity, self._on_joint_velocity, "joint_velocity")
        self.subscribe(keys.desired_jog, Jog, self._on_jog, "jog")
        self.subscribe(keys.estop, EStop, self._on_estop, "estop")
        self._declared.append(self.session.liveliness().declare_subscriber(
            keys.liveliness_all, self._on_liveliness, history=True))
        self._thread = start_thread(self._loop, "safety-loop")

    def on_stop(self) -> None:
        # leave the arm stopping rather than holding a last command for the watchdog's grace
        try:
            with self.lock:
                self._carry_out(self.core.stop("safety service stopping"))
        except Exception:
            pass
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def check_health(self) -> tuple[bool, str]:
        alive = self._thread is not None and self._thread.is_alive()
        core = self.core
        with self.lock:
            control = f"in control: {core.in_control or 'nobody'}"
        if core.monitor is None:
            arm = core.wrong_arm or "no robot state has declared its arm yet"
            return alive, f"state={core.safety_state.value} estop={core.estop_latched} {control}; arm: {arm}"
        peaks = " ".join(f"peak_{name}={ratio:.2f}" for name, ratio in core.monitor.peak_ratio.items())
        return alive, (f"state={core.safety_state.value} estop={core.estop_latched} {control}; arm={core.arm.name} "
                       f"alive={sorted(core.alive)} measured speeds/limits: {peaks}")

    # ------------------------------------------------------------------ inputs: decoded, then the core decides
    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        name = last_chunk(sample.key_expr)
        with self.lock:
            self._carry_out(self.core.liveliness(name, sample.kind == zenoh.SampleKind.PUT))

    def _on_state(self, state: RobotState, _recv_ns: int) -> None:
        with self.lock:
            if self.lockstep and state.header.stamp_ns > self.clock.now_ns():
                self.clock.set_ns(state.header.stamp_ns)
            self._carry_out(self.core.state(state, self.clock.now_ns()))

    def _on_estop(self, message: EStop, _recv_ns: int) -> None:
        with self.lock:
            before = self.core.safety_state
            self._carry_out(self.core.estop(message))
            changed = self.core.safety_state is not before
        if changed:
            # said at once, not at the next status period: whoever pressed it (the console, `mfvs estop`) waits for
            # this confirmation, and repeats the request until it comes
            self.status_pub.put(self.status_message())

    def _on_twist(self, twist: Twist, recv_ns: int) -> None:
        with self.lock:
            self._carry_out(self.core.desired(HeldCommand(twist, None, recv_ns), self.clock.now_ns()))

    def _on_joint_velocity(self, command: JointVelocity, recv_ns: int) -> None:
        with self.lock:
            self._carry_out(self.core.desired(HeldCommand(None, command, recv_ns), self.clock.now_ns()))

    def _on_jog(self, jog: Jog, recv_ns: int) -> None:
        with self.lock:
            self._carry_out(self.core.jog(jog, recv_ns, self.clock.now_ns()))

    def _cycle(self) -> None:
        with self.lock:
            self._carry_out(self.core.cycle(self.clock.now_ns()))

    # ------------------------------------------------------------------ output
    def _carry_out(self, actions: list[Action]) -> None:
        """Carries out the core's actions; a change of who is in control is said at once (the controller pauses
        its task on it, and a touch of the stick may be shorter than a status period). Called under the lock."""
        before = self.core.in_control
        self._do(actions)
        if self.core.in_control != before and hasattr(self, "status_pub"):
            self.status_pub.put(self._status_locked())

    def _do(self, actions: list[Action]) -> None:
        for action in actions:
            if isinstance(action, Send):
                now = self.clock.now_ns() if action.stamp_ns is None else action.stamp_ns
                for leaving in self.core.leaving(action, now):
                    if isinstance(leaving, Send):
                        self._publish(leaving, now)
                    else:
                        self._do([leaving])
            elif isinstance(action, Refused):
                self.counters.inc(f"refused.{action.kind}")
                self.limited_log.warning(f"refuse:{action.kind}", "safety: stop: %s", action.reason)
            elif isinstance(action, Count):
                self.counters.inc(action.name)
            else:
                self.log.log(action.level, action.text)

    def _publish(self, send: Send, now: int) -> None:
        """The core's command with its header, stamped ``now`` (when the core checked it last): this service's
        sequence number, and with ``held``, that input's source stamp and trace."""
        if send.held is not None:
            header = self.header("command", stamp_ns=now, source=send.held.source, recv_ns=send.held.recv_ns)
        else:
            header = self.header("command", stamp_ns=now)
        command = send.command
        command.header = header
        if command.twist is not None:
            command.twist.header = header
        self.command_pub.put(command)
        self._resend_due = time.monotonic() + 1.0 / self.config.rate_hz

    def _loop(self) -> None:
        if not self.lockstep:
            request_realtime(self.config.realtime_priority, "safety resend loop")
            self.declare_loop("pub.command", self.config.rate_hz, ("cycles.late",))
        status_period = 1.0 / self.config.status_rate_hz
        next_status = time.monotonic()
        period = 1.0 / self.config.rate_hz
        self._resend_due = time.monotonic()
        while not self.stop_requested:
            now = time.monotonic()
            due = self._resend_due
            if not self.lockstep and now >= due:
                if now - due > period:  # a resend missed its deadline (the robot's watchdog is two)
                    self.counters.inc("cycles.late")
                try:
                    self._cycle()
                except Exception:
                    self.counters.inc("errors.cycle")
                    self.limited_log.error("cycle", "safety cycle failed")
                    self.log.debug("cycle failure", exc_info=True)
                if self._resend_due <= now:  # nothing went out: try again a period on
                    self._resend_due = now + period
            if now >= next_status:
                self.status_pub.put(self.status_message())
                next_status = now + status_period
            wake = next_status if self.lockstep else min(self._resend_due, next_status)
            time.sleep(max(0.0, min(wake - time.monotonic(), 0.05)))

    def status_message(self) -> SafetyStatus:
        with self.lock:
            return self._status_locked()

    def _status_locked(self) -> SafetyStatus:
        core = self.core
        return SafetyStatus(header=self.header("status"), state=core.safety_state,
                            active_limits=list(core.active_limits)[:32], last_refusal=core.last_refusal[:256],
                            counters=self.counters.snapshot(), in_control=core.in_control)
