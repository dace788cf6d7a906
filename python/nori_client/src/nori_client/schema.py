"""The fleet's messages (docs/fleet-schema.md) by name, from the schema traced from the Rust types.

>>> from nori_client import schema
>>> msg = schema.decode("ObservationMsg", payload)      # dict of fields, vectors as numpy
>>> payload = schema.encode("ActionChunk", {...})

Every message starts with its schema version; one of another version is refused by name, as the
robot refuses it, rather than misread.
"""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

from .postcard import Codec, PostcardError, decode_varint

_SCHEMA = json.loads(resources.files(__package__).joinpath("schema.json").read_text())

#: The schema version this package speaks (the Rust `fleet_agent::schema::SCHEMA_VERSION`).
SCHEMA_VERSION: int = _SCHEMA["version"]

#: Every message type, by the Rust name.
MESSAGES: tuple[str, ...] = tuple(_SCHEMA["messages"])

_CODEC = Codec(_SCHEMA["types"])


class SchemaError(ValueError):
    """A message that cannot be read or written: malformed, or of another schema version."""


def encode(type_name: str, value: dict[str, Any]) -> bytes:
    """postcard bytes of ``value`` as ``type_name``; its ``version`` is set when absent."""
    if type_name not in MESSAGES:
        raise SchemaError(f"{type_name} is not a fleet message (one of {', '.join(MESSAGES)})")
    value = {"version": SCHEMA_VERSION, **value}
    try:
        return _CODEC.encode(type_name, value)
    except PostcardError as e:
        raise SchemaError(f"{type_name}: {e}") from None


def decode(type_name: str, data: bytes) -> dict[str, Any]:
    """The fields of the ``type_name`` in ``data``; trailing bytes and other versions refused."""
    if type_name not in MESSAGES:
        raise SchemaError(f"{type_name} is not a fleet message (one of {', '.join(MESSAGES)})")
    try:
        version, _ = decode_varint(memoryview(bytes(data)), 0, 16)
    except PostcardError as e:
        raise SchemaError(f"{type_name}: no version: {e}") from None
    if version != SCHEMA_VERSION:
        raise SchemaError(
            f"{type_name}: schema version {version}, this client speaks {SCHEMA_VERSION}"
        )
    try:
        return _CODEC.decode(type_name, data)
    except PostcardError as e:
        raise SchemaError(f"{type_name}: malformed: {e}") from None
