"""The observe commands' mistakes and absences are one line and exit 2: a key that is no topic (with the closest
one), a file that is no recording, no router where the stack should be."""
import socket
import subprocess
import sys

import pytest

from tests.helpers import REPO


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def mfvs(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "services.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=60)


@pytest.mark.parametrize("args, says", [
    (["echo", "robot/stat"], "did you mean mfvs/jaco/robot/state?"),
    (["hz", "vision/featurs"], "did you mean mfvs/jaco/vision/features?"),
    (["record", "--out", "{tmp}/x.mcap", "--keys", "camera/*", "robot/sate"], "did you mean mfvs/jaco/robot/state?"),
    (["replay", "{tmp}/notes.mcap"], "not a readable MCAP recording"),
    (["echo", "robot/state"], "cannot reach the stack's router"),
])
def test_a_mistake_is_one_line_and_exit_2(tmp_path, args, says):
    (tmp_path / "notes.mcap").write_text("not a recording\n")
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    out = mfvs(*args, "--connect", f"tcp/127.0.0.1:{free_port()}")
    assert out.returncode == 2, out
    assert says in out.stderr and len(out.stderr.strip().splitlines()) == 1 and "Traceback" not in out.stderr
    assert not (tmp_path / "x.mcap").exists()
