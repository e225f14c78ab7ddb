"""Shared fixtures.  Tests never depend on the working directory."""
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)


import pytest  # noqa: E402

#: test directories whose modules start real ROS 2 graphs (node processes over DDS)
GRAPH_DIRS = ("nodes", "ros")
HERE = os.path.dirname(os.path.abspath(__file__))


def pytest_collection_modifyitems(config, items):
    """Under pytest-xdist ``--dist loadgroup`` (``scripts/test.sh``): each ROS graph module is one
    group, run whole by one worker (its module fixtures start their graph once; every test still
    has a ROS_DOMAIN_ID of its own), and the groups go out first, largest first (xdist orders
    groups by size), so that their waiting on the graph overlaps the CPU-bound tests that follow
    on the other workers.  Every other test is a group of its own.  Without xdist the marker is
    inert."""
    for item in items:
        rel = os.path.relpath(str(item.path), HERE)
        if rel.split(os.sep)[0] in GRAPH_DIRS:
            item.add_marker(pytest.mark.xdist_group(rel.replace(os.sep, "/")))
