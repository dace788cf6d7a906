#!/usr/bin/env bash
# Records a LeRobot dataset from the simulated robot with two cameras, for the LeRobot training
# check (lerobot-train-check.sh): the whole stack (`nori up`) with the head and left-wrist
# cameras at 320x240, 30 fps, `nori policy-server` waving the left arm, the left elbow's servo
# silenced for 2 s during the second episode (a recording in which a servo went missing), the
# lift going up and down and the base backing and returning (a 19-wide state and action), and
# `nori record --lift --base` taking EPISODES episodes of 8 s.
#
#   tests/python/record-sim-dataset.sh OUT [EPISODES]
set -euo pipefail
out="${1:?usage: $0 OUT [EPISODES]}"
episodes="${2:-6}"
repo="$(cd "$(dirname "$0")/../.." && pwd)"
bin="$repo/target/release"
(cd "$repo" && cargo build --release --workspace --bins)
work="$(mktemp -d)"
small() { perl -0pe 's/width = 1280\nheight = 720\nfps = 30/width = 320\nheight = 240\nfps = 30/g' "$1"; }
small "$repo/body/robots/nori-a3.toml" >"$work/robot.toml"
small "$repo/deploy/config/camera.toml" >"$work/camera.toml"
domain="lrcheck$$"
"$bin/nori" up --dir "$work/dev" --domain "$domain" --robot "$work/robot.toml" \
  --camera-config "$work/camera.toml" --camera head --camera left_wrist \
  --silence left_arm:4@18+2 2>"$work/up.log" &
up=$!
"$bin/nori" policy-server --joints left_shoulder_pitch,left_elbow --centre -0.7 --amplitude 0.35 \
  --period-s 3 2>"$work/policy.log" >/dev/null &
policy=$!
# The body: the lift between 0.1 and 0.35 m, the base 0.4 m back and forth (clear of the table
# ahead of it), while the recording lasts. The lidar runs: without it the base's protective field
# is blind and lets it move nowhere.
(
  while true; do
    "$bin/nori" goal --domain "$domain" lift=0.35 2>/dev/null || true
    "$bin/nori" base --domain "$domain" -0.1 0.0 --for 4 >/dev/null 2>&1 || sleep 1
    "$bin/nori" goal --domain "$domain" lift=0.1 2>/dev/null || true
    "$bin/nori" base --domain "$domain" 0.1 0.0 --for 4 >/dev/null 2>&1 || sleep 1
  done
) &
body=$!
trap 'kill $policy $body 2>/dev/null; kill -INT $up 2>/dev/null; wait $up 2>/dev/null || true' EXIT
"$bin/nori" record --domain "$domain" --dataset "$out" --task "wave the left arm" \
  --camera head --camera left_wrist --lift --base --episodes "$episodes" --episode-s 8 --reset-s 1 --wait-s 30
echo "recorded into $out (logs in $work)" >&2
