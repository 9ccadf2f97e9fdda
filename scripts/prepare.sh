# Shared prologue of main.sh and test.sh (source it): set up .venv if needed, keep DDS on
# loopback, and leave $root (the repository) as the working folder and $venv set.
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/setup.sh"
# shellcheck source=scripts/env.sh
source "$root/scripts/env.sh"
venv="${LCA_HIL_VENV:-$root/.venv}"
cd "$root"
