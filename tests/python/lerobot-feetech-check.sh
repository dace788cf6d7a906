#!/usr/bin/env bash
# LeRobot's own Feetech driver (`lerobot.motors.feetech.FeetechMotorsBus`, lerobot 0.6.1 with
# feetech-servo-sdk) against the simulated servos: the simulator must answer what LeRobot asks of
# real STS servos. Without torch: lerobot is installed without its dependencies, with the few its
# motors package imports (see lerobot_feetech_check.py for the one module it must skip).
#
#   tests/python/lerobot-feetech-check.sh --install          # the venv only
#   tests/python/lerobot-feetech-check.sh DEVICE [ARGS...]   # the checks on a served bus
#
# The venv lives in $NORI_LEROBOT_FEETECH_VENV (default ~/.cache/nori/lerobot-feetech-venv),
# made with Python 3.12 (lerobot >= 0.6 needs it). tests/tests/lerobot_feetech.rs runs it
# against `nori sim serve`.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
venv="${NORI_LEROBOT_FEETECH_VENV:-$HOME/.cache/nori/lerobot-feetech-venv}"
lerobot_version=0.6.1

# shellcheck source=python312.sh
. "$here/python312.sh"

install() {
  if ! "$venv/bin/python" -c "import lerobot, scservo_sdk; assert lerobot.__version__ == '$lerobot_version'" \
      >/dev/null 2>&1; then
    rm -rf "$venv"
    "$(find_python312)" -m venv "$venv"
    "$venv/bin/python" -m pip install --quiet --no-deps "lerobot==$lerobot_version"
    # lerobot's `feetech` extra and what its motors package imports (pyproject of 0.6.1).
    "$venv/bin/python" -m pip install --quiet "feetech-servo-sdk>=1.0.0,<2.0.0" \
      "pyserial>=3.5,<4.0" "deepdiff>=7.0.1,<9.0.0" "draccus>=0.11.6,<0.12.0" \
      "tqdm>=4.66.0,<5.0.0" "numpy>=2.0.0,<2.3.0"
  fi
}

install
[ "${1:-}" = "--install" ] && exit 0
exec "$venv/bin/python" "$here/lerobot_feetech_check.py" "$@"
