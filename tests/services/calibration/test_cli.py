"""`mfvs calibrate ... --simulate --json` as a user runs it: the files the camera service reads, and the figures
against the simulator's truth."""
import json

import numpy as np

from services.camera.calibration import read_camera_in_ee, read_intrinsics
from services.calibration.simulate import CAMERA
from tests.services.cli.test_commands import run


def test_intrinsics_simulate_writes_a_calibration_the_camera_service_reads(tmp_path):
    out = tmp_path / "calibration.yaml"
    done = run("calibrate", "intrinsics", "--simulate", "--views", "10", "--json", "--out", str(out), timeout=300)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["passed"] and report["fx_error_pct"] < 0.5 and report["fy_error_pct"] < 0.5
    assert read_intrinsics(out).fx == report["fx"]


def test_hand_eye_simulate_prints_the_error_against_the_true_mounting(tmp_path):
    out = tmp_path / "hand_eye.yaml"
    done = run("calibrate", "hand-eye", "--simulate", "--poses", "10", "--json", "--out", str(out), timeout=300)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["translation_error_mm"] < 2.0 and report["rotation_error_deg"] < 0.5 and report["passed"]
    written = read_camera_in_ee(out).matrix()
    assert np.linalg.norm(written[:3, 3] - CAMERA.camera_in_ee.matrix()[:3, 3]) < 0.002


def test_what_is_missing_is_said(tmp_path):
    for args, said in [(("intrinsics", "--images", str(tmp_path)), "--out"),
                       (("hand-eye", "--recording", str(tmp_path), "--out", "x.yaml"), "--calibration"),
                       (("intrinsics", "--images", str(tmp_path / "none"), "--out", "x.yaml"), "no folder"),
                       (("intrinsics", "--simulate", "--squares", "7by5"), "--squares")]:
        done = run("calibrate", *args)
        assert done.returncode == 2 and said in done.stderr and "Traceback" not in done.stderr, done.stderr
