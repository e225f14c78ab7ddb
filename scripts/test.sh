#!/usr/bin/env bash
# Set up everything (idempotent) and run the whole test suite.  Extra arguments go to pytest (then
# one pytest run of what they name, e.g. ./scripts/test.sh test/calibrate/test_turntable.py -x).
#
# Without arguments, two pytest runs at once (the exit status is the numerics' failure, else the
# graph tests'; the wall time of each is printed at the end):
# - the ROS 2 graph tests (test/nodes, test/ros: real node processes over real DDS, a
#   ROS_DOMAIN_ID per test, discovery on this machine only), two at a time, a module per worker
#   (--dist loadscope: a module's graph fixture runs once), at normal priority: a live graph must
#   keep up with its replay, as it would on a rig computer with nothing else to do;
# - every test without a ROS graph (CPU-bound numerics) on every core at the lowest priority
#   (nice 19): they take the CPU the graphs leave, which is most of it (a graph waits on its
#   replay's clock), --dist loadgroup: a test runs wherever a worker is free, except the modules
#   marked as one xdist_group (their costly module fixtures then run once, not once per worker).
# Both hand out their units in collection order (--no-loadscope-reorder; xdist would sort them by
# their number of tests): the long poles first (the ``long`` marker, test/conftest.py), so that
# none is left running alone at the end.
# Even at nice 19 the numerics slow the graphs (two vCPUs share caches and memory bandwidth, and
# a niced task still runs until preempted): four graph tests at a time beside them at nice 10
# failed in 3 of 6 fresh-clone runs, and three numerics workers beside two graph tests made
# test_graph's replay lose messages; two and two pass (docs/benchmarks.md, section 9).
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
mmss() { printf '%d:%02d' $(($1 / 60)) $(($1 % 60)); }
# CPU-seconds (user + system) of this shell's finished children, from /proc: the work done,
# whatever the wall clock (on a shared virtual machine the same suite's CPU time varies by a third
# from run to run, and its wall time with it)
cpu_s() { awk -v hz="$(getconf CLK_TCK)" '{ sub(/.*\) /, ""); print int(($14 + $15) / hz) }' "/proc/$$/stat" 2>/dev/null || echo 0; }
cpu0=$(cpu_s)
t0=$SECONDS
graph_log="$(mktemp -t test-graph.XXXXXX)"
# the graph tests' report waits in a file while the numerics print theirs, then follows it
( rc_g=0; python -m pytest test/nodes test/ros -q -n 2 --dist loadscope --no-loadscope-reorder >"$graph_log" 2>&1 || rc_g=$?
  echo "graph tests: $(mmss $((SECONDS - t0))) wall" >>"$graph_log"; exit "$rc_g" ) &
graph=$!
# the background run ignores Ctrl-C (a script's background jobs do): stop it with the numerics
stop_graph() { pkill -TERM -P "$graph" 2>/dev/null || kill "$graph" 2>/dev/null || true; rm -f "$graph_log"; }
trap 'stop_graph; exit 130' INT
trap 'stop_graph; exit 143' TERM
rc=0
echo "test.sh: the ROS 2 graph tests run beside these numerics; their report follows"
nice -n 19 python -m pytest test -q -n auto --dist loadgroup --no-loadscope-reorder --ignore=test/nodes --ignore=test/ros || rc=$?
t_num=$((SECONDS - t0))
rc_g=0
wait "$graph" || rc_g=$?
trap - INT TERM
cat "$graph_log"
rm -f "$graph_log"
[ "$rc" -eq 0 ] && rc=$rc_g
echo "test.sh: numerics $(mmss "$t_num"), whole suite $(mmss $((SECONDS - t0))) wall, $(($(cpu_s) - cpu0)) CPU-s (exit status $rc)"
exit "$rc"
