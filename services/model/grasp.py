"""Whether the hand holds something, from its fingers alone (their positions and currents as the robot reports them,
at its state rate): a pure detector, no clock of its own, no zenoh.

==========  ===============================================================================================
verdict     when
==========  ===============================================================================================
moving      a finger is still moving (or the fingers were never asked to close and have not arrived)
reached     every finger at its target and still, none pushing: an open (or partly closed) hand where it was
            sent, with nothing in it
grasped     closing, at least two fingers stopped short of closed and pushing at least ``current_share`` of
            their full-force current (an object between them)
empty       closing, every finger still at the closed end or pushing on something, and fewer than two of
            them holding: nothing between them
slipping    after a grasp: a finger closed further than ``slip_rad`` past where it stopped on the object, or
            fewer than two fingers pushing any more (the object moved in the hand, or left it)
==========  ===============================================================================================

"Stopped" is judged over ``window_s``: a finger that moved less than ``stall_share`` of the hand's top speed over the
window. Kinova's own finger action server (kinova-ros ``kinova_fingers_action.cpp``) calls a finger stalled after less
than one unit (0.012°) in 0.5 s; ros2_control's GripperActionController after 0.001 rad/s for 1 s. Neither holds for the
emulated fingers: blocked on an object they go on settling as MuJoCo's contacts do (measured on a 0.35 kg cup and a
6 cm box, ``tests/services/model/test_grasp.py``: up to 0.08 rad/s over a window in the first half second of contact,
0.0013 rad of creep in a 5 s hold), so the window's stall speed is a tenth of the closing speed (0.116 rad/s for the
KG-3: a tenth of what a moving finger does, above the settling measured), and once grasped the verdict holds until a
finger has closed ``slip_rad`` further or let go. The current is judged as a share of the hand's full-force current
(the hand file's ``full_force_current_a``): a finger closing freely draws at most 12 % of it (measured), a blocked one
all of it. Measured on both objects, the grasp is seen 0.25-0.27 s after the first contact.

What fingers alone cannot see: an object sliding along flat finger pads changes nothing they measure; it is seen
slipping as it leaves them (a slippery box: within half a second of its last contact).
"""
from __future__ import annotations

import collections
import math
from typing import Optional

import numpy as np

from protocol.messages import FingerState, GraspVerdict
from services.model.arm import HandDescription
from services.runtime.config import ConfigStruct


class GraspThresholds(ConfigStruct):
    """What the detector judges by (see the module's docstring for where each comes from)."""

    #: the window a finger is judged stopped over (s)
    window_s: float = 0.2
    #: stopped: slower than this share of the hand's top speed over the window
    stall_share: float = 0.1
    #: pushing: at least this share of the full-force current (closing)
    current_share: float = 0.5
    #: at its target or at the closed end: within kinova-ros's finger tolerance (64 units, 0.75° on the KG-3)
    reached_units: float = 64.0
    #: slipping: a finger closed this much further than where it stopped on the object (rad, mfvs's choice: 5°, more
    #: than twice the creep measured in a 5 s hold; an object that leaves the hand lets the fingers close fully)
    slip_rad: float = math.radians(5.0)

    def __post_init__(self) -> None:
        for name in ("window_s", "stall_share", "current_share", "reached_units", "slip_rad"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"grasp.{name} must be positive")
        if self.stall_share >= 1.0 or self.current_share > 1.0:
            raise ValueError("grasp.stall_share must be below 1 and grasp.current_share at most 1")


#: at least this many fingers, pushing and stopped short of closed, hold an object (two oppose each other)
HOLDING_FINGERS = 2


class GraspDetector:
    """Fed every state of the fingers (:meth:`observe`), says the verdict; :meth:`reset` for a new grasp. A change
    of the fingers' targets starts the window afresh."""

    def __init__(self, hand: HandDescription, thresholds: Optional[GraspThresholds] = None) -> None:
        self.hand = hand
        self.thresholds = thresholds or GraspThresholds()
        t = self.thresholds
        self._tolerance = float(hand.units_to_angle(t.reached_units))
        self._stall_rad = t.stall_share * hand.max_speed * t.window_s
        self._history: collections.deque = collections.deque()
        self._target: Optional[np.ndarray] = None
        #: where the fingers stopped on the object when the grasp was first seen (None: no grasp yet)
        self.grasped_at: Optional[np.ndarray] = None
        #: the verdict last said, and since when (s, the caller's clock)
        self.verdict = GraspVerdict.MOVING
        self.since_s = 0.0

    def reset(self) -> None:
        self._history.clear()
        self._target = None
        self.grasped_at = None
        self.verdict, self.since_s = GraspVerdict.MOVING, 0.0

    def observe(self, t_s: float, fingers: FingerState) -> GraspVerdict:
        """One state of the fingers at ``t_s`` (s, any clock that only goes forward): the verdict."""
        position = np.asarray(fingers.position, dtype=float)
        if len(position) != self.hand.n_fingers:
            raise ValueError(f"the {self.hand.name} has {self.hand.n_fingers} fingers, the state {len(position)}")
        target = np.asarray(fingers.target, dtype=float)
        if self._target is not None and not np.array_equal(target, self._target):
            self._history.clear()  # the hand sent elsewhere: nothing it did before says where it is going now
        self._target = target
        self._history.append((t_s, position))
        while len(self._history) > 1 and self._history[1][0] <= t_s - self.thresholds.window_s:
            self._history.popleft()
        verdict = self._judge(position, np.asarray(fingers.current_a, dtype=float), target, t_s)
        if verdict is not self.verdict:
            self.verdict, self.since_s = verdict, t_s
        return verdict

    def _judge(self, position: np.ndarray, current: np.ndarray, target: np.ndarray, t_s: float) -> GraspVerdict:
        t = self.thresholds
        pushing = current >= t.current_share * self.hand.full_force_current_a
        short_of_closed = position < self.hand.closed_angle - self._tolerance
        holding = pushing & short_of_closed
        if self.grasped_at is not None:  # after a grasp: it holds until the object moves in the hand or leaves it
            if np.any(position > self.grasped_at + t.slip_rad) or np.count_nonzero(holding) < HOLDING_FINGERS:
                return GraspVerdict.SLIPPING
            return GraspVerdict.GRASPED
        oldest_t, oldest = self._history[0]
        if t_s - oldest_t < t.window_s - 1e-9:  # not seen long enough to call anything stopped
            return GraspVerdict.MOVING
        stopped = np.abs(position - oldest) < self._stall_rad
        closing = np.all(target >= self.hand.closed_angle - self._tolerance)
        if closing and np.count_nonzero(holding & stopped) >= HOLDING_FINGERS and np.all(stopped | holding):
            self.grasped_at = position.copy()
            return GraspVerdict.GRASPED
        if not np.all(stopped):
            return GraspVerdict.MOVING
        if closing and np.all(~short_of_closed | pushing):
            # closing, every finger still at the closed end or on something, fewer than two holding: nothing held
            return GraspVerdict.EMPTY
        if np.all(np.abs(position - target) <= self._tolerance) and not np.any(pushing):
            return GraspVerdict.REACHED
        return GraspVerdict.MOVING
