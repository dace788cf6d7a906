#!/usr/bin/env bash
# The loop closed in simulation (outside CI: LeRobot with torch is several GB): a scripted
# demonstrator reaches a red ball placed at random in view of the left wrist camera while
# `nori record` records; `lerobot-train` trains a small ACT on the CPU; `nori-serve-lerobot`
# serves it to the simulated robot on new ball positions; each run is judged by where the ball
# ends up in the wrist camera's picture and how far the tool point is from it, against the
# demonstrator and a policy that holds still. What it does is in lerobot_e2e.py beside this.
#
#   tests/python/lerobot-e2e.sh WORK [--episodes 20] [--evaluations 6] [--steps 3000] ...
#
# WORK receives the dataset, the training run, each run's logs and report.json. The LeRobot
# environment is lerobot-train-check.sh's ($NORI_LEROBOT_VENV, made when missing); the Python
# client is installed into it.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../.." && pwd)"
work="${1:?usage: $0 WORK [options of lerobot_e2e.py]}"
shift
venv="${NORI_LEROBOT_VENV:-$HOME/.cache/nori/lerobot-venv}"
[ -x "$venv/bin/lerobot-train" ] || "$here/lerobot-train-check.sh" --install
"$venv/bin/python" -c "import nori_client" 2>/dev/null \
  || "$venv/bin/python" -m pip install --quiet -e "$repo/python/nori_client"
(cd "$repo" && cargo build --release --workspace --bins)
mkdir -p "$work"
"$venv/bin/python" "$here/lerobot_e2e.py" --work "$(cd "$work" && pwd)" --venv "$venv" "$@"
