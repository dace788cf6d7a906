# Sourced by the LeRobot scripts beside it: LeRobot >= 0.6 needs Python 3.12.
#
# find_python312 prints a Python 3.12 (pyenv's or the system's) or fails naming what needs it.
find_python312() {
  # pyenv's shim for python3.12 exists but fails unless 3.12 is selected: try each for real.
  for p in "$HOME"/.pyenv/versions/3.12*/bin/python3.12 python3.12; do
    if "$p" -c 'import sys; assert sys.version_info[:2] == (3, 12)' >/dev/null 2>&1; then
      echo "$p"; return
    fi
  done
  echo "no Python 3.12 found (lerobot $lerobot_version needs >= 3.12): install one with pyenv" >&2
  exit 2
}
