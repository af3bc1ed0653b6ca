"""A grasp in the emulated arm: the KG-3's fingers (their worm gear included) close on a free object standing on the
table, the arm lifts it, and it stays in the hand; a slippery one does not (the harness: tests/grasping.py)."""
import math

import numpy as np
import pytest

from services.model.arm import load_arm
from services.robot_sim import scene as sc
from tests.grasping import box, close_lift_hold, cup


@pytest.mark.parametrize("arm_name", ["j2s7s300", "j2n6s300"])
def test_the_hand_closes_on_a_cup_and_the_arm_lifts_it_ten_centimetres_and_holds_it(arm_name):
    arm = load_arm(arm_name)
    out = close_lift_hold(arm, cup(), sc.CupShape().height_m / 2)
    assert out["lifted_m"] > 0.095
    assert out["slip_m"] < 0.003
    grip = out["held"][-1].fingers
    # short of closed, each finger pushing at its full force (the current of a blocked finger)
    assert np.all(grip.position < arm.hand.closed_angle - 0.3)
    assert np.all(grip.current_a > 0.9)


def test_the_thumb_alone_on_its_side_is_not_pushed_open_by_the_two_fingers_facing_it():
    """The worm gear holds each finger where it stopped: the thumb (finger 1) against the two others' force."""
    arm = load_arm("j2s7s300")
    out = close_lift_hold(arm, cup(), sc.CupShape().height_m / 2)
    thumb = np.array([r.fingers.position[0] for r in out["closed"]])
    stopped = thumb[int(np.argmax(thumb))]
    assert thumb[-1] > stopped - math.radians(1.0)


def test_a_slippery_box_is_held_on_the_table_and_slips_out_of_the_hand_when_lifted():
    arm = load_arm("j2s7s300")
    out = close_lift_hold(arm, box(friction=0.1), 0.05)
    assert np.all(out["closed"][-1].fingers.position < arm.hand.closed_angle - 0.3)  # it had it on the table
    assert out["lifted_m"] < 0.02
    assert np.all(out["held"][-1].fingers.position > arm.hand.closed_angle - 0.05)  # closed on nothing
