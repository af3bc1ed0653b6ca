"""Test helpers that start real services against a real router, and stand-ins for services not under test."""
import itertools
import threading
import time

import numpy as np

from protocol import messages as m
from protocol.conventions import AngularConvention, ClockMode, Frame
from protocol.keys import Keys
from services.runtime.transport import GuardedPublisher

#: robot commands are numbered per sender (the robot refuses a repeat): tests number theirs from here
_command_seq = itertools.count(1)


def next_seq() -> int:
    return next(_command_seq)


KEYS = Keys()


def wait_for(predicate, timeout=30.0, period=0.01):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period)
    return predicate()


class Recorder:
    """Collects decoded messages of one key."""

    def __init__(self, session, key, message_type):
        self.items = []
        self.lock = threading.Lock()
        self._type = message_type
        self._sub = session.declare_subscriber(key, self._on)

    def _on(self, sample):
        message = m.decode(sample.payload.to_bytes(), self._type)
        with self.lock:
            self.items.append(message)

    def __len__(self):
        return len(self.items)

    def last(self):
        with self.lock:
            return self.items[-1]

    def snapshot(self):
        with self.lock:
            return list(self.items)

    def close(self):
        self._sub.undeclare()


class FakePipeline:
    """Plays vision and controller: alive under both names, and for every camera frame publishes the desired
    twist ``twist_for(capture_ns)`` (mixed, seed000) stamped at the capture, as the controller would."""

    def __init__(self, session, twist_for, convention=AngularConvention.SEED000, frame=Frame.MIXED,
                 fingers_for=lambda capture_ns: None):
        self.session = session
        self.twist_for = twist_for
        #: the hand's part each twist carries (a FingerCommand, or None)
        self.fingers_for = fingers_for
        self.convention = convention
        self.frame = frame
        self.enabled = True
        self.sent = 0
        self.tokens = [session.liveliness().declare_token(KEYS.liveliness(name)) for name in ("vision", "controller")]
        self.publisher = GuardedPublisher.declare(session, KEYS.desired_twist)
        self.sub = session.declare_subscriber(KEYS.camera_image, self._on_image)

    def _on_image(self, sample):
        if not self.enabled:
            return
        capture = m.decode(sample.payload.to_bytes(), m.Image).header.source_stamp_ns
        linear, rotational = self.twist_for(capture)
        header = m.Header(stamp_ns=capture, source_stamp_ns=capture)
        twist = m.Twist(header=header, frame=self.frame, angular=self.convention, linear=tuple(map(float, linear)),
                        rotational=tuple(map(float, rotational)), fingers=self.fingers_for(capture))
        self.publisher.put(m.encode(twist))
        self.sent += 1

    def drop_liveliness(self, name):
        index = ("vision", "controller").index(name)
        self.tokens[index].undeclare()

    def close(self):
        self.sub.undeclare()
        self.publisher.undeclare()
        for token in self.tokens:
            try:
                token.undeclare()
            except Exception:
                pass


def ee_speeds(states):
    """EE linear speed between successive robot states (m/s), from the reported Kinova pose. A tick's state sent
    again (a lockstep retry, when the answer to it was late on a loaded host) is that tick's, once: two states with
    one stamp made a 0/0 speed."""
    states = [s for i, s in enumerate(states) if i == 0 or s.header.stamp_ns != states[i - 1].header.stamp_ns]
    xyz = np.array([[s.pose.X, s.pose.Y, s.pose.Z] for s in states])
    t = np.array([s.header.stamp_ns for s in states]) * 1e-9
    return np.linalg.norm(np.diff(xyz, axis=0), axis=1) / np.diff(t), t[1:]


__all__ = ["ClockMode", "FakePipeline", "KEYS", "Recorder", "ee_speeds", "wait_for"]
