"""The servo runner's view of a running stack: it subscribes to the controller's status, the features, the law's
output, the robot's state and commands and safety's status, and pairs each iteration with what it was computed
from (:class:`Watcher`); what the services counted as frames lost (:func:`frames_lost`)."""
from __future__ import annotations

import threading
from typing import Optional

from protocol import messages as m
from protocol.keys import Keys, ROBOT_SERVICES
from services.runtime.service import query_health


class Watcher:
    """Collects what the runner needs from the bus: controller statuses, the commands, features, robot states."""

    def __init__(self, session, keys: Keys, joint_output: bool) -> None:
        #: guards everything below; each wait is on the condition of what it waits for, so that a message wakes
        #: only a runner waiting for its kind (the runner waits for statuses; ten other messages come per frame)
        self.lock = threading.RLock()
        self.new_status, self.new_state, self.new_answer, self.new_input = (
            threading.Condition(self.lock) for _ in range(4))
        self.statuses: list[m.ControllerStatus] = []
        self.features: dict[int, m.Features] = {}
        self.commands: dict[int, list] = {}
        self.state: Optional[m.RobotState] = None
        #: the robot's states by stamp, to log each iteration with the state of its frame's tick
        self.state_at: dict[int, m.RobotState] = {}
        self.latest_state_stamp = -1
        #: safety's answer to each frame's command, by the frame's stamp
        self.answers: dict[int, m.RobotCommand] = {}
        #: safety's statuses by state, its limits seen, its last refusal and what a latched stop said
        self.safety_states: dict[str, int] = {}
        self.safety_limits: dict[str, int] = {}
        self.safety_refusal = ""
        self.safety_stop = ""
        self.states: list[m.RobotState] = []
        self.joint_output = joint_output
        output_key = keys.desired_joint_velocity if joint_output else keys.desired_twist
        output_type = m.JointVelocity if joint_output else m.Twist
        self._subs = [
            session.declare_subscriber(keys.controller_status, self._typed(m.ControllerStatus, self._on_status)),
            session.declare_subscriber(keys.features, self._typed(m.Features, self._on_features)),
            session.declare_subscriber(output_key, self._typed(output_type, self._on_output)),
            session.declare_subscriber(keys.robot_state, self._typed(m.RobotState, self._on_state)),
            session.declare_subscriber(keys.safety_status, self._typed(m.SafetyStatus, self._on_safety)),
            session.declare_subscriber(keys.robot_command, self._typed(m.RobotCommand, self._on_command)),
        ]

    @staticmethod
    def _typed(message_type, handler):
        return lambda sample: handler(m.decode(sample.payload.to_bytes(), message_type))

    def _on_status(self, status):
        with self.lock:
            last = self.statuses[-1] if self.statuses else None
            if last is not None and (last.header.seq, last.header.source_stamp_ns) == (
                    status.header.seq, status.header.source_stamp_ns):
                return  # the controller's answer to a frame again (a lockstep retry): one record per frame
            self.statuses.append(status)
            self.new_status.notify_all()

    def _on_features(self, features):
        with self.lock:
            self.features[features.header.source_stamp_ns] = features
            self.new_input.notify_all()

    def _on_output(self, output):
        values = output.velocities if isinstance(output, m.JointVelocity) else [*output.linear, *output.rotational]
        with self.lock:
            self.commands[output.header.source_stamp_ns] = list(values)
            self.new_input.notify_all()

    def _on_state(self, state):
        with self.lock:
            self.state = state
            self.states.append(state)
            self.state_at[state.header.stamp_ns] = state
            self.latest_state_stamp = max(self.latest_state_stamp, state.header.stamp_ns)
            self.new_state.notify_all()

    def state_for_frame(self, stamp_ns: int, timeout_s: float = 1.0) -> Optional[m.RobotState]:
        """The state of the tick at which the frame ``stamp_ns`` was taken (in lockstep the robot publishes one
        with that stamp; it may reach us after the controller's answer, so wait for it), else the last state
        before it, else the newest. Call with :attr:`lock` held."""
        self.new_state.wait_for(lambda: self.latest_state_stamp >= stamp_ns, timeout=timeout_s)
        state = self.state_at.get(stamp_ns)
        if state is None:
            before = [s for s in self.state_at if s <= stamp_ns]
            state = self.state_at[max(before)] if before else self.state
        return state

    def _on_command(self, command):
        with self.lock:  # the first command derived from a frame is safety's answer to it (later ones resend it)
            self.answers.setdefault(command.header.source_stamp_ns, command)
            self.new_answer.notify_all()

    def answer_for_frame(self, stamp_ns: int, timeout_s: float) -> Optional[m.RobotCommand]:
        """Safety's answer to the command derived from frame ``stamp_ns`` (in lockstep there is exactly one, sent
        before the robot's next tick; wait for it). Call with :attr:`lock` held."""
        self.new_answer.wait_for(lambda: stamp_ns in self.answers, timeout=timeout_s)
        return self.answers.get(stamp_ns)

    def _on_safety(self, status):
        with self.lock:
            self.safety_states[status.state.value] = self.safety_states.get(status.state.value, 0) + 1
            for name in status.active_limits:
                self.safety_limits[name] = self.safety_limits.get(name, 0) + 1
            self.safety_refusal = status.last_refusal or self.safety_refusal
            if status.state is m.SafetyState.ESTOP and not self.safety_stop:
                self.safety_stop = status.last_refusal or "latched stop"

    def safety_summary(self) -> dict:
        with self.lock:
            return {"states": dict(self.safety_states), "limits": dict(self.safety_limits),
                    "last_refusal": self.safety_refusal, "protective_stop": self.safety_stop or None}

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


#: (service, counter) → the name ``ServoResult.frames_lost`` gives it
FRAME_LOSS_COUNTERS = {("robot_sim", "frames.dropped"): "camera.dropped", ("vision", "frames.skipped"): "vision.skipped",
                       ("vision", "frames.stale"): "vision.stale"}


#: the robot node's lockstep waits that ran out (wall time): the arm went on without the pipeline's answer
LOCKSTEP_TIMEOUT_COUNTERS = ("lockstep.timeouts.frame", "lockstep.timeouts.cycle",
                             "lockstep.timeouts.answerers")


def frames_lost(session, keys: Keys) -> tuple[dict, int]:
    """Where frames were lost, from the services' health counters (every run starts a new stack: a counter is
    the run's; a service that does not answer is left out), and how many times the robot node's lockstep wait ran
    out."""
    health = query_health(session, keys)
    lost = {name: health[service].errors.get(counter, 0)
            for (service, counter), name in FRAME_LOSS_COUNTERS.items() if service in health}
    timeouts = sum(health[service].errors.get(counter, 0) for service in ROBOT_SERVICES
                   if service in health for counter in LOCKSTEP_TIMEOUT_COUNTERS)
    return lost, timeouts
