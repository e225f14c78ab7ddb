#!/usr/bin/env bash
# Set up everything (idempotent) and run the whole test suite.  Extra arguments go to pytest (then
# one pytest run of what they name, e.g. ./scripts/test.sh test/test_turntable.py -x).
#
# Without arguments: one pytest run on pytest-xdist workers (TEST_WORKERS, default: twice the
# cores), --dist loadgroup.  Each ROS 2 graph module (test/nodes, test/ros: real node processes
# over real DDS, a ROS_DOMAIN_ID per test, discovery on this machine only) is one group that a
# worker runs whole, and the groups start first (test/conftest.py); they spend much of their time
# waiting on the graph, so the other workers' CPU-bound numerics fill the cores meanwhile.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$here/scripts/setup.sh"
# shellcheck disable=SC1091
source "$here/scripts/env.sh"
cd "$here"
# the suite starts hundreds of Python processes (CLI commands, nodes, workers): let them share
# compiled bytecode instead of compiling the package again in each (some shells set this)
unset PYTHONDONTWRITEBYTECODE
# the workers already outnumber the cores: BLAS threads on top would only wait for each other
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
if [ "$#" -gt 0 ]; then
    exec python -m pytest -q "$@"
fi
cores="$(nproc 2>/dev/null || echo 2)"
exec python -m pytest test -q -n "${TEST_WORKERS:-$((2 * cores))}" --dist loadgroup
