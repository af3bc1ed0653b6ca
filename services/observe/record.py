"""``mfvs record``: every message on the chosen keys of a running stack into an MCAP file, as it arrives.

Each key's MessagePack payloads are kept byte for byte in a channel of their own (the key is the channel's topic,
the message type's name in its metadata, its JSON schema as the schema), logged at their receive time (the
payload's header carries the source stamps); beside them the viewer's channels in Foxglove's well-known schemas
(:mod:`services.observe.foxglove_view`). Foxglove's SDK writes the file; the ``mcap`` package reads it
(:func:`services.observe.replay.read_recording`).
"""
from __future__ import annotations

import queue
import threading
import time
from collections import Counter
from pathlib import Path

import foxglove

from protocol import messages as m
from protocol.keys import Keys
from protocol.topics import Topic, UnknownTopic, matching, topic_of
from services.observe.foxglove_view import RawChannels, ViewChannels

#: the keys recorded when none are named: every topic of the stack
ALL = ("**",)


class Tap:
    """Subscribes to the topics ``patterns`` select and logs what arrives on a foxglove Context: the raw payloads
    (``raw``) and the viewer's channels (``view``). Its sinks are the subclass's; :attr:`counts` says how many
    messages each key gave."""

    def __init__(self, session, keys: Keys, patterns=ALL, raw: bool = True, view: bool = True) -> None:
        self.topics: dict[str, Topic] = {}
        for pattern in patterns:
            self.topics.update({t.key: t for t in matching(pattern, keys)})
        self.counts: Counter = Counter()
        #: messages a publisher's sequence numbers say never arrived (zenoh drops a put for a slow subscriber)
        self.missed: Counter = Counter()
        self.undecodable: Counter = Counter()
        self.view_failures: Counter = Counter()
        self._last_seq: dict[str, int] = {}
        # zenoh's callback only queues: the writing (compression, the viewer's JPEG) happens in a thread of its own,
        # so that the subscriber keeps up and the router does not drop what it cannot deliver
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self.context = foxglove.Context()
        self.open_sinks()
        self.raw = RawChannels(self.context) if raw else None
        self.view = ViewChannels(self.context) if view else None
        self._worker = threading.Thread(target=self._write, name="mfvs-tap-writer", daemon=True)
        self._worker.start()
        self._closed = False
        self._subscribers = [session.declare_subscriber(key, self._on_sample) for key in self.topics]

    def open_sinks(self) -> None:
        raise NotImplementedError

    def close_sinks(self) -> None:
        raise NotImplementedError

    def _on_sample(self, sample) -> None:
        self._queue.put((time.time_ns(), str(sample.key_expr), sample.payload.to_bytes()))

    def _write(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            received_ns, key, payload = item
            topic = self.topics.get(key)
            if topic is None:  # a key below a wildcard topic (each service's health)
                try:
                    topic = topic_of(key)
                except UnknownTopic:
                    continue
            self._log(topic, payload, received_ns)

    def _log(self, topic: Topic, payload: bytes, received_ns: int) -> None:
        if self.raw is not None:
            self.raw.log(topic, payload, received_ns)
        self.counts[topic.key] += 1
        try:
            message = m.decode(payload, topic.message_type)
        except m.ProtocolError:
            self.undecodable[topic.key] += 1  # kept raw as it came; nothing to show
            return
        seq = getattr(getattr(message, "header", None), "seq", 0)
        last = self._last_seq.get(topic.key)
        if last is not None and seq > last + 1:
            self.missed[topic.key] += seq - last - 1
        self._last_seq[topic.key] = seq
        if self.view is not None:
            try:
                self.view.on_message(topic, message, received_ns)
            except Exception:  # a message the viewer cannot draw is still recorded raw
                self.view_failures[topic.key] += 1

    def close(self) -> None:
        """Stop listening, write what is queued, close the sinks."""
        for subscriber in self._subscribers:
            subscriber.undeclare()
        if not self._closed:
            self._closed = True
            self._queue.put(None)
            self._worker.join()
            self.close_sinks()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class Recorder(Tap):
    """Records into an MCAP file while open (a context manager)."""

    def __init__(self, session, keys: Keys, path, patterns=ALL, view: bool = True) -> None:
        self.path = Path(path)
        super().__init__(session, keys, patterns, raw=True, view=view)

    def open_sinks(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._mcap = foxglove.open_mcap(str(self.path), allow_overwrite=True, context=self.context)

    def close_sinks(self) -> None:
        self._mcap.close()

    def report(self) -> dict:
        return {"file": str(self.path), "messages": dict(sorted(self.counts.items())),
                "missed": dict(self.missed), "undecodable": dict(self.undecodable),
                "view_failures": dict(self.view_failures),
                "bytes": self.path.stat().st_size if self.path.exists() else 0}
