#!/usr/bin/env bash
# Installs the Python client (editable, with pytest) into its own virtual environment, for its
# tests and for `nori-serve-lerobot` without LeRobot: ${NORI_CLIENT_VENV:-~/.cache/nori/client-venv}.
# The process tests run it from there (tests/tests/python_client.rs). Python >= 3.11; only the
# package registry is needed. Does nothing when the environment is already up to date.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
venv=${NORI_CLIENT_VENV:-$HOME/.cache/nori/client-venv}
python=${PYTHON:-python3}
stamp="$venv/.nori-client-$(sha256sum "$here/pyproject.toml" | cut -c1-16)"
# Up to date only if it is this checkout's client (an editable install of another clone, a CI
# run's say, would test that clone's code).
if [ -f "$stamp" ] && "$venv/bin/python" -c "import nori_client, pytest, sys
sys.exit(not nori_client.__file__.startswith('$here/'))" 2>/dev/null; then
  exit 0
fi
if ! "$python" -m venv --help >/dev/null 2>&1; then
  as_root=(); [ "$(id -u)" = 0 ] || as_root=(sudo)
  "${as_root[@]}" apt-get update -qq
  "${as_root[@]}" env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv >/dev/null
fi
"$python" -m venv "$venv"
"$venv/bin/python" -m pip install --quiet --upgrade pip
"$venv/bin/python" -m pip install --quiet -e "$here[test]"
rm -f "$venv"/.nori-client-*
touch "$stamp"
echo "nori-client installed in $venv ($("$venv/bin/python" --version))"
