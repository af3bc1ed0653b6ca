"""The robot node: what every robot service offers on zenoh, whatever drives the arm (robot_sim's simulated arm,
robot_gateway's actuators on a bus or Kinova's own DSP through its SDK), and the robot's one loop. It is wiring and
lifecycle: it declares what comes in and goes out, calls the pieces below, counts, and publishes.

On zenoh: robot commands in (``…/robot/command``, from safety), the Kinova API as queryables
(``…/robot/api/<Function>``, run and answered between DSP cycles, with a timeout), the robot state out at every DSP
tick (100 Hz), the low-level torque API (``…/robot/lowlevel/*``, every bus cycle, realtime only), and the
commissioning check (``…/robot/check/arm``): while it runs, the node moves the arm itself, joint by joint, and holds
safety's commands (an emergency stop ends the check and stops the arm); its verdict goes out in every state.

The pieces, each without zenoh but the first:

* what comes in, checked, refused or handed over on zenoh's threads (:mod:`services.robot.node_inputs`), and the
  Kinova API's queries, handed to the DSP's thread and answered (:mod:`services.robot.api_queries`);
* what drives the arm (:mod:`services.robot.arm_driver`): every cycle of the loop the driver talks to the arm
  (exchanges the core's targets with the joints, or reads the arm through Kinova's SDK) and says whether the cycle
  is a DSP tick; the rules between the commands and the arm are its :class:`~services.robot.core.RobotCore`;
* the DSP cycle of a tick (:meth:`RobotNode.dsp_tick`): publish the state (:mod:`services.robot.state_message`),
  take the latest command (:mod:`services.robot.command_inbox`; in lockstep the pipeline's answer,
  :mod:`services.robot.lockstep_gate`), run the Kinova API calls, let the commissioning check
  (:mod:`services.robot.commissioning`) hold or replace the command, run the DSP. In realtime it runs beside the
  loop (:mod:`services.robot.dsp_worker`), so that the bus cycle goes out on time whatever the DSP costs, and the
  core holds the arm if no DSP cycle came for two DSP periods. In lockstep, and on a driver whose DSP is the arm's
  own, it runs in the loop;
* low-level torque control (:mod:`services.robot.lowlevel`), every bus cycle of a driver that offers the joints;
* the loop's meters, said in every state and in the health (:mod:`services.robot.loop_meters`); the configuration
  (:mod:`services.robot.node_config`).

Clock modes:

* ``realtime``: the loop runs every bus cycle of wall time (:class:`~services.runtime.pacing.CyclePacer`), at
  realtime priority where the OS allows; lateness is counted and reported in the state (``timing``) and health;
* ``lockstep``: the arm's own timeline drives the loop, cycle after cycle with no pacing; at each DSP tick the node
  waits for the pipeline's answer while a service that answers is alive (:mod:`services.robot.lockstep_gate`).

Subclasses open the hardware (or a driver of their own) and say which frame, if any, was taken at a tick (robot_sim
takes it; robot_gateway learns it from the simulator's clock): :mod:`services.robot.service_hooks`.

Which thread owns what (lockstep, and a driver whose DSP is the arm's own, have no DSP worker: the loop does its
part):

===========================  ==========================================  ============================================
thread                       runs                                        owns; touches under a lock
===========================  ==========================================  ============================================
zenoh's callbacks            ``NodeInputs``' ``on_command``,             nothing of the loop's: they decode, refuse
                             ``on_torque``, ``on_liveliness``,           and hand over: the inbox and the gate's
                             ``on_arm_check``; ``ApiQueries.on_query``   answerers (``inbox.changed``), the API
                             (and robot_gateway's ``on_sim_clock``:      calls (their queue's lock), low-level
                             the simulator's ticks, under a condition    control's latest command (its lock), a
                             of its own)                                 check's request (the coordinator's lock);
                                                                         a refused command's note for the states
``<name>-loop`` (the loop)   pacing, :meth:`RobotNode.bus_cycle`:        the driver (the hardware, its counts, its
                             low-level control, the driver's cycle,      link health), low-level control, the loop's
                             the low-level state                         meters; the core's reference, targets and
                                                                         torque mode (``_core_lock``)
``<name>-dsp`` (realtime,    ``DspWorker`` running                       the DSP (``core.dsp``) and the Kinova API
a driver whose DSP may run   :meth:`RobotNode.dsp_tick`: the state,      on it, ``kin``, the applied command's
beside the loop)             the command, the Kinova API calls, the      header, the check's run; the command taken
                             commissioning check, the DSP's plan         (``inbox.changed``), the core's plan
                                                                         (``_core_lock``); reads the link's health
                                                                         and the driver's count of cycles
``<name>-api-timeouts``      ``ApiQueries.answer_timeouts``: answers     nothing; the API calls' queue (its lock)
                             the API calls not taken in time
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
from typing import Optional

from protocol.conventions import ClockMode
from protocol.messages import Header, LowLevelState, RobotCommand, RobotState, TorqueCommand
from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics
from services.robot.api_queries import ApiQueries
from services.robot.arm_driver import ArmDriver, JointDriver, NodeLoop
from services.robot.command_inbox import CommandInbox
from services.robot.commissioning import Commissioning
from services.robot.contact_watch import ContactWatch
from services.robot.core import RobotCore
from services.robot.dsp_worker import DspWorker
from services.robot.hardware import CYCLE_S, DEFAULT_TIMING, JointReading
# LockstepConfig and MAX_COMMAND_WINDOW_S: tests import them from here, where they were before node_config
from services.robot.lockstep_gate import LockstepConfig, LockstepGate  # noqa: F401
from services.robot.loop_meters import LoopMeters
from services.robot.lowlevel import LowLevelControl, Outcome
from services.robot.node_config import MAX_COMMAND_WINDOW_S, RobotNodeConfig  # noqa: F401
from services.robot.node_inputs import NodeInputs
from services.robot.service_hooks import RobotServiceHooks
from services.robot.state_message import RecentRefusal, lowlevel_state, robot_state
from services.robot.torque_setup import TorqueSetup
from services.runtime.metrics import LoopTimer
from services.runtime.pacing import CyclePacer, request_realtime
from services.runtime.ports import Port, Ports
from services.runtime.service import Service
from services.runtime.threads import run_loop, start_thread

#: an in-process simulated arm runs at most this many late cycles back to back (0.1 s), then drops the stall
MAX_CATCH_UP_CYCLES = 50


class RobotNode(RobotServiceHooks, Service):
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
        #: the Kinova API's queries (robot/api/*), run and answered between DSP cycles, and the calls on their way
        self.api_queries = ApiQueries(self.name, self.counters, self.limited_log, self.refuse, self.inbox.wake,
                                      stopping=lambda: self.stop_requested)
        self.api_calls = self.api_queries.calls
        #: the commissioning check (its verdict goes out in every state)
        self.commissioning = Commissioning(config.arm_check, self.arm, self.counters, self.log, self.header)
        #: the header of the command the last DSP cycle applied, and a refused one, both said in the states
        self._applied: Optional[Header] = None
        self._recent_refusal = RecentRefusal()
        #: the contact monitor (on_start, where the config enables it): fed by the loop, read by the states
        self.contact_watch: Optional[ContactWatch] = None
        self._contact_lock = threading.Lock()

        # the threads
        self._thread: Optional[threading.Thread] = None
        self.finished = threading.Event()
        #: realtime: the DSP cycle's own thread, handed each tick (services.robot.dsp_worker)
        self.dsp_worker: Optional[DspWorker] = None
        self._api_timeouts_thread: Optional[threading.Thread] = None
        #: when the loop's current cycle was due (monotonic): the next is a cycle later
        self._slot_start = time.monotonic()

        # the loop's meters
        self.loop_timer = LoopTimer(self.cycle_s)
        self.meters = LoopMeters()
        #: what a driver shares with this loop: the clock, where it counts and logs
        self.loop = NodeLoop(self.name, self.lockstep, self.clock, self.counters, self.limited_log,
                             self.meters.missed, self.meters.exchange_time)

    # ---------------------------------------------------------- what a robot service provides (and service_hooks)
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

    def cycles_dropped(self, n: int) -> None:
        """Cycles the loop did not run (a stall): counted as missed; the in-process arm's time skips them."""
        self.counters.inc("cycles.missed", n)
        for _ in range(n):
            self.meters.missed.tick()

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
            if self.config.contact.enabled:
                self.contact_watch = ContactWatch(self.arm, self.config.contact, self.cycle_s, self.config.dsp.cycle_s)
            keys = self.keys
            self.state_pub = self.publisher(keys.robot_state, "state")
            self.lowlevel_pub = self.publisher(keys.lowlevel_state, "lowlevel_state")
            if self.driver.torque_joints is not None:
                self.lowlevel = LowLevelControl(self.config.lowlevel, self.driver.torque_joints,
                                                self.gravity_kin.gravity, self.torque_setup)
            # why torque commands are refused ('' where the low-level API is offered)
            unavailable = ("low-level torque control runs in realtime only" if self.lockstep
                           else self.driver.lowlevel_unavailable)
            self.incoming = NodeInputs(self.arm, self.inbox, self.gate, self.commissioning, self.core, self.lowlevel,
                                     unavailable, self.counters, self.log, self.refuse, self._refuse_command)
            self.subscribe(keys.robot_command, RobotCommand, self.incoming.on_command, "command")
            self.subscribe(keys.lowlevel_command, TorqueCommand, self.incoming.on_torque, "lowlevel_command")
            self.queryable(keys.robot_api_all, self.api_queries.on_query)
            self.queryable(keys.robot_check_arm, self.incoming.on_arm_check)
            # who is alive: lockstep waits for its answerers; a sender's new session restarts its numbering
            self._declared.append(self.session.liveliness().declare_subscriber(
                keys.liveliness_all, self.incoming.on_liveliness, history=True))
            self.declare_outputs()
        except BaseException:
            self.driver.close()
            raise
        self._thread = start_thread(self._run, f"{self.name}-loop")
        self._api_timeouts_thread = start_thread(self.api_queries.answer_timeouts, f"{self.name}-api-timeouts")

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
        detail = self.meters.health_detail(self.arm_summary(), self.torque_setup_summary())
        if self.contact_watch is not None:
            with self._contact_lock:
                detail += f"; {self.contact_watch.summary()}"
        return True, detail

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
            self.dsp_worker = DspWorker(self.name, self.driver, self.dsp_tick, self.config.command_window_s,
                                        self.meters.dsp_time, self.counters, self.log, self.limited_log)
        if request_realtime(self.config.realtime_priority, f"{self.name} bus loop"):
            self.counters.inc("realtime_priority.granted")
        self.on_loop_start()
        pacer = CyclePacer(self.cycle_s, MAX_CATCH_UP_CYCLES if self.driver.simulated_in_process else 0)
        self.loop_timer = LoopTimer(self.cycle_s)
        while not self.done():
            slot = pacer.wait()
            self._slot_start = time.monotonic() - slot.lag_s  # when this exchange was due
            self.meters.wake_lag.add(slot.lag_s)
            if slot.late:
                self.counters.inc("cycles.late")
                self.meters.late.tick()
            if slot.missed:
                self.cycles_dropped(slot.missed)
            start = time.monotonic()
            self.bus_cycle()
            self.meters.work.add(time.monotonic() - start)

    def bus_cycle(self) -> None:
        """One cycle of the loop: low-level control, the driver's cycle with the arm, and at a DSP tick the DSP."""
        self.loop_timer.tick()
        self.meters.cycles.tick()
        if not self.lockstep:
            self.rates.tick("bus_cycle")
            if self.lowlevel is not None:
                self._lowlevel_step()
        tick_ns = self.driver.cycle()
        if self.contact_watch is not None:
            self._watch_contact(tick_ns is not None)
        if self.lowlevel is not None and self.lowlevel_pub.matching:
            self._publish_lowlevel()
        if tick_ns is None:
            return
        reading = self.core.reading
        if self.dsp_worker is not None:
            self.dsp_worker.hand_over(tick_ns, reading, exchange_due=self._slot_start + self.cycle_s)
        else:
            self.driver.run_dsp(lambda: self.dsp_tick(tick_ns, reading))

    def _watch_contact(self, at_dsp_tick: bool) -> None:
        """The cycle's reading to the contact monitor; a contact it starts is counted and logged (safety, seeing it
        in the next state, stops the arm)."""
        with self._contact_lock:
            started = self.contact_watch.observe(self.core.reading, at_dsp_tick, time.monotonic_ns())
            line = self.contact_watch.last_contact() if started is not None else ""
        if line:
            self.counters.inc("contact.detected")
            self.log.warning("%s", line)

    def _contact_for_state(self):
        if self.contact_watch is None:
            return None
        with self._contact_lock:
            return self.contact_watch.for_state()

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
                self.meters.command_wait.add(waited_s)
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
        plan, refusal = self.core.dsp_plan(taken[0] if taken is not None else None, reading)
        with self._core_lock:
            self.core.take_plan(plan)
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
        self.api_queries.run_waiting(self.driver.api, self.core)

    def _refuse_command(self, rejection) -> None:
        """A robot command not applied: counted by kind, logged, and named in the states' faults for a while."""
        self.counters.inc(f"refused.{rejection.kind}")
        self.refuse("command", rejection.reason)
        self._recent_refusal.note(rejection.reason)

    def publish_state(self, stamp_ns: int, reading: JointReading) -> None:
        self.state_pub.put(robot_state(
            self.header("state", stamp_ns=stamp_ns), self.arm, reading, self.kin, self.core.dsp,
            link_faults=self.driver.link.faults, refused=self._recent_refusal.for_next_state(), applied=self._applied,
            timing=self.meters.timing(), arm_check=self.commissioning.state,
            finger_targets=None if self.core.fingers is None else self.core.fingers.target,
            contact=self._contact_for_state()))
