"""The policy of `nori bench policy-latency`, in Python: it answers every observation of a robot
at once with a one-step chunk (20 ms after the observation) that puts one joint at -0.9 or -0.5
rad, flipping every half second of the robot's clock, so the bench can tell which observation
each goal on the wire answers. The Rust reference of the same policy runs inside the bench.

    python -m nori_client.flip --listen tcp/127.0.0.1:PORT --robot ID --joint left_elbow --run-for S
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from .client import Fleet, action_chunk, open_session

#: The two targets, and how long each holds on the robot's clock.
TARGETS = (-0.9, -0.5)
FLIP_NS = 500_000_000


def target_at(timestamp_ns: int) -> float:
    return TARGETS[(timestamp_ns // FLIP_NS) % 2]


def main() -> None:
    ap = argparse.ArgumentParser(prog="python -m nori_client.flip")
    ap.add_argument("--listen", required=True)
    ap.add_argument("--robot", required=True)
    ap.add_argument("--joint", default="left_elbow")
    ap.add_argument("--run-for", type=float, required=True)
    args = ap.parse_args()
    session = open_session(listen=[args.listen])
    fleet = Fleet(session)
    try:
        layout = fleet.layout(args.robot, timeout=30)
        j = layout.names.index(args.joint)
        targets = np.zeros((1, len(layout.names)), np.float32)
        seq = 0
        end = time.monotonic() + args.run_for
        while time.monotonic() < end:
            obs = fleet.observations(timeout=0.2).get(args.robot)
            if obs is None:
                continue
            targets[0, j] = target_at(obs.timestamp_ns)
            seq += 1
            fleet.send(args.robot, action_chunk(seq, obs.timestamp_ns, [20_000_000], targets, 1 << j))
    finally:
        fleet.close()
        session.close()


if __name__ == "__main__":
    main()
