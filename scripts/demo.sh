#!/usr/bin/env bash
# Set up everything (idempotent) and run the main job: the live survey demo on the built-in
# simulated probe, whose magnetometer bias drifts with temperature (2.5 nT/°C, a fluxgate's
# typical size; the well heats it from 25 to 60 °C, the stand calibrates it at 25 °C).  The whole
# ROS 2 graph (probe → calibration → correction, recorder) runs as separate processes over DDS on
# this machine only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST), at 5× real time; the correction
# node's field monitor says when the calibration's model stops explaining the survey.  Then the
# model loop: the lab finds the missing effect on the recorded data, fits it, and the bag is
# replayed through each record.  Leaves DIR/survey.mcap, coeffs.yaml, lab_model.yaml, truth.json,
# summary.json, report.md, report.html (plots), compare/ and trajectory.xml (the survey as a WITSML 2.1
# Trajectory, rewritten by the wits node after every station).
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
# The rig: the site by latitude/longitude/date (config/rig_site.yaml: WMM2025, grid azimuths), the
# stations as WITS0 record 07 on tcp://127.0.0.1:${WITS_PORT} and as a WITSML 2.1 trajectory
# (DIR/trajectory.xml), and live in Foxglove on ws://127.0.0.1:${FOXGLOVE_PORT}
# (layout config/foxglove_layout.json).  Set WITS_PORT / FOXGLOVE_PORT to 0 to leave a server out.
exec inclinometer-calib-launch --out "$out" --overwrite --speed 5 --effect temperature_bias:mag=2.5 \
    --site "$here/config/rig_site.yaml" --witsml --wits-port "${WITS_PORT:-7007}" \
    --foxglove-port "${FOXGLOVE_PORT:-8765}"
