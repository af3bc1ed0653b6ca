"""The person's stick on the console's page (the on-screen stick, or a gamepad read by the browser's Gamepad API) as
jog requests (protocol.messages.Jog on ``Keys.desired_jog``), with no zenoh and no web server in it: what a page's
snapshot must be (:func:`check_snapshot`), which page holds the stick, and what goes out at each slot of the steady
stream (:class:`ConsoleJog`: services/jog/mapping.py's StickMapper, services/jog/sender.py's JogStamper).

The page sends a snapshot (its three axes in [-1, 1], the dead-man, the mode, the speed level, which input, the
gamepad's ``connected`` and ``timestamp``, the page's own sequence number) every 20 ms while its stick is held or a
gamepad is connected, and one released snapshot when neither is. The console sends one request per slot at
``rate_hz`` while the newest snapshot is fresh. Freshness, our rules (docs/console.md):

* a snapshot older than ``page_budget_s`` (0.1 s, safety's own command budget: a stalled WebSocket, a hidden tab
  whose timers the browser slows to once a second) is never acted on: the console sends **one released request**
  (the dead-man let go: safety stops the arm at once if the stick is in control, sooner than its staleness would),
  then nothing until the page speaks again;
* the device is *heard* (``header.source_stamp_ns``) when a snapshot arrives, on the console's clock (the page's
  may be another device's): the on-screen stick always, a gamepad only while the browser says it is ``connected``.
  The Gamepad API moves a pad's ``timestamp`` only when the pad's state changes, so a pad held still keeps its
  timestamp: a frozen timestamp alone is no sign of a lost pad, and it is not used for freshness (it is checked and
  shown only). A pad the browser no longer calls connected is released and not heard, so safety's device budget
  (250 ms) stops it even if a page kept on sending;
* the page that held the dead-man first holds the stick until it lets go or goes silent: another page's snapshot
  meanwhile is refused (``jog_busy``); a page whose WebSocket closes lets go at once (a released request).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Optional

import msgspec

from protocol.messages import JOG_SPEED_LEVELS, Jog, JogMode
from services.jog.config import check_stream
from services.jog.mapping import JogMapping, JogMotion, StickInput, StickMapper
from services.jog.sender import JogStamper
from services.runtime.config import ConfigStruct

#: the console's requests name this source (safety declares the jog source; each device counts its own sequence)
CONSOLE_JOG_SOURCE = "jog/console"
#: the inputs a page's snapshot may say it comes from
INPUTS = ("stick", "gamepad")


class ConsoleJogConfig(ConfigStruct):
    """The console's stick: how it streams and maps (the mapping is `mfvs jog`'s, services/jog/jog.yaml)."""

    source: str = CONSOLE_JOG_SOURCE
    #: requests per second: 50, as `mfvs jog` (twice what safety's 100 ms command budget needs): our choice
    rate_hz: float = 50.0
    #: a page's snapshot older than this is not acted on (one released request goes out): 0.1 s, safety's own
    #: command budget (services/safety/checks.py command_budget_s): our choice to match it
    page_budget_s: float = 0.1
    #: the jog identity's zenoh client config (behind authority only it may put on jog/request); none: the
    #: console's own session (which works without access control)
    zenoh_config: Optional[str] = None
    mapping: JogMapping = msgspec.field(default_factory=JogMapping)

    def __post_init__(self) -> None:
        check_stream(self.source, self.rate_hz, "jog.")
        if not (math.isfinite(self.page_budget_s) and 0.02 <= self.page_budget_s <= 0.1):
            raise ValueError("jog.page_budget_s must be within 0.02..0.1 s (safety's command budget)")


class GamepadState(msgspec.Struct, forbid_unknown_fields=True):
    """What the browser says of the pad the page reads (the Gamepad API's fields)."""

    connected: bool
    #: the pad's ``timestamp`` (ms, the page's clock): moves only when the pad's state changes
    timestamp: Optional[float] = None
    id: Annotated[str, msgspec.Meta(max_length=128)] = ""
    mapping: Annotated[str, msgspec.Meta(max_length=32)] = ""


class JogSnapshot(msgspec.Struct, tag="jog", tag_field="type", forbid_unknown_fields=True):
    """The page's stick at one moment. Types are checked when it is decoded; values by :func:`check_snapshot`
    (a NaN comes as null: JSON has none, and the page's JSON.stringify writes NaN as null)."""

    seq: Annotated[int, msgspec.Meta(ge=0, le=2**53)]
    input: Annotated[str, msgspec.Meta(max_length=16)]
    axes: Annotated[list[Optional[float]], msgspec.Meta(max_length=8)]
    deadman: bool
    mode: Annotated[str, msgspec.Meta(max_length=32)]
    speed_level: int
    gamepad: Optional[GamepadState] = None


class JogRefused(Exception):
    """A snapshot the console does not take: ``reason`` names its counter (``refused.<reason>``)."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason
        self.message = message


def check_snapshot(snapshot: JogSnapshot) -> StickInput:
    """The stick a snapshot says, or JogRefused: ``jog_malformed`` (not three axes, an input the console does not
    know), ``jog_not_finite`` (an axis or the pad's timestamp NaN, null or infinite), ``jog_range`` (an axis beyond
    [-1, 1], a speed level not 1..3), ``jog_mode`` (a mode that is not translation, wrist or fingers). A gamepad the
    browser does not call connected is released, whatever its buttons say."""
    if snapshot.input not in INPUTS:
        raise JogRefused("jog_malformed", f"input {snapshot.input!r}: a snapshot comes from one of {', '.join(INPUTS)}")
    if len(snapshot.axes) != 3:
        raise JogRefused("jog_malformed", f"{len(snapshot.axes)} axes: the stick has three")
    for i, axis in enumerate(snapshot.axes):
        if axis is None or not math.isfinite(axis):
            raise JogRefused("jog_not_finite", f"axis {i} is not a number ({axis}): nothing moves on it")
        if not -1.0 <= axis <= 1.0:
            raise JogRefused("jog_range", f"axis {i} is {axis:g}: a stick's axes are within -1..1")
    try:
        mode = JogMode(snapshot.mode)
    except ValueError:
        raise JogRefused("jog_mode", f"mode {snapshot.mode!r}: the stick's modes are "
                                     f"{', '.join(m.value for m in JogMode)}") from None
    if snapshot.speed_level not in JOG_SPEED_LEVELS:
        raise JogRefused("jog_range", f"speed level {snapshot.speed_level}: the levels are "
                                      f"{JOG_SPEED_LEVELS[0]}..{JOG_SPEED_LEVELS[-1]}")
    pad = snapshot.gamepad
    if pad is not None and pad.timestamp is not None and not (math.isfinite(pad.timestamp) and pad.timestamp >= 0):
        raise JogRefused("jog_not_finite", f"the gamepad's timestamp is {pad.timestamp}: not a time")
    if snapshot.input == "gamepad" and pad is None:
        raise JogRefused("jog_malformed", "a gamepad's snapshot says nothing of the pad (its gamepad field)")
    deadman = snapshot.deadman and (snapshot.input == "stick" or pad.connected)
    return StickInput(axes=tuple(float(a) for a in snapshot.axes), mode=mode, speed_level=snapshot.speed_level,
                      deadman=deadman)


@dataclass
class _Taken:
    page: int
    stick: StickInput
    input: str
    received_ns: int
    heard: bool
    gamepad: Optional[GamepadState] = None


@dataclass
class JogCounts:
    taken: int = 0
    sent: int = 0
    #: the stream went silent on a stale snapshot (one released request each time)
    stale: int = 0
    released_on_close: int = 0


class ConsoleJog:
    """The console's stick: the pages' snapshots in, one request per slot out (:meth:`tick`). Not thread-safe:
    the service calls it under its lock. Times are the console's wall clock (ns), given with each call.

    ``enabled`` False (``why`` says why: behind authority with no jog identity's config): every snapshot is refused
    as ``jog_disabled`` and nothing is ever sent."""

    def __init__(self, config: ConsoleJogConfig, enabled: bool = True, why: str = "") -> None:
        self.config = config
        self.enabled, self.why = enabled, why
        self.mapper = StickMapper(config.mapping)
        self.stamper = JogStamper(config.source)
        self.budget_ns = int(config.page_budget_s * 1e9)
        self.latest: Optional[_Taken] = None
        #: the last request sent (None before the first)
        self.last: Optional[Jog] = None
        #: the stream is silent until the next snapshot (the stale one was answered by a release)
        self._silent = True
        self._page_seq: dict[int, int] = {}
        self.counts = JogCounts()

    # ------------------------------------------------------------------ in
    def offer(self, page: int, snapshot: JogSnapshot, received_ns: int) -> StickInput:
        """A page's snapshot, received at ``received_ns``: taken (the stick it says), or JogRefused."""
        if not self.enabled:
            raise JogRefused("jog_disabled", self.why or "the console's stick is off")
        last_seq = self._page_seq.get(page)
        if last_seq is not None and snapshot.seq <= last_seq:
            raise JogRefused("jog_seq", f"snapshot {snapshot.seq} after {last_seq}: a page's snapshots rise")
        stick = check_snapshot(snapshot)
        self._page_seq[page] = snapshot.seq
        held = self.latest
        if held is not None and held.page != page and self.fresh(received_ns) and held.stick.deadman:
            raise JogRefused("jog_busy", "another page holds the stick (its dead-man is held): wait until it lets go")
        heard = snapshot.input == "stick" or (snapshot.gamepad is not None and snapshot.gamepad.connected)
        self.latest = _Taken(page, stick, snapshot.input, received_ns, heard, snapshot.gamepad)
        self._silent = False
        self.counts.taken += 1
        return stick

    def page_gone(self, page: int) -> None:
        """A page's stream closed: if it held the stick, the next slot sends a release (then silence)."""
        self._page_seq.pop(page, None)
        if self.latest is not None and self.latest.page == page:
            self.latest.received_ns = -(2**62)  # stale from now on: never acted on again
            self.counts.released_on_close += 1

    def fresh(self, now_ns: int) -> bool:
        return self.latest is not None and now_ns - self.latest.received_ns <= self.budget_ns

    # ------------------------------------------------------------------ out
    def tick(self, now_ns: int) -> Optional[Jog]:
        """The request for the slot at ``now_ns``, or None (nothing to send: no page spoke, or the stale snapshot
        was answered by a release already)."""
        taken = self.latest
        if taken is None or not self.enabled or self._silent:
            return None
        if not self.fresh(now_ns):  # never keep moving on an old snapshot: let go, once, then say nothing
            self._silent = True
            self.counts.stale += 1
            stick = taken.stick
            self.mapper(StickInput(stick.axes, stick.mode, stick.speed_level, False), now_ns * 1e-9)
            return self._send(JogMotion(stick.mode, stick.speed_level, False), now_ns, heard=False)
        motion = self.mapper(taken.stick, now_ns * 1e-9)
        return self._send(motion, now_ns, heard=taken.heard, heard_ns=taken.received_ns)

    def release(self, now_ns: int) -> Optional[Jog]:
        """A released request now if the last one held the dead-man (the console stopping), else None."""
        if self.last is None or not self.last.deadman:
            return None
        self._silent = True
        return self._send(JogMotion(self.last.mode, self.last.speed_level, False), now_ns, heard=False)

    def _send(self, motion: JogMotion, now_ns: int, heard: bool, heard_ns: Optional[int] = None) -> Jog:
        self.last = self.stamper.message(motion, heard, now_ns=now_ns, heard_ns=heard_ns)
        self.counts.sent += 1
        return self.last

    # ------------------------------------------------------------------ shown
    def status(self, now_ns: int) -> dict:
        """What the page shows of the stick: whether it is on (and why not), which page holds it and with what."""
        taken, last = self.latest, self.last
        return {
            "enabled": self.enabled, "why": self.why, "source": self.config.source,
            "sending": self.enabled and not self._silent and taken is not None,
            "fresh": self.fresh(now_ns),
            "page": None if taken is None else taken.page,
            "input": None if taken is None else taken.input,
            "gamepad": None if taken is None or taken.gamepad is None else msgspec.to_builtins(taken.gamepad),
            "mode": None if last is None else last.mode.value,
            "speed_level": None if last is None else last.speed_level,
            "deadman": bool(last is not None and last.deadman and self.fresh(now_ns)),
            "sent": self.counts.sent, "stale": self.counts.stale,
        }
