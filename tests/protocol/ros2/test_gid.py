"""GIDs: this XXH3-128 equals the xxhash package's (the reference library's binding) on every length class of the
algorithm and on the design document's tokens, and the GID's byte order is rmw_zenoh's."""
import json
from pathlib import Path

import pytest

from protocol.ros2 import gid

GIDS = json.loads((Path(__file__).parent / "fixtures" / "fixtures.json").read_text())["gids"]


@pytest.mark.parametrize("text", sorted(GIDS, key=len), ids=lambda text: f"{len(text)} bytes")
def test_gids_equal_xxhash(text):
    assert gid.entity_gid(text).hex() == GIDS[text]


def test_the_fixtures_cover_every_branch_of_xxh3():
    lengths = {len(text.encode()) for text in GIDS}
    assert {0, 1, 3, 4, 8, 9, 16, 17, 128, 129, 240, 241} <= lengths
    assert max(lengths) > 1024 + 64  # more than one block of the long path (16 stripes of 64 bytes)


def test_the_gid_is_the_low_half_then_the_high_half_little_endian():
    low, high = gid.xxh3_128(b"@ros2_lv/0/1f/0/0/NN/%/%/mfvs")
    assert gid.entity_gid("@ros2_lv/0/1f/0/0/NN/%/%/mfvs") == low.to_bytes(8, "little") + high.to_bytes(8, "little")
    assert len(gid.entity_gid("")) == 16
