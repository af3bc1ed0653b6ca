"""Engage or release safety's latched e-stop over zenoh (``…/safety/estop``) and wait for safety to confirm it in its
status, as `mfvs estop` and the console do. The e-stop is a plain put that a lost sample would lose: it is repeated
until safety's status shows it (or the time runs out)."""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Callable, Optional

from protocol import messages as m
from protocol.keys import Keys
from services.runtime.transport import GuardedPublisher, publisher_options

#: how often an unconfirmed e-stop request is sent again (s)
RESEND_PERIOD_S = 0.1


def confirms(status: m.SafetyStatus, reset: bool) -> bool:
    """Whether safety's ``status`` shows an engage (``reset`` False) or a release (``reset`` True) carried out."""
    return (status.state is m.SafetyState.ESTOP) != reset


class EStopClient:
    """A session's e-stop: its publisher and a subscription to safety's status, declared once (a console keeps them
    for its life, so that an engage goes out at once). Safe to use from several threads; a context manager."""

    def __init__(self, session, keys: Keys) -> None:
        self._keys = keys
        #: safety's recent statuses, each with its number in the order heard
        self._statuses: deque[tuple[int, m.SafetyStatus]] = deque(maxlen=16)
        self._count = 0
        self._heard = threading.Condition()
        self._publisher = GuardedPublisher.declare(session, keys.estop, **publisher_options(keys.estop))
        self._subscriber = session.declare_subscriber(keys.safety_status, self._on_status)

    def _on_status(self, sample) -> None:
        try:
            status = m.decode(sample.payload.to_bytes(), m.SafetyStatus)
        except m.ProtocolError:  # not safety's: nothing to confirm with
            return
        with self._heard:
            self._count += 1
            self._statuses.append((self._count, status))
            self._heard.notify_all()

    def send(self, reset: bool, operator: str, reason: str = "", timeout_s: float = 5.0,
             on_sent: Optional[Callable[[], None]] = None) -> Optional[m.SafetyStatus]:
        """Engage (``reset`` False) or release the e-stop, sent again every RESEND_PERIOD_S until a status of
        safety's heard after the first send confirms it: that status, or None when none did within ``timeout_s``.
        ``on_sent`` is called once the first is on the wire."""
        message = m.encode(m.EStop(header=m.Header(stamp_ns=time.time_ns()), reset=reset, operator=operator,
                                   reason=reason))
        with self._heard:
            since = self._count  # only what safety says after this request counts

        def confirmed() -> list[m.SafetyStatus]:
            return [s for n, s in self._statuses if n > since and confirms(s, reset)]

        deadline = time.monotonic() + timeout_s
        while True:
            self._publisher.put(message)
            if on_sent is not None:
                on_sent()
                on_sent = None
            with self._heard:
                self._heard.wait_for(confirmed, timeout=max(0.0, min(RESEND_PERIOD_S, deadline - time.monotonic())))
                found = confirmed()
            if found:
                return found[-1]
            if time.monotonic() >= deadline:
                return None

    def close(self) -> None:
        for entity in (self._subscriber, self._publisher):
            try:
                entity.undeclare()
            except Exception:  # gone with a closed session
                pass

    def __enter__(self) -> "EStopClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
