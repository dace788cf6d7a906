"""Reads a black box with the official `mcap` package, as a viewer would, and decodes every
message with its channel's schema (JSON Schema, validated by `jsonschema`).

    python3 check_blackbox.py BOX.mcap [--partial]

Prints one JSON object: messages per topic, the box's metadata, and whether it was read to
its footer. A whole box is read twice: by its summary (`make_reader`, the indexed path viewers
take) and linearly; the two must agree. `--partial`: a box cut short by a crash, read linearly
as far as its finished chunks go. Exits non-zero on any message that does not decode or does
not match its schema.
"""

import json
import sys
from collections import Counter

import jsonschema
from mcap.reader import make_reader
from mcap.records import Channel, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader


def linear(path):
    schemas, channels, counts, metadata = {}, {}, Counter(), {}
    footer = False
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Metadata):
                    metadata[record.name] = dict(record.metadata)
                elif isinstance(record, Message):
                    channel = channels[record.channel_id]
                    decode(schemas[channel.schema_id], channel, record.data)
                    counts[channel.topic] += 1
                elif isinstance(record, Footer):
                    footer = True
        except Exception as e:  # a box cut short ends mid-record
            if footer:
                raise
            print(f"read to a cut: {type(e).__name__}: {e}", file=sys.stderr)
    return counts, metadata, footer


validators = {}


def decode(schema, channel, data):
    assert schema.encoding == "jsonschema", schema.encoding
    assert channel.message_encoding == "json", channel.message_encoding
    if schema.id not in validators:
        validators[schema.id] = jsonschema.Draft202012Validator(json.loads(schema.data))
    validators[schema.id].validate(json.loads(data))


def indexed(path):
    counts = Counter()
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages():
            decode(schema, channel, message.data)
            counts[channel.topic] += 1
    return counts


def main():
    path = sys.argv[1]
    partial = "--partial" in sys.argv[2:]
    counts, metadata, footer = linear(path)
    if not partial:
        assert footer, "a whole box ends with its footer"
        assert indexed(path) == counts, "the summary's path and the linear read disagree"
    print(json.dumps({"messages": counts, "metadata": metadata, "footer": footer}))


if __name__ == "__main__":
    main()
