#!/usr/bin/env bash
# Creates the virtualenv the client tests run (tests/tests/clients.rs):
# OctoPrint and Printrun's printcore from PyPI, pinned. Does nothing if the
# venv is there with the same pins.
#
#   tests/clients/setup.sh [VENV]      (default: target/clients-venv)
#
# Python: $PYTHON, else python3.11 (OctoPrint 1.11), else python3.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
venv=${1:-$here/../../target/clients-venv}
python=${PYTHON:-$(command -v python3.11 || command -v python3)}
pins=$(cat "$here/requirements.txt" "$here/requirements-nodeps.txt")
if [ -x "$venv/bin/python" ] && [ "$(cat "$venv/.pins" 2>/dev/null)" = "$pins" ]; then
    echo "client venv up to date: $venv"
    exit 0
fi
rm -rf "$venv"
"$python" -m venv "$venv"
pip=("$venv/bin/pip" install --quiet --disable-pip-version-check)
"${pip[@]}" -r "$here/requirements.txt"
"${pip[@]}" --no-deps -r "$here/requirements-nodeps.txt"
printf '%s' "$pins" > "$venv/.pins"
echo "client venv ready: $venv"
