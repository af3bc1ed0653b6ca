"""The grasp detector: on the emulated hand's own fingers (a cup, a box whose turning in the grip snaps the fingers,
nothing, a slippery box), and on what it must refuse or wait for."""
import math

import numpy as np
import pytest

from protocol import messages as m
from protocol.messages import GraspVerdict
from services.model.arm import load_arm
from services.model.grasp import GraspDetector, GraspThresholds
from tests.grasping import box, close_lift_hold, cup

ARM = load_arm("j2s7s300")
HAND = ARM.hand


def watch(obj, centre_z, hold_s=2.0):
    """Every cycle's verdict (time, verdict), when the hand first touched the object, whether it touched it (time,
    bool), and where the object was in the hand (time, position in the end effector's frame)."""
    detector = GraspDetector(HAND)
    seen = {"verdicts": [], "contact_s": None, "in_hand": [], "touching": []}
    clock = {"t": 0.0, "start": None}
    names = {f"{n}_{part}" for n in HAND.finger_names for part in ("proximal_link", "distal_link")} | {"palm"}

    def each(sim, reading, targets):
        clock["t"] += 0.002
        t = clock["t"]
        state = m.FingerState(position=reading.fingers.position.tolist(), velocity=reading.fingers.velocity.tolist(),
                              current_a=reading.fingers.current_a.tolist(), target=np.asarray(targets).tolist())
        seen["verdicts"].append((t, detector.observe(t, state)))
        if obj is None:
            return
        touching = False
        for c in sim.data.contact[:sim.data.ncon]:
            pair = {sim.model.geom(c.geom1).name, sim.model.geom(c.geom2).name}
            touching = touching or bool(pair & names and f"object_{obj.name}_shape" in pair)
        if touching and seen["contact_s"] is None:
            seen["contact_s"] = t
        seen["touching"].append((t, touching))
        T = np.linalg.inv(sim.ee_pose()) @ sim.object_pose(obj.name)
        seen["in_hand"].append((t, T[:3, 3].copy()))

    out = close_lift_hold(ARM, obj, centre_z, each=each, hold_s=hold_s)
    return out, seen


def first(verdicts, verdict, after_s=0.0):
    return next((t for t, v in verdicts if v is verdict and t >= after_s), None)


@pytest.mark.parametrize("name, obj, centre_z", [("cup", cup(), 0.0475), ("box", box(), 0.05)])
def test_a_grasp_is_seen_within_half_a_second_of_the_contact_and_holds_through_the_lift_and_the_hold(name, obj,
                                                                                                     centre_z):
    out, seen = watch(obj, centre_z, hold_s=5.0)
    assert out["lifted_m"] > 0.095
    grasped = first(seen["verdicts"], GraspVerdict.GRASPED)
    assert grasped is not None and 0.0 < grasped - seen["contact_s"] <= 0.5
    after = [v for t, v in seen["verdicts"] if t >= grasped]
    assert set(after) == {GraspVerdict.GRASPED}  # no flicker: not through the box's snap, the lift or 5 s held


def test_closed_on_nothing_the_hand_is_empty_within_half_a_second_of_the_fingers_stopping():
    out, seen = watch(None, 0.05)
    verdicts = seen["verdicts"]
    empty = first(verdicts, GraspVerdict.EMPTY)
    assert empty is not None and GraspVerdict.GRASPED not in {v for _, v in verdicts}
    closes_s = 0.3 + HAND.closing_time_s  # the fingers asked to close at 0.3 s, at their top speed
    assert closes_s < empty <= closes_s + 0.5


def test_a_slippery_box_is_grasped_on_the_table_and_seen_slipping_within_half_a_second_of_leaving_the_hand():
    """The fingers alone cannot see a box sliding along their pads (nothing they measure changes); they see it as
    it leaves them, and the verdict comes within half a second of that."""
    out, seen = watch(box(friction=0.1), 0.05)
    assert out["lifted_m"] < 0.02
    grasped = first(seen["verdicts"], GraspVerdict.GRASPED)
    assert grasped is not None and seen["contact_s"] < grasped
    left = next(t for t, touching in seen["touching"] if t > grasped and not touching)
    slipping = first(seen["verdicts"], GraspVerdict.SLIPPING)
    assert slipping is not None and grasped < slipping <= left + 0.5


def state(position, current=0.0, target=None):
    n = HAND.n_fingers
    position = [position] * n if np.isscalar(position) else list(position)
    return m.FingerState(position=position, velocity=[0.0] * n,
                         current_a=[current] * n if np.isscalar(current) else list(current),
                         target=[HAND.closed_angle] * n if target is None else [target] * n)


def test_nothing_is_called_still_before_a_whole_window_and_an_open_hand_at_its_target_has_reached_it():
    detector = GraspDetector(HAND)
    assert detector.observe(0.0, state(0.0, target=0.0)) is GraspVerdict.MOVING
    assert detector.observe(0.1, state(0.0, target=0.0)) is GraspVerdict.MOVING
    assert detector.observe(0.2, state(0.0, target=0.0)) is GraspVerdict.REACHED
    assert detector.since_s == 0.2


def test_one_finger_pushing_is_not_a_grasp_and_a_grasp_lost_is_slipping_not_empty():
    detector = GraspDetector(HAND)
    for t in (0.0, 0.1, 0.2):
        verdict = detector.observe(t, state([0.7, HAND.closed_angle, HAND.closed_angle], current=[1.0, 0.0, 0.0]))
    assert verdict is GraspVerdict.EMPTY
    detector.reset()
    for t in (0.0, 0.1, 0.2):
        verdict = detector.observe(t, state(0.7, current=1.0))
    assert verdict is GraspVerdict.GRASPED
    creep = 0.7 + math.radians(4.0)
    assert detector.observe(0.3, state(creep, current=1.0)) is GraspVerdict.GRASPED
    assert detector.observe(0.4, state(0.7 + math.radians(6.0), current=1.0)) is GraspVerdict.SLIPPING
    detector.reset()
    for t in (0.0, 0.1, 0.2):
        detector.observe(t, state(0.7, current=1.0))
    assert detector.observe(0.3, state(0.7, current=[1.0, 0.1, 0.1])) is GraspVerdict.SLIPPING


def test_the_detector_refuses_a_hand_it_was_not_made_for_and_thresholds_that_mean_nothing():
    with pytest.raises(ValueError, match="3 fingers, the state 2"):
        GraspDetector(HAND).observe(0.0, m.FingerState(position=[0.0] * 2, velocity=[0.0] * 2, current_a=[0.0] * 2,
                                                       target=[0.0] * 2))
    for bad in ({"window_s": 0.0}, {"current_share": float("nan")}, {"stall_share": 1.5}):
        with pytest.raises(ValueError):
            GraspThresholds(**bad)
