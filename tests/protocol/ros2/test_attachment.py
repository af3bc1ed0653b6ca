"""The attachment's bytes, checked against the design document's layout and against zenoh's own serializer (the
one rmw_zenoh writes it with: zenoh-ext, here through zenoh-python)."""
import pytest
import zenoh.ext as zenoh_ext
from hypothesis import given, strategies as st

from protocol.ros2 import attachment as a

GID = bytes(range(0xA0, 0xB0))


def test_positional_layout_is_the_design_documents():
    # design.md "Publishers": 8 bytes sequence number LE, 8 bytes timestamp LE, 1 byte GID length (16), 16 bytes GID
    data = a.encode(a.Attachment(1, 1767225600123456789, GID))
    assert len(data) == 33 == a.POSITIONAL_SIZE
    assert data == (1).to_bytes(8, "little") + (1767225600123456789).to_bytes(8, "little") + b"\x10" + GID


def test_both_formats_equal_zenohs_serializer():
    sequence, stamp = 42, 1767225600000000001
    positional = zenoh_ext.z_serialize((zenoh_ext.Int64(sequence), zenoh_ext.Int64(stamp), GID)).to_bytes()
    labelled = zenoh_ext.z_serialize(("sequence_number", zenoh_ext.Int64(sequence), "source_timestamp",
                                      zenoh_ext.Int64(stamp), "source_gid", GID)).to_bytes()
    value = a.Attachment(sequence, stamp, GID)
    assert a.encode(value) == positional
    assert a.encode(value, a.AttachmentFormat.LABELLED) == labelled and len(labelled) == 77 == a.LABELLED_SIZE


def test_negative_values_are_twos_complement_as_int64():
    value = a.Attachment(-1, -2, GID)
    assert a.encode(value)[:16] == b"\xff" * 8 + (2**64 - 2).to_bytes(8, "little")
    assert a.decode(a.encode(value)) == value


@given(st.integers(-2**63, 2**63 - 1), st.integers(-2**63, 2**63 - 1), st.binary(min_size=16, max_size=16),
       st.sampled_from(list(a.AttachmentFormat)))
def test_every_attachment_survives_either_format(sequence, stamp, gid, attachment_format):
    value = a.Attachment(sequence, stamp, gid)
    data = a.encode(value, attachment_format)
    assert a.attachment_format(data) is attachment_format and a.decode(data) == value


@given(st.binary(max_size=100))
def test_arbitrary_bytes_decode_or_raise_attachment_error(data):
    try:
        a.decode(data)
    except a.AttachmentError:
        pass


def test_malformed_attachments_are_refused():
    good = a.encode(a.Attachment(1, 2, GID))
    labelled = a.encode(a.Attachment(1, 2, GID), a.AttachmentFormat.LABELLED)
    with pytest.raises(a.AttachmentError, match="33 bytes"):
        a.decode(good[:-1])
    with pytest.raises(a.AttachmentError, match="GID's length byte"):
        a.decode(good[:16] + b"\x0f" + good[17:])
    with pytest.raises(a.AttachmentError, match="'source_timestamp' expected"):
        a.decode(labelled.replace(b"source_timestamp", b"source_timestamq"))
    with pytest.raises(a.AttachmentError, match="16 bytes"):
        a.Attachment(1, 2, GID[:8])
    with pytest.raises(a.AttachmentError, match="64-bit"):
        a.Attachment(2**63, 2, GID)
