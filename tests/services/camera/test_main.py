"""`python -m services.camera`: what it cannot have (a calibration, a source) it says in one line and exits 2,
before joining any network."""
import subprocess
import sys

import pytest

from tests.helpers import REPO

SHIPPED = REPO / "services" / "camera" / "camera.yaml"


@pytest.mark.parametrize("overrides, said", [
    ([], "needs a calibration file"),
    (["--set", "calibration=examples/camera/missing.yaml"], "cannot read"),
    (["--set", "calibration=examples/camera/calibration.yaml", "--set", "source.kind=video",
      "--set", "source.path=nowhere.avi"], "no video file nowhere.avi"),
    (["--set", "calibration=examples/camera/calibration.yaml", "--set", "source.device=/dev/video97"],
     "cannot open camera '/dev/video97'"),
    (["--clock", "lockstep"], "realtime only"),
])
def test_what_the_camera_cannot_have_is_said_in_one_line(overrides, said):
    done = subprocess.run([sys.executable, "-m", "services.camera", "--config", str(SHIPPED),
                           "--connect", "tcp/127.0.0.1:9", *overrides], cwd=REPO, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2 and said in done.stderr and "Traceback" not in done.stderr, done.stderr
