"""nori-client: the Nori fleet's messages and zenoh link in Python (docs/fleet-schema.md).

``schema`` encodes and decodes the fleet's postcard messages from the schema traced from the
Rust definitions; ``client`` opens zenoh sessions as the fleet's processes do and turns
observations into numpy and action chunks into bytes the robot's gate accepts.
"""

from .client import (
    ChunkError,
    Fleet,
    Image,
    Layout,
    Observation,
    action_chunk,
    open_session,
    robot_key,
    robot_of,
    seconds_to_offsets,
)
from .schema import SCHEMA_VERSION, SchemaError, decode, encode

__all__ = [
    "SCHEMA_VERSION",
    "ChunkError",
    "Fleet",
    "Image",
    "Layout",
    "Observation",
    "SchemaError",
    "action_chunk",
    "decode",
    "encode",
    "open_session",
    "robot_key",
    "robot_of",
    "seconds_to_offsets",
]
