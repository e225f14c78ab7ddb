"""Fixtures for the ROS 2 tests (importable without ROS: nothing here imports rclpy).

``ros_env`` gives each test its own DDS domain, so tests (and concurrent test runs on the same
machine) do not see each other's topics, and keeps all discovery on this machine.
"""
import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from inclinometer_calib.apps.rosenv import WIDENING, isolated_settings, reserve_domain_id  # noqa: E402


@pytest.fixture
def ros_env(monkeypatch):
    """Environment dict for ROS 2 child processes, with a ROS_DOMAIN_ID unique to this test.

    The same settings are applied to ``os.environ`` of the test process for the duration of the
    test (so an in-process ``rclpy.init()`` joins the same domain); pass the returned dict as
    ``env=`` to subprocesses. Discovery is always restricted to this machine
    (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST).
    """
    domain_id, lock = reserve_domain_id()
    for key, value in isolated_settings(domain_id).items():
        monkeypatch.setenv(key, value)
    for key in WIDENING:  # deprecated / conflicting discovery settings must not widen the range
        monkeypatch.delenv(key, raising=False)
    env = dict(os.environ)
    try:
        yield env
    finally:
        lock.close()
