"""``mfvs doctor`` (services/commissioning/doctor.py): the host's figures measured, and a verdict that is a function of
them."""
import json
import subprocess
import sys

import pytest

from services.commissioning.doctor import Figures, assess
from tests.helpers import REPO

CAMERA = {"width": 640, "height": 480, "rate_hz": 30.0}


def figures(**changes) -> Figures:
    """The issue's slower host: a 640×480 frame rendered in 6.9 ms, two cores, realtime granted."""
    base = dict(cores=2, cpu_model="test", cpu_mhz=2000.0, memory_available_mb=8000.0, camera=dict(CAMERA),
                render_ms=6.9, detect_ms=2.5, arm_cycle_ms=0.3, encode_ms=3.0, realtime={"granted": True, "why": "granted"})
    return Figures(**{**base, **changes})


def test_on_the_slower_host_rendering_is_named_with_its_measured_figure():
    verdict = assess(figures())
    assert verdict["limiting"]["what"] == "rendering" and verdict["limiting"]["ms"] == 6.9
    assert verdict["limiting"]["share_of_period"] == pytest.approx(6.9 / (1000 / 30), abs=1e-3)
    assert all(profile["holds"] for profile in verdict["profiles"].values()) and not verdict["advice"]


def test_a_frame_that_takes_most_of_its_period_is_what_to_change_and_the_realtime_profiles_will_not_hold():
    verdict = assess(figures(render_ms=20.0))
    assert verdict["limiting"]["what"] == "rendering"
    assert not verdict["profiles"]["sim"]["holds"] and "rendering: 20.00 ms" in verdict["profiles"]["sim"]["why_not"][0]
    assert any("lower the camera's resolution or rate" in advice for advice in verdict["advice"])
    assert any("browser on another computer" in advice for advice in verdict["advice"])
    # at a quarter of the pixels' rate the same host holds
    assert assess(figures(render_ms=20.0, camera={**CAMERA, "rate_hz": 10.0}))["profiles"]["sim"]["holds"]


def test_a_console_slow_to_encode_is_told_apart_from_the_stack_it_watches():
    verdict = assess(figures(encode_ms=20.0))
    assert verdict["console"]["share_of_period"] == pytest.approx(20.0 / (1000 / 30), abs=1e-3)
    assert verdict["profiles"]["sim"]["holds"] and verdict["limiting"]["what"] == "rendering"
    assert not verdict["profiles"]["sim with the console"]["holds"]
    assert "the console's encoding: 20.00 ms" in verdict["profiles"]["sim with the console"]["why_not"][0]
    assert any("console's JPEG of a frame takes 20.0 ms" in advice for advice in verdict["advice"])
    assert assess(figures())["profiles"]["sim with the console"]["holds"]


@pytest.mark.parametrize("changes, advice", [
    ({"realtime": {"granted": False, "why": "refused"}}, "CAP_SYS_NICE"),
    ({"cores": 1, "render_ms": 15.0, "detect_ms": 8.0, "arm_cycle_ms": 0.8}, "one core"),
    ({"arm_cycle_ms": 1.5}, "cannot emulate the arm in realtime"),
    ({"memory_available_mb": 700.0}, "700 MB available"),
    ({"real_arm": {"comm_layer": None, "comm_layer_missing": "no USBCommLayerUbuntu.so in /x", "command_layer": False,
                   "libusb": None, "udev_rule": False, "devices": []}}, "no USBCommLayerUbuntu.so in /x"),
])
def test_each_shortfall_says_what_to_change(changes, advice):
    verdict = assess(figures(**changes))
    assert any(advice in line for line in verdict["advice"]), verdict["advice"]


def test_a_ready_real_arm_side_adds_nothing_to_change():
    ready = {"comm_layer": "/sdk/USBCommLayerUbuntu.so", "comm_layer_missing": "", "command_layer": True,
             "libusb": "libusb-1.0.so.0", "udev_rule": True, "devices": ["1-1"]}
    assert assess(figures(real_arm=ready))["advice"] == []


def test_mfvs_doctor_measures_this_host_and_prints_one_json_object():
    done = subprocess.run([sys.executable, "-m", "services.cli", "doctor", "--json", "--repeats", "3"], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    output = json.loads(done.stdout)
    found = output["figures"]
    assert found["cores"] > 0 and found["camera"] == CAMERA  # (a CPU quota may allow less than one) and found["realtime"]["why"]
    assert found["render_ms"] > 0 and found["detect_ms"] > 0 and found["arm_cycle_ms"] > 0 and found["encode_ms"] > 0
    assert output["limiting"]["what"] in output["parts"]
    assert set(output["profiles"]) == {"sim", "gateway", "sim with the console"}
    for bad in (["--repeats", "0"], ["--arm", "j2x9"]):
        refused = subprocess.run([sys.executable, "-m", "services.cli", "doctor", *bad], cwd=REPO,
                                 capture_output=True, text=True, timeout=60)
        assert refused.returncode == 2 and "mfvs doctor:" in refused.stderr, refused.stderr


def test_a_cgroups_cpu_quota_counts_as_the_cores_it_allows(tmp_path):
    from services.commissioning.doctor import cpu_quota_cores

    v1 = tmp_path / "v1"
    (v1 / "cpu" / "box").mkdir(parents=True)
    (v1 / "cpu" / "box" / "cpu.cfs_quota_us").write_text("40000\n")
    (v1 / "cpu" / "box" / "cpu.cfs_period_us").write_text("100000\n")
    (tmp_path / "cgroup.v1").write_text("4:memory:/x\n1:cpu:/box\n0::/\n")
    assert cpu_quota_cores(str(tmp_path / "cgroup.v1"), str(v1)) == pytest.approx(0.4)
    v2 = tmp_path / "v2"
    (v2 / "box").mkdir(parents=True)
    (v2 / "box" / "cpu.max").write_text("150000 100000\n")
    (tmp_path / "cgroup.v2").write_text("0::/box\n")
    assert cpu_quota_cores(str(tmp_path / "cgroup.v2"), str(v2)) == pytest.approx(1.5)
    (v2 / "box" / "cpu.max").write_text("max 100000\n")
    assert cpu_quota_cores(str(tmp_path / "cgroup.v2"), str(v2)) is None
    assert cpu_quota_cores(str(tmp_path / "absent"), str(v2)) is None
