"""The codec against the bytes the Rust side writes (golden.json, checked by both sides), and
against what must be refused."""

import io
import json
from pathlib import Path

import numpy as np
import pytest

from nori_client import SCHEMA_VERSION, ChunkError, Image, Observation, SchemaError, action_chunk, decode, encode
from nori_client import schema

GOLDEN = json.loads((Path(__file__).parent / "golden.json").read_text())["messages"]


def plain(value):
    """Decoded values as JSON would hold them: arrays and bytes as lists."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return [float(v) for v in value]
    if isinstance(value, bytes):
        return list(value)
    return value


def test_every_message_type_has_golden_bytes():
    assert sorted({m["type"] for m in GOLDEN}) == sorted(schema.MESSAGES)
    assert all(m["hex"] for m in GOLDEN), "golden.json has unblessed entries"


@pytest.mark.parametrize("entry", GOLDEN, ids=lambda e: e["type"])
def test_golden_bytes_encode_and_decode(entry):
    data = bytes.fromhex(entry["hex"])
    assert entry["value"]["version"] == SCHEMA_VERSION
    assert encode(entry["type"], entry["value"]).hex() == entry["hex"]
    assert plain(decode(entry["type"], data)) == entry["value"]


def test_another_version_is_refused_by_name():
    good = next(m for m in GOLDEN if m["type"] == "ActionChunk")
    data = bytearray.fromhex(good["hex"])
    data[0] = SCHEMA_VERSION + 1
    with pytest.raises(SchemaError, match=f"schema version {SCHEMA_VERSION + 1}, this client speaks {SCHEMA_VERSION}"):
        decode("ActionChunk", bytes(data))


@pytest.mark.parametrize("entry", GOLDEN, ids=lambda e: e["type"])
def test_every_cut_and_a_padded_message_are_malformed(entry):
    data = bytes.fromhex(entry["hex"])
    for cut in range(len(data)):
        with pytest.raises(SchemaError):
            decode(entry["type"], data[:cut])
    with pytest.raises(SchemaError, match="1 bytes after"):
        decode(entry["type"], data + b"\0")


def test_bad_bools_overlong_integers_and_bad_text_are_malformed():
    state = next(m for m in GOLDEN if m["type"] == "StateMsg")
    data = bytearray.fromhex(state["hex"])
    # safe_state follows version (1 byte), seq (1), timestamp_ns (2 bytes: 10000), wall_ms (6).
    i = 1 + 1 + 2 + 6
    assert data[i] == 1
    data[i] = 2
    with pytest.raises(SchemaError, match="bool byte 2"):
        decode("StateMsg", bytes(data))
    with pytest.raises(SchemaError, match="longer than a 64-bit varint"):
        decode("EventMsg", bytes([SCHEMA_VERSION]) + b"\xff" * 11)
    layout = bytes([SCHEMA_VERSION, 1, 2, 0xC3, 0x28]) + b"\0" * 8
    with pytest.raises(SchemaError, match="not UTF-8"):
        decode("LayoutMsg", layout)
    with pytest.raises(SchemaError, match="not a fleet message"):
        decode("Pickle", b"\x04")


def test_encoding_refuses_what_the_type_cannot_hold():
    ok = {"seq": 1, "observation_ns": 2, "step_offsets_ns": [3], "joint_count": 1, "joint_mask": 1, "targets": [0.5],
          "lift_m": [], "base_twist": []}
    encode("ActionChunk", ok)
    with pytest.raises(SchemaError, match="needs 'targets'"):
        encode("ActionChunk", {k: v for k, v in ok.items() if k != "targets"})
    with pytest.raises(SchemaError, match="no field"):
        encode("ActionChunk", {**ok, "pickle": 1})
    with pytest.raises(SchemaError, match="joint_count.*16-bit"):
        encode("ActionChunk", {**ok, "joint_count": 70000})
    with pytest.raises(SchemaError, match="seq.*64-bit"):
        encode("ActionChunk", {**ok, "seq": -1})


def test_an_observation_decodes_to_numpy_with_its_images():
    entry = next(m for m in GOLDEN if m["type"] == "ObservationMsg" and m["value"]["images"])
    obs = Observation.from_bytes("a3", bytes.fromhex(entry["hex"]))
    assert obs.position.dtype == np.float32 and obs.position.tolist() == [0.0, -1.5, 0.25]
    assert obs.images["left_wrist"].jpeg == bytes([255, 216, 255, 224, 0, 16, 255, 217])
    assert (obs.images["left_wrist"].width, obs.images["left_wrist"].height) == (160, 120)


def test_a_missing_servo_is_nan_and_survives_the_round_trip():
    data = encode("ObservationMsg", {"seq": 1, "timestamp_ns": 2, "position": [np.nan, 0.5], "velocity": [0.0, 0.0], "images": [],
                                        "lift": None, "base": None})
    assert np.isnan(decode("ObservationMsg", data)["position"][0])


def test_an_image_decodes_to_its_pixels_and_a_lying_size_is_refused():
    from PIL import Image as PilImage

    picture = np.zeros((12, 16, 3), dtype=np.uint8)
    picture[:, :8] = (200, 30, 30)
    out = io.BytesIO()
    PilImage.fromarray(picture).save(out, format="JPEG", quality=95)
    rgb = Image("head", 1, 2, 16, 12, out.getvalue()).rgb()
    assert rgb.shape == (12, 16, 3)
    assert abs(int(rgb[6, 2, 0]) - 200) < 10 and rgb[6, 14].max() < 20
    with pytest.raises(ValueError, match="16x12 JPEG in an image that says 32x24"):
        Image("head", 1, 2, 32, 24, out.getvalue()).rgb()


def test_an_action_chunk_is_what_the_gate_reads():
    data = action_chunk(
        7, 1_000_000_000, [20_000_000, 40_000_000], np.array([[0.5, -0.25], [1.5, -1.0]]),
        lift_m=[0.25, 0.375], base_twist=[[0.125, -0.5], [0.125, -0.5]],
    )
    golden = next(m for m in GOLDEN if m["type"] == "ActionChunk")
    assert data.hex() == golden["hex"]
    for bad, why in [
        (dict(targets=np.array([[np.nan, 0.0]]), offsets=[1]), "finite"),
        (dict(targets=np.zeros((2, 2)), offsets=[1]), "shape"),
        (dict(targets=np.zeros((2, 2)), offsets=[5, 5]), "rise"),
        (dict(targets=np.zeros((1, 2)), offsets=[1], mask=0b100), "mask"),
        (dict(targets=np.zeros((1, 2)), offsets=[1], mask=0), "mask"),
        (dict(targets=np.zeros((1, 2)), offsets=[1], lift=[0.1, 0.2]), "lift heights"),
        (dict(targets=np.zeros((1, 2)), offsets=[1], twist=[0.1]), "base twist"),
        (dict(targets=np.zeros((1, 2)), offsets=[1], twist=[[0.1, np.inf]]), "finite"),
    ]:
        with pytest.raises(ChunkError, match=why):
            action_chunk(1, 0, bad["offsets"], bad["targets"], bad.get("mask"), bad.get("lift"), bad.get("twist"))
    # The base alone, no joint.
    m = decode("ActionChunk", action_chunk(1, 0, [1], np.zeros((1, 2)), 0, None, [[0.1, 0.5]]))
    assert (m["joint_mask"], list(m["lift_m"]), list(m["base_twist"])) == (0, [], pytest.approx([0.1, 0.5]))
