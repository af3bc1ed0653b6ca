"""A computed-torque client of the robot's low-level zenoh API: on every low-level state it publishes the
torque of :class:`~services.controller.computed_torque.ComputedTorque` for the cubic reference (seed 003 ch. 4
and eq. 5.1). Runs against robot_gateway (or any robot offering ``robot/lowlevel/*``).

The reference is evaluated at the state's stamp (the arm's time), not at the client's clock: a state delivered
late is compared with where the arm should have been when it was measured, so a late host or transport costs
tracking only through the delay of the torque it answers with, never through a reference that ran ahead."""
from __future__ import annotations

import threading
import time

import numpy as np

from protocol import messages as m
from protocol.keys import Keys
from services.runtime.transport import GuardedPublisher
from services.controller.computed_torque import ComputedTorque, cubic


class CubicTorqueClient:
    def __init__(self, session, keys: Keys, q0, qf, duration_s: float, controller: ComputedTorque):
        self.keys = keys
        self.q0, self.qf, self.duration_s = np.asarray(q0, float), np.asarray(qf, float), duration_s
        self.controller = controller
        self.errors_deg: list[float] = []
        #: the arm's time (ns) of the first state: the cubic starts there
        self.start_ns: int | None = None
        self.done = threading.Event()
        self._lock = threading.Lock()
        # the robot refuses a sequence number not above the sender's last; a client without a liveliness token
        # (whose new session the robot cannot see) starts above any earlier run's numbers
        self._seq = time.time_ns() // 1000
        self._publisher = GuardedPublisher.declare(session, keys.lowlevel_command)
        self._subscriber = session.declare_subscriber(keys.lowlevel_state, self._on_state)

    def _on_state(self, sample) -> None:
        if self.done.is_set():
            return
        state = m.decode(sample.payload.to_bytes(), m.LowLevelState)
        with self._lock:
            if self.start_ns is None:
                self.start_ns = state.header.stamp_ns
            t = (state.header.stamp_ns - self.start_ns) / 1e9
            q, dq = np.asarray(state.q), np.asarray(state.dq)
            q_d, dq_d, ddq_d = cubic(self.q0, self.qf, self.duration_s, t)
            if state.mode is m.ActuatorMode.TORQUE:
                self.errors_deg.append(float(np.degrees(np.abs(q_d - q)).max()))
            tau = self.controller.torque(q, dq, q_d, dq_d, ddq_d)
        self._seq += 1
        self._publisher.put(m.encode(m.TorqueCommand(header=m.Header(seq=self._seq, stamp_ns=time.time_ns()),
                                                     torques=tau.tolist(), gravity_compensation=True)))
        if t > self.duration_s + 0.3:
            self.done.set()

    def close(self) -> None:
        self.done.set()
        self._subscriber.undeclare()
        self._publisher.undeclare()
