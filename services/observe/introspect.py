"""Looking at a running stack from outside, as ``ros2 topic`` does: ``mfvs echo KEY`` (each message decoded, a line
each or JSON), ``mfvs hz KEY`` (rate and jitter), ``mfvs keys`` (what is published now, with its type).

The summaries and the statistics are pure functions; the commands subscribe, decode with the topic's type
(:mod:`protocol.topics`), and print. A key that is no topic says what it might have been; a payload that does not
decode is reported on stderr and counted, and the command goes on.
"""
from __future__ import annotations

import json
import math
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Optional

import msgspec

from protocol import messages as m
from protocol.keys import Keys
from protocol.topics import Topic, UnknownTopic, matching, resolve, topic_of
from services.runtime.jsonsafe import json_safe

#: lists longer than this are cut in a summary line
SUMMARY_ITEMS = 8


# ------------------------------------------------------------------------------------------------ summaries
def _short(value):
    """A message's fields, made short for one line: bytes as their length, long lists cut, floats to 4 digits."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return f"<{len(value)} bytes>"
    if isinstance(value, float):
        return value if not math.isfinite(value) else float(f"{value:.4g}")
    if isinstance(value, dict):
        return {k: _short(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        items = [_short(v) for v in value[:SUMMARY_ITEMS]]
        if len(value) > SUMMARY_ITEMS:
            items.append(f"…{len(value) - SUMMARY_ITEMS} more")
        return items
    return value


def summary(message) -> str:
    """One line: the fields that say most, the header's stamps and trace folded to a few characters."""
    data = msgspec.to_builtins(_without_bytes(message), enc_hook=repr)
    header = data.pop("header", None)
    parts = []
    if header:
        parts.append(f"stamp={header['stamp_ns'] / 1e9:.3f}")
        if header.get("source_stamp_ns"):
            parts.append(f"source={header['source_stamp_ns'] / 1e9:.3f}")
        if header.get("trace"):
            parts.append("trace=" + ">".join(hop["service"] for hop in header["trace"]))
    for name, value in data.items():
        if value in (None, [], {}, ""):
            continue
        parts.append(f"{name}={json.dumps(_short(value), ensure_ascii=False, separators=(',', ':'))}")
    return " ".join(parts)


def _without_bytes(message):
    """The message with its bytes fields replaced by their length (an image's pixels are no line's business)."""
    if isinstance(message, m.Image):
        return _ImageSummary(header=message.header, width=message.width, height=message.height,
                             encoding=message.encoding, data_bytes=len(message.data))
    return message


class _ImageSummary(msgspec.Struct, kw_only=True):
    header: m.Header
    width: int
    height: int
    encoding: m.ImageEncoding
    data_bytes: int


def as_json(message) -> str:
    """The whole message as one JSON line; bytes as {"bytes": length} (the pixels are in ``mfvs record``'s file),
    a non-finite figure as null."""
    data = msgspec.to_builtins(message, builtin_types=(bytes,))
    return json.dumps(json_safe(data), ensure_ascii=False, separators=(",", ":"), allow_nan=False)


# ------------------------------------------------------------------------------------------------ rates
@dataclass
class RateStats:
    """Arrivals of one key (monotonic seconds), over the last ``window`` of them."""

    window: int = 1000
    count: int = 0

    def __post_init__(self) -> None:
        self.arrivals: deque = deque(maxlen=self.window)

    def add(self, t_s: float) -> None:
        self.arrivals.append(t_s)
        self.count += 1

    def report(self) -> Optional[dict]:
        """rate (Hz), period mean/min/max and jitter (the periods' standard deviation), ms; None below 2 arrivals."""
        if len(self.arrivals) < 2:
            return None
        t = list(self.arrivals)
        periods = [b - a for a, b in zip(t, t[1:])]
        mean = sum(periods) / len(periods)
        jitter = math.sqrt(sum((p - mean) ** 2 for p in periods) / len(periods))
        return {"rate_hz": 1.0 / mean if mean > 0 else math.inf, "mean_ms": 1e3 * mean,
                "min_ms": 1e3 * min(periods), "max_ms": 1e3 * max(periods), "jitter_ms": 1e3 * jitter,
                "window": len(t), "count": self.count}


def rate_line(key: str, report: Optional[dict]) -> str:
    if report is None:
        return f"{key}: fewer than 2 messages so far"
    return (f"{key}: {report['rate_hz']:.1f} Hz  period {report['mean_ms']:.2f} ms (min {report['min_ms']:.2f}, "
            f"max {report['max_ms']:.2f}, jitter {report['jitter_ms']:.2f})  over {report['window']} messages")


# ------------------------------------------------------------------------------------------------ commands
@dataclass
class Decoded:
    topic: Topic
    message: object = None
    error: str = ""
    payload_bytes: int = 0


class Listener:
    """Subscribes to the topics a key pattern selects and decodes what arrives; ``on_message(decoded, t_s)`` is
    called in zenoh's thread, one message at a time."""

    def __init__(self, session, pattern: str, keys: Keys, on_message) -> None:
        self.topics = {t.key: t for t in matching(pattern, keys)}
        self.undecodable = 0
        self._lock = threading.Lock()
        self._on_message = on_message
        self._subscribers = [session.declare_subscriber(key, self._on_sample) for key in self.topics]

    def _on_sample(self, sample) -> None:
        now = time.monotonic()
        key = str(sample.key_expr)
        topic = self.topics.get(key) or topic_of(key)
        payload = sample.payload.to_bytes()
        decoded = Decoded(topic, payload_bytes=len(payload))
        try:
            decoded.message = m.decode(payload, topic.message_type)
        except m.ProtocolError as exc:
            decoded.error = str(exc)
        with self._lock:
            if decoded.error:
                self.undecodable += 1
            self._on_message(decoded, now)

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()


def _run(until_s: Optional[float], done: threading.Event, tick=None, tick_s: float = 1.0) -> None:
    """Until ``done``, ``until_s`` seconds or Ctrl-C; ``tick()`` every ``tick_s``."""
    start = time.monotonic()
    next_tick = start + tick_s
    try:
        while not done.is_set():
            now = time.monotonic()
            if until_s is not None and now - start >= until_s:
                return
            if tick is not None and now >= next_tick:
                tick()
                next_tick += tick_s
            done.wait(0.05)
    except KeyboardInterrupt:
        return


def echo(session, keys: Keys, pattern: str, as_json_lines: bool = False, count: Optional[int] = None,
         seconds: Optional[float] = None, out=sys.stdout, err=sys.stderr) -> int:
    """Print each message on the keys ``pattern`` selects; 0, or 1 when a payload did not decode."""
    done, printed = threading.Event(), [0]
    several = None

    def on_message(decoded: Decoded, _t: float) -> None:
        if done.is_set():
            return
        prefix = f"{decoded.topic.key}: " if several else ""
        if decoded.error:
            print(f"{decoded.topic.key}: undecodable {decoded.topic.message_type.__name__} payload "
                  f"({decoded.payload_bytes} bytes): {decoded.error}", file=err, flush=True)
            return
        if as_json_lines:
            line = as_json(decoded.message)
            if several:
                line = json.dumps({"key": decoded.topic.key, "message": json.loads(line)}, separators=(",", ":"))
            print(line, file=out, flush=True)
        else:
            print(prefix + summary(decoded.message), file=out, flush=True)
        printed[0] += 1
        if count is not None and printed[0] >= count:
            done.set()

    listener = Listener(session, pattern, keys, on_message)
    several = len(listener.topics) > 1
    try:
        _run(seconds, done)
    finally:
        done.set()
        listener.close()
    return 1 if listener.undecodable else 0


def hz(session, keys: Keys, pattern: str, seconds: Optional[float] = None, window: int = 1000,
       as_json_lines: bool = False, out=sys.stdout) -> dict:
    """Print each selected key's rate every second (and at the end); the last reports, by key."""
    stats: dict[str, RateStats] = {}

    def on_message(decoded: Decoded, t: float) -> None:
        stats.setdefault(decoded.topic.key, RateStats(window)).add(t)

    def show() -> dict:
        reports = {key: s.report() for key, s in sorted(stats.items())}
        for key, report in reports.items():
            print(json.dumps({"key": key, **(report or {})}) if as_json_lines else rate_line(key, report),
                  file=out, flush=True)
        if not reports:
            print(f"no messages yet on {resolve(pattern, keys)}", file=out, flush=True)
        return reports

    listener = Listener(session, pattern, keys, on_message)
    try:
        _run(seconds, threading.Event(), tick=show)
    finally:
        listener.close()
    return show()


def discover(session, keys: Keys, seconds: float = 2.0) -> list[dict]:
    """What is published under the robot's prefix during ``seconds``: per key its type (or that it is no topic of
    the stack), messages, rate, bytes, and how many did not decode; with the services alive."""
    seen: dict[str, dict] = {}
    lock = threading.Lock()

    def on_sample(sample) -> None:
        now = time.monotonic()
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        with lock:
            entry = seen.get(key)
            if entry is None:
                try:
                    topic = topic_of(key)
                except UnknownTopic:
                    topic = None
                entry = seen[key] = {"key": key, "type": topic.message_type.__name__ if topic else None,
                                     "publisher": topic.publisher if topic else None, "stats": RateStats(),
                                     "bytes": 0, "undecodable": 0, "topic": topic}
            entry["stats"].add(now)
            entry["bytes"] += len(payload)
            if entry["topic"] is not None:
                try:
                    m.decode(payload, entry["topic"].message_type)
                except m.ProtocolError:
                    entry["undecodable"] += 1

    subscriber = session.declare_subscriber(f"{keys.prefix}/**", on_sample)
    try:
        time.sleep(seconds)
    finally:
        subscriber.undeclare()
    rows = []
    with lock:
        for key, entry in sorted(seen.items()):
            report = entry["stats"].report()
            rows.append({"key": key, "type": entry["type"], "publisher": entry["publisher"],
                         "messages": entry["stats"].count,
                         "rate_hz": round(report["rate_hz"], 1) if report else None,
                         "bytes_per_message": entry["bytes"] // max(1, entry["stats"].count),
                         "undecodable": entry["undecodable"]})
    return rows


def keys_table(rows: list[dict], services: list[str], seconds: float) -> str:
    lines = [f"services alive: {', '.join(services) if services else 'none'}",
             f"published in the last {seconds:g} s:"]
    if not rows:
        lines.append("  nothing (is the stack up? `mfvs status`)")
    width = max([len(r["key"]) for r in rows] + [3])
    for r in rows:
        kind = r["type"] or "(no topic of the stack)"
        rate = f"{r['rate_hz']:.1f} Hz" if r["rate_hz"] is not None else "once"
        bad = f"  {r['undecodable']} undecodable" if r["undecodable"] else ""
        lines.append(f"  {r['key']:<{width}}  {kind:<18} {rate:>9}  {r['bytes_per_message']} B{bad}")
    return "\n".join(lines)
