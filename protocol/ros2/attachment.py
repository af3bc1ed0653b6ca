"""The attachment rmw_zenoh puts on every sample, query and reply: sequence number, source timestamp, GID.

rmw_zenoh drops a sample that has none ("Unable to obtain attachment", ros2/rmw_zenoh#479). Two formats exist, both
written with zenoh-ext's serializer (a signed 64-bit integer as 8 little-endian bytes; a string or a byte array as
its LEB128 length, then its bytes):

- POSITIONAL, 33 bytes (design.md at ros2/rmw_zenoh 99a6a2bd, "Publishers"; attachment_helpers.cpp of humble 0.1.2+,
  jazzy 0.2.4+, kilted, lyrical)::

      int64 sequence number (LE) | int64 source timestamp, ns since the UNIX epoch (LE) | 0x10 | 16-byte GID

- LABELLED, 77 bytes, before ros2/rmw_zenoh#601 ("Change serialization format in attachment_helpers.cpp"): humble
  0.1.0-0.1.1 and jazzy 0.2.0-0.2.3 (attachment_helpers.cpp of release/jazzy/rmw_zenoh_cpp/0.2.3-1)::

      "sequence_number" | int64 | "source_timestamp" | int64 | "source_gid" | 0x10 | 16-byte GID

A reply carries the request's sequence number and client GID, with the reply's own timestamp (design.md "Service
Servers").
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import Enum

#: a GID's size on rmw_zenoh's wire (rmw/types.h RMW_GID_STORAGE_SIZE 16; Humble's rmw defines 24, so its
#: rmw_zenoh hard-codes 16: ros2/rmw_zenoh#388)
GID_SIZE = 16
_INT64 = struct.Struct("<q")
_LABELS = (b"sequence_number", b"source_timestamp", b"source_gid")


class AttachmentFormat(Enum):
    POSITIONAL = "positional"  # 33 bytes: Humble >= 0.1.2, Jazzy >= 0.2.4, Kilted, Lyrical
    LABELLED = "labelled"      # 77 bytes: Humble 0.1.0-0.1.1, Jazzy 0.2.0-0.2.3


POSITIONAL_SIZE = 8 + 8 + 1 + GID_SIZE
LABELLED_SIZE = sum(1 + len(label) for label in _LABELS) + POSITIONAL_SIZE


class AttachmentError(ValueError):
    """Bytes that are no rmw_zenoh attachment, or values that do not fit one."""


@dataclass(frozen=True)
class Attachment:
    sequence_number: int     # int64, counted per publisher (per client for requests) from 1
    source_timestamp_ns: int  # int64, nanoseconds since the UNIX epoch when the sample was sent
    source_gid: bytes         # the publisher's (the client's) 16-byte GID

    def __post_init__(self) -> None:
        for name in ("sequence_number", "source_timestamp_ns"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not -2**63 <= value < 2**63:
                raise AttachmentError(f"{name} {value!r}: a signed 64-bit integer")
        if not isinstance(self.source_gid, bytes) or len(self.source_gid) != GID_SIZE:
            raise AttachmentError(f"source_gid: {GID_SIZE} bytes, got {self.source_gid!r}")


def encode(attachment: Attachment, attachment_format: AttachmentFormat = AttachmentFormat.POSITIONAL) -> bytes:
    """The attachment's bytes in the given format (POSITIONAL for every current rmw_zenoh)."""
    sequence = _INT64.pack(attachment.sequence_number)
    timestamp = _INT64.pack(attachment.source_timestamp_ns)
    gid = bytes([GID_SIZE]) + attachment.source_gid
    if attachment_format is AttachmentFormat.POSITIONAL:
        return sequence + timestamp + gid
    labels = [bytes([len(label)]) + label for label in _LABELS]
    return labels[0] + sequence + labels[1] + timestamp + labels[2] + gid


def attachment_format(data: bytes) -> AttachmentFormat:
    """Which format ``data`` is in, told by its size (the two cannot be confused: 33 and 77 bytes)."""
    if len(data) == POSITIONAL_SIZE:
        return AttachmentFormat.POSITIONAL
    if len(data) == LABELLED_SIZE:
        return AttachmentFormat.LABELLED
    raise AttachmentError(f"an rmw_zenoh attachment is {POSITIONAL_SIZE} bytes (or {LABELLED_SIZE} before Jazzy "
                          f"0.2.4), got {len(data)}")


def decode(data: bytes) -> Attachment:
    """The attachment in ``data``, in either format."""
    data = bytes(data)
    if attachment_format(data) is AttachmentFormat.LABELLED:
        position, values = 0, []
        for label in _LABELS:
            if data[position] != len(label) or data[position + 1:position + 1 + len(label)] != label:
                raise AttachmentError(f"labelled attachment: {label.decode()!r} expected at byte {position}")
            position += 1 + len(label)
            values.append(data[position:position + 8] if label != b"source_gid" else data[position:])
            position += 8
        data = values[0] + values[1] + values[2]
    if data[16] != GID_SIZE:
        raise AttachmentError(f"the GID's length byte is {data[16]}, {GID_SIZE} expected")
    return Attachment(_INT64.unpack_from(data, 0)[0], _INT64.unpack_from(data, 8)[0], data[17:])
