"""A zenoh link to the robots of the fleet, in the fleet's own terms.

A policy server subscribes to robots' observations and answers with action chunks, exactly as
`nori policy-server` does. Times are the robot's clock: an action chunk names the observation it
was computed from by that observation's ``timestamp_ns`` and its steps are offsets from it, so
the robot judges the chunk's age with its own clock and no clock synchronisation is needed (the
robot's gate refuses a chunk whose observation is older than its `max-age-ms`, 250 ms by
default).
"""

from __future__ import annotations

import io
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import zenoh

from . import schema

#: Where `nori policy-server` listens by default, and so where robots' agents connect.
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"


def open_session(
    zenoh_config: str | Path | None = None,
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    default_listen: str = DEFAULT_LISTEN,
) -> zenoh.Session:
    """A zenoh session as the fleet's own processes open theirs: wholly from a zenoh JSON5 file
    when given (a TLS identity made by `deploy/zenoh/make-dev-ca.sh`, e.g. `inference.json5`,
    a client of the router it names), else a peer listening on ``listen`` and connecting to
    ``connect`` (``default_listen`` when told neither), multicast scouting off."""
    if zenoh_config is not None:
        if listen or connect:
            raise ValueError("a zenoh configuration file says where to connect: no listen/connect with it")
        return zenoh.open(zenoh.Config.from_file(str(zenoh_config)))
    config = zenoh.Config()
    listen = list(listen) if (listen or connect) else [default_listen]
    for key, value in [
        ("mode", '"peer"'),
        ("listen/endpoints", json.dumps(listen)),
        ("connect/endpoints", json.dumps(list(connect))),
        ("scouting/multicast/enabled", "false"),
    ]:
        config.insert_json5(key, value)
    return zenoh.open(config)


def robot_key(robot: str, leaf: str) -> str:
    """``nori/<robot>/<leaf>``."""
    return f"nori/{robot}/{leaf}"


def robot_of(key: str) -> str | None:
    """The robot id in ``nori/<id>/...``."""
    parts = str(key).split("/")
    return parts[1] if len(parts) >= 3 and parts[0] == "nori" else None


@dataclass
class Image:
    """One camera image of an observation: the camera's own JPEG."""

    camera: str
    seq: int
    capture_ns: int
    width: int
    height: int
    jpeg: bytes

    def rgb(self) -> np.ndarray:
        """The picture as ``uint8[height, width, 3]``; a JPEG that does not decode to the
        size it claims is an error, not a picture."""
        from PIL import Image as PilImage

        with PilImage.open(io.BytesIO(self.jpeg)) as im:
            pixels = np.asarray(im.convert("RGB"))
        if pixels.shape != (self.height, self.width, 3):
            raise ValueError(
                f"camera {self.camera}: a {pixels.shape[1]}x{pixels.shape[0]} JPEG in an image that says {self.width}x{self.height}"
            )
        return pixels


@dataclass
class Observation:
    """What a policy sees of one robot at one instant (``ObservationMsg``)."""

    robot: str
    seq: int
    timestamp_ns: int
    position: np.ndarray
    velocity: np.ndarray
    images: dict[str, Image] = field(default_factory=dict)
    # The lift (``LiftMsg``: height_m, goal_m, state, held, duty_wait_s) and the base
    # (``BaseMsg``: x_m, y_m, heading_rad, linear_m_s, angular_rad_s, ...), when running.
    lift: dict | None = None
    base: dict | None = None

    def body_state(self) -> np.ndarray | None:
        """The lift's height and the base's measured twist, the three dimensions a dataset
        recorded with ``nori record --lift --base`` puts after the joints; ``None`` unless the
        lift is homed and the base is running."""
        if self.lift is None or self.base is None or not np.isfinite(self.lift["height_m"]):
            return None
        return np.array([self.lift["height_m"], self.base["linear_m_s"], self.base["angular_rad_s"]], dtype=np.float32)

    @classmethod
    def from_bytes(cls, robot: str, data: bytes) -> "Observation":
        m = schema.decode("ObservationMsg", data)
        images = {
            i["camera"]: Image(i["camera"], i["seq"], i["capture_ns"], i["width"], i["height"], i["data"])
            for i in m["images"]
        }
        for i in m["images"]:
            if i["encoding"] != "jpeg":
                raise schema.SchemaError(f"camera {i['camera']}: encoding {i['encoding']!r}, not jpeg")
        return cls(robot, m["seq"], m["timestamp_ns"], m["position"], m["velocity"], images, m["lift"], m["base"])


@dataclass
class Layout:
    """The robot's joints in the order of every vector, with their calibrated ranges (rad)."""

    names: list[str]
    lower: np.ndarray
    upper: np.ndarray

    @classmethod
    def from_bytes(cls, data: bytes) -> "Layout":
        m = schema.decode("LayoutMsg", data)
        joints = m["joints"]
        return cls(
            [j["name"] for j in joints],
            np.array([j["min"] for j in joints], dtype=np.float32),
            np.array([j["max"] for j in joints], dtype=np.float32),
        )


class ChunkError(ValueError):
    """An action chunk the robot would refuse, caught before it is sent."""


def action_chunk(
    seq: int,
    observation_ns: int,
    step_offsets_ns: Iterable[int],
    targets: np.ndarray,
    joint_mask: int | None = None,
    lift_m: np.ndarray | None = None,
    base_twist: np.ndarray | None = None,
) -> bytes:
    """An ``ActionChunk``: ``targets[k, j]`` (rad) to be reached by joint ``j`` at
    ``observation_ns + step_offsets_ns[k]`` on the robot's clock. ``joint_mask`` bit ``j``
    set: joint ``j`` is commanded (default: all); the others keep their goal. ``lift_m[k]``
    (m) and ``base_twist[k] = (m/s, rad/s)`` command the lift and the base at the same steps
    (absent: left alone). Checked here as the robot's gate checks it (shape, finite, offsets
    rising); the calibrated ranges, the body's limits and the chunk's age are the robot's to
    judge."""
    targets = np.asarray(targets, dtype=np.float32)
    offsets = [int(o) for o in step_offsets_ns]
    if targets.ndim != 2 or targets.shape[0] != len(offsets) or not offsets:
        raise ChunkError(f"targets of shape {targets.shape} for {len(offsets)} steps: (steps, joints) needed")
    joints = targets.shape[1]
    if not 0 < joints <= 32:
        raise ChunkError(f"{joints} joints: 1 to 32")
    if not np.isfinite(targets).all():
        raise ChunkError("a target that is not a finite number")
    if any(b <= a for a, b in zip(offsets, offsets[1:])) or offsets[0] < 0:
        raise ChunkError(f"step offsets must rise from 0: {offsets[:5]}...")
    mask = (1 << joints) - 1 if joint_mask is None else joint_mask
    lift = np.zeros(0, np.float32) if lift_m is None else np.asarray(lift_m, dtype=np.float32).ravel()
    twist = np.zeros((0, 2), np.float32) if base_twist is None else np.asarray(base_twist, dtype=np.float32)
    if lift.size and lift.shape != (len(offsets),):
        raise ChunkError(f"{lift.size} lift heights for {len(offsets)} steps")
    if twist.size and twist.shape != (len(offsets), 2):
        raise ChunkError(f"base twist of shape {twist.shape} for {len(offsets)} steps: (steps, 2) needed")
    if not (np.isfinite(lift).all() and np.isfinite(twist).all()):
        raise ChunkError("a lift or base target that is not a finite number")
    if mask < 0 or mask >> joints or (mask == 0 and not lift.size and not twist.size):
        raise ChunkError(f"joint mask {mask:#x} for {joints} joints")
    return schema.encode(
        "ActionChunk",
        {
            "seq": seq,
            "observation_ns": observation_ns,
            "step_offsets_ns": offsets,
            "joint_count": joints,
            "joint_mask": mask,
            "targets": targets.ravel(),
            "lift_m": lift,
            "base_twist": twist.ravel(),
        },
    )


class Fleet:
    """Observations of every robot on the session, newest first per robot, and their action
    keys. Messages that do not decode are counted by kind, never fatal."""

    def __init__(self, session: zenoh.Session):
        self.session = session
        self.undecodable: dict[str, int] = {}
        self._observations = session.declare_subscriber(
            "nori/*/observation", zenoh.handlers.RingChannel(64)
        )
        self._layouts: dict[str, Layout] = {}
        self._layout_sub = session.declare_subscriber("nori/*/layout", self._on_layout)
        self._publishers: dict[str, zenoh.Publisher] = {}

    def _on_layout(self, sample: zenoh.Sample) -> None:
        robot = robot_of(sample.key_expr)
        try:
            self._layouts[robot] = Layout.from_bytes(sample.payload.to_bytes())
        except schema.SchemaError:
            self.undecodable["layout"] = self.undecodable.get("layout", 0) + 1

    def layout(self, robot: str, timeout: float = 10.0) -> Layout:
        """The robot's layout (its agent re-sends it every 5 s by default)."""
        deadline = time.monotonic() + timeout
        while robot not in self._layouts:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no layout from robot {robot} within {timeout} s")
            time.sleep(0.01)
        return self._layouts[robot]

    def observations(self, timeout: float | None = None) -> dict[str, Observation]:
        """Every observation received since the last call, the newest per robot; waits up to
        ``timeout`` s for the first one (None: returns at once)."""
        newest: dict[str, Observation] = {}
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            sample = self._observations.try_recv()
            if sample is None:
                if newest or deadline is None or time.monotonic() > deadline:
                    return newest
                time.sleep(0.001)
                continue
            robot = robot_of(sample.key_expr)
            try:
                obs = Observation.from_bytes(robot, sample.payload.to_bytes())
            except schema.SchemaError:
                self.undecodable["observation"] = self.undecodable.get("observation", 0) + 1
                continue
            newest[robot] = obs

    def send(self, robot: str, chunk: bytes) -> None:
        """Publishes an encoded action chunk to the robot."""
        if robot not in self._publishers:
            self._publishers[robot] = self.session.declare_publisher(robot_key(robot, "actions"))
        self._publishers[robot].put(chunk)

    def close(self) -> None:
        for p in self._publishers.values():
            p.undeclare()
        self._observations.undeclare()
        self._layout_sub.undeclare()


def seconds_to_offsets(fps: float, steps: int, first: float = 0.0) -> list[int]:
    """``steps`` step offsets (ns) ``1/fps`` apart, the first at ``first`` s."""
    if not (fps > 0 and math.isfinite(fps)):
        raise ChunkError(f"{fps} steps per second")
    return [int(round((first + k / fps) * 1e9)) for k in range(steps)]
