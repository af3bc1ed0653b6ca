"""``mfvs replay``: a recording's payloads published back onto zenoh, byte for byte, so that vision, the controller
and safety run on a recorded session.

With its original timing (``--rate`` scales it), or in lockstep: as fast as the consumers answer, each camera
frame published only once every answering key (the features, the controller's output) has answered the frame
before it. A replay never moves an arm: the keys that command one (robot commands, torque commands, the e-stop)
are never published, and robot states are refused while a robot is alive on the stack.
"""
from __future__ import annotations

import struct
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Optional

from mcap.exceptions import McapError
from mcap.reader import make_reader

from protocol import messages as m
from protocol.keys import Keys
from protocol.topics import UnknownTopic, key_pattern, resolve, topic_of
from services.observe.foxglove_view import RAW_ENCODING, RAW_TYPE
from protocol.keys import ROBOT_SERVICES
from services.runtime.service import alive_services

#: what a replay never publishes: these move an arm
COMMAND_TYPES = (m.RobotCommand, m.TorqueCommand, m.EStop)
#: nor this: a recorded service's health would stand in for the live one's
NOT_REPLAYED = COMMAND_TYPES + (m.ServiceHealth,)
#: how long lockstep waits for a frame's answers before going on (counted as unanswered)
ANSWER_TIMEOUT_S = 5.0
#: lockstep sends a frame still unanswered after this again, as the robot's lockstep retry does: zenoh drops a
#: sample on a congested queue (a starved host's frame or answer), and vision and the controller answer a frame
#: delivered again with the answer they gave it
RETRY_S = 0.5


@dataclass(frozen=True)
class Recorded:
    """One recorded payload: the key it came on (below the robot's prefix), its type's name, when it was received
    (ns) and its bytes."""

    suffix: str
    type_name: str
    log_time: int
    payload: bytes


def _suffix(key: str) -> str:
    return key.split("/", 2)[2]


def read_recording(path, patterns=None, keys: Optional[Keys] = None) -> Iterator[Recorded]:
    """The raw payloads of an ``mfvs record`` file in receive order, of the keys ``patterns`` select (all when
    None). Raises ValueError for a file that is not MCAP or holds no mfvs payloads."""
    keys = keys or Keys()
    selectors = [key_pattern(resolve(p, keys).replace(keys.prefix, "mfvs/*", 1)) for p in patterns or ["**"]]
    found = False
    with open(path, "rb") as stream:
        try:
            reader = make_reader(stream)
            for _schema, channel, message in reader.iter_messages(log_time_order=True):
                if channel.message_encoding != RAW_ENCODING or RAW_TYPE not in channel.metadata:
                    continue
                found = True
                if any(s.match(channel.topic) for s in selectors):
                    yield Recorded(_suffix(channel.topic), channel.metadata[RAW_TYPE], message.log_time,
                                   bytes(message.data))
        except (McapError, ValueError, EOFError, KeyError, struct.error) as exc:
            raise ValueError(f"{path}: not a readable MCAP recording ({type(exc).__name__}: {exc})") from None
    if not found:
        raise ValueError(f"{path}: no mfvs payloads in this file (was it written by `mfvs record`?)")


def replayable(recorded: Recorded) -> bool:
    try:
        return topic_of(f"mfvs/jaco/{recorded.suffix}").message_type not in NOT_REPLAYED
    except UnknownTopic:
        return False


def _stamp(recorded: Recorded) -> int:
    """The header's stamp of a recorded payload (every topic's message has a header)."""
    kind = topic_of(f"mfvs/jaco/{recorded.suffix}").message_type
    header = m.decode(recorded.payload, kind).header
    return header.source_stamp_ns if kind in (m.Features, m.Twist, m.JointVelocity, m.ControllerStatus) \
        else header.stamp_ns


def lockstep_order(inputs: list[Recorded], answers: list[Recorded]) -> list[Recorded]:
    """A lockstep recording in the order the run had: the inputs of each tick (by their simulated stamps, in
    receive order within a tick), then the answers to that tick's frame, then the next tick's. Receive order alone
    is not that order: a frame of a megabyte may reach the recorder after the features a service derived from it."""
    keyed = [((_stamp(r), 0, i), r) for i, r in enumerate(inputs)]
    keyed += [((_stamp(r), 1, i), r) for i, r in enumerate(answers)]
    return [r for _, r in sorted(keyed, key=lambda item: item[0])]


@dataclass
class ReplayReport:
    published: dict = field(default_factory=dict)
    not_replayed: int = 0
    frames: int = 0
    unanswered: int = 0
    #: the source stamps of the first frames left unanswered (ns)
    unanswered_stamps: list = field(default_factory=list)
    #: frames sent again because their answers were late (:data:`RETRY_S`)
    retries: int = 0
    seconds: float = 0.0


class _Answers:
    """The source stamps each answering key has answered (lockstep)."""

    def __init__(self, session, keys: Keys, answer_keys) -> None:
        self.cond = threading.Condition()
        self.seen: dict[str, set] = {k: set() for k in answer_keys}
        self.types = {k: topic_of(k).message_type for k in answer_keys}
        self._subscribers = [session.declare_subscriber(k, self._on_sample) for k in answer_keys]

    def _on_sample(self, sample) -> None:
        key = str(sample.key_expr)
        try:
            message = m.decode(sample.payload.to_bytes(), self.types[key])
        except (m.ProtocolError, KeyError):
            return
        with self.cond:
            self.seen[key].add(message.header.source_stamp_ns)
            self.cond.notify_all()

    def wait(self, stamp_ns: int, timeout_s: float, keys=None) -> bool:
        """Until each of ``keys`` (default all) has answered the frame stamped ``stamp_ns``."""
        chosen = [self.seen[k] for k in (keys if keys is not None else self.seen)]
        with self.cond:
            return self.cond.wait_for(lambda: all(stamp_ns in s for s in chosen), timeout_s)

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()


def replay(session, path, keys: Keys, patterns=None, rate: float = 1.0, lockstep: bool = False,
           answer_patterns=("vision/features",), alive=None, progress=None,
           retry_s: float = RETRY_S) -> ReplayReport:
    """Publish the recording at ``path`` under ``keys``'s prefix. ``alive``: the services alive on the stack
    (for the robot check; looked up when None). ``progress(report)`` after each camera frame."""
    if rate <= 0:
        raise ValueError("--rate must be positive")
    report = ReplayReport()
    messages = _payloads_to_publish(path, patterns, keys, report)
    _refuse_beside_a_robot(session, keys, messages, alive)
    plan = _LockstepPlan.make(session, path, keys, messages, answer_patterns) if lockstep else None
    publishing = _Publishing(session, keys, report, plan, retry_s)
    try:
        publishing.run(plan.messages if plan is not None else messages, rate, progress)
    finally:
        publishing.close()
    return report


def _payloads_to_publish(path, patterns, keys: Keys, report: ReplayReport) -> list[Recorded]:
    """The recording's payloads a replay publishes (those it never does counted in ``report``). Raises ValueError
    when none is left."""
    messages = list(read_recording(path, patterns, keys))
    report.not_replayed = len([r for r in messages if not replayable(r)])
    messages = [r for r in messages if replayable(r)]
    if not messages:
        raise ValueError(f"{path}: nothing to replay on the chosen keys")
    return messages


def _refuse_beside_a_robot(session, keys: Keys, messages: list[Recorded], alive) -> None:
    """Robot states are not replayed beside a live robot (``alive``: the services alive; looked up when None)."""
    if alive is None:
        alive = alive_services(session, keys)
    robots = sorted(set(alive) & set(ROBOT_SERVICES))
    if robots and any(r.suffix == _suffix(keys.robot_state) for r in messages):
        raise ValueError(f"{', '.join(robots)} is running on this stack: replaying robot states beside a robot "
                         f"would give the stack two arms (stop it, or leave robot/state out with --keys)")


@dataclass
class _LockstepPlan:
    """Lockstep: where the recording holds the answers too, each is a point to wait at (the fresh consumer's answer
    to the same frame), so that what follows an answer in the recording (the next clock ticks) follows it in the
    replay; an answer key the recording lacks is waited for before the next frame."""

    answers: _Answers
    #: the recorded answers' suffixes waited at, and each one's key
    sync: dict[str, str]
    #: the answer keys the recording lacks
    unsynced: list[str]
    #: what to publish, with the recorded answers to wait at in their places
    messages: list[Recorded]

    @classmethod
    def make(cls, session, path, keys: Keys, messages: list[Recorded], answer_patterns) -> "_LockstepPlan":
        answer_keys = [resolve(p, keys) for p in answer_patterns]
        for key in answer_keys:
            topic_of(key)  # a typo says so before anything is published
        answer_suffixes = {_suffix(k): k for k in answer_keys}
        if answer_suffixes.keys() & {r.suffix for r in messages}:
            raise ValueError("the answering keys are the consumers' to publish: leave them out of --keys")
        answers = _Answers(session, keys, answer_keys)
        recorded_answers = list(read_recording(path, list(answer_suffixes), keys))
        sync = {suffix: key for suffix, key in answer_suffixes.items()
                if any(r.suffix == suffix for r in recorded_answers)}
        messages = lockstep_order(messages, [r for r in recorded_answers if r.suffix in sync])
        unsynced = [key for suffix, key in answer_suffixes.items() if suffix not in sync]
        return cls(answers, sync, unsynced, messages)


class _Publishing:
    """One replay's publishing: a publisher per key, paced by the recording's timing or, in lockstep (``plan``),
    by the consumers' answers; the last frame sent (what a retry sends again) and the frames left unanswered."""

    def __init__(self, session, keys: Keys, report: ReplayReport, plan: Optional[_LockstepPlan],
                 retry_s: float) -> None:
        self.session = session
        self.keys = keys
        self.report = report
        self.plan = plan
        self.retry_s = retry_s
        self.image_suffix = _suffix(keys.camera_image)
        self.publishers = {}
        self.unanswered: set[int] = set()
        self.last_frame: Optional[int] = None
        self.last_payload = b""  # the last frame sent: what a retry sends again

    def run(self, messages: list[Recorded], rate: float, progress) -> None:
        report, plan = self.report, self.plan
        sync = plan.sync if plan is not None else {}
        start = time.monotonic()
        first = messages[0].log_time
        for recorded in messages:
            if recorded.suffix in sync:
                key = sync[recorded.suffix]
                stamp = m.decode(recorded.payload, plan.answers.types[key]).header.source_stamp_ns
                if stamp not in self.unanswered and not self.answered(stamp, [key]):
                    self.unanswered.add(stamp)
                continue
            is_frame = recorded.suffix == self.image_suffix
            if plan is not None:
                if is_frame and self.last_frame is not None and plan.unsynced:
                    if not self.answered(self.last_frame, plan.unsynced):
                        self.unanswered.add(self.last_frame)
            else:
                delay = start + (recorded.log_time - first) / 1e9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            self._publish(recorded, is_frame, progress)
        if plan is not None and self.last_frame is not None and not self.answered(self.last_frame):
            self.unanswered.add(self.last_frame)
        report.unanswered = len(self.unanswered)
        report.unanswered_stamps = sorted(self.unanswered)[:20]
        report.seconds = time.monotonic() - start

    def answered(self, stamp: int, wanted=None) -> bool:
        """Whether ``wanted`` (default every answering key) answered the frame stamped ``stamp`` within
        :data:`ANSWER_TIMEOUT_S`; the last frame sent again every ``retry_s`` while it waits."""
        deadline = time.monotonic() + ANSWER_TIMEOUT_S
        while not self.plan.answers.wait(stamp, min(self.retry_s, max(0.0, deadline - time.monotonic())), wanted):
            if time.monotonic() >= deadline:
                return False
            if stamp == self.last_frame:
                self.publishers[self.image_suffix].put(self.last_payload)
                self.report.retries += 1
        return True

    def _publish(self, recorded: Recorded, is_frame: bool, progress) -> None:
        publisher = self.publishers.get(recorded.suffix)
        if publisher is None:
            publisher = self.publishers[recorded.suffix] = self.session.declare_publisher(
                f"{self.keys.prefix}/{recorded.suffix}")
        publisher.put(recorded.payload)
        self.report.published[recorded.suffix] = self.report.published.get(recorded.suffix, 0) + 1
        if is_frame:
            self.report.frames += 1
            self.last_frame = m.decode(recorded.payload, m.Image).header.stamp_ns
            self.last_payload = recorded.payload
            if progress is not None:
                progress(self.report)

    def close(self) -> None:
        if self.plan is not None:
            self.plan.answers.close()
        for publisher in self.publishers.values():
            publisher.undeclare()


def recording_summary(path) -> dict:
    """Channels and message counts of an MCAP file (any, not only mfvs's), from its summary."""
    with open(Path(path), "rb") as stream:
        summary = make_reader(stream).get_summary()
    if summary is None:
        raise ValueError(f"{path}: no summary section (was the recording closed?)")
    counts = summary.statistics.channel_message_counts if summary.statistics else {}
    return {channel.topic: {"messages": counts.get(cid, 0), "encoding": channel.message_encoding,
                            "schema": summary.schemas[channel.schema_id].name if channel.schema_id else None}
            for cid, channel in summary.channels.items()}
