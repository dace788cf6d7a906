"""A policy server in a few lines against a running robot (the process test
tests/tests/python_client.rs starts the simulated robot and its fleet agent, then this):
the layout by name, observations with the wrist camera's picture decoded to numpy, action
chunks that move one joint, and two the robot must refuse. Prints a JSON report.

    python robot_round_trip.py --listen tcp/127.0.0.1:7447 --robot sim-0001 \
        --camera left_wrist --joint left_elbow --target -0.8
"""

import argparse
import json
import time

import numpy as np

from nori_client import Fleet, action_chunk, encode, open_session, seconds_to_offsets


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--listen", required=True)
    ap.add_argument("--robot", required=True)
    ap.add_argument("--camera", required=True)
    ap.add_argument("--joint", required=True)
    ap.add_argument("--target", type=float, required=True)
    ap.add_argument("--seconds", type=float, default=4.0)
    args = ap.parse_args()

    session = open_session(listen=[args.listen])
    fleet = Fleet(session)
    try:
        run(args, fleet)
    finally:
        # zenoh's threads keep the interpreter alive until the session is closed.
        fleet.close()
        session.close()


def run(args: argparse.Namespace, fleet: Fleet) -> None:
    layout = fleet.layout(args.robot, timeout=30)
    j = layout.names.index(args.joint)
    n = len(layout.names)

    # The first observation that carries the camera's picture.
    deadline = time.monotonic() + 30
    picture = None
    while picture is None:
        if time.monotonic() > deadline:
            raise SystemExit(f"no picture of {args.camera} within 30 s")
        obs = fleet.observations(timeout=1.0).get(args.robot)
        if obs is not None and args.camera in obs.images:
            picture = obs.images[args.camera].rgb()

    # Nonsense the robot's gate must refuse: a NaN target and one far outside the range.
    obs = fleet.observations(timeout=5.0)[args.robot]
    nan_targets = np.zeros(n, dtype=np.float32)
    nan_targets[j] = np.nan
    bad = dict(seq=1, observation_ns=obs.timestamp_ns, step_offsets_ns=[20_000_000], joint_count=n, joint_mask=1 << j,
               lift_m=[], base_twist=[])
    fleet.send(args.robot, encode("ActionChunk", {**bad, "targets": nan_targets}))
    far = np.zeros(n, dtype=np.float32)
    far[j] = 50.0
    fleet.send(args.robot, encode("ActionChunk", {**bad, "seq": 2, "targets": far}))

    # Then a policy: every observation, ten steps 20 ms apart from where the joint is towards
    # the target, only that joint commanded.
    seq, sent, observations = 2, 0, 0
    end = time.monotonic() + args.seconds
    last = obs
    while time.monotonic() < end:
        newest = fleet.observations(timeout=0.2).get(args.robot)
        # A servo that missed its reply in that cycle reads NaN: no plan from it.
        if newest is None or not np.isfinite(newest.position[j]):
            continue
        last = newest
        observations += 1
        start = float(newest.position[j])
        steps = np.linspace(start, args.target, 11)[1:]
        targets = np.zeros((10, n), dtype=np.float32)
        targets[:, j] = steps
        seq += 1
        fleet.send(args.robot, action_chunk(seq, newest.timestamp_ns, seconds_to_offsets(50, 10, first=0.02), targets, 1 << j))
        sent += 1
    print(
        json.dumps(
            {
                "joints": layout.names,
                "picture_shape": list(picture.shape),
                "picture_spread": int(picture.max()) - int(picture.min()),
                "observations": observations,
                "chunks_sent": sent,
                "position_end": float(last.position[j]),
                "undecodable": fleet.undecodable,
            }
        )
    )


if __name__ == "__main__":
    main()
