"""Isolated ROS 2 environments for child processes: a private DDS domain, discovery on this
machine only.  Used by the launcher, the tests and the benchmarks (ROS-free: no rclpy import).

* :func:`reserve_domain_id` picks a ``ROS_DOMAIN_ID`` that no other live process of ours holds
  (an ``flock`` on one file per id, released automatically if the holder dies), so concurrent
  test runs and benchmarks never see each other's topics; :func:`reserve_this_domain_id` takes
  one given id or raises :class:`DomainInUse` naming the process that holds it.
* :func:`isolated_env` builds the environment: that domain, ``ROS_AUTOMATIC_DISCOVERY_RANGE=
  LOCALHOST`` (no discovery traffic leaves the machine), no setting that could widen discovery,
  and the source tree first on ``PYTHONPATH`` (as ``scripts/env.sh`` arranges).  It also sets
  :data:`RESERVED_BY_PARENT`: the caller holds that domain's lock for its children, so a
  launcher started with this environment uses the domain without reserving it a second time.
"""
from __future__ import annotations

import fcntl
import os
import tempfile

# Fast DDS maps a domain id to UDP ports 7400 + 250·id + …; ids above 232 overflow the port range.
# 0 is the default domain of everything else on the machine: stay well clear of it.
DOMAIN_ID_MIN = 101
DOMAIN_ID_MAX = 232
LOCK_DIR = os.path.join(tempfile.gettempdir(), "inclinometer_calib-ros-domain-ids")
REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
#: Settings that could make discovery leave this machine or bypass the range; always removed.
WIDENING = ("ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS", "FASTRTPS_DEFAULT_PROFILES_FILE",
            "FASTDDS_DEFAULT_PROFILES_FILE", "ROS_DISCOVERY_SERVER")
#: Environment variable naming the ROS_DOMAIN_ID whose lock the parent process holds for its
#: children (set by :func:`isolated_settings`).  A lock is per process: without this marker a
#: launcher started by a test could not tell "my parent reserved it for me" from "another run
#: uses it".
RESERVED_BY_PARENT = "INCLINOMETER_CALIB_DOMAIN_RESERVED"
#: Highest ROS_DOMAIN_ID Fast DDS can map to UDP ports.
DOMAIN_ID_LIMIT = 232
_counter = 0


class DomainInUse(RuntimeError):
    """Another live process of ours holds the lock of ``domain_id`` (``holder``: its pid, or "")."""

    def __init__(self, domain_id: int, holder: str):
        self.domain_id = domain_id
        self.holder = holder
        who = f"process {holder}" if holder else "another process"
        super().__init__(f"ROS_DOMAIN_ID {domain_id} is in use by another inclinometer_calib run on this "
                         f"machine ({who}; lock {lock_path(domain_id)})")


def lock_path(domain_id: int) -> str:
    """The lock file of ``domain_id`` (holds the pid of the process that holds the lock)."""
    return os.path.join(LOCK_DIR, f"{domain_id}.lock")


def _try_lock(domain_id: int):
    """The open, locked lock file of ``domain_id`` (our pid written into it), or None if held."""
    os.makedirs(LOCK_DIR, exist_ok=True)
    return try_lock_file(lock_path(domain_id))


def try_lock_file(path: str):
    """Hold an exclusive ``flock`` on ``path`` (created if need be; our pid written into it): the
    open file, kept open while the lock is needed (released when closed, or when the process
    dies), or None if another process holds it."""
    fh = open(path, "a+")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        return None
    fh.seek(0)
    fh.truncate()
    fh.write(f"{os.getpid()}\n")
    fh.flush()
    return fh


def reserve_this_domain_id(domain_id: int):
    """Lock exactly ``domain_id`` (0..232); returns the lock file, keep it open while the domain is in use.

    Raises :class:`DomainInUse` (with the holder's pid) if another live process holds it, and
    ValueError for an id Fast DDS cannot use.
    """
    if not 0 <= int(domain_id) <= DOMAIN_ID_LIMIT:
        raise ValueError(f"ROS_DOMAIN_ID {domain_id} is outside 0..{DOMAIN_ID_LIMIT} (Fast DDS port range)")
    fh = _try_lock(int(domain_id))
    if fh is None:
        try:
            with open(lock_path(domain_id), encoding="utf-8") as f:
                holder = f.read().strip()
        except OSError:
            holder = ""
        raise DomainInUse(int(domain_id), holder)
    return fh


def reserve_domain_id(lo: int = DOMAIN_ID_MIN, hi: int = DOMAIN_ID_MAX):
    """``(domain_id, lock_file)``: keep the file open while the domain is in use."""
    global _counter
    os.makedirs(LOCK_DIR, exist_ok=True)
    span = hi - lo + 1
    start = (os.getpid() * 7 + _counter) % span  # pid-dependent start: concurrent runs rarely contend
    _counter += 1
    for k in range(span):
        domain_id = lo + (start + k) % span
        fh = _try_lock(domain_id)
        if fh is not None:
            return domain_id, fh
    raise RuntimeError(f"no free ROS_DOMAIN_ID in [{lo}, {hi}]")


def isolated_settings(domain_id: int, base: dict | None = None) -> dict:
    """The variables to set for an isolated graph (the ones of :func:`isolated_env`)."""
    base = os.environ if base is None else base
    return {"ROS_DOMAIN_ID": str(domain_id), RESERVED_BY_PARENT: str(domain_id),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "RMW_IMPLEMENTATION": base.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp"), "PYTHONUNBUFFERED": "1"}


def isolated_env(domain_id: int, base: dict | None = None) -> dict:
    """A copy of ``base`` (default ``os.environ``) for children in domain ``domain_id``."""
    env = dict(os.environ if base is None else base)
    env.update(isolated_settings(domain_id, env))
    for key in WIDENING:
        env.pop(key, None)
    paths = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    if REPO not in paths:
        env["PYTHONPATH"] = os.pathsep.join([REPO] + paths)
    return env
