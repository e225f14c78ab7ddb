#!/usr/bin/env bash
# Set up everything (idempotent) and run the main job: the live survey demo on the built-in
# simulated probe.  The whole ROS 2 graph (probe → calibration → correction, recorder) runs as
# separate processes over DDS on this machine only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST),
# at 5× real time.  Leaves DIR/survey.mcap, coeffs.yaml, truth.json, summary.json and report.md.
# Usage: scripts/demo.sh [DIR] (default ./demo_out).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
out="${1:-demo_out}"
bash "$here/scripts/setup.sh"
# shellcheck disable=SC1091
source "$here/scripts/env.sh"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
# No --domain-id: the launcher reserves a free ROS_DOMAIN_ID for the run (or exactly the one set in
# the environment, refused while another run holds it), so two demos at once never mix.
exec inclinometer-calib-launch --out "$out" --overwrite --speed 5
