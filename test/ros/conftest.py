"""Fixtures for the ROS 2 tests (importable without ROS: nothing here imports rclpy).

``ros_env`` gives each test its own DDS domain, so tests (and concurrent test runs on the same
machine) do not see each other's topics, and keeps all discovery on this machine.
"""
import fcntl
import os
import tempfile

import pytest

# Fast DDS maps a domain id to UDP ports 7400 + 250 * id + ...; ids above 232 overflow the port
# range. 0 is the default domain of everything else on the machine, so stay well clear of it.
DOMAIN_ID_MIN = 101
DOMAIN_ID_MAX = 232
_LOCK_DIR = os.path.join(tempfile.gettempdir(), "inclinometer_calib-ros-domain-ids")
_counter = 0


def _reserve_domain_id():
    """Return (domain_id, lock_file): a domain id no other live process holds.

    Ids are reserved with an flock on one file per id (released automatically if the process
    dies); the search starts at a pid-dependent offset so concurrent runs rarely contend.
    """
    global _counter
    os.makedirs(_LOCK_DIR, exist_ok=True)
    span = DOMAIN_ID_MAX - DOMAIN_ID_MIN + 1
    start = (os.getpid() * 7 + _counter) % span
    _counter += 1
    for k in range(span):
        domain_id = DOMAIN_ID_MIN + (start + k) % span
        fh = open(os.path.join(_LOCK_DIR, f"{domain_id}.lock"), "a+")
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            continue
        return domain_id, fh
    raise RuntimeError(f"no free ROS_DOMAIN_ID in [{DOMAIN_ID_MIN}, {DOMAIN_ID_MAX}]")


@pytest.fixture
def ros_env(monkeypatch):
    """Environment dict for ROS 2 child processes, with a ROS_DOMAIN_ID unique to this test.

    The same settings are applied to ``os.environ`` of the test process for the duration of the
    test (so an in-process ``rclpy.init()`` joins the same domain); pass the returned dict as
    ``env=`` to subprocesses. Discovery is always restricted to this machine
    (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST).
    """
    domain_id, lock = _reserve_domain_id()
    settings = {
        "ROS_DOMAIN_ID": str(domain_id),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp"),
        "PYTHONUNBUFFERED": "1",
    }
    for key, value in settings.items():
        monkeypatch.setenv(key, value)
    # deprecated / conflicting discovery settings must not widen the range
    for key in ("ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS", "FASTRTPS_DEFAULT_PROFILES_FILE",
                "FASTDDS_DEFAULT_PROFILES_FILE", "ROS_DISCOVERY_SERVER"):
        monkeypatch.delenv(key, raising=False)
    env = dict(os.environ)
    try:
        yield env
    finally:
        lock.close()
