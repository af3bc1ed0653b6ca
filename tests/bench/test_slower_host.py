"""bench.slower_host's cgroup: the quota for normal threads, a realtime budget of each core that does not stall
the stack's realtime threads more than the quota says, and a limit made within a slowed run nested in it."""
import subprocess
import sys
from pathlib import Path

import pytest

from bench.slower_host import PERIOD_US, CgroupUnavailable, make_cgroup, remove_cgroup
from tests.helpers import REPO

NESTED = """
from bench.slower_host import make_cgroup, remove_cgroup
group = make_cgroup("mfvs-test-inner", 0.2)
print(group, (group / "cpu.rt_runtime_us").read_text().strip(), (group / "cpu.cfs_quota_us").read_text().strip())
remove_cgroup(group)
"""


@pytest.fixture
def group():
    made = []

    def make(*args):
        try:
            made.append(make_cgroup(*args))
        except (CgroupUnavailable, OSError) as exc:
            pytest.skip(f"no cpu cgroup here: {exc}")
        return made[-1]

    yield make
    for g in made:
        remove_cgroup(g)


def test_realtime_threads_get_as_much_of_each_core_as_the_quota_by_default(group):
    # (small shares: this suite may itself run slowed, and a group's limits must fit in its parent's)
    slowed = group("mfvs-test-slowed", 0.3)
    if not (slowed / "cpu.rt_runtime_us").exists():
        pytest.skip("no realtime group scheduling (cgroup v2)")
    assert int((slowed / "cpu.cfs_quota_us").read_text()) == max(1000, int(0.3 * PERIOD_US))
    assert int((slowed / "cpu.rt_runtime_us").read_text()) == int(0.3 * PERIOD_US)
    remove_cgroup(slowed)  # (siblings' realtime budgets must fit their parent's together)
    harsher = group("mfvs-test-harsher", 0.3, 0.1)
    assert int((harsher / "cpu.rt_runtime_us").read_text()) == int(0.1 * PERIOD_US)
    with pytest.raises(ValueError, match="realtime"):
        make_cgroup("mfvs-test-refused", 0.3, 1.5)


def test_a_limit_made_inside_a_slowed_run_nests_in_its_group():
    out = subprocess.run([sys.executable, "-m", "bench.slower_host", "--cpus", "0.3", "--name", "mfvs-test-outer",
                          "--", sys.executable, "-c", NESTED], cwd=REPO, capture_output=True, text=True, timeout=60)
    if out.returncode == 2 and "slower_host:" in out.stderr:
        pytest.skip(out.stderr)
    assert out.returncode == 0, out.stderr
    path, realtime, quota = out.stdout.split()
    assert path.endswith("/mfvs-test-outer/mfvs-test-inner")
    assert (int(realtime), int(quota)) == (int(0.2 * PERIOD_US), max(1000, int(0.2 * PERIOD_US)))
    assert not Path(path).parent.exists()  # the run's group is gone with it
