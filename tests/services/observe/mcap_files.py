"""Reading back what the observe tools wrote: every message of an MCAP file by topic, decoded (Foxglove's
protobuf messages through their schemas in the file, JSON as dicts, mfvs's MessagePack as bytes)."""
import json
from collections import defaultdict

from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory


def read_mcap(path) -> dict[str, list]:
    """{topic: [(schema name, log time, decoded message)]} in log-time order."""
    factory = DecoderFactory()
    out = defaultdict(list)
    with open(path, "rb") as stream:
        for schema, channel, message in make_reader(stream).iter_messages(log_time_order=True):
            if channel.message_encoding == "protobuf":
                value = factory.decoder_for(channel.message_encoding, schema)(message.data)
            elif channel.message_encoding == "json":
                value = json.loads(message.data)
            else:
                value = bytes(message.data)
            out[channel.topic].append((schema.name if schema else None, message.log_time, value))
    return dict(out)
