"""Isolated ROS 2 environments for child processes: a private DDS domain, discovery on this
machine only.  Used by the launcher, the tests and the benchmarks (ROS-free: no rclpy import).

* :func:`reserve_domain_id` picks a ``ROS_DOMAIN_ID`` that no other live process of ours holds
  (an ``flock`` on one file per id, released automatically if the holder dies), so concurrent
  test runs and benchmarks never see each other's topics.
* :func:`isolated_env` builds the environment: that domain, ``ROS_AUTOMATIC_DISCOVERY_RANGE=
  LOCALHOST`` (no discovery traffic leaves the machine), no setting that could widen discovery,
  and the source tree first on ``PYTHONPATH`` (as ``scripts/env.sh`` arranges).
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
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: Settings that could make discovery leave this machine or bypass the range; always removed.
WIDENING = ("ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS", "FASTRTPS_DEFAULT_PROFILES_FILE",
            "FASTDDS_DEFAULT_PROFILES_FILE", "ROS_DISCOVERY_SERVER")
_counter = 0


def reserve_domain_id(lo: int = DOMAIN_ID_MIN, hi: int = DOMAIN_ID_MAX):
    """``(domain_id, lock_file)``: keep the file open while the domain is in use."""
    global _counter
    os.makedirs(LOCK_DIR, exist_ok=True)
    span = hi - lo + 1
    start = (os.getpid() * 7 + _counter) % span  # pid-dependent start: concurrent runs rarely contend
    _counter += 1
    for k in range(span):
        domain_id = lo + (start + k) % span
        fh = open(os.path.join(LOCK_DIR, f"{domain_id}.lock"), "a+")
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            continue
        return domain_id, fh
    raise RuntimeError(f"no free ROS_DOMAIN_ID in [{lo}, {hi}]")


def isolated_settings(domain_id: int, base: dict | None = None) -> dict:
    """The variables to set for an isolated graph (the ones of :func:`isolated_env`)."""
    base = os.environ if base is None else base
    return {"ROS_DOMAIN_ID": str(domain_id), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
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
