"""Recent robot states by stamp, for the services that combine a camera frame with the robot's state (the
controller, safety). In lockstep an input derived from a frame must be used with the state of the frame's tick
(the robot publishes it at that tick, stamped with the frame's capture stamp); zenoh orders nothing between keys,
so the state may arrive after the input: the input then waits for it (:meth:`StateHistory.for_input`)."""
from __future__ import annotations

import collections
from typing import Generic, Optional, TypeVar

S = TypeVar("S")


class StateHistory(Generic[S]):
    def __init__(self, size: int = 64) -> None:
        self._states: collections.OrderedDict[int, S] = collections.OrderedDict()
        self._size = size
        self.latest: Optional[S] = None
        self.latest_stamp = -1

    def add(self, stamp_ns: int, state: S) -> None:
        self._states[stamp_ns] = state
        while len(self._states) > self._size:
            self._states.popitem(last=False)
        if stamp_ns >= self.latest_stamp:
            self.latest, self.latest_stamp = state, stamp_ns

    def at_capture(self, source_stamp_ns: int) -> Optional[S]:
        """Realtime: the state the arm was in when the frame captured at ``source_stamp_ns`` was taken (the newest
        at or before it), or None when every state kept is later."""
        before = [stamp for stamp in self._states if stamp <= source_stamp_ns]
        return self._states[max(before)] if before else None

    def for_input(self, source_stamp_ns: int) -> tuple[Optional[S], bool]:
        """(state, ready) for an input derived from the frame captured at ``source_stamp_ns``: the state of that
        tick when it is here; not ready while no state of that tick or later has arrived; the first later one
        when that tick's state was lost."""
        state = self._states.get(source_stamp_ns)
        if state is not None:
            return state, True
        if self.latest_stamp < source_stamp_ns:
            return None, False
        later = [stamp for stamp in self._states if stamp > source_stamp_ns]
        return (self._states[min(later)] if later else self.latest), True
