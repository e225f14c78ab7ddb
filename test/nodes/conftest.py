"""Fixtures of the node/graph tests: the ``ros_env`` fixture of test/ros/conftest.py (a unique
ROS_DOMAIN_ID per test, discovery on this machine only), and ``domain_env`` for module-scoped
fixtures that start a graph once for several tests.  Nothing here imports rclpy."""
import importlib.util
import os

import pytest

_ROS_CONFTEST = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "ros", "conftest.py")
_spec = importlib.util.spec_from_file_location("inclinometer_calib_test_ros_conftest", _ROS_CONFTEST)
_ros = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_ros)

ros_env = _ros.ros_env  # re-exported fixture (function scope)

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def make_env(domain_id: int) -> dict:
    """Environment for ROS child processes in their own domain, discovery on localhost only."""
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               RMW_IMPLEMENTATION=env.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp"), PYTHONUNBUFFERED="1")
    for key in ("ROS_LOCALHOST_ONLY", "ROS_STATIC_PEERS", "FASTRTPS_DEFAULT_PROFILES_FILE",
                "FASTDDS_DEFAULT_PROFILES_FILE", "ROS_DISCOVERY_SERVER"):
        env.pop(key, None)
    # child processes must import the source tree first (as scripts/env.sh arranges)
    paths = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    if REPO not in paths:
        env["PYTHONPATH"] = os.pathsep.join([REPO] + paths)
    return env


@pytest.fixture(scope="module")
def domain_env():
    """(env dict, domain id) reserved for a whole test module (released at its end)."""
    domain_id, lock = _ros._reserve_domain_id()
    try:
        yield make_env(domain_id), domain_id
    finally:
        lock.close()
