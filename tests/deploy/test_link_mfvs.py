"""The install's `mfvs` link: to the checkout that ran it, saying so when it replaces another checkout's (or a
dangling one, a deleted clone's), never clobbering a file that is not a link."""
import subprocess

from tests.helpers import REPO

SCRIPT = REPO / "deploy" / "link_mfvs.sh"


def link(bin_dir, target) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(SCRIPT), str(bin_dir), str(target)], capture_output=True, text=True,
                          timeout=30, check=True)


def test_the_link_says_where_it_points_and_what_it_replaced(tmp_path):
    bin_dir = tmp_path / "bin"
    first, second = tmp_path / "a" / "mfvs", tmp_path / "b" / "mfvs"
    for target in (first, second):
        target.parent.mkdir()
        target.write_text("#!/bin/sh\n")
    out = link(bin_dir, first)
    assert (bin_dir / "mfvs").resolve() == first and "replacing" not in out.stdout
    assert "replacing" not in link(bin_dir, first).stdout  # the same checkout again: nothing to say
    out = link(bin_dir, second)
    assert f"-> {first} (another checkout) with -> {second}" in out.stdout
    second.unlink()
    second.parent.rmdir()  # the clone is deleted: the link dangles
    out = link(bin_dir, first)
    assert "(a checkout that is gone)" in out.stdout and (bin_dir / "mfvs").resolve() == first


def test_a_file_that_is_not_a_link_is_left_alone(tmp_path):
    (tmp_path / "mfvs").write_text("someone's own mfvs\n")
    out = link(tmp_path, tmp_path / "checkout" / "mfvs")
    assert "is not a link: left alone" in out.stderr
    assert (tmp_path / "mfvs").read_text() == "someone's own mfvs\n"
