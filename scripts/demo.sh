#!/usr/bin/env bash
# Set up everything (idempotent) and run the main job: the survey demo on the built-in simulated
# probe.  Output directory: first argument (default ./demo_out).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
out="${1:-demo_out}"
bash "$here/scripts/setup.sh"
# shellcheck disable=SC1091
source "$here/scripts/env.sh"
exec inclinometer-calib demo --out "$out"
