#!/usr/bin/env bash
# Create .venv (Python 3.11) and install lca_hil with ROS 2 Jazzy (PyPI wheels) and its test
# tools. Idempotent: a stamp of the install inputs skips pip when nothing changed.
# Sourced by scripts/main.sh and scripts/test.sh; safe to run on its own.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${LCA_HIL_VENV:-$root/.venv}"
python="${PYTHON:-python3.11}"
command -v "$python" >/dev/null 2>&1 || python=python3

if [ ! -x "$venv/bin/python" ]; then
  echo "setup: creating $venv with $("$python" --version)"
  "$python" -m venv "$venv"
fi

stamp="$venv/.lca_hil-install-stamp"
inputs="$(cat "$root/setup.py" "$root/setup.cfg" "$root/pyproject.toml" "$root/package.xml" | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$inputs" ]; then
  echo "setup: installing lca_hil and its dependencies into $venv (a few minutes the first time)"
  "$venv/bin/python" -m pip install --quiet --upgrade pip "setuptools<80" wheel
  "$venv/bin/python" -m pip install --quiet -e "$root[ros,test,bench]"
  echo "$inputs" > "$stamp"
fi
