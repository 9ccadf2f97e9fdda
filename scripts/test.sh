#!/usr/bin/env bash
# The test command: set up .venv if needed, then lint (ruff), type-check (mypy, strict on the
# core) and run the test suite (pytest). Extra arguments go to pytest.
set -euo pipefail
# shellcheck source=scripts/prepare.sh
source "$(dirname "${BASH_SOURCE[0]}")/prepare.sh"
echo "== ruff"
"$venv/bin/ruff" check .
"$venv/bin/ruff" format --check .
echo "== mypy"
"$venv/bin/mypy"
echo "== pytest"
"$venv/bin/python" -m pytest "$@"
