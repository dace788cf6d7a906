#!/usr/bin/env python3
"""The sensor-plane issue's acceptance check with the real `lerobot` package (run by
lerobot-train-check.sh, in its venv; outside CI: LeRobot with torch is several GB).

On a dataset recorded by `nori record` with cameras:
1. `LeRobotDataset` from the local root: items carry decoded images (float, CHW, in [0, 1], of
   the feature's size) for every camera;
2. a `DataLoader` over every frame;
3. `delta_timestamps` for action chunks (shape, padding at an episode's end);
4. the recording has a servo that went missing (some `observation.joint_valid` 0) and no NaN;
5. `lerobot-train` for each policy asked (ACT by default, on the CPU, no pretrained backbone:
   this machine reaches no model hub) runs the asked steps with finite, falling loss.

Prints one JSON report; exits 1 with the reason on the first failure.
"""
import argparse
import json
import math
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def fail(msg):
    print(f"LeRobot training check failed: {msg}", file=sys.stderr)
    sys.exit(1)


def check(cond, msg):
    if not cond:
        fail(msg)


def train(venv, root, policy, steps, out):
    """Runs lerobot-train; returns the logged losses, in order, and the wall time."""
    cmd = [
        str(Path(venv) / "bin/lerobot-train"),
        "--dataset.repo_id=local/nori", f"--dataset.root={root}",
        f"--policy.type={policy}", "--policy.device=cpu", "--policy.push_to_hub=false",
        f"--steps={steps}", "--batch_size=4", "--log_freq=1", "--save_checkpoint=false",
        "--num_workers=0", "--wandb.enable=false", f"--output_dir={out}",
    ]
    # Both default to ImageNet weights for their ResNet, downloaded at start: no hub here.
    cmd.append("--policy.pretrained_backbone_weights=null")
    t0 = time.monotonic()
    done = subprocess.run(cmd, capture_output=True, text=True, env={"HF_HUB_OFFLINE": "1", "PATH": "/usr/bin:/bin"})
    wall = time.monotonic() - t0
    log = done.stdout + done.stderr
    (Path(out).parent / f"{policy}.log").write_text(log)
    check(done.returncode == 0, f"lerobot-train --policy.type={policy} exited {done.returncode}:\n{log[-3000:]}")
    losses = [float(x) for x in re.findall(r"\bloss:\s*([-+0-9.eEnaif]+)", log)]
    return losses, wall


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--venv", required=True)
    ap.add_argument("--policies", default="act", help="comma-separated policy types to train")
    a = ap.parse_args()
    root = Path(a.dataset).resolve()

    import torch
    import lerobot
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    report = {"python": sys.version.split()[0], "lerobot": lerobot.__version__, "torch": torch.__version__}
    ds = LeRobotDataset("local/nori", root=root)
    cams = list(ds.meta.video_keys)
    check(cams, "no video feature: record with --camera")
    report.update(frames=ds.num_frames, episodes=ds.num_episodes, cameras=cams,
                  video_backend=getattr(ds, "_video_backend", None))

    # 1. Decoded images.
    for i in [0, ds.num_frames // 2, ds.num_frames - 1]:
        item = ds[i]
        for k in cams:
            h, w, c = ds.meta.features[k]["shape"]
            img = item[k]
            check(tuple(img.shape) == (c, h, w), f"frame {i} {k}: shape {tuple(img.shape)}, feature {(c, h, w)}")
            check(img.dtype == torch.float32 and 0.0 <= float(img.min()) and float(img.max()) <= 1.0,
                  f"frame {i} {k}: {img.dtype} in [{float(img.min())}, {float(img.max())}]")
    first, later = ds[0][cams[0]], ds[min(ds.num_frames - 1, 60)][cams[0]]
    report["image_change_first_vs_2s"] = float((first - later).abs().mean())

    # 2. Every frame through a DataLoader.
    t0 = time.monotonic()
    seen, nan = 0, 0
    valid_zero = 0
    for batch in torch.utils.data.DataLoader(ds, batch_size=32, num_workers=0, shuffle=False):
        seen += len(batch["index"])
        for k, v in batch.items():
            if torch.is_tensor(v) and v.is_floating_point():
                nan += int((~torch.isfinite(v)).sum())
        valid_zero += int((batch["observation.joint_valid"] < 0.5).sum())
    check(seen == ds.num_frames, f"the DataLoader gave {seen} frames of {ds.num_frames}")
    check(nan == 0, f"{nan} non-finite values in the batches")
    report["dataloader_s"] = round(time.monotonic() - t0, 1)

    # 4. A servo went missing in the recording: held values marked, nothing NaN.
    check(valid_zero > 0, "no joint was ever missing: record with a silenced servo (record-sim-dataset.sh does)")
    report["missing_joint_samples"] = valid_zero

    # 4b. The whole body (`nori record --lift --base`): the lift's height and the base's twist
    # after the joints in the state and the action, named, and moving.
    names = ds.meta.features["observation.state"]["names"]
    report["state_width"] = len(names)
    body = ["lift.height_m", "base.linear_m_s", "base.angular_rad_s"]
    if names[-3:] == body:
        check(ds.meta.features["action"]["names"] == names, "action and state name different dimensions")
        state = torch.stack([ds[i]["observation.state"] for i in range(0, ds.num_frames, 5)])
        spans = (state.max(dim=0).values - state.min(dim=0).values)[-3:].tolist()
        check(spans[0] > 0.05 and spans[1] > 0.05, f"the lift and base do not move in the data: spans {spans}")
        report["body_spans"] = [round(x, 3) for x in spans]
        report["odometry_shape"] = list(ds[0]["observation.odometry"].shape)

    # 3. Action chunks by delta_timestamps.
    fps, chunk = ds.meta.fps, 20
    deltas = {"action": [k / fps for k in range(chunk)], cams[0]: [-1 / fps, 0.0]}
    chunks = LeRobotDataset("local/nori", root=root, delta_timestamps=deltas)
    width = ds.meta.features["action"]["shape"][0]
    mid = chunks[0]
    check(tuple(mid["action"].shape) == (chunk, width), f"action chunk {tuple(mid['action'].shape)}")
    check(tuple(mid[cams[0]].shape)[0] == 2, f"two frames of {cams[0]}: {tuple(mid[cams[0]].shape)}")
    ends = chunks.meta.episodes["dataset_to_index"]
    last = chunks[int(ends[0]) - 1]
    check(bool(last["action_is_pad"][1:].all()) and not bool(last["action_is_pad"][0]),
          "an episode's last frame: its chunk is padded after the first step")

    # 5. Training.
    out = Path(tempfile.mkdtemp(prefix="nori-lerobot-train-"))
    report["train"] = {}
    for policy in a.policies.split(","):
        losses, wall = train(a.venv, root, policy, a.steps, out / policy)
        check(len(losses) >= a.steps, f"{policy}: {len(losses)} losses logged for {a.steps} steps")
        check(all(math.isfinite(x) for x in losses), f"{policy}: non-finite loss {losses}")
        head, tail = losses[:5], losses[-5:]
        check(sum(tail) / len(tail) < sum(head) / len(head), f"{policy}: loss not falling: {losses}")
        report["train"][policy] = {"steps": len(losses), "first5": head, "last5": tail,
                                   "wall_s": round(wall, 1), "log": str(out / f"{policy}.log")}
    print(json.dumps(report))


if __name__ == "__main__":
    main()
