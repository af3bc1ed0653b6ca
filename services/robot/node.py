"""The robot node: what every robot service offers on zenoh, whatever drives the arm (robot_sim's simulated arm,
robot_gateway's actuators on a bus or Kinova's own DSP through its SDK), and the robot's one loop. It is wiring and
lifecycle: it decodes what comes in, calls the pieces below, counts, and publishes.

On zenoh: robot commands in (``…/robot/command``, from safety), the Kinova API as queryables
(``…/robot/api/<Function>``, run and answered between DSP cycles, with a timeout: :mod:`services.robot.api_calls`),
the robot state out at every DSP tick (100 Hz), the low-level torque API (``…/robot/lowlevel/*``, every bus cycle,
realtime only), and the commissioning check (``…/robot/check/arm``): while it runs, the node moves the arm itself,
joint by joint, and holds safety's commands (an emergency stop ends the check and stops the arm); its verdict goes
out in every state.

The pieces, each without zenoh:

* what drives the arm (:mod:`services.robot.arm_driver`): every cycle of the loop the driver talks to the arm
  (exchanges the core's targets with the joints, or reads the arm through Kinova's SDK) and says whether the cycle
  is a DSP tick; the rules between the commands and the arm are its :class:`~services.robot.core.RobotCore`;
* the DSP cycle of a tick (:meth:`RobotNode.dsp_tick`): publish the state (:mod:`services.robot.state_message`),
  take the latest command (:mod:`services.robot.command_inbox`; in lockstep the pipeline's answer,
  :mod:`services.robot.lockstep_gate`), run the Kinova API calls, let the commissioning check
  (:mod:`services.robot.commissioning`) hold or replace the command, run the DSP. In realtime it runs beside the
  loop (:class:`~services.runtime.async_cycle.AsyncCycle`), handed each tick's reading, so that the bus cycle goes
  out on time whatever the DSP costs (as a robot's servo loop never waits for its planner): a tick the worker has
  not taken when the next comes is skipped and counted (``dsp.overruns``), and the core holds the arm if no DSP
  cycle came for two DSP periods. In lockstep, and on a driver whose DSP is the arm's own, it runs in the loop;
* low-level torque control (:mod:`services.robot.lowlevel`), every bus cycle of a driver that offers the joints.

Clock modes:

* ``realtime``: the loop runs every bus cycle of wall time (:class:`~services.runtime.pacing.CyclePacer`), at
  realtime priority where the OS allows; lateness is counted and reported in the state (``timing``) and health;
* ``lockstep``: the arm's own timeline drives the loop, cycle after cycle with no pacing; at each DSP tick the node
  waits for the pipeline's answer while a service that answers is alive (:mod:`services.robot.lockstep_gate`).

Subclasses open the hardware (or a driver of their own) and say which frame, if any, was taken at a tick (robot_sim
takes it; robot_gateway learns it from the simulator's clock).

Which thread owns what (lockstep, and a driver whose DSP is the arm's own, have no DSP worker: the loop does its
part):

===========================  ==========================================  ============================================
thread                       runs                                        owns; touches under a lock
===========================  ==========================================  ============================================
zenoh's callbacks            ``_on_command``, ``_on_torque``,            nothing of the loop's: they decode, refuse
                             ``_on_liveliness``, ``_on_api``,            and hand over: the inbox and the gate's
                             ``_on_arm_check`` (and robot_gateway's      answerers (``inbox.changed``), the API
                             ``on_sim_clock``: the simulator's ticks,    calls (their queue's lock), low-level
                             under a condition of its own)               control's latest command (its lock), a
                                                                         check's request (the coordinator's lock);
                                                                         a refused command's note for the states
``<name>-loop`` (the loop)   pacing, :meth:`RobotNode.bus_cycle`:        the driver (the hardware, its counts, its
                             low-level control, the driver's cycle,      link health), low-level control, the loop's
                             the low-level state                         meters; the core's reference, targets and
                                                                         torque mode (``_core_lock``)
``<name>-dsp`` (realtime,    :meth:`RobotNode.dsp_tick`: the state,      the DSP (``core.dsp``) and the Kinova API
a driver whose DSP may run   the command, the Kinova API calls, the      on it, ``kin``, the applied command's
beside the loop)             commissioning check, the DSP's plan         header, the check's run; the command taken
                                                                         (``inbox.changed``), the core's plan
                                                                         (``_core_lock``); reads the link's health
                                                                         and the driver's count of cycles
``<name>-api-timeouts``      answers the API calls not taken in time     nothing; the API calls' queue (its lock)
``<name>-health`` (runtime)  the health                                  nothing; reads counters, meters, link health
===========================  ==========================================  ============================================

The locks: ``_core_lock`` serialises the core between the loop (targets, readings, holds, torque mode) and the DSP
worker (its plan); ``inbox.changed`` guards the command waiting, both admissions and the gate's answerers, and
wakes the DSP wherever it waits for a command. The counters, rates and meters are thread-safe of their own; what
a reader takes without a lock (the link's faults, the check's verdict) is replaced whole, never changed in place,
and a refusal's note is the one unguarded count (a refusal noted while a state goes out may be named in fewer).
"""
from __future__ import annotations

import threading
import time
from concurrent.futures import Future
from typing import Optional

import msgspec
import zenoh

from protocol import kinova
from protocol.conventions import ClockMode
from protocol.keys import last_chunk
from protocol.messages import (ArmCheckReply, ArmCheckRequest, Header, LoopTiming, LowLevelState, ProtocolError,
                               RobotCommand, RobotState, TorqueCommand, encode, missing_fields)
from services.model.arm import DEFAULT_ARM, load_arm
from services.model.kinematics import ArmKinematics
from services.robot import arm_check
from services.robot.admission import AdmissionConfig
from services.robot.api_calls import ApiCallQueue
from services.robot.arm_driver import ArmDriver, JointDriver, NodeLoop
from services.robot.command_inbox import CommandInbox
from services.robot.commissioning import Commissioning
from services.robot.core import RobotCore
from services.robot.dsp import DSPConfig, for_arm
from services.robot.hardware import CYCLE_S, DEFAULT_TIMING, JointReading, RobotHardware
from services.robot.lockstep_gate import LockstepConfig, LockstepGate
from services.robot.lowlevel import LowLevelConfig, LowLevelControl, Outcome
from services.robot.state_message import RecentRefusal, lowlevel_state, robot_state
from services.robot.torque_setup import TorqueSetup
from services.runtime.async_cycle import AsyncCycle
from services.runtime.metrics import DurationStats, LoopTimer, RateMeter
from services.runtime.pacing import CyclePacer, request_realtime
from services.runtime.ports import Port, Ports
from services.runtime.service import Service, ServiceConfig, query_argument
from services.runtime.threads import run_loop, start_thread

#: Kinova API functions that move the arm: refused while low-level torque control owns it (they would be queued
#: in the DSP and run, unexpectedly, once torque control ends)
MOTION_FUNCTIONS = frozenset({"SendBasicTrajectory", "MoveHome"})
#: an in-process simulated arm runs at most this many late cycles back to back (0.1 s), then drops the stall
MAX_CATCH_UP_CYCLES = 50
#: a Kinova API call not taken by the robot's worker within this long is answered as timed out, without being run
API_TIMEOUT_S = 5.0
#: the DSP's plan must be ready this long before the next bus exchange: the command window ends there at the latest
#: (the plan takes 0.2-0.4 ms; the rest is for a late wake-up of the DSP's thread: with 0.5 ms, one plan in about a
#: thousand missed its exchange on this host)
PLAN_MARGIN_S = 0.0007
#: the longest command window: a bus cycle less the plan's margin
MAX_COMMAND_WINDOW_S = CYCLE_S - PLAN_MARGIN_S


class RobotNodeConfig(ServiceConfig):
    #: the arm (its description: services/model/arms/<arm>.yaml); the node declares it in every state, and the other
    #: services run on it
    arm: str = DEFAULT_ARM
    dsp: DSPConfig = msgspec.field(default_factory=DSPConfig)
    lockstep: LockstepConfig = msgspec.field(default_factory=LockstepConfig)
    #: which robot commands are applied at all: fresh, not from the future, in sequence per sender
    admission: AdmissionConfig = msgspec.field(default_factory=AdmissionConfig)
    #: the low-level torque API's watchdog and release (services.robot.lowlevel)
    lowlevel: LowLevelConfig = msgspec.field(default_factory=LowLevelConfig)
    #: the commissioning check's verdict: kept where, or waived (services.robot.arm_check)
    arm_check: arm_check.ArmCheckConfig = msgspec.field(default_factory=arm_check.ArmCheckConfig)
    #: after this many consecutive failed exchanges the node reports itself unhealthy and refuses motion
    max_bus_errors: int = 5
    #: realtime: SCHED_FIFO priority of the robot's process where the OS grants it (0: normal scheduling), above
    #: the router's and safety's (30). A robot's hardware loop must not wait behind the rest of the host
    realtime_priority: int = 40
    #: realtime: after its tick's reading, the DSP waits up to this long for a command derived from a newer frame
    #: than the last one it took, before it plans with what it has: a command that just missed the tick is then
    #: applied at this tick rather than 10 ms later, with the same motion (the plan is first used at the next bus
    #: exchange, 2 ms after the tick, either way). Never later than PLAN_MARGIN_S before that exchange; a stop is
    #: never waited past. 0: plan at once
    command_window_s: float = MAX_COMMAND_WINDOW_S

    def __post_init__(self) -> None:
        for_arm(self.dsp, load_arm(self.arm))  # an unknown arm, or speeds outside its ranges, refused now
        if self.max_bus_errors < 1:
            raise ValueError("max_bus_errors must be at least 1")
        if not 0.0 <= self.command_window_s <= MAX_COMMAND_WINDOW_S:
            raise ValueError(f"command_window_s must be within 0..{MAX_COMMAND_WINDOW_S} s: the DSP's plan is needed "
                             f"at the next bus exchange, {CYCLE_S * 1e3:.0f} ms after its tick")
        if not 0 <= self.realtime_priority <= 99:
            raise ValueError("realtime_priority must be within 0..99 (SCHED_FIFO)")


class RobotNode(Service):
    follows_sim_clock = True
    PORTS = Ports(consumes=(Port("robot_command", RobotCommand), Port("lowlevel_command", TorqueCommand)),
                  produces=(Port("robot_state", RobotState), Port("lowlevel_state", LowLevelState)),
                  answers=(Port("robot_api_all"), Port("robot_check_arm")))

    def __init__(self, config: RobotNodeConfig, **kw) -> None:
        super().__init__(config, **kw)
        self.config: RobotNodeConfig = config
        self.lockstep = ClockMode(config.clock) is ClockMode.LOCKSTEP
        #: the arm this node runs (its description), declared in every state
        self.arm = load_arm(config.arm)
        #: the DSP's thread's kinematics workspace, and the loop's own (ArmKinematics is not thread-safe)
        self.kin = ArmKinematics(self.arm)
        self.gravity_kin = ArmKinematics(self.arm)
        #: the torque-mode setup (Table 5.1's functions): the Kinova API sets it, low-level control applies it
        self.torque_setup = TorqueSetup(self.arm)

        # what drives the arm, known once it is open (open_driver)
        self.driver: Optional[ArmDriver] = None
        self.core: Optional[RobotCore] = None
        #: the loop's cycle: the bus's (services.robot.hardware.BusTiming), or the DSP's own where there is no bus
        self.bus_timing = DEFAULT_TIMING
        self.cycle_s = CYCLE_S
        #: low-level torque control, where the driver offers the joints to it
        self.lowlevel: Optional[LowLevelControl] = None
        #: serialises the core between the loop and the DSP worker
        self._core_lock = threading.Lock()

        # the pieces the loop and the DSP cycle call
        #: the commands in, admitted, for the DSP and low-level control; its condition wakes the DSP's waits
        self.inbox = CommandInbox(config.admission)
        #: lockstep: each tick waits for the pipeline's answer while a service that answers is alive
        self.gate = LockstepGate(config.lockstep, self.inbox, self.counters, self.log,
                                 stopping=lambda: self.stop_requested)
        #: Kinova API calls from the robot/api/* queryable, run and answered between DSP cycles
        self.api_calls = ApiCallQueue(API_TIMEOUT_S, on_timeout=lambda call: self.counters.inc("api.timeouts"))
        #: the commissioning check (its verdict goes out in every state)
        self.commissioning = Commissioning(config.arm_check, self.arm, self.counters, self.log, self.header)
        #: the header of the command the last DSP cycle applied, and a refused one, both said in the states
        self._applied: Optional[Header] = None
        self._recent_refusal = RecentRefusal()

        # the threads
        self._thread: Optional[threading.Thread] = None
        self.finished = threading.Event()
        #: realtime: the DSP cycle's own thread, handed each tick (a tick it has not taken when the next comes is
        #: skipped: dsp.overruns)
        self.dsp_worker: Optional[AsyncCycle] = None
        self._api_timeouts_thread: Optional[threading.Thread] = None
        #: when the loop's current cycle was due (monotonic): the next is a cycle later
        self._slot_start = time.monotonic()

        # the loop's meters
        self.loop_timer = LoopTimer(self.cycle_s)
        #: the loop's work per cycle (without its sleep), and the exchanges' share of it
        self.work = DurationStats()
        self.exchange_time = DurationStats()
        #: how late the loop woke for its slots, and how long the DSP cycles took (realtime)
        self.wake_lag = DurationStats()
        self.dsp_time = DurationStats()
        #: how long the DSP waited in its command window (realtime), apart from its own time above
        self.command_wait = DurationStats()
        self._late = RateMeter()
        self._missed = RateMeter()
        self._cycles = RateMeter()
        #: what a driver shares with this loop: the clock, where it counts and logs
        self.loop = NodeLoop(self.name, self.lockstep, self.clock, self.counters, self.limited_log, self._missed,
                             self.exchange_time)

    # ------------------------------------------------------------------ what a robot service provides
    def open_driver(self) -> ArmDriver:
        """What drives the arm: by default the emulated Kinova DSP on the joints :meth:`open_hardware` opens (an arm
        behind Kinova's SDK has a driver of its own)."""
        hardware, reading = self.open_hardware()
        try:
            return JointDriver(hardware, reading, self.loop, dsp=self.config.dsp, kin=self.kin,
                               gravity=self.gravity_kin.gravity, torque_setup=self.torque_setup,
                               core_lock=self._core_lock)
        except BaseException:
            hardware.close()
            raise

    def open_hardware(self) -> tuple[RobotHardware, JointReading]:
        """The joints' hardware and its first reading (the arm's joints before the first cycle)."""
        raise NotImplementedError

    def declare_outputs(self) -> None:
        """Further publishers and queryables of a robot service (robot_sim: camera and clock)."""

    def frame_at_tick(self, tick_ns: int) -> Optional[int]:
        """At a DSP tick (after its state went out): the capture stamp of the camera frame taken at this tick, if
        any (robot_sim takes and publishes it here)."""
        return None

    def on_lockstep_retry(self, tick_ns: int) -> None:
        """The answer to a tick is late: publish what it answers again (robot_sim: the frame and the tick)."""

    def lockstep_outputs_matched(self) -> bool:
        """Whether what the pipeline answers (robot_sim: its camera's images) has its subscribers."""
        return True

    def on_loop_start(self) -> None:
        """The realtime loop is about to run its first cycle (robot_sim starts its arm's time now)."""

    def on_lockstep_end(self) -> None:
        """The lockstep loop's thread is about to end (robot_sim frees the renderer that thread rendered with)."""

    def cycles_dropped(self, n: int) -> None:
        """Cycles the loop did not run (a stall): counted as missed; the in-process arm's time skips them."""
        self.counters.inc("cycles.missed", n)
        for _ in range(n):
            self._missed.tick()

    def done(self) -> bool:
        return self.stop_requested

    def torque_setup_summary(self) -> str:
        """The torque-mode setup (Table 5.1) low-level control applies, for the health's detail."""
        return self.torque_setup.describe()

    def arm_summary(self) -> str:
        """The arm this node runs, and what drives its joints (the first part of its health's detail)."""
        return f"arm {self.arm.name}: {self.arm.n_joints} joints"

    # ------------------------------------------------------------------ lifecycle
    def on_start(self) -> None:
        self.driver = self.open_driver()
        try:
            self.bus_timing = self.driver.timing
            self.cycle_s = self.bus_timing.period_s
            self.core = self.driver.core
            keys = self.keys
            self.state_pub = self.publisher(keys.robot_state, "state")
            self.lowlevel_pub = self.publisher(keys.lowlevel_state, "lowlevel_state")
            if self.driver.torque_joints is not None:
                self.lowlevel = LowLevelControl(self.config.lowlevel, self.driver.torque_joints,
                                                self.gravity_kin.gravity, self.torque_setup)
            self.subscribe(keys.robot_command, RobotCommand, self._on_command, "command")
            self.subscribe(keys.lowlevel_command, TorqueCommand, self._on_torque, "lowlevel_command")
            self.queryable(keys.robot_api_all, self._on_api)
            self.queryable(keys.robot_check_arm, self._on_arm_check)
            # who is alive: lockstep waits for its answerers; a sender's new session restarts its numbering
            self._declared.append(self.session.liveliness().declare_subscriber(
                keys.liveliness_all, self._on_liveliness, history=True))
            self.declare_outputs()
        except BaseException:
            self.driver.close()
            raise
        self._thread = start_thread(self._run, f"{self.name}-loop")
        self._api_timeouts_thread = start_thread(self._answer_api_timeouts, f"{self.name}-api-timeouts")

    def on_stop(self) -> None:
        self.commissioning.stop()
        self.inbox.wake()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self.dsp_worker is not None:
            self.dsp_worker.stop()
        self.api_calls.close(f"{self.name} is stopping")
        if self._api_timeouts_thread is not None:
            self._api_timeouts_thread.join(timeout=5.0)
        if self.driver is not None:
            self.driver.close()

    def check_health(self) -> tuple[bool, str]:
        if self._thread is None or not self._thread.is_alive():
            return False, "robot loop stopped"
        if self.driver.link.failing(self.config.max_bus_errors):
            return False, f"hardware failing: {self.driver.link.faults[:1]}"
        timing = self.timing()
        work, exchange, lag, dsp, wait = (self.work.stats(), self.exchange_time.stats(), self.wake_lag.stats(),
                                          self.dsp_time.stats(), self.command_wait.stats())
        return True, (f"{self.arm_summary()}; bus_rate_hz={timing.rate_hz:.1f} late_per_s={timing.late_per_s:.1f} "
                      f"missed_per_s={timing.missed_per_s:.1f} work_ms={work['p50_ms']:.2f}/{work['p99_ms']:.2f} "
                      f"exchange_ms={exchange['p50_ms']:.2f}/{exchange['p99_ms']:.2f} "
                      f"wake_lag_ms={lag['p50_ms']:.2f}/{lag['p99_ms']:.2f} dsp_ms={dsp['p50_ms']:.2f}/"
                      f"{dsp['p99_ms']:.2f} command_wait_ms={wait['p50_ms']:.2f}/{wait['p99_ms']:.2f} (p50/p99)"
                      + (f"; {setup}" if (setup := self.torque_setup_summary()) else ""))

    def timing(self) -> LoopTiming:
        return LoopTiming(rate_hz=self._cycles.rate_hz(), late_per_s=self._late.rate_hz(),
                          missed_per_s=self._missed.rate_hz())

    # ------------------------------------------------------------------ inputs (zenoh threads)
    def _wrong_joint_count(self, kind: str, values: Optional[list]) -> bool:
        """A joint vector for another arm than this one: refused and counted (``refused.joint_count``)."""
        if values is None or len(values) == self.arm.n_joints:
            return False
        self.counters.inc("refused.joint_count")
        self.refuse(kind, f"{len(values)} joint values for the {self.arm.name}'s {self.arm.n_joints} joints")
        return True

    def _on_command(self, command: RobotCommand, recv_ns: int) -> None:
        if self._wrong_joint_count("command", command.joint_velocities):
            return
        rejection = self.inbox.offer(command, recv_ns)
        if rejection is not None:
            self._refuse_command(rejection)

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        name, alive = last_chunk(sample.key_expr), sample.kind == zenoh.SampleKind.PUT
        if alive:
            self.inbox.new_session(name)  # a new session of a sender numbers its commands afresh
        self.gate.liveliness(name, alive)

    def lowlevel_unavailable(self) -> str:
        """Why torque commands are refused ('' when the low-level API is offered)."""
        return "low-level torque control runs in realtime only" if self.lockstep else self.driver.lowlevel_unavailable

    def _on_torque(self, command: TorqueCommand, recv_ns: int) -> None:
        if self._wrong_joint_count("lowlevel_command", command.torques):
            return
        unavailable = self.lowlevel_unavailable()
        if unavailable:
            self.refuse("lowlevel_command", unavailable)
            return
        rejection = self.inbox.admit_torque(command.header, recv_ns)
        if rejection is not None:  # torques bypass safety: the same freshness and sequence as robot commands
            self.counters.inc(f"refused.lowlevel_{rejection.kind}")
            self.refuse("lowlevel_command", rejection.reason)
            return
        refusal = self.lowlevel.receive(command, time.monotonic())
        if refusal:
            self.counters.inc("refused.lowlevel_after_safety_stop")
            self.refuse("lowlevel_command", refusal)

    def _on_api(self, query: zenoh.Query) -> None:
        function = last_chunk(query.key_expr)
        spec = kinova.API_FUNCTIONS.get(function)
        if spec is None:
            self.refuse("api", f"unknown Kinova API function {function!r}")
            query.reply(query.key_expr, encode(kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM),
                                                               message=f"unknown function {function}")))
            return
        argument_type, _ = spec
        try:
            argument = query_argument(query, function, argument_type)  # no payload for MoveHome & co
            if argument_type is not None and function in kinova.MUTATING_API_FUNCTIONS:
                missing = missing_fields(query.payload.to_bytes(), argument_type)
                if missing:
                    raise ProtocolError(argument_type.__name__, "a request that changes the arm must give every "
                                        f"field; missing: {', '.join(missing[:8])}")
        except ProtocolError as exc:
            self.refuse("api", str(exc))
            query.reply(query.key_expr, encode(kinova.ApiReply(
                code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=str(exc)[:256])))
            return
        # handed to the worker, which answers (this callback must not wait: its session delivers nothing meanwhile)
        refusal = self.api_calls.submit(function, argument, lambda reply: self._answer_api(query, reply))
        if refusal:
            self.refuse("api", f"{function}: {refusal}")
            self._answer_api(query, kinova.ApiReply(code=int(kinova.ErrorCode.UNKNOWN_ERROR),
                                                    message=f"not run: {refusal}"))
            return
        self.inbox.wake()  # a DSP waiting for a command runs the call now

    def _answer_api(self, query: zenoh.Query, reply: kinova.ApiReply) -> None:
        try:
            query.reply(query.key_expr, encode(reply))
        except Exception:  # the session closed under it (the node stopping)
            self.counters.inc("errors.api_reply")
        finally:
            query.drop()  # the final answer goes out now, not when the query is collected

    def _answer_api_timeouts(self) -> None:
        """Answer the API calls the worker did not take in time, even while it is held up (a slow SDK call)."""
        while not self.stop_requested:
            self.api_calls.wait_for_deadline(0.5)
            self.api_calls.expire()

    def _on_arm_check(self, query: zenoh.Query) -> None:
        """Run the commissioning check (the reply comes when it is over: a minute or two)."""
        try:
            request = query_argument(query, "arm_check", ArmCheckRequest)
        except ProtocolError as exc:
            self.refuse("arm_check", str(exc))
            query.reply(query.key_expr, encode(ArmCheckReply(ok=False, state=self.commissioning.state,
                                                             message=str(exc)[:512])))
            return
        future, reason = self.commissioning.request(request, self.core.torque_mode)
        if reason:
            self.refuse("arm_check", reason)
            query.reply(query.key_expr, encode(ArmCheckReply(ok=False, state=self.commissioning.state,
                                                             message=reason)))
            return
        self.log.info("commissioning check requested by %s: joints %s, %.1f° at %.1f°/s", request.operator or "?",
                      request.joints, request.step_deg, request.speed_dps)
        # the reply goes when the check is over: this callback returns now, so that zenoh goes on delivering the
        # session's other messages meanwhile (an emergency stop among them); the query is kept until then
        future.add_done_callback(lambda done: self._reply_arm_check(query, done))

    def _reply_arm_check(self, query: zenoh.Query, done: Future) -> None:
        try:
            reply = done.result()
        except Exception as exc:
            reply = ArmCheckReply(ok=False, state=self.commissioning.state,
                                  message=f"the check did not finish: {exc}")
        try:
            query.reply(query.key_expr, encode(reply))
        finally:
            query.drop()  # the final answer: the caller's get ends here

    # ------------------------------------------------------------------ the loop thread
    def _run(self) -> None:
        run_loop(self._run_lockstep if self.lockstep else self._run_realtime, "robot loop", self.log, self.counters,
                 self.finished)

    def _run_lockstep(self) -> None:
        try:
            self.gate.await_answerers(self.lockstep_outputs_matched)
            while not self.done():
                self.bus_cycle()
        finally:
            self.on_lockstep_end()

    #: counters whose growth means the robot's own loop did not keep up (mfvs status shows it degraded); the
    #: cycles the arm ran without a frame for other reasons (transport jitter) are in the missed rate only
    OVERRUNS = ("cycles.late", "cycles.missed", "bus.failed_exchanges", "dsp.overruns", "dsp.stale_holds")

    def _run_realtime(self) -> None:
        self.declare_loop("bus_cycle", 1.0 / self.cycle_s, self.OVERRUNS)
        if self.cycle_s < self.config.dsp.cycle_s:
            self.declare_loop("cycle", 1.0 / self.config.dsp.cycle_s)
        if self.driver.dsp_beside_loop:
            self.dsp_worker = AsyncCycle(f"{self.name}-dsp", on_overrun=lambda: self.counters.inc("dsp.overruns"))
        if request_realtime(self.config.realtime_priority, f"{self.name} bus loop"):
            self.counters.inc("realtime_priority.granted")
        self.on_loop_start()
        pacer = CyclePacer(self.cycle_s, MAX_CATCH_UP_CYCLES if self.driver.simulated_in_process else 0)
        self.loop_timer = LoopTimer(self.cycle_s)
        while not self.done():
            slot = pacer.wait()
            self._slot_start = time.monotonic() - slot.lag_s  # when this exchange was due
            self.wake_lag.add(slot.lag_s)
            if slot.late:
                self.counters.inc("cycles.late")
                self._late.tick()
            if slot.missed:
                self.cycles_dropped(slot.missed)
            start = time.monotonic()
            self.bus_cycle()
            self.work.add(time.monotonic() - start)

    def bus_cycle(self) -> None:
        """One cycle of the loop: low-level control, the driver's cycle with the arm, and at a DSP tick the DSP."""
        self.loop_timer.tick()
        self._cycles.tick()
        if not self.lockstep:
            self.rates.tick("bus_cycle")
            if self.lowlevel is not None:
                self._lowlevel_step()
        tick_ns = self.driver.cycle()
        if self.lowlevel is not None and self.lowlevel_pub.matching:
            self._publish_lowlevel()
        if tick_ns is None:
            return
        reading = self.core.reading
        if self.dsp_worker is not None:
            self._hand_to_dsp(tick_ns, reading)
        else:
            self.driver.run_dsp(lambda: self.dsp_tick(tick_ns, reading))

    def _lowlevel_step(self) -> None:
        """Engage, apply, hold or release low-level torque control (services.robot.lowlevel)."""
        outcome, detail = self.lowlevel.step(time.monotonic(), self.core.reading.q, self.core.reading.dq)
        if outcome is Outcome.SAFETY_STOP:
            self.counters.inc("lowlevel.safety_stops")
            self.log.warning("torque safety factor: back to trajectory control (%s)", detail)
        elif outcome is Outcome.ENGAGED:
            self.log.info("low-level torque control engaged")
        elif outcome is Outcome.RELEASED:
            self.log.info("low-level torque control released %s", detail)
        elif outcome is Outcome.WATCHDOG:
            self.counters.inc("lowlevel.watchdog")
        elif outcome is Outcome.REFUSED:
            self.refuse("lowlevel_command", detail)

    def _publish_lowlevel(self) -> None:
        reading = self.core.reading
        self.lowlevel_pub.put(lowlevel_state(self.header("lowlevel_state", stamp_ns=reading.stamp_ns or None), reading,
                                             self.core.torque_mode, self.driver.link.faults,
                                             self.bus_timing.period_ns))

    # ------------------------------------------------------------------ the DSP cycle (the DSP worker, or the loop)
    def _hand_to_dsp(self, tick_ns: int, reading: JointReading) -> None:
        wait_until = min(time.monotonic() + self.config.command_window_s,
                         self._slot_start + self.cycle_s - PLAN_MARGIN_S)
        exchanges = self.driver.cycles
        self.dsp_worker.submit(lambda: self._dsp_on_worker(tick_ns, reading, wait_until, exchanges))

    def _dsp_on_worker(self, tick_ns: int, reading: JointReading, wait_until: float, exchanges: int) -> None:
        """The DSP cycle of a tick on the worker: ``exchanges``, the bus exchanges done when it was handed over (a
        plan taken after another exchange is late)."""
        try:
            start = time.monotonic()
            # a window of 0 ends as it begins
            waited_s = self.driver.run_dsp(lambda: self.dsp_tick(tick_ns, reading, wait_until))
            self.dsp_time.add(time.monotonic() - start - waited_s)
            if self.driver.cycles > exchanges:
                self.counters.inc("dsp.late_plans")  # the next exchange went out on the last cycle's plan
        except Exception:
            self.counters.inc("errors.dsp")
            self.limited_log.error("dsp", "%s: DSP cycle failed", self.name)
            self.log.debug("DSP cycle failure", exc_info=True)

    def dsp_tick(self, tick_ns: int, reading: JointReading, wait_until: Optional[float] = None) -> float:
        """One DSP cycle on the reading of the tick at ``tick_ns`` (realtime: waiting for a fresh command until
        ``wait_until``, see ``command_window_s``); how long it waited (s)."""
        self.rates.tick("cycle")
        self.publish_state(tick_ns, reading)
        frame_stamp = self.frame_at_tick(tick_ns)
        waited_s = 0.0  # in the command window (realtime); lockstep waits for its answer instead
        if self.lockstep and self.gate.waits:
            taken = self._wait_for_answer(tick_ns, frame_stamp, reading)
        else:
            waiting = time.monotonic()
            taken = self.inbox.take(wait_until, self.done)
            waited_s = time.monotonic() - waiting
            if wait_until is not None:
                self.command_wait.add(waited_s)
        self.run_api_calls()
        taken = self.commissioning.command(tick_ns, taken, reading, self.core.dsp)
        if self.driver.link.failing(self.config.max_bus_errors):
            taken = None  # no motion on a failing bus
            self.core.dsp.erase_all_trajectories()
            self.commissioning.abort("the bus is failing")
        applied_ns = self.clock.now_ns()
        if taken is not None:
            stale = self.inbox.admission.stale(taken[0].header, applied_ns)
            if stale is not None:  # fresh on arrival, aged past the bound waiting for its tick
                self._refuse_command(stale)
                taken = None
        dq_ref, refusal = self.core.dsp_plan(taken[0] if taken is not None else None, reading)
        with self._core_lock:
            self.core.take_plan(dq_ref)
        self._applied = None
        if taken is not None:
            command, recv_ns = taken
            if refusal is None:
                self._applied = command.header.with_hop(self.name, recv_ns, applied_ns)
            else:
                self._refuse_command(refusal)
        return waited_s

    def _wait_for_answer(self, tick_ns: int, frame_stamp: Optional[int], reading: JointReading):
        """Lockstep: the pipeline's answer to this tick (services.robot.lockstep_gate), the Kinova API calls run
        while it is awaited, the state (and the frame) published again when it is late."""
        def again() -> None:
            self.publish_state(tick_ns, reading)
            self.on_lockstep_retry(tick_ns)

        return self.gate.wait_for_answer(tick_ns, frame_stamp, meanwhile=self.run_api_calls, again=again)

    def run_api_calls(self) -> None:
        """Run and answer the Kinova API calls waiting (on the worker, between DSP cycles)."""
        while (call := self.api_calls.take()) is not None:
            if call.function in MOTION_FUNCTIONS and self.core.torque_mode:
                self.refuse("api", f"{call.function}: low-level torque control is active")
                reply = kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM),
                                        message="low-level torque control is active")
            else:
                try:
                    reply = self.driver.api.call(call.function, call.argument)
                except Exception as exc:
                    self.counters.inc("errors.api")
                    self.limited_log.error("api", "%s: %s failed: %s", self.name, call.function, exc)
                    reply = kinova.ApiReply(code=int(kinova.ErrorCode.UNKNOWN_ERROR),
                                            message=f"{call.function} failed: {exc}"[:512])
            self.api_calls.finish(call, reply)

    def _refuse_command(self, rejection) -> None:
        """A robot command not applied: counted by kind, logged, and named in the states' faults for a while."""
        self.counters.inc(f"refused.{rejection.kind}")
        self.refuse("command", rejection.reason)
        self._recent_refusal.note(rejection.reason)

    def publish_state(self, stamp_ns: int, reading: JointReading) -> None:
        self.state_pub.put(robot_state(
            self.header("state", stamp_ns=stamp_ns), self.arm, reading, self.kin, self.core.dsp,
            link_faults=self.driver.link.faults, refused=self._recent_refusal.for_next_state(), applied=self._applied,
            timing=self.timing(), arm_check=self.commissioning.state))
