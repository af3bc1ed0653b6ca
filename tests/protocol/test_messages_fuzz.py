"""The message decoder under fuzzing (Hypothesis): arbitrary bytes, arbitrary MessagePack, and valid messages with
one field replaced by an arbitrary value, for every message type on the wire. Decoding either returns a valid
message of the asked type or raises ProtocolError: no other exception may reach a service's handler."""
import inspect
import subprocess
import sys

import msgpack
import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol import kinova
from protocol import messages as m
from tests.helpers import REPO

MESSAGE_TYPES = sorted({cls for module in (m, kinova) for _, cls in inspect.getmembers(module, inspect.isclass)
                        if issubclass(cls, m.Message) and cls is not m.Message}, key=lambda c: c.__name__)

keys = st.one_of(st.text(max_size=12), st.binary(max_size=6), st.integers(), st.sampled_from(
    ["header", "schema", "seq", "stamp_ns", "source_stamp_ns", "trace", "q", "dq", "linear", "rotational", "frame",
     "angular", "mode", "points", "zones", "velocities", "torques"]))
scalars = st.one_of(st.none(), st.booleans(), st.integers(min_value=-(2**64), max_value=2**64 - 1),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=20), st.binary(max_size=20))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=8),
                                                         st.dictionaries(keys, inner, max_size=6)), max_leaves=30)
FUZZ = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def decode_or_reject(payload: bytes, message_type) -> None:
    try:
        message = m.decode(payload, message_type)
    except m.ProtocolError:
        return
    assert isinstance(message, message_type)


def pack(obj) -> bytes:
    try:
        return msgpack.packb(obj, use_bin_type=True, strict_types=False)
    except (OverflowError, ValueError, TypeError):
        return b"\xc1"  # an unpackable Python value: the never-used byte, malformed on the wire


def test_an_invalid_utf8_map_key_is_a_protocol_error():
    with pytest.raises(m.ProtocolError, match="malformed"):
        m.decode(bytes.fromhex("81a1ff00"), m.Twist)


@pytest.mark.parametrize("message_type", MESSAGE_TYPES, ids=lambda t: t.__name__)
@FUZZ
@given(payload=st.binary(max_size=200))
def test_arbitrary_bytes(message_type, payload):
    decode_or_reject(payload, message_type)


@pytest.mark.parametrize("message_type", MESSAGE_TYPES, ids=lambda t: t.__name__)
@FUZZ
@given(obj=values)
def test_arbitrary_msgpack(message_type, obj):
    decode_or_reject(pack(obj), message_type)


@pytest.mark.parametrize("message_type", MESSAGE_TYPES, ids=lambda t: t.__name__)
@FUZZ
@given(data=st.data())
def test_one_field_of_a_message_replaced(message_type, data):
    fields = msgspec.structs.fields(message_type)
    if not fields:
        return
    field = data.draw(st.sampled_from(fields))
    obj = {f.name: None for f in fields if f.required}
    obj["header"] = {"schema": m.SCHEMA_VERSION, "seq": 1, "stamp_ns": 1}
    obj[field.encode_name] = data.draw(values)
    decode_or_reject(pack(obj), message_type)


@pytest.mark.parametrize("field", ["seq", "stamp_ns", "source_stamp_ns"])
def test_header_stamps_and_sequence_numbers_are_int64(field):
    """A goal stamped 2**64 - 1 was accepted and moved the arm: stamps and sequence numbers are range-checked."""
    goal = m.to_builtins(m.VisionGoal(header=m.Header(), features=[(0.0, 0.0)] * 4, depth_m=0.3))
    goal["header"][field] = 2**64 - 1
    with pytest.raises(m.ProtocolError, match=field):
        m.decode(msgpack.packb(goal), m.VisionGoal)
    goal["header"][field] = 2**63 - 1
    assert getattr(m.decode(msgpack.packb(goal), m.VisionGoal).header, field) == 2**63 - 1


def test_every_wire_type_has_its_decoder_before_any_thread_decodes():
    """A decoder built while another thread decoded crashed a service at start-up (a segfault in msgspec's type
    caches, two subscriber threads each with its first message): importing the protocol builds them all."""
    script = ("import inspect\nfrom protocol import kinova, messages as m\n"
              "types = {c for mod in (m, kinova) for _, c in inspect.getmembers(mod, inspect.isclass)\n"
              "         if issubclass(c, m.Message) and c is not m.Message}\n"
              "missing = sorted(t.__name__ for t in types if t not in m._decoders)\n"
              "print(len(types), missing)")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60,
                         cwd=REPO)
    assert out.returncode == 0, out.stderr
    count, missing = out.stdout.split(" ", 1)
    assert int(count) > 30 and missing.strip() == "[]", out.stdout
