"""``python -m services.torque_controller``: bad input is one line on stderr and exit 2."""
import subprocess
import sys

import pytest

from services.model.arm import arm_names
from tests.helpers import REPO

#: the arms described (services/model/arms): an unknown arm's refusal lists them, whichever there are
KNOWN = ", ".join(arm_names())


@pytest.mark.parametrize("args, message", [
    (["--controller", "pid"], "unknown controller 'pid'; known: jt-pid, null-space"),
    (["--controller", "jt-pid", "--arm", "j2x9"], f"unknown arm 'j2x9'; known: {KNOWN}"),
    (["--controller", "joint-pd", "--duration", "0"], "duration_s must be positive"),
    (["--controller", "joint-pd", "--set", "options.amplitude_deg=90"], "0 <= amplitude_deg <= 45"),
])
def test_bad_input_is_one_line_and_exit_2(args, message):
    done = subprocess.run([sys.executable, "-m", "services.torque_controller", *args], cwd=REPO, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 2
    assert message in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr
