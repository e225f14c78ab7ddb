"""Shared fixtures.  Tests never depend on the working directory."""
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

#: The modules whose tests take longest (serial CPU seconds on the CI's 2-core EPYC, 2026-11-25,
#: ``--durations``), run first: a module of the numerics' queue that starts late and runs long alone
#: leaves the other core idle at the end of the suite (``scripts/test.sh`` runs them on every core).
#: A module keeps its tests together (its module fixtures are set up once); the rest keep their order.
SLOW_MODULES = (
    "test/lab/test_diagnose.py", "test/lab/test_field_validation.py", "test/test_readme_examples.py",
    "test/test_strangers.py", "test/fleet/test_reprocess_fleet.py", "test/test_compare.py",
    "test/lab/test_cli_lab.py", "test/test_stranger_probe.py", "test/lab/test_loop.py", "test/lab/test_methods.py",
)


def pytest_collection_modifyitems(session, config, items):
    rank = {m: i for i, m in enumerate(SLOW_MODULES)}
    items.sort(key=lambda it: rank.get(it.nodeid.split("::")[0], len(rank)))   # stable: the others keep their order
