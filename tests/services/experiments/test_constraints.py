"""`mfvs experiment constraints` (Muñoz 2018): every constraint type binds in one task, and the sliding-mode law holds
each within its chattering band with exact gradients and with 30 % gradient error (eq. 49)."""
import json
import subprocess

import pytest

from services.experiments.constraints import constraint_figures
from services.experiments.registry import run_experiment
from tests.services.experiments.test_mixed_frame import MFVS, check_shape, shortened

KINDS = {"fov", "occlusion", "joint_range", "joint_speed", "sphere"}


def _assert_every_type_binds_and_holds(output: dict) -> None:
    summary = output["summary"]
    for row in output["runs"]:
        assert set(row["constraints"]) == KINDS, row["label"]
        for kind, figures in row["constraints"].items():
            assert figures["active_s"] > 0, (row["label"], kind)
            assert figures["held"] and figures["max_phi"] <= figures["band"], (row["label"], kind, figures)
    assert summary["held"] and all(summary["every_type_active"].values())
    assert summary["runs_differ"] and summary["law_rate_hz"] == pytest.approx(100.0)


def test_the_figures_of_each_constraint_type():
    """From the law's notes: the largest φ, the median band, held only when every iteration's φ is within that
    iteration's band, the largest σ, and the time active."""
    notes = [{"Ts": 0.01, "max_phi.fov": -0.5, "band.fov": 0.02, "max_sigma.fov": -0.6, "active.fov": 0},
             {"Ts": 0.01, "max_phi.fov": 0.01, "band.fov": 0.02, "max_sigma.fov": -0.1, "active.fov": 1},
             {"Ts": 0.02, "max_phi.fov": 0.03, "band.fov": 0.04, "max_sigma.fov": 0.002, "active.fov": 1}]
    figures = constraint_figures([{"notes": n} for n in notes] + [{"notes": {}}])
    assert figures == {"fov": {"max_phi": 0.03, "band": 0.02, "held": True, "max_sigma": 0.002, "active_s": 0.03}}
    notes[1]["max_phi.fov"] = 0.021  # beyond its own sample's band
    assert not constraint_figures([{"notes": n} for n in notes])["fov"]["held"]


def test_every_constraint_type_binds_and_holds_in_the_first_eleven_seconds(tmp_path):
    """The default test run's check: the shipped case, cut at 1100 iterations (11 s at 100 Hz), in which every
    type has bound in both runs."""
    path = shortened("constraints.yaml", tmp_path, 1100)
    output = run_experiment("constraints", path)
    check_shape(output, "constraints")
    assert [row["gradient_error"] for row in output["runs"]] == [0.0, 0.3]
    _assert_every_type_binds_and_holds(output)


@pytest.mark.slow
def test_mfvs_experiment_constraints_json(tmp_path):
    out = subprocess.run([MFVS, "experiment", "constraints", "--json", "--out", str(tmp_path)], capture_output=True,
                         text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    output = json.loads(out.stdout)
    _assert_every_type_binds_and_holds(output)
    assert all(output["summary"]["completed"].values())
    assert (tmp_path / "constraints.png").exists() and (tmp_path / "constraint_image.png").exists()
    assert "| exact-gradients | fov |" in (tmp_path / "report.md").read_text()
