"""Faults injected into a service's outputs: messages dropped at a rate, or held back a while, per key.

A test or a soak makes a link lossy or slow without kernel support (no netem here): it writes a fault plan to the
file a service names in ``faults_file`` (any service: ``--set faults_file=PATH``), and the service's publishers
drop or delay what they send on the keys the plan names, until the file changes again or goes away. The plan::

    seed: 7                       # the drops' random draws (the same plan and messages drop the same ones)
    faults:
      - key: mfvs/jaco/robot/command     # a key expression: mfvs/*/robot/command, mfvs/jaco/** ...
        drop: 1.0                        # the share of messages dropped, 0-1
      - key: mfvs/jaco/robot/state
        delay_ms: 300                    # every message held back this long (order kept)

The first fault whose key expression includes a message's key applies. A file that does not parse is refused with
a clear error and a counter (``faults.plan_rejected``), and the plan in force stays; a missing file is no faults.
What a plan does is counted per output stream (``faults.dropped.<stream>``, ``faults.delayed.<stream>``) and shows
in the service's health. Never configure it on a robot in service: it exists to prove the stack safe when links
misbehave.

:func:`fault_for` and :func:`decide` are the rules; :class:`FaultInjector` reads the file and keeps time.
"""
from __future__ import annotations

import heapq
import itertools
import os
import random
import threading
import time
from pathlib import Path
from typing import Annotated, Callable

import msgspec
import yaml
import zenoh

from services.runtime.config import ConfigError, ConfigStruct, load_config
from services.runtime.threads import start_thread

#: how often a publishing service looks at its fault file (a stat, at most this often)
RELOAD_PERIOD_S = 0.1


class KeyFault(ConfigStruct):
    #: a zenoh key expression: the messages it includes suffer this fault
    key: str
    #: the share of messages dropped (0: none, 1: every one)
    drop: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)] = 0.0
    #: how long every message that is not dropped is held back before it goes out
    delay_ms: Annotated[float, msgspec.Meta(ge=0.0, le=60_000.0)] = 0.0

    def __post_init__(self) -> None:
        try:
            zenoh.KeyExpr(self.key)
        except Exception as exc:  # zenoh's own error type, with its reason
            raise ValueError(f"not a key expression: {self.key!r} ({exc})") from None


class FaultPlan(ConfigStruct):
    seed: int = 0
    faults: list[KeyFault] = []


NO_FAULTS = FaultPlan()


def fault_for(plan: FaultPlan, key: str) -> KeyFault | None:
    """The fault that applies to a message on ``key``: the plan's first whose key expression includes it."""
    for fault in plan.faults:
        if zenoh.KeyExpr(fault.key).includes(zenoh.KeyExpr(key)):
            return fault
    return None


def decide(fault: KeyFault | None, draw: float) -> tuple[bool, int]:
    """(dropped, delay in ns) for one message under ``fault``, given a uniform ``draw`` in [0, 1)."""
    if fault is None:
        return False, 0
    if draw < fault.drop:
        return True, 0
    return False, int(fault.delay_ms * 1e6)


def read_fault_plan(path: str | os.PathLike) -> FaultPlan:
    """The plan in a YAML file; :class:`ConfigError` naming the bad key when it is not one."""
    return load_config(path, FaultPlan)


def write_fault_plan(path: str | os.PathLike, faults: list[dict], seed: int = 0) -> None:
    """Put a plan in force for the service that reads ``path``: written whole (a rename), so the service never
    reads half a plan; ``faults`` as :class:`KeyFault` fields. Checked first: a plan the service would refuse
    raises here instead."""
    plan = msgspec.convert({"seed": seed, "faults": faults}, FaultPlan)
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(yaml.safe_dump(msgspec.to_builtins(plan), sort_keys=False))
    tmp.replace(path)


class FaultInjector:
    """A service's fault plan in force: rereads ``path`` when it changes (checked at most every
    :data:`RELOAD_PERIOD_S`), and sends, drops or holds back each output message as the plan says. Held-back
    messages go out from a thread of their own, in the order they were put on each key."""

    def __init__(self, path: str | os.PathLike, counters, log, name: str = "faults") -> None:
        self.path = str(path)
        self._counters = counters
        self._log = log
        self._name = name
        self._plan = NO_FAULTS
        self._rng = random.Random(0)
        self._seen: tuple[int, int] | None = None
        self._checked = 0.0
        self._lock = threading.Lock()
        self._queue: list[tuple[int, int, str, Callable[[bytes], object], bytes]] = []
        self._order = itertools.count()
        self._last_due: dict[str, int] = {}
        self._held: dict[str, int] = {}
        self._wake = threading.Condition(self._lock)
        self._closed = False
        self._thread: threading.Thread | None = None
        self._reload(time.monotonic())

    @property
    def plan(self) -> FaultPlan:
        return self._plan

    def _reload(self, now: float) -> None:
        self._checked = now
        try:
            stat = os.stat(self.path)
            seen = (stat.st_mtime_ns, stat.st_size)
        except FileNotFoundError:
            seen = None
        if seen == self._seen:
            return
        self._seen = seen
        if seen is None:
            plan = NO_FAULTS
        else:
            try:
                plan = read_fault_plan(self.path)
            except ConfigError as exc:
                self._counters.inc("faults.plan_rejected")
                self._log.error("fault plan refused, the one in force stays: %s", exc)
                return
        self._plan, self._rng = plan, random.Random(plan.seed)
        self._log.warning("fault plan %s: %s", self.path, [msgspec.structs.asdict(f) for f in plan.faults] or "none")

    def send(self, key: str, stream: str, put: Callable[[bytes], object], payload: bytes) -> bool:
        """Put ``payload`` on ``key`` as the plan says; True when it went out now."""
        with self._lock:
            now = time.monotonic()
            if now - self._checked >= RELOAD_PERIOD_S:
                self._reload(now)
            fault = fault_for(self._plan, key) if self._plan.faults else None
            dropped, delay_ns = decide(fault, self._rng.random() if fault is not None and fault.drop else 1.0)
            if dropped:
                self._counters.inc(f"faults.dropped.{stream}")
                return False
            if not delay_ns and not self._held.get(key):
                # a put outside the lock would let a message overtake one the thread is sending
                put(payload)
                return True
            due = max(time.monotonic_ns() + delay_ns, self._last_due.get(key, 0))
            self._last_due[key] = due
            self._held[key] = self._held.get(key, 0) + 1
            heapq.heappush(self._queue, (due, next(self._order), key, put, payload))
            self._counters.inc(f"faults.delayed.{stream}")
            if self._thread is None:
                self._thread = start_thread(self._release, f"{self._name}-delay")
            self._wake.notify()
            return False

    def _release(self) -> None:
        with self._lock:
            while not self._closed:
                if not self._queue:
                    self._wake.wait()
                    continue
                wait_s = (self._queue[0][0] - time.monotonic_ns()) / 1e9
                if wait_s > 0:
                    self._wake.wait(wait_s)
                    continue
                _, _, key, put, payload = heapq.heappop(self._queue)
                self._held[key] -= 1
                put(payload)

    def close(self) -> None:
        """Stop sending held-back messages (what is still held is dropped with the service)."""
        with self._lock:
            self._closed = True
            self._queue.clear()
            self._held.clear()
            self._wake.notify()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
