"""No two commands write into the same default output folder.

A newcomer runs ``inclinometer-calib demo`` (offline) and ``scripts/demo.sh`` (live graph) from the
same directory; if both defaulted to ``demo_out`` the second would mix its files with, or refuse to
run because of, the first's. The defaults are read from the parsers and scripts themselves.
"""
import argparse
import os
import re

from inclinometer_calib.apps import cli, launcher

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
OUTPUT_DESTS = ("out", "output", "out_dir", "output_dir")


def _cli_output_defaults(parser, prefix="inclinometer-calib"):
    """{"inclinometer-calib <sub-command>": default} for every output option that has a default."""
    found = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found.update(_cli_output_defaults(sub, f"{prefix} {name}"))
        elif action.dest in OUTPUT_DESTS and action.default not in (None, argparse.SUPPRESS):
            found[prefix] = action.default
    return found


def _script_default(path, pattern):
    with open(os.path.join(ROOT, path), encoding="utf-8") as fh:
        m = re.search(pattern, fh.read())
    assert m, f"{path}: default output folder not found (pattern {pattern!r}); update this test"
    return m.group(1)


def _norm(folder):
    return os.path.normpath(folder)


def test_offline_demo_default_is_demo_offline():
    assert _cli_output_defaults(cli.build_parser())["inclinometer-calib demo"] == "demo_offline"


def test_default_output_folders_are_distinct():
    defaults = _cli_output_defaults(cli.build_parser())
    defaults["inclinometer-calib-launch"] = launcher.parse_args([]).out
    defaults["scripts/demo.sh"] = _script_default("scripts/demo.sh", r'out="\$\{1:-([^}"]+)\}"')
    by_folder = {}
    for command, folder in defaults.items():
        by_folder.setdefault(_norm(folder), []).append(command)
    shared = {f: cmds for f, cmds in by_folder.items() if len(cmds) > 1}
    assert not shared, f"commands sharing a default output folder: {shared}"
    assert defaults["scripts/demo.sh"] == "demo_out"
    assert defaults["inclinometer-calib-launch"] == "run"


def test_launch_file_matches_launcher_default():
    """``ros2 launch ... survey.launch.py`` and ``inclinometer-calib-launch`` start the same graph:
    one default output folder for both is intended."""
    launch_default = _script_default("launch/survey.launch.py",
                                     r'DeclareLaunchArgument\(\s*"out",\s*default_value="([^"]+)"')
    assert launch_default == launcher.parse_args([]).out
