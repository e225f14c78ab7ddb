"""Command-line interface ``inclinometer-calib`` (works without ROS installed).

One module per group of sub-commands, each registering its parsers and holding its commands:
:mod:`.calibrate` (``simulate``, ``twelve-position``, ``turntable``, ``demo``), :mod:`.survey`
(``correct``), :mod:`.rig` (``wits``, ``witsml``), :mod:`.bags` (``reprocess``, ``replay-test``,
``bag``), :mod:`.lab` (``lab ...``), :mod:`.fleet` (``fleet ...``); what they share is in
:mod:`.shared`.  Errors in the input are reported as ``error: ...`` on stderr with exit status 2;
rejected rows and dropped stations are listed as warnings and the good data is used.
"""
from __future__ import annotations

import argparse
import sys

from ... import __version__
from ...core.deps import MissingDependency
from ...core.output import OutputError
from ..common import UserError
from . import bags, calibrate, fleet, lab, rig, survey


def build_parser():
    p = argparse.ArgumentParser(prog="inclinometer-calib",
                                description="Calibrate magnetic borehole inclinometers and correct their surveys.")
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    # the order of the sub-commands in the help
    calibrate.register(sub)
    rig.register(sub)
    survey.register(sub)
    calibrate.register_demo(sub)
    bags.register(sub)
    lab.register(sub)
    fleet.register(sub)
    return p


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (UserError, MissingDependency, OutputError) as exc:  # an optional package (deps.py), an output refused
        print(f"error: {exc}", file=sys.stderr)
        return 2
