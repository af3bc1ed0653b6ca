"""Which robot commands the robot node accepts at all, before the DSP sees them: pure rules, no zenoh, no clock of
their own.

A command the robot applies must be fresh (not older than ``max_age_s`` by the robot's clock: a stamp of 0, a
capture replayed later, a link that lags), not from the future beyond ``max_future_s`` (clock skew between
hosts is allowed that much, no more), and in sequence: each sender (the last hop of the command's trace, the
service that published it; ``""`` for a command without a trace) numbers its commands, and a number not above
the last accepted one is a repeat or a replay. A sender's numbering starts again only with a new session of the
sender (its liveliness token appears again: :meth:`CommandAdmission.new_session`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from protocol.messages import Header
from services.runtime.config import ConfigStruct


class AdmissionConfig(ConfigStruct):
    #: a command older than this (robot's clock minus the command's stamp) is stale
    max_age_s: float = 0.2
    #: a command stamped further ahead than this is from the future
    max_future_s: float = 0.05

    def __post_init__(self) -> None:
        if not (self.max_age_s > 0 and self.max_future_s >= 0):
            raise ValueError("admission needs max_age_s > 0 and max_future_s >= 0")


@dataclass(frozen=True)
class Rejection:
    #: ``stale``, ``future`` or ``sequence``
    kind: str
    reason: str


def sender(header: Header) -> str:
    return header.trace[-1].service if header.trace else ""


class CommandAdmission:
    def __init__(self, config: AdmissionConfig | None = None) -> None:
        self.config = config or AdmissionConfig()
        self._last_seq: dict[str, int] = {}

    def admit(self, header: Header, now_ns: int) -> Optional[Rejection]:
        """None when the command may go on to the DSP (and its sequence number is then the sender's last), else
        why not."""
        stale = self.stale(header, now_ns)
        if stale is not None:
            return stale
        age_s = (now_ns - header.stamp_ns) * 1e-9
        if -age_s > self.config.max_future_s:
            return Rejection("future", f"stamped {-age_s * 1e3:.0f} ms ahead of the robot's clock "
                                       f"(at most {self.config.max_future_s * 1e3:.0f})")
        source = sender(header)
        last = self._last_seq.get(source)
        if last is not None and header.seq <= last:
            return Rejection("sequence", f"sequence {header.seq} from {source or 'an unnamed sender'} after {last}: "
                                         "a repeat or a replay")
        self._last_seq[source] = header.seq
        return None

    def stale(self, header: Header, now_ns: int) -> Optional[Rejection]:
        """Why a command is too old to apply at ``now_ns``, or None. Checked on arrival and again at the tick that
        would apply it: a command fresh when it arrived can age past the bound while it waits for its tick."""
        age_s = (now_ns - header.stamp_ns) * 1e-9
        if header.stamp_ns == 0 or age_s > self.config.max_age_s:
            return Rejection("stale", f"stamped {age_s * 1e3:.0f} ms ago (at most {self.config.max_age_s * 1e3:.0f})"
                             if header.stamp_ns else "not stamped")
        return None

    def new_session(self, source: str) -> None:
        """The sender started a new session: its numbering may start again."""
        self._last_seq.pop(source, None)

