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
from inclinometer_calib.apps.rosenv import isolated_env, reserve_domain_id  # noqa: E402  (path set by _ros)

@pytest.fixture(scope="module")
def domain_env():
    """(env dict, domain id) reserved for a whole test module (released at its end)."""
    domain_id, lock = reserve_domain_id()
    try:
        yield isolated_env(domain_id), domain_id
    finally:
        lock.close()


@pytest.fixture
def ros(ros_env):
    """rclpy initialised in this test's private domain; append nodes to the list to have them destroyed."""
    import rclpy

    rclpy.init()
    nodes = []
    try:
        yield nodes
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()
