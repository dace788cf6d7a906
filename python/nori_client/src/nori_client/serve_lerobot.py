"""nori-serve-lerobot: a LeRobot policy checkpoint served to a robot of the fleet.

    nori-serve-lerobot CHECKPOINT --robot sim-0001 [--dataset DATASET] [--task TEXT]
        [--zenoh-config inference.json5 | --listen tcp/127.0.0.1:7447 | --connect ...]

CHECKPOINT is a directory `lerobot-train` wrote (`.../checkpoints/last/pretrained_model`:
`config.json`, the weights, the saved pre- and post-processors). The checkpoint knows its
features' shapes but not their names; the names come from the training dataset's
`meta/info.json` (`--dataset`, else the `dataset.root` of the checkpoint's `train_config.json`).

At start every name is checked against the robot, and any that does not match stops the server
with the mismatch named, never a silent zero: each joint of `observation.state` and of `action`
must be a joint of the robot's layout, each `observation.images.<camera>` a camera the robot's
observations carry, at the size the policy was trained on. Then, for each observation carrying
every camera the policy needs, the policy's whole action chunk goes to the robot as one
`ActionChunk`: step `k` at `k / fps` after the observation on the robot's clock (`fps` of the
dataset), only the policy's joints commanded. The robot's gate checks every chunk as it checks
any other (ranges, age); what it refuses is counted in its status, never executed.

A dataset recorded with `nori record --lift --base` names the lift's height and the base's twist
after the joints (`lift.height_m`, `base.linear_m_s`, `base.angular_rad_s`): the state takes them
from the observation, and the chunk's columns for them command the lift and the base (the gate
checks them against the body's limits).

A servo that missed its reply in a cycle reads NaN: the policy gets that joint's last valid
position (what `nori record` writes for it too), and nothing until every joint was read once.

The name checks (`plan`) need no LeRobot; the policy itself needs `lerobot` (and torch), Python
>= 3.12: `tests/python/lerobot-train-check.sh --install` makes such an environment.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .client import Fleet, Layout, Observation, action_chunk, open_session

STATE = "observation.state"
IMAGES = "observation.images."
ACTION = "action"

#: The body's dimensions after the joints, in the order `nori record` writes them.
BODY = ["lift.height_m", "base.linear_m_s", "base.angular_rad_s"]

#: Input features the robot's observations can fill, beside `observation.state` and the images.
SERVED = {"observation.velocity", "observation.joint_valid", "observation.camera_valid"}


class MismatchError(ValueError):
    """The checkpoint, its dataset and the robot do not name the same things."""


@dataclass
class Plan:
    """How the robot's observation becomes the policy's input and its chunk the robot's action."""

    #: For each name of the dataset's `observation.state`, its index in the robot's layout.
    state_index: list[int]
    #: For each name of the dataset's `action`, its index in the robot's layout.
    action_index: list[int]
    #: Policy image key -> (camera name, (height, width)).
    cameras: dict[str, tuple[str, tuple[int, int]]]
    #: The dataset's frame rate: the chunk's step spacing.
    fps: float
    #: Other input features filled from the observation (velocity, validity masks).
    extras: list[str]
    #: The body's dimensions after the joints of `observation.state` (indices into BODY).
    state_body: list[int] = field(default_factory=list)
    #: The body's dimensions after the joints of `action` (indices into BODY).
    action_body: list[int] = field(default_factory=list)
    #: Input features the robot's observations cannot fill (ACT and Diffusion read only the
    #: state and the images; a policy that reads one of these fails its first inference).
    unserved: list[str] = field(default_factory=list)

    @property
    def joint_mask(self) -> int:
        return sum(1 << j for j in self.action_index)


def names_of(info: dict[str, Any], key: str) -> list[str]:
    names = info.get("features", {}).get(key, {}).get("names")
    if isinstance(names, dict):  # {"motors": [...]}, as some LeRobot datasets write them
        names = next(iter(names.values()), None)
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise MismatchError(f"the dataset names no joints for {key!r}")
    return names


def plan(config: dict[str, Any], info: dict[str, Any], layout: list[str]) -> Plan:
    """Checks the checkpoint's `config.json` and its dataset's `meta/info.json` against the
    robot's joint names; every mismatch at once, named."""
    inputs = config.get("input_features", {})
    outputs = config.get("output_features", {})
    problems = []

    def indices(key: str, features: dict[str, Any]) -> tuple[list[int], list[int]]:
        if key not in features:
            problems.append(f"the policy has no {key!r} feature")
            return [], []
        names = names_of(info, key)
        shape = features[key].get("shape")
        if shape != [len(names)]:
            problems.append(f"{key}: the policy's shape {shape} is not the dataset's {len(names)} names")
        joints = [n for n in names if n not in BODY]
        body = [n for n in names if n in BODY]
        if names != joints + body:
            problems.append(f"{key}: the lift and base come after the joints, as nori record writes them: {names}")
        unknown = [n for n in joints if n not in layout]
        if unknown:
            problems.append(f"{key}: joints {unknown} are not the robot's (it has {layout})")
        if key == ACTION and ("base.linear_m_s" in body) != ("base.angular_rad_s" in body):
            problems.append(f"{key}: the base is commanded by its speed and turn rate together: {body}")
        return [layout.index(n) for n in joints if n in layout], [BODY.index(n) for n in body]

    state_index, state_body = indices(STATE, inputs)
    action_index, action_body = indices(ACTION, outputs)
    cameras = {}
    for key, feature in inputs.items():
        if key.startswith(IMAGES):
            shape = feature.get("shape", [])
            if len(shape) != 3 or shape[0] != 3:
                problems.append(f"{key}: shape {shape} is not an RGB image (3, height, width)")
                continue
            cameras[key] = (key[len(IMAGES):], (shape[1], shape[2]))
    extras = sorted(k for k in inputs if k in SERVED)
    unserved = sorted(k for k in inputs if k not in SERVED and k != STATE and not k.startswith(IMAGES))
    fps = info.get("fps")
    if not isinstance(fps, (int, float)) or fps <= 0:
        problems.append(f"the dataset's fps {fps!r} is not a frame rate")
    if problems:
        raise MismatchError("; ".join(problems))
    return Plan(state_index, action_index, cameras, float(fps), extras, state_body, action_body, unserved)


def check_cameras(plan: Plan, obs: Observation) -> None:
    """The policy's cameras against an observation carrying images: each present, at the
    size the policy was trained on."""
    problems = []
    for key, (camera, (h, w)) in plan.cameras.items():
        image = obs.images.get(camera)
        if image is None:
            problems.append(f"{key}: the robot sends no camera {camera!r} (it sends {sorted(obs.images)})")
        elif (image.height, image.width) != (h, w):
            problems.append(f"{key}: camera {camera!r} is {image.width}x{image.height}, the policy was trained on {w}x{h}")
    if problems:
        raise MismatchError("; ".join(problems))


class Inputs:
    """The policy's inputs from the robot's observations, a NaN reading held at the joint's
    last valid value."""

    def __init__(self, plan: Plan, joints: int):
        self.plan = plan
        self.last = np.full(joints, np.nan, dtype=np.float32)

    def take(self, obs: Observation) -> dict[str, np.ndarray] | None:
        """The input features of ``obs`` (images as uint8 HxWx3), or None when a joint was
        never read or a camera's image is missing."""
        fresh = np.isfinite(obs.position)
        self.last = np.where(fresh, obs.position, self.last).astype(np.float32)
        if not np.isfinite(self.last[self.plan.state_index]).all():
            return None
        if any(camera not in obs.images for camera, _ in self.plan.cameras.values()):
            return None
        state = self.last[self.plan.state_index]
        if self.plan.state_body:
            body = obs.body_state()
            if body is None:  # the lift not homed or the base not running: nothing to act on
                return None
            state = np.concatenate([state, body[self.plan.state_body]]).astype(np.float32)
        out = {STATE: state}
        for key in self.plan.extras:
            if key == "observation.velocity":
                out[key] = np.nan_to_num(obs.velocity[self.plan.state_index]).astype(np.float32)
            elif key == "observation.joint_valid":
                out[key] = fresh[self.plan.state_index].astype(np.float32)
            elif key == "observation.camera_valid":
                out[key] = np.ones(len(self.plan.cameras), dtype=np.float32)
        for key, (camera, _) in self.plan.cameras.items():
            out[key] = obs.images[camera].rgb()
        return out


class Policy:
    """A LeRobot checkpoint: numpy inputs in, its whole action chunk (steps, action_dim) out,
    in the robot's units, as LeRobot's own inference computes it."""

    def __init__(self, checkpoint: Path, device: str = "cpu"):
        import torch
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors

        self.torch = torch
        directory = str(checkpoint.resolve())
        kind = json.loads((checkpoint / "config.json").read_text())["type"]
        # strict: a weight missing or left over is an error, not a log line.
        self.policy = get_policy_class(kind).from_pretrained(directory, strict=True)
        self.policy.to(device)
        self.policy.config.device = device
        overrides = {"device_processor": {"device": device}}
        self.pre, self.post = make_pre_post_processors(
            self.policy.config,
            pretrained_path=directory,
            preprocessor_overrides=overrides,
            postprocessor_overrides=overrides,
        )
        self.kind = kind
        self.image_keys = list(self.policy.config.image_features)
        self.reset()

    def reset(self) -> None:
        self.policy.reset()
        self.pre.reset()
        self.post.reset()

    def chunk(self, inputs: dict[str, np.ndarray], task: str) -> np.ndarray:
        torch = self.torch
        from lerobot.policies.utils import populate_queues

        with torch.inference_mode():
            obs: dict[str, Any] = {"task": task}
            for key, value in inputs.items():
                if value.dtype == np.uint8:  # HxWx3 -> (1, 3, H, W) in [0, 1]
                    obs[key] = torch.from_numpy(value).permute(2, 0, 1).float().div_(255).unsqueeze(0)
                else:
                    obs[key] = torch.from_numpy(np.asarray(value, dtype=np.float32)).unsqueeze(0)
            batch = {k: v for k, v in self.pre(obs).items() if k != ACTION}
            if self.kind == "diffusion":  # its observation history, as its select_action keeps it
                if self.image_keys:
                    batch["observation.images"] = torch.stack([batch[k] for k in self.image_keys], dim=-4)
                populate_queues(self.policy._queues, batch)
            return self.post(self.policy.predict_action_chunk(batch))[0].cpu().numpy()


def load_info(checkpoint: Path, dataset: Path | None) -> dict[str, Any]:
    if dataset is None:
        train = checkpoint / "train_config.json"
        root = json.loads(train.read_text()).get("dataset", {}).get("root") if train.exists() else None
        if not root:
            raise MismatchError(
                "the checkpoint does not name its joints and no training dataset is known: give --dataset DIR"
            )
        dataset = Path(root)
    info = dataset / "meta" / "info.json"
    if not info.exists():
        raise MismatchError(f"{info}: no such file (the training dataset's meta/info.json)")
    return json.loads(info.read_text())


def chunk_message(plan: Plan, layout: Layout, obs: Observation, chunk: np.ndarray, seq: int, steps: int | None) -> bytes:
    """The robot's ActionChunk of the policy's ``chunk`` (steps, action_dim) computed from ``obs``."""
    if steps:
        chunk = chunk[:steps]
    width = len(plan.action_index) + len(plan.action_body)
    if chunk.ndim != 2 or chunk.shape[1] != width:
        raise MismatchError(f"the policy returned a chunk of shape {chunk.shape}, not (steps, {width})")
    joints = len(plan.action_index)
    targets = np.zeros((chunk.shape[0], len(layout.names)), dtype=np.float32)
    targets[:, plan.action_index] = chunk[:, :joints]
    body = {BODY[axis]: chunk[:, joints + i] for i, axis in enumerate(plan.action_body)}
    lift = body.get("lift.height_m")
    twist = np.stack([body["base.linear_m_s"], body["base.angular_rad_s"]], axis=1) if "base.linear_m_s" in body else None
    offsets = [int(round(k * 1e9 / plan.fps)) for k in range(chunk.shape[0])]
    return action_chunk(seq, obs.timestamp_ns, offsets, targets, plan.joint_mask, lift, twist)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="nori-serve-lerobot", description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint", type=Path, help="a pretrained_model directory lerobot-train wrote")
    ap.add_argument("--robot", required=True, help="the robot's fleet id (nori/<id>/...)")
    ap.add_argument("--dataset", type=Path, help="the training dataset (for the names); default: from train_config.json")
    ap.add_argument("--task", default="", help="the task text given to language-conditioned policies")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--steps", type=int, help="send only the chunk's first STEPS steps")
    ap.add_argument("--zenoh-config", type=Path, help="a zenoh JSON5 file (the fleet's inference TLS identity)")
    ap.add_argument("--listen", action="append", default=[])
    ap.add_argument("--connect", action="append", default=[])
    ap.add_argument("--run-for", type=float, help="stop after this many seconds")
    ap.add_argument("--wait-s", type=float, default=30.0, help="how long to wait for the robot at start")
    ap.add_argument("--report", type=Path, help="write a JSON report here on exit")
    args = ap.parse_args(argv)

    checkpoint = args.checkpoint
    config_file = checkpoint / "config.json"
    try:
        if not config_file.exists():
            raise MismatchError(f"{config_file}: no such file (give the pretrained_model directory)")
        config = json.loads(config_file.read_text())
        info = load_info(checkpoint, args.dataset)
    except (MismatchError, json.JSONDecodeError) as e:
        print(f"nori-serve-lerobot: {e}", file=sys.stderr)
        return 2

    session = open_session(args.zenoh_config, args.listen, args.connect)
    fleet = Fleet(session)
    try:
        return serve(args, config, info, fleet)
    except MismatchError as e:
        print(f"nori-serve-lerobot: {checkpoint} does not fit robot {args.robot}: {e}", file=sys.stderr)
        return 2
    except TimeoutError as e:
        print(f"nori-serve-lerobot: {e}", file=sys.stderr)
        return 3
    finally:
        fleet.close()
        session.close()


def serve(args: argparse.Namespace, config: dict[str, Any], info: dict[str, Any], fleet: Fleet) -> int:
    layout = fleet.layout(args.robot, timeout=args.wait_s)
    the_plan = plan(config, info, layout.names)
    for key in the_plan.unserved:
        print(f"nori-serve-lerobot: note: {key} is not in the robot's observations; the policy must not read it", file=sys.stderr)
    # The cameras: checked on the first observation that carries images.
    if the_plan.cameras:
        deadline = time.monotonic() + args.wait_s
        while True:
            obs = fleet.observations(timeout=1.0).get(args.robot)
            if obs is not None and obs.images:
                check_cameras(the_plan, obs)
                break
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"robot {args.robot} sent no observation with images within {args.wait_s} s "
                    "(its agent's [observation] cameras in fleet-agent.toml)"
                )
    policy = Policy(args.checkpoint, args.device)
    inputs = Inputs(the_plan, len(layout.names))
    print(
        f"nori-serve-lerobot: {policy.kind} policy serving robot {args.robot}: "
        f"{len(the_plan.state_index)} joints in, {len(the_plan.action_index)} out, cameras "
        f"{[c for c, _ in the_plan.cameras.values()]}, steps 1/{the_plan.fps:g} s",
        file=sys.stderr,
    )
    seq, latencies, observations, skipped = 0, [], 0, 0
    started = time.monotonic()
    try:
        while args.run_for is None or time.monotonic() - started < args.run_for:
            obs = fleet.observations(timeout=0.5).get(args.robot)
            if obs is None:
                continue
            observations += 1
            x = inputs.take(obs)
            if x is None:
                skipped += 1
                continue
            t = time.perf_counter()
            chunk = policy.chunk(x, args.task)
            seq += 1
            fleet.send(args.robot, chunk_message(the_plan, layout, obs, chunk, seq, args.steps))
            latencies.append(time.perf_counter() - t)
    except KeyboardInterrupt:
        pass
    if args.report:
        ms = np.array(latencies) * 1e3
        args.report.write_text(
            json.dumps(
                {
                    "policy": policy.kind,
                    "chunks_sent": seq,
                    "observations": observations,
                    "observations_skipped": skipped,
                    "inference_ms_p50": float(np.percentile(ms, 50)) if len(ms) else None,
                    "inference_ms_p99": float(np.percentile(ms, 99)) if len(ms) else None,
                    "undecodable": fleet.undecodable,
                }
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
