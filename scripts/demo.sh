#!/usr/bin/env bash
# Set up everything (idempotent) and run the main job: the live survey demo on the built-in
# simulated probe, whose magnetometer bias drifts with temperature (2.5 nT/°C, a fluxgate's
# typical size; the well heats it from 25 to 60 °C, the stand calibrates it at 25 °C).  The whole
# ROS 2 graph (probe → calibration → correction, recorder) runs as separate processes over DDS on
# this machine only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST), at 5× real time; the correction
# node's field monitor says when the calibration's model stops explaining the survey.  Then the
# model loop: the lab finds the missing effect on the recorded data, fits it, and the bag is
# replayed through each record.  Leaves DIR/survey.mcap, coeffs.yaml, lab_model.yaml, truth.json,
# summary.json, report.md, report.html (plots) and compare/.
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
exec inclinometer-calib-launch --out "$out" --overwrite --speed 5 --effect temperature_bias:mag=2.5
