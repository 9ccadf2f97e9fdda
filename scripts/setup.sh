#!/usr/bin/env bash
# Create .venv (Python 3.11) and install lca_hil with ROS 2 Jazzy (PyPI wheels) and its test
# tools. Idempotent: a stamp of the install inputs skips pip when nothing changed.
# Sourced by scripts/main.sh and scripts/test.sh; safe to run on its own.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${LCA_HIL_VENV:-$root/.venv}"

# The interpreter: $PYTHON if set; else the first Python 3.11 that can make a venv and has the
# interpreter in its executable, not loaded from libpython3.11.so; else the first one that can
# make a venv. A shared-libpython build (this host's pyenv 3.11.7, configured --enable-shared)
# runs the interpreter as position-independent code in a shared library: on the project's
# 2-core host the CAN bridge's master and rack cycle cost 0.82 of their CPU on Debian's
# /usr/bin/python3.11 against it (docs/can-transport.md, "The fifth round: the interpreter").
# An existing venv is kept.
pick_python() {
  local candidate first=""
  for candidate in python3.11 /usr/bin/python3.11 /usr/local/bin/python3.11; do
    command -v "$candidate" >/dev/null 2>&1 || continue
    "$candidate" -c 'import sys, venv, ensurepip; sys.exit(sys.version_info[:2] != (3, 11))' \
      >/dev/null 2>&1 || continue
    [ -n "$first" ] || first="$candidate"
    if "$candidate" -c 'import sys; sys.exit(any("libpython" in l for l in open("/proc/self/maps")))' \
      >/dev/null 2>&1; then
      echo "$candidate"
      return
    fi
  done
  echo "${first:-python3}"
}
python="${PYTHON:-$(pick_python)}"

if [ ! -x "$venv/bin/python" ]; then
  echo "setup: creating $venv with $("$python" --version) ($(command -v "$python"))"
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
