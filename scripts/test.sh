#!/usr/bin/env bash
# Set up everything (idempotent) and run the whole test suite.  Extra arguments go to pytest (then
# one pytest run of what they name, e.g. ./scripts/test.sh test/test_turntable.py -x).
#
# Without arguments, in two parts: the tests without a ROS graph on every core (pytest-xdist: they
# are CPU-bound numerics and share no state), then the ROS 2 graph tests two at a time, a module per
# worker (--dist loadscope: a module's graph fixture runs once), each test in a ROS_DOMAIN_ID of its
# own (real processes over real DDS; they mostly wait on the graph, so two overlap well on 2 cores;
# more would compete for the cores their timing assumes).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$here/scripts/setup.sh"
# shellcheck disable=SC1091
source "$here/scripts/env.sh"
cd "$here"
if [ "$#" -gt 0 ]; then
    exec python -m pytest -q "$@"
fi
rc=0
python -m pytest test -q -n auto --ignore=test/nodes --ignore=test/ros || rc=$?
python -m pytest test/nodes test/ros -q -n 2 --dist loadscope || { r=$?; [ "$rc" -eq 0 ] && rc=$r; }
exit "$rc"
