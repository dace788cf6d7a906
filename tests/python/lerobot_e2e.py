"""The loop closed in simulation: demonstrations recorded, a LeRobot ACT policy trained on them,
served back to the simulated robot, and judged against the demonstrator and a policy that does
nothing. Run by lerobot-e2e.sh (in the LeRobot environment, with nori_client installed).

The task: a red ball is placed at random on the table in view of the left wrist camera; reach it,
i.e. bring the arm over it so that it sits at the centre of the wrist camera's picture. Each run
starts the whole simulated stack (`nori up`) with the ball moved in the robot description, and
the arm is first brought to one start pose (shoulder pitch -0.6, elbow -0.8).

- The demonstrator knows where it put the ball: `nori sim aim` (the simulated world's ground
  truth, the same kinematics and camera model the renderer uses) gives the shoulder roll and
  elbow that centre it, and the demonstrator moves there from the start pose on a minimum-jerk
  path, through the fleet agent's gate like any policy (nori_client, action chunks on the
  robot's clock), while `nori record` records the episode with the wrist camera's video.
- lerobot-train trains a small ACT (CPU, 160x120 images, no pretrained backbone).
- nori-serve-lerobot serves the checkpoint on new ball positions.
- Each run is judged on the arm's final joint angles as the robot reads them by `nori sim aim`:
  where the ball is in the wrist camera's picture (0 = centre, 1 = the edge) and how far the
  tool point is from the ball's centre. The do-nothing policy (it outputs the observation it got:
  the arm holds the start pose) is judged at the start pose as read before each policy run.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from nori_client import Fleet, action_chunk, open_session

START = {"left_shoulder_pitch": -0.6, "left_elbow": -0.8, "left_shoulder_roll": 0.0}
TURNED = ("left_shoulder_roll", "left_elbow")
COMMANDED = ("left_shoulder_pitch", "left_shoulder_roll", "left_elbow")
TASK = "reach the red ball"


def log(*a):
    print("e2e:", *a, file=sys.stderr, flush=True)


class Repo:
    def __init__(self, root: Path, work: Path):
        self.root = root
        self.bin = root / "target/release"
        self.work = work

    def nori(self, *args: str, **kw) -> subprocess.CompletedProcess:
        return subprocess.run([str(self.bin / "nori"), *args], check=True, capture_output=True, text=True, **kw)

    def aim(self, robot: Path, at: dict[str, float], centre: bool = False) -> dict:
        args = ["sim", "aim", "--description", str(robot), "--camera", "left_wrist",
                "--at", ",".join(f"{k}={v}" for k, v in at.items())]
        if centre:
            args += ["--centre", ",".join(TURNED)]
        return json.loads(self.nori(*args).stdout)


def small(text: str) -> str:
    return text.replace("width = 1280\nheight = 720\nfps = 30", "width = 160\nheight = 120\nfps = 30")


def robot_with_ball(repo: Repo, x: float, y: float, out: Path) -> Path:
    text = small((repo.root / "body/robots/nori-a3.toml").read_text())
    text, n = re.subn(r'(name = "red ball"\ncolour = \[[^\]]*\]\ncenter = )\[[^\]]*\]',
                      lambda m: f"{m.group(1)}[{x:.4f}, {y:.4f}, 0.74]", text)
    assert n == 1, "the red ball's centre in the description"
    out.write_text(text)
    return out


def ball_positions(repo: Repo, n: int, seed: int) -> list[tuple[float, float, dict]]:
    """n positions on the table, each in view at the start pose and centrable (by aim)."""
    rng = random.Random(seed)
    out = []
    while len(out) < n:
        x, y = rng.uniform(0.42, 0.62), rng.uniform(-0.02, 0.32)
        robot = robot_with_ball(repo, x, y, repo.work / "probe.toml")
        try:
            a = repo.aim(robot, START, centre=True)
        except subprocess.CalledProcessError:
            continue
        o = a["offset"]
        if o is not None and max(abs(o[0]), abs(o[1])) < 0.85:
            out.append((x, y, a))
    return out


class Stack:
    """`nori up` of the simulated robot with the ball at (x, y), its agent connecting to `endpoint`."""

    def __init__(self, repo: Repo, tag: str, robot: Path, endpoints: list[str]):
        self.repo, self.dir = repo, repo.work / tag
        self.dir.mkdir(parents=True, exist_ok=True)
        self.domain = "e2e" + re.sub(r"[^a-z0-9]", "", tag)
        camera = self.dir / "camera.toml"
        camera.write_text(small((repo.root / "deploy/config/camera.toml").read_text()))
        agent = self.dir / "fleet-agent.toml"
        text = (repo.root / "deploy/config/fleet-agent.toml").read_text()
        text = re.sub(r'connect = \[[^\]]*\]', "connect = " + json.dumps(endpoints), text, count=1)
        text = text.replace("cameras = []", 'cameras = ["left_wrist"]')
        text = text.replace("lidar = true", "lidar = false")
        agent.write_text(text)
        self.log = open(self.dir / "up.log", "w")
        self.proc = subprocess.Popen(
            [str(repo.bin / "nori"), "up", "--dir", str(self.dir / "dev"), "--domain", self.domain,
             "--robot", str(robot), "--camera-config", str(camera), "--camera", "left_wrist",
             "--no-lidar", "--agent-config", str(agent)],
            stdout=self.log, stderr=subprocess.STDOUT)

    def stop(self) -> None:
        """Stops the stack (torque off: the arm sags, so its angles are read before)."""
        self.proc.send_signal(signal.SIGINT)
        self.proc.wait(timeout=30)
        self.log.close()


def angles_now(fleet: Fleet, robot: str) -> dict[str, float]:
    """The arm's joint angles as the robot reads them now (each joint's newest valid reading
    over half a second of observations)."""
    names = fleet.layout(robot).names
    last = np.full(len(names), np.nan)
    deadline = time.monotonic() + 0.5
    while time.monotonic() < deadline or not np.isfinite(last).all():
        obs = fleet.observations(timeout=1.0).get(robot)
        if obs is not None:
            last = np.where(np.isfinite(obs.position), obs.position, last)
    return dict(zip(names, last.tolist()))


def minjerk(a: float, b: float, s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return a + (b - a) * (10 * s**3 - 15 * s**4 + 6 * s**5)


def drive(fleet: Fleet, robot: str, goal: dict[str, float], duration_s: float, hold_s: float, seq: list[int]) -> None:
    """Moves the commanded joints from where they are to `goal` on a minimum-jerk path of
    `duration_s`, then holds for `hold_s`: chunks of 0.5 s at 50 Hz, re-planned on each
    observation, on the robot's clock."""
    layout = fleet.layout(robot)
    idx = [layout.names.index(j) for j in COMMANDED]
    mask = sum(1 << i for i in idx)
    first = None
    while first is None:
        first = fleet.observations(timeout=2.0).get(robot)
        if first is not None and not np.isfinite(first.position[idx]).all():
            first = None
    t0, start = first.timestamp_ns, first.position[idx].astype(float)
    target = np.array([goal[j] for j in COMMANDED])
    end_ns = t0 + int((duration_s + hold_s) * 1e9)
    while True:
        obs = fleet.observations(timeout=1.0).get(robot)
        if obs is None:
            continue
        if obs.timestamp_ns > end_ns:
            return
        offsets = [k * 20_000_000 for k in range(25)]
        targets = np.zeros((25, len(layout.names)), np.float32)
        for k, off in enumerate(offsets):
            s = (obs.timestamp_ns + off - t0) / 1e9 / duration_s
            targets[k, idx] = [minjerk(a, b, s) for a, b in zip(start, target)]
        seq[0] += 1
        fleet.send(robot, action_chunk(seq[0], obs.timestamp_ns, offsets, targets, mask))


def settle(fleet: Fleet, robot: str, target: dict[str, float], seq: list[int], rounds: int = 4) -> dict[str, float]:
    """Brings the commanded joints to `target` as read, not only as commanded: a loaded
    servo's position loop stops short (the shoulder sags ~0.04 rad under the arm's weight), so
    the command is corrected by what is left, a few times. Returns the last command."""
    cmd = dict(target)
    for _ in range(rounds):
        drive(fleet, robot, cmd, 0.5, 0.4, seq)
        now = angles_now(fleet, robot)
        err = {j: target[j] - now[j] for j in COMMANDED}
        if max(abs(e) for e in err.values()) < 0.004:
            break
        cmd = {j: cmd[j] + err[j] for j in COMMANDED}
    return cmd


def wait_line(path: Path, pattern: str, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if path.exists() and re.search(pattern, path.read_text()):
            return
        time.sleep(0.05)
    raise TimeoutError(f"no {pattern!r} in {path} within {timeout} s")


def free_endpoint() -> str:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def judge(repo: Repo, robot: Path, final: dict[str, float]) -> dict:
    at = {j: final[j] for j in ("left_shoulder_pitch", "left_shoulder_roll", "left_bicep_rotation", "left_elbow",
                                "left_forearm_roll", "left_wrist_pitch", "left_wrist_roll")}
    a = repo.aim(robot, at)
    o = a["offset"]
    return {"offset": None if o is None else float(np.hypot(*o)), "tip_distance_m": a["tip_distance_m"],
            "final": {k: round(v, 3) for k, v in at.items() if abs(v) > 1e-3}}


def record(repo: Repo, dataset: Path, positions, episode_s: float) -> list[dict]:
    results = []
    for k, (x, y, aim) in enumerate(positions):
        robot = robot_with_ball(repo, x, y, repo.work / f"demo-{k}.toml")
        endpoint = free_endpoint()
        session = open_session(listen=[endpoint])
        fleet = Fleet(session)
        stack = Stack(repo, f"demo-{k}", robot, [endpoint])
        seq = [0]
        try:
            fleet.layout("sim-0001", timeout=60)
            drive(fleet, "sim-0001", START, 1.5, 0.5, seq)
            start_cmd = settle(fleet, "sim-0001", START, seq)
            rec_log = stack.dir / "record.log"
            rec = subprocess.Popen(
                [str(repo.bin / "nori"), "record", "--domain", stack.domain, "--dataset", str(dataset),
                 "--task", TASK, "--camera", "left_wrist", "--episodes", "1", "--episode-s", str(episode_s),
                 "--wait-s", "30"],
                stdout=subprocess.DEVNULL, stderr=open(rec_log, "w"))
            wait_line(rec_log, r"episode\(s\) of", 60)
            # Still for a moment, then to the ball (corrected as read), then holding over it.
            drive(fleet, "sim-0001", start_cmd, 0.6, 0.0, seq)
            goal = {**START, **aim["centre"]["at"]}
            shift = {j: start_cmd[j] - START[j] for j in COMMANDED}
            drive(fleet, "sim-0001", {j: goal[j] + shift[j] for j in COMMANDED}, 2.5, 0.0, seq)
            cmd = settle(fleet, "sim-0001", goal, seq)
            while rec.poll() is None:
                drive(fleet, "sim-0001", cmd, 0.1, 0.3, seq)
            if rec.wait(timeout=60) != 0:
                raise RuntimeError(f"nori record failed: {rec_log.read_text()[-2000:]}")
            final = angles_now(fleet, "sim-0001")
        finally:
            fleet.close()
            session.close()
            stack.stop()
        r = judge(repo, robot, final)
        log(f"demonstration {k}: ball at ({x:.3f}, {y:.3f}), offset {r['offset']:.3f}, tip {r['tip_distance_m']:.3f} m")
        results.append({"ball": [x, y], **r})
    return results


def train(venv: Path, dataset: Path, out: Path, steps: int, batch: int) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    cmd = [str(venv / "bin/lerobot-train"), "--dataset.repo_id=local/nori-reach", f"--dataset.root={dataset}",
           "--policy.type=act", "--policy.device=cpu", "--policy.push_to_hub=false",
           "--policy.pretrained_backbone_weights=null", "--policy.chunk_size=30", "--policy.n_action_steps=30",
           "--policy.dim_model=256", "--policy.dim_feedforward=1024", "--policy.n_encoder_layers=2",
           "--policy.n_decoder_layers=1", f"--steps={steps}", f"--batch_size={batch}", "--log_freq=50",
           f"--save_freq={steps}", "--num_workers=2", "--wandb.enable=false", f"--output_dir={out}"]
    t = time.monotonic()
    done = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "HF_HUB_OFFLINE": "1"})
    wall = time.monotonic() - t
    text = done.stdout + done.stderr
    (out.parent / "train.log").write_text(text)
    if done.returncode != 0:
        raise RuntimeError(f"lerobot-train exited {done.returncode}:\n{text[-3000:]}")
    losses = [float(m) for m in re.findall(r"\bloss:\s*([-+0-9.eEnaif]+)", text)]
    return {"steps": steps, "batch_size": batch, "wall_s": round(wall, 1), "loss_first": losses[:3], "loss_last": losses[-3:]}


def serve(repo: Repo, venv: Path, checkpoint: Path, dataset: Path, positions, seconds: float) -> list[dict]:
    results = []
    for k, (x, y, _) in enumerate(positions):
        robot = robot_with_ball(repo, x, y, repo.work / f"eval-{k}.toml")
        ours, policy = free_endpoint(), free_endpoint()
        session = open_session(listen=[ours])
        fleet = Fleet(session)
        stack = Stack(repo, f"eval-{k}", robot, [ours, policy])
        report = stack.dir / "serve.json"
        try:
            # The start pose first (the demonstrator's driving, not recorded), then the policy.
            fleet.layout("sim-0001", timeout=60)
            drive(fleet, "sim-0001", START, 1.5, 0.5, [0])
            settle(fleet, "sim-0001", START, [0])
            start = angles_now(fleet, "sim-0001")
            served = subprocess.run(
                [str(venv / "bin/nori-serve-lerobot"), str(checkpoint), "--robot", "sim-0001", "--dataset", str(dataset),
                 "--task", TASK, "--listen", policy, "--run-for", str(seconds), "--report", str(report)],
                capture_output=True, text=True, timeout=300)
            if served.returncode != 0:
                raise RuntimeError(f"nori-serve-lerobot exited {served.returncode}: {served.stderr[-2000:]}")
            final = angles_now(fleet, "sim-0001")
        finally:
            fleet.close()
            session.close()
            stack.stop()
        r = judge(repo, robot, final)
        r["hold_start"] = judge(repo, robot, start)
        s = json.loads(report.read_text())
        log(f"policy {k}: ball at ({x:.3f}, {y:.3f}), offset {r['offset']}, tip {r['tip_distance_m']:.3f} m, "
            f"{s['chunks_sent']} chunks, inference p50 {s['inference_ms_p50']:.0f} ms")
        results.append({"ball": [x, y], **r, "serve": s})
    return results


def summary(runs: list[dict]) -> dict:
    off = [r["offset"] if r["offset"] is not None else float("nan") for r in runs]
    tip = [r["tip_distance_m"] for r in runs]
    return {"offset_mean": float(np.nanmean(off)), "offset_max": float(np.nanmax(off)),
            "out_of_view": sum(r["offset"] is None for r in runs),
            "tip_distance_mean_m": float(np.mean(tip)), "tip_distance_max_m": float(np.max(tip))}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--venv", type=Path, required=True)
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--evaluations", type=int, default=6)
    ap.add_argument("--episode-s", type=float, default=5.0)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--skip-record", action="store_true", help="reuse the dataset in WORK")
    ap.add_argument("--skip-train", action="store_true", help="reuse the checkpoint in WORK")
    args = ap.parse_args()
    repo = Repo(Path(__file__).resolve().parents[2], args.work)
    args.work.mkdir(parents=True, exist_ok=True)
    dataset = args.work / "dataset"
    report: dict = {"task": TASK, "seed": args.seed}
    import lerobot
    import torch

    report["versions"] = {"lerobot": lerobot.__version__, "torch": torch.__version__, "python": sys.version.split()[0]}
    positions = ball_positions(repo, args.episodes + args.evaluations, args.seed)
    demo_positions, eval_positions = positions[: args.episodes], positions[args.episodes :]
    t = time.monotonic()
    if not args.skip_record:
        shutil.rmtree(dataset, ignore_errors=True)
        report["demonstrations"] = record(repo, dataset, demo_positions, args.episode_s)
        report["record_wall_s"] = round(time.monotonic() - t, 1)
    out = args.work / "train"
    if not args.skip_train:
        report["train"] = train(args.venv, dataset, out, args.steps, args.batch)
        log(f"trained: {report['train']}")
    checkpoint = out / "checkpoints/last/pretrained_model"
    policy = serve(repo, args.venv, checkpoint, dataset, eval_positions, args.episode_s + 1.0)
    # The demonstrator on the evaluation positions: where it puts the arm (its aim, which the
    # recorded demonstrations show it reaching as read), and the do-nothing policy: the start
    # pose as read before each policy run.
    demo = [{"ball": [x, y], "offset": float(np.hypot(*a["centre"]["offset"])),
             "tip_distance_m": a["centre"]["tip_distance_m"]} for x, y, a in eval_positions]
    hold = [{"ball": r["ball"], **r.pop("hold_start")} for r in policy]
    report["evaluation"] = {"act": policy, "demonstrator_aim": demo, "hold_start": hold}
    report["summary"] = {"act": summary(policy), "demonstrator_aim": summary(demo), "hold_start": summary(hold)}
    if "demonstrations" in report:
        report["summary"]["demonstrations_recorded"] = summary(report["demonstrations"])
    (args.work / "report.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report["summary"], indent=1))


if __name__ == "__main__":
    main()
