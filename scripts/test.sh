#!/usr/bin/env bash
# Set up everything (idempotent) and run the whole test suite.  Extra arguments go to pytest (then
# one pytest run of what they name, e.g. ./scripts/test.sh test/test_turntable.py -x).
#
# Without arguments, two pytest runs, one after the other:
# - every test without a ROS graph (CPU-bound numerics) on every core, --dist loadgroup: a test
#   runs wherever a worker is free, except the modules marked as one xdist_group (their costly
#   module fixtures then run once, not once per worker);
# - the ROS 2 graph tests (test/nodes, test/ros: real node processes over real DDS, a
#   ROS_DOMAIN_ID per test, discovery on this machine only), two at a time, a module per worker
#   (--dist loadscope: a module's graph fixture runs once).  They run alone: beside the numerics
#   (tried: at nice 10, four at a time, 3:40-4:15 for the whole suite) fresh-clone runs failed in
#   3 of 6 (docs/benchmarks.md, section 9).
# The exit status is the first failure's.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$here/scripts/setup.sh"
# shellcheck disable=SC1091
source "$here/scripts/env.sh"
cd "$here"
# the suite starts hundreds of Python processes (CLI commands, nodes, workers): let them share
# compiled bytecode instead of compiling the package again in each (some shells set this)
unset PYTHONDONTWRITEBYTECODE
# the workers already use every core: BLAS threads on top would only wait for each other
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
# a process that crashes (a node, a worker) prints every thread's Python stack
export PYTHONFAULTHANDLER=1
if [ "$#" -gt 0 ]; then
    exec python -m pytest -q "$@"
fi
rc=0
python -m pytest test -q -n auto --dist loadgroup --ignore=test/nodes --ignore=test/ros || rc=$?
python -m pytest test/nodes test/ros -q -n 2 --dist loadscope || { r=$?; [ "$rc" -eq 0 ] && rc=$r; }
exit "$rc"
