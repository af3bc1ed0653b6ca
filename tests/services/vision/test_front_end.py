import numpy as np
import pytest

from services.vision.front_end import Goal, point_errors


def test_a_goal_gives_each_points_goal_by_id_in_the_order_asked():
    goal = Goal(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]), np.array([0.3, 0.4, 0.5]), "test", ids=[7, 3, 11])
    points, depths = goal.for_ids([11, 7])
    assert points.tolist() == [[2.0, 2.0], [0.0, 0.0]] and depths.tolist() == [0.5, 0.3]
    with pytest.raises(KeyError, match="point id 4 is not in the goal"):
        goal.for_ids([4])


def test_a_goal_needs_one_depth_and_one_unique_id_per_point():
    with pytest.raises(ValueError, match="one depth and one id per point"):
        Goal(np.zeros((3, 2)), np.ones(2), "test")
    with pytest.raises(ValueError, match="unique"):
        Goal(np.zeros((2, 2)), np.ones(2), "test", ids=[5, 5])


def test_point_errors_of_a_tag_keep_sensors_2022s_norm():
    points, goal = np.full((4, 2), 0.1), np.zeros((4, 2))
    e, norm, rms = point_errors(points, goal, np.ones(4))
    assert np.allclose(e, 0.1) and norm == pytest.approx(np.sqrt(8) * 0.1) and rms == norm / 2
