"""postcard, the wire format of the fleet's messages, driven by the schema the Rust types trace.

postcard (https://postcard.jamesmunns.com/wire-format) writes a struct as its fields in order,
with no names and no lengths of its own: u8 as one byte, every wider unsigned integer as a LEB128
varint, signed ones zig-zagged first, f32/f64 little-endian, bool as one byte 0 or 1, a string or
a sequence as a varint length and its items, an option as a byte 0 or 1 and the value, a map as
a varint length and its pairs.

The formats come from ``schema.json``, traced from the Rust definitions by ``serde-reflection``
(`fleet-agent/tests/python_schema.rs` checks the file against them), so this module knows no
message of its own and cannot drift from them. Sequences of u8 are ``bytes`` and sequences of
f32 are ``numpy`` arrays (the images and the joint vectors: decoding them one value at a time
would cost milliseconds per observation).
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np


class PostcardError(ValueError):
    """Bytes that are not a message of the expected format, or a value that cannot be one."""


_UNSIGNED_BITS = {"U16": 16, "U32": 32, "U64": 64, "U128": 128}
_SIGNED_BITS = {"I16": 16, "I32": 32, "I64": 64, "I128": 128}
_FLOATS = {"F32": ("<f", 4), "F64": ("<d", 8)}


def encode_varint(n: int, bits: int = 64) -> bytes:
    if n < 0 or n >= 1 << bits:
        raise PostcardError(f"{n} does not fit an unsigned {bits}-bit integer")
    out = bytearray()
    while True:
        byte = n & 0x7F
        n >>= 7
        if n:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def decode_varint(buf: memoryview, i: int, bits: int = 64) -> tuple[int, int]:
    n = shift = 0
    max_bytes = (bits + 6) // 7
    for k in range(max_bytes):
        if i >= len(buf):
            raise PostcardError("the message ends inside an integer")
        byte = buf[i]
        i += 1
        n |= (byte & 0x7F) << shift
        shift += 7
        if byte < 0x80:
            if n >= 1 << bits:
                raise PostcardError(f"an integer over {bits} bits")
            return n, i
    raise PostcardError(f"an integer longer than a {bits}-bit varint")


class Codec:
    """Encodes and decodes the named types of a serde-reflection registry."""

    def __init__(self, registry: dict[str, Any]):
        self.registry = registry

    # -- encoding ---------------------------------------------------------------------------

    def encode(self, type_name: str, value: Any) -> bytes:
        out = bytearray()
        self._encode({"TYPENAME": type_name}, value, out, type_name)
        return bytes(out)

    def _encode(self, fmt: Any, value: Any, out: bytearray, path: str) -> None:
        if isinstance(fmt, str):
            self._encode_primitive(fmt, value, out, path)
            return
        ((kind, inner),) = fmt.items()
        if kind == "TYPENAME":
            container = self._container(inner)
            if not isinstance(value, dict):
                raise PostcardError(f"{path}: a {inner} is a dict of its fields, not {type(value).__name__}")
            fields = [next(iter(f.items())) for f in container]
            names = [name for name, _ in fields]
            unknown = set(value) - set(names)
            if unknown:
                raise PostcardError(f"{path}: {inner} has no field {sorted(unknown)}")
            for name, field_fmt in fields:
                if name not in value:
                    raise PostcardError(f"{path}: {inner} needs {name!r}")
                self._encode(field_fmt, value[name], out, f"{path}.{name}")
        elif kind == "SEQ":
            if inner == "U8":
                data = bytes(value)
                out += encode_varint(len(data)) + data
                return
            items = list(np.asarray(value, dtype=np.float32).ravel()) if inner == "F32" and isinstance(value, np.ndarray) else list(value)
            out += encode_varint(len(items))
            for k, item in enumerate(items):
                self._encode(inner, item, out, f"{path}[{k}]")
        elif kind == "OPTION":
            if value is None:
                out.append(0)
            else:
                out.append(1)
                self._encode(inner, value, out, path)
        elif kind == "MAP":
            items = sorted(value.items()) if isinstance(value, dict) else list(value)
            out += encode_varint(len(items))
            for k, v in items:
                self._encode(inner["KEY"], k, out, f"{path}[{k!r}]")
                self._encode(inner["VALUE"], v, out, f"{path}[{k!r}]")
        elif kind == "TUPLEARRAY":
            items = list(value)
            if len(items) != inner["SIZE"]:
                raise PostcardError(f"{path}: {inner['SIZE']} items, not {len(items)}")
            for k, item in enumerate(items):
                self._encode(inner["CONTENT"], item, out, f"{path}[{k}]")
        else:
            raise PostcardError(f"{path}: format {kind} is not used by the fleet schema")

    def _encode_primitive(self, fmt: str, value: Any, out: bytearray, path: str) -> None:
        try:
            if fmt == "U8":
                out += int(value).to_bytes(1, "little")
            elif fmt in _UNSIGNED_BITS:
                out += encode_varint(int(value), _UNSIGNED_BITS[fmt])
            elif fmt in _SIGNED_BITS:
                n, bits = int(value), _SIGNED_BITS[fmt]
                if not -(1 << (bits - 1)) <= n < 1 << (bits - 1):
                    raise PostcardError(f"{n} does not fit a signed {bits}-bit integer")
                out += encode_varint((n << 1) ^ (n >> (bits - 1)), bits)
            elif fmt == "I8":
                out += int(value).to_bytes(1, "little", signed=True)
            elif fmt in _FLOATS:
                out += struct.pack(_FLOATS[fmt][0], float(value))
            elif fmt == "BOOL":
                if not isinstance(value, (bool, np.bool_)):
                    raise PostcardError(f"{value!r} is not a bool")
                out.append(1 if value else 0)
            elif fmt == "STR":
                if not isinstance(value, str):
                    raise PostcardError(f"{value!r} is not a string")
                data = value.encode()
                out += encode_varint(len(data)) + data
            elif fmt == "UNIT":
                pass
            else:
                raise PostcardError(f"format {fmt} is not used by the fleet schema")
        except (OverflowError, TypeError, ValueError) as e:
            if isinstance(e, PostcardError):
                raise PostcardError(f"{path}: {e}") from None
            raise PostcardError(f"{path}: {value!r} is not a {fmt}: {e}") from None

    # -- decoding ---------------------------------------------------------------------------

    def decode(self, type_name: str, data: bytes) -> dict[str, Any]:
        buf = memoryview(bytes(data))
        value, i = self._decode({"TYPENAME": type_name}, buf, 0)
        if i != len(buf):
            raise PostcardError(f"{len(buf) - i} bytes after the {type_name}")
        return value

    def _decode(self, fmt: Any, buf: memoryview, i: int) -> tuple[Any, int]:
        if isinstance(fmt, str):
            return self._decode_primitive(fmt, buf, i)
        ((kind, inner),) = fmt.items()
        if kind == "TYPENAME":
            out = {}
            for field in self._container(inner):
                ((name, field_fmt),) = field.items()
                out[name], i = self._decode(field_fmt, buf, i)
            return out, i
        if kind == "SEQ":
            n, i = decode_varint(buf, i)
            if inner == "U8":
                if i + n > len(buf):
                    raise PostcardError(f"{n} bytes announced, {len(buf) - i} left")
                return bytes(buf[i : i + n]), i + n
            if inner == "F32":
                if i + 4 * n > len(buf):
                    raise PostcardError(f"{n} floats announced, {len(buf) - i} bytes left")
                return np.frombuffer(buf[i : i + 4 * n], dtype="<f4").copy(), i + 4 * n
            if n > len(buf) - i:
                raise PostcardError(f"{n} items announced, {len(buf) - i} bytes left")
            items = []
            for _ in range(n):
                item, i = self._decode(inner, buf, i)
                items.append(item)
            return items, i
        if kind == "OPTION":
            tag, i = self._decode_primitive("U8", buf, i)
            if tag == 0:
                return None, i
            if tag != 1:
                raise PostcardError(f"option tag {tag}")
            return self._decode(inner, buf, i)
        if kind == "MAP":
            n, i = decode_varint(buf, i)
            if n > len(buf) - i:
                raise PostcardError(f"{n} entries announced, {len(buf) - i} bytes left")
            out = {}
            for _ in range(n):
                k, i = self._decode(inner["KEY"], buf, i)
                out[k], i = self._decode(inner["VALUE"], buf, i)
            return out, i
        if kind == "TUPLEARRAY":
            items = []
            for _ in range(inner["SIZE"]):
                item, i = self._decode(inner["CONTENT"], buf, i)
                items.append(item)
            return items, i
        raise PostcardError(f"format {kind} is not used by the fleet schema")

    def _decode_primitive(self, fmt: str, buf: memoryview, i: int) -> tuple[Any, int]:
        if fmt in ("U8", "I8", "BOOL"):
            if i >= len(buf):
                raise PostcardError("the message ends early")
            b = buf[i]
            if fmt == "BOOL":
                if b > 1:
                    raise PostcardError(f"bool byte {b}")
                return b == 1, i + 1
            return (b - 256 if fmt == "I8" and b > 127 else b), i + 1
        if fmt in _UNSIGNED_BITS:
            return decode_varint(buf, i, _UNSIGNED_BITS[fmt])
        if fmt in _SIGNED_BITS:
            z, i = decode_varint(buf, i, _SIGNED_BITS[fmt])
            return (z >> 1) ^ -(z & 1), i
        if fmt in _FLOATS:
            code, size = _FLOATS[fmt]
            if i + size > len(buf):
                raise PostcardError("the message ends inside a float")
            return struct.unpack_from(code, buf, i)[0], i + size
        if fmt == "STR":
            n, i = decode_varint(buf, i)
            if i + n > len(buf):
                raise PostcardError(f"a {n}-byte string announced, {len(buf) - i} bytes left")
            try:
                return bytes(buf[i : i + n]).decode(), i + n
            except UnicodeDecodeError as e:
                raise PostcardError(f"a string that is not UTF-8: {e}") from None
        if fmt == "UNIT":
            return None, i
        raise PostcardError(f"format {fmt} is not used by the fleet schema")

    def _container(self, name: str) -> list[dict[str, Any]]:
        try:
            container = self.registry[name]
        except KeyError:
            raise PostcardError(f"no type {name} in the schema") from None
        if "STRUCT" not in container:
            raise PostcardError(f"{name}: only structs are used by the fleet schema")
        return container["STRUCT"]
