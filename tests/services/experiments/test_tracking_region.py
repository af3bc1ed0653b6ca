"""`mfvs experiment tracking-region` (Nelson 1995): a target moving at 10 cm/s, tracked on two translational axes
without the manipulability term and on four axes with it: the baseline meets a singularity, the full law tracks
several times as far."""
import json
import subprocess

import numpy as np
import pytest

from services.experiments.registry import run_experiment
from services.experiments.tracking_region import beyond_vision
from tests.services.experiments.test_mixed_frame import MFVS, check_shape, shortened
from services.model.arm import load_arm

ARM = load_arm("j2s7s300")


def test_joint_limit_margins_and_the_edge_of_vision():
    lower, upper = ARM.model_limits()
    q = ARM.home.copy()
    limited = np.flatnonzero(np.isfinite(lower))
    q[limited[0]] = lower[limited[0]] + np.radians(2.0)
    assert ARM.limit_margins_deg(q).min() == pytest.approx(2.0)
    assert ARM.limit_margins_deg(np.stack([q, ARM.home])).shape == (2, int(limited.size))
    square = [[-0.1, -0.1], [0.1, -0.1], [0.1, 0.1], [-0.1, 0.1]]
    assert not beyond_vision(square, 615.0)  # 123-px sides, facing the camera
    assert beyond_vision([[x / 5 for x in p] for p in square], 615.0)  # 25-px sides
    assert beyond_vision([[x * 0.4, y] for x, y in square], 615.0)  # foreshortened to 0.4


def test_the_baseline_meets_a_singularity_the_full_law_tracks_to_the_end_of_a_short_path(tmp_path):
    """The default test run's check: the shipped case on a 1.3-m path (400 frames)."""
    path = shortened("tracking_region.yaml", tmp_path, 400)
    output = run_experiment("tracking-region", path)
    check_shape(output, "tracking-region")
    baseline, full = output["runs"]
    assert baseline["failure"] in ("singularity", "joint_limit") and baseline["distance_m"] < 1.0
    assert full["failure"] is None and full["ended"] == "path_end"
    assert full["min_w_prime"] > 10 * baseline["min_w_prime"]
    assert output["summary"]["distance_ratio"] > 2.0


@pytest.mark.slow
def test_mfvs_experiment_tracking_region_json(tmp_path):
    out = subprocess.run([MFVS, "experiment", "tracking-region", "--json", "--out", str(tmp_path)],
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    output = json.loads(out.stdout)
    summary = output["summary"]
    assert summary["distance_ratio"] >= 3.0
    assert summary["failure"]["two-axis"] in ("singularity", "joint_limit")
    assert summary["failure"]["four-axis-avoidance"] in (None, "vision_range")
    for row in output["runs"]:
        assert row["distance_m"] > 0 and row["min_joint_margin_deg"] is not None
    assert (tmp_path / "tracking_paths.png").exists() and (tmp_path / "manipulability.png").exists()
    assert "Ratio of distances" in (tmp_path / "report.md").read_text()
