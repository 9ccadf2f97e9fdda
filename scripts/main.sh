#!/usr/bin/env bash
# The main job: set up .venv if needed, then run the closed-loop HIL loop of the paper's Fig. 15:
# simulator, controller and recorder as ROS 2 processes in lockstep (DDS on loopback only).
# Writes out/fig15/bag (MCAP), PNG plots and summary.json, and prints the summary.
set -euo pipefail
# shellcheck source=scripts/prepare.sh
source "$(dirname "${BASH_SOURCE[0]}")/prepare.sh"
out="${1:-out/fig15}"
if [ -e "$out/bag" ]; then
  out="$out-$(date +%Y%m%d-%H%M%S)"  # never overwrite an earlier run's bag
fi
"$venv/bin/lca-hil" fig15 --out "$out"
