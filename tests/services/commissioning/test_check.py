"""`mfvs check arm` as a user runs it, on the emulated arm: it passes on the arm that is its description, fails and
names the joint on one with a joint turning the other way, and moves nothing without --yes."""
import json

import pytest

from tests.services.cli.test_commands import run


@pytest.mark.parametrize("mirror", [None, 1, 4])
def test_check_arm_simulate_passes_or_names_the_mirrored_joint(mirror):
    args = ["check", "arm", "--simulate", "--yes", "--json"] + (["--mirror-joint", str(mirror)] if mirror else [])
    done = run(*args, timeout=300)
    report = json.loads(done.stdout)
    assert [j["joint"] for j in report["joints"]] == list(range(1, 8))
    if mirror is None:
        assert done.returncode == 0 and report["passed"] and report["state"] == "passed"
        assert all(j["direction"] == "ok" for j in report["joints"])
    else:
        assert done.returncode == 1 and not report["passed"] and report["state"] == "failed"
        assert [j["joint"] for j in report["joints"] if not j["passed"]] == [mirror]
        assert f"joint {mirror} turns the other way" in report["message"]


def test_nothing_moves_without_yes_and_bad_requests_are_said():
    for args, said in [(("check", "arm", "--simulate"), "--yes"),
                       (("check", "arm", "--mirror-joint", "1", "--yes"), "needs --simulate"),
                       (("check", "arm", "--simulate", "--yes", "--step-deg", "40"), "step_deg")]:
        done = run(*args)
        assert done.returncode == 2 and said in done.stderr and "Traceback" not in done.stderr, done.stderr
