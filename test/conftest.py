"""Shared fixtures.  Tests never depend on the working directory."""
import gc
import os
import shutil
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)


def pytest_configure(config):
    config.addinivalue_line("markers", "long(seconds): one of the suite's long poles, the seconds measured "
                                       "for one test or one xdist group (CPU-seconds; a graph module's wall "
                                       "time): collected first, the longest first (pytest_collection_modifyitems)")


def pytest_collection_finish(session):
    """Full garbage collections less often in the test processes.  Every full collection walks the
    whole heap — the imported libraries (numpy, scipy, matplotlib, dask, sqlalchemy, rosbags: about
    230 000 objects after collection) and what the module fixtures hold — and a numerics worker
    made 21–33 of them, 0.3 s each: 13–16 CPU-seconds of the numerics' 270 (measured with
    ``gc.callbacks``).  The objects alive after collection are frozen (never walked again) and a
    full collection waits for 100 middle-generation collections, not 10; cyclic garbage is still
    collected (the two younger generations as before, the full ones less often, and at the end of
    the session)."""
    gc.collect()
    gc.freeze()
    young, middle, _ = gc.get_threshold()
    gc.set_threshold(young, middle, 100)


def pytest_collection_modifyitems(config, items):
    """The tests marked ``long`` first, the longest first, then the others in their order (a stable
    sort: a module's tests stay in order).  pytest-xdist hands tests (or groups) to its workers in
    this order: a long one started last would run alone at the end while the other core idles
    (scripts/test.sh; docs/benchmarks.md, section 10)."""
    def weight(item):
        mark = item.get_closest_marker("long")
        return -float(mark.args[0]) if mark is not None else 0.0
    items.sort(key=weight)
    _xdist_groups(config, items)


def _xdist_groups(config, items):
    """``--dist loadgroup``'s groups, restored: pytest-xdist 3.8 puts a test's ``xdist_group`` in
    its node id (``item._nodeid += "@group"``, the scheduler's unit of work), which pytest 9.2 no
    longer reads (a node's id is ``item._id``).  Without this every test was a unit of its own, and
    a group's module fixtures were built again on each worker that got one of its tests (the
    fleet's bags and runs: 10 CPU-seconds).  The same suffix, where pytest 9.2 reads it."""
    if not getattr(config.option, "loadgroup", False):
        return
    from _pytest.nodeid import NodeId

    for item in items:
        names = sorted({str(m.args[0] if m.args else m.kwargs.get("name", "default"))
                        for m in item.iter_markers("xdist_group")})
        suffix = "@" + "_".join(names)
        if names and not item.nodeid.endswith(suffix):
            item._id = NodeId.parse(item.nodeid + suffix)
            assert item.nodeid.endswith(suffix), "pytest's node id moved again: see _xdist_groups"


FULL_DISK = r"""
set -u
mnt="$1"; ro="$2"; seed="$3"; shift 3
mount -t tmpfs -o size=256k tmpfs "$mnt" || exit 97
cd "$mnt"
if [ -n "$seed" ]; then
    cp -a "$seed"/. . || exit 97              # what is there before the command runs
fi
if [ "$ro" = ro ]; then
    mount -o remount,ro "$mnt" || exit 97     # a read-only file system (root may write anywhere else)
else
    cat /dev/zero > .fill 2>/dev/null         # every block taken: the command's first write fails
fi
"$@"
rc=$?
rm -f .fill 2>/dev/null
echo "LEFT:$(ls -A | tr '\n' ' ')" >&2
exit $rc
"""


class FullDisk:
    """A real full, or read-only, file system for one command: a tmpfs mounted on ``mnt`` in a
    mount namespace of the command's own (``unshare --mount``), holding a copy of ``seed``'s
    files (if given), then filled to the last block (or remounted read-only); the command runs in
    it and the last line of its stderr is ``LEFT:`` and the names left there.  The mount goes
    with the namespace: ``mnt`` is empty again afterwards."""

    def __init__(self, mnt):
        self.mnt = mnt

    def run(self, command, *, ro=False, seed=None, timeout=180):
        return subprocess.run(["unshare", "--mount", "sh", "-c", FULL_DISK, "sh", str(self.mnt), "ro" if ro else "rw",
                               str(seed or ""), *map(str, command)], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="session")
def full_disk(tmp_path_factory):
    """A :class:`FullDisk` (skips, saying what is missing, without ``unshare`` or the right to mount)."""
    if shutil.which("unshare") is None:
        pytest.skip("unshare (util-linux) is not installed")
    mnt = tmp_path_factory.mktemp("mnt")
    r = subprocess.run(["unshare", "--mount", "sh", "-c", f"mount -t tmpfs -o size=64k tmpfs {mnt}"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"a tmpfs in a mount namespace of its own needs root or CAP_SYS_ADMIN: {r.stderr.strip()}")
    return FullDisk(mnt)
