"""The rig's formats out of a recorded run: ``wits`` (WITS level 0 record 07) and ``witsml``
(a WITSML 2.1 or 1.4.1.1 trajectory, validated against its schema)."""
from __future__ import annotations

import math
import sys

from ...core import yamltext

from ...core.output import atomic_write_bytes, atomic_write_text, check_output
from ..common import UserError


def cmd_wits(args):
    """Export the corrected stations of a recorded run as WITS0 record 07 (:mod:`wits`)."""
    if args.output:
        check_output(args.output)        # said before the work, not after it
    import datetime as dt

    from ...io.bag import read_bag
    from ...rig.wits import describe, encode

    try:
        stations = read_bag(args.bag)[0]
    except (OSError, ValueError) as exc:
        raise UserError(f"{args.bag}: {exc}") from None
    survey = [s for s in stations if s["coefficients_id"] and s["status"] != 2]
    if not survey:
        raise UserError(f"{args.bag}: no corrected survey station to export")
    data = b"".join(encode(s, k + 1, args.well_id, args.hole_section,
                           dt.datetime.fromtimestamp(s["stamp"], dt.timezone.utc), units=args.units)
                    for k, s in enumerate(survey))
    if args.output:
        atomic_write_bytes(args.output, data)
        print(f"wrote {args.output}: {len(survey)} WITS0 record 07 ({len(stations) - len(survey)} raw or error "
              f"stations not exported); {describe(survey, args.units)}")
    else:
        sys.stdout.buffer.write(data)
    return 0


def cmd_witsml(args):
    """Export the survey stations of a recorded run as a WITSML 2.1 or 1.4.1.1 trajectory (:mod:`witsml`):
    every document validated against its schema before it is written, and written atomically —
    with ``-o``, the well, wellbore (and 2.1 datum) documents beside it unless they exist in the store."""
    from ...io.bag import read_bag
    from ...rig.witsml import (OPTION_HELP, Options, WitsmlError, mag_models, parent_path, trajectory_document,
                         validate)

    options = {name: getattr(args, name) for name in OPTION_HELP}
    try:
        Options(**options).check()       # a bad option: one line, before the bag is read
    except WitsmlError as exc:
        raise UserError(str(exc)) from None
    if args.output:
        check_output(args.output)        # said before the work, not after it
    try:
        stations, records, _ = read_bag(args.bag)
    except (OSError, ValueError) as exc:
        raise UserError(f"{args.bag}: {exc}") from None
    for path in args.coeffs or ():
        try:
            with open(path, encoding="utf-8") as fh:
                text = fh.read()
            records.append({"id": str((yamltext.load(text) or {})["id"]), "coefficients_yaml": text})
        except (OSError, yamltext.YAMLError, KeyError, TypeError) as exc:
            raise UserError(f"--coeffs {path}: not a calibration record ({type(exc).__name__}: {exc})") from None
    try:
        export = trajectory_document(stations, models=mag_models(records), **options)
        if not export.exported:
            raise UserError(f"{args.bag}: no corrected survey station with a measured depth to export (left out: "
                            f"{export.skipped_text()})")
        validate(export.xml)
        for _, xml in export.parents:
            validate(xml)
    except WitsmlError as exc:
        raise UserError(f"{args.bag}: {exc}") from None
    for note in export.notes:
        print(f"note: {note}", file=sys.stderr)
    if args.output:
        parents = [(parent_path(args.output, kind), xml) for kind, xml in export.parents]
        for path, xml in parents:
            atomic_write_text(path, xml.decode("utf-8"))
        atomic_write_text(args.output, export.xml.decode("utf-8"))
        hung = (f"; load {', '.join(p for p, _ in parents)} first" if parents else
                f"; it references the store's well {args.well_uid} and wellbore {args.wellbore_uid}")
        print(f"wrote {args.output}: WITSML {export.version} trajectory of {export.exported} stations in "
              f"{args.units} (left out: {export.skipped_text()}){hung}")
    else:
        sys.stdout.buffer.write(export.xml)
        if export.parents:
            print("note: the well and wellbore documents are written beside the trajectory with -o FILE",
                  file=sys.stderr)
    return 0


def _witsml_options(parser):
    """The WITSML options (:data:`witsml.OPTION_HELP`), checked by :meth:`witsml.Options.check` (one line, exit 2)."""
    from ...rig.witsml import OPTION_HELP, Options

    defaults = Options()
    for name, text in OPTION_HELP.items():
        default = getattr(defaults, name)
        shown = "" if default == "" or (isinstance(default, float) and math.isnan(default)) else f" (default {default})"
        parser.add_argument("--" + name.replace("_", "-"), default=default, type=type(default), help=text + shown,
                            metavar=name.split("_")[-1].upper())


def register(sub):
    """``wits``, ``witsml``."""
    w = sub.add_parser("wits", help="export a recorded run's corrected survey stations as WITS level 0 record 07")
    w.add_argument("bag", help="a recorded run (MCAP) with /survey/station")
    w.add_argument("-o", "--output", help="file to write (default: standard output)")
    w.add_argument("--well-id", default="WELL", help="item 0701")
    w.add_argument("--hole-section", type=int, default=0, help="item 0702")
    w.add_argument("--units", choices=("m", "ft"), default="m",
                   help="the WITS dictionary's metric (m, deg/100 m) or FPS units (ft, deg/100 ft); default m")
    w.set_defaults(func=cmd_wits)

    wx = sub.add_parser("witsml", help="export a recorded run's survey stations as a WITSML 2.1 or 1.4.1.1 "
                                       "trajectory (validated against the Energistics schema)")
    wx.add_argument("bag", help="a recorded run (MCAP) with /survey/station")
    wx.add_argument("-o", "--output", help="file to write (default: standard output); the well and wellbore "
                                           "documents are written beside it (FILE's stem + .well.xml, ...)")
    _witsml_options(wx)
    wx.add_argument("--coeffs", action="append", metavar="RECORD.yaml",
                    help="a calibration record the stations were corrected with, when the bag does not carry it "
                         "(reprocessed with --coeffs): its site names the geomagnetic model (repeatable)")
    wx.set_defaults(func=cmd_witsml)
