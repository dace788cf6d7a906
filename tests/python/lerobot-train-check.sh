#!/usr/bin/env bash
# The acceptance check of the sensor-plane issue, outside CI (LeRobot with torch is several GB):
# a dataset recorded by `nori record` from the simulated robot, cameras included, is loaded by
# the real `lerobot` package and trains an ACT policy on the CPU.
#
#   tests/python/lerobot-train-check.sh --install        # the venv only (Python 3.12, lerobot)
#   tests/python/lerobot-train-check.sh DATASET [STEPS]  # load, iterate, train STEPS (default 30)
#                                                        # of ACT and Diffusion ($NORI_LEROBOT_POLICIES)
#
# The venv lives in $NORI_LEROBOT_VENV (default ~/.cache/nori/lerobot-venv), made with Python
# 3.12 (LeRobot >= 0.6 needs it; pyenv's or the system's). What it checks and prints is in
# lerobot_train_check.py beside this script.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
venv="${NORI_LEROBOT_VENV:-$HOME/.cache/nori/lerobot-venv}"
lerobot_version="${NORI_LEROBOT_VERSION:-0.6.1}"

# shellcheck source=python312.sh
. "$here/python312.sh"

install() {
  if [ ! -x "$venv/bin/python" ]; then
    "$(find_python312)" -m venv "$venv"
  fi
  "$venv/bin/python" -m pip install --quiet --upgrade pip
  "$venv/bin/python" -m pip install --quiet "lerobot[dataset,training,diffusion]==$lerobot_version" av
  "$venv/bin/python" -c "import lerobot, torch; print('lerobot', lerobot.__version__, 'torch', torch.__version__)"
}

if [ "${1:-}" = "--install" ]; then
  install
  exit 0
fi
dataset="${1:?usage: $0 --install | DATASET [STEPS]}"
steps="${2:-30}"
[ -x "$venv/bin/lerobot-train" ] || install
"$venv/bin/python" "$here/lerobot_train_check.py" "$dataset" --steps "$steps" --venv "$venv" --policies "${NORI_LEROBOT_POLICIES:-act,diffusion}"
