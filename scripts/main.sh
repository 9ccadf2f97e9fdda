#!/usr/bin/env bash
# The main job: set up .venv if needed, then run the paper's open-loop pivot experiment
# (Figs 9-10) headless. Writes out/fig9/result.csv and result.png and prints the state phases.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/setup.sh"
# shellcheck source=scripts/env.sh
source "$root/scripts/env.sh"
venv="${LCA_HIL_VENV:-$root/.venv}"
cd "$root"
"$venv/bin/lca-sim" run --robot default --scenario fig9_open_loop_pivot --out "${1:-out/fig9}"
