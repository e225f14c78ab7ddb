"""The commands on recorded bags: ``reprocess`` (the live graph's processing offline; with
``--compare`` the field effect ladder), ``replay-test`` (a bag through the live graph against an
expected set) and ``bag`` (``recover`` a damaged recording, ``from-csv`` probe logs as a bag)."""
from __future__ import annotations

import os
import sys

from ...core.output import OutputError, atomic_write_text, check_output, output_path, refused_write_words
from ...correct.pipeline import NO_SITE, site_override_note
from ...io.probelog import MAG_UNITS, Limits, read_csv, report
from ...io.progress import progress_bar
from ..common import UserError, load_calibration, load_site
from .shared import (detector_from_args, detector_options, load_plugins, north_option, site_for, tolerance_options,
                     tolerances_from_args, warn)


def field_monitor(args):
    """The correction node's model check (:class:`lab.field.FieldMonitor`) over ``--monitor-window``
    stations, or None when it is 0."""
    if not getattr(args, "monitor_window", 0):
        return None
    from ...lab.field import FieldMonitor

    return FieldMonitor(window=args.monitor_window)


def cmd_reprocess(args):
    """Offline reprocessing of a recorded bag (see :mod:`inclinometer_calib.correct.reprocess`).

    Exit status 0; 1 when the input bag is damaged (everything readable was processed and
    written, the damage is reported as ``error:``), ``--calibrate`` did not solve, or it left
    survey stations raw before it solved (outside the stand's span its record gives: the survey,
    or part of it, came before the stand's poses — :func:`accounting.survey_raw`, the live
    summary's rule); 2 when nothing could be done.
    """
    from ...io.bag import BagError
    from ...io.accounting import beyond_captures, first_record, raw_before_calibration, survey_raw
    from ...correct.reprocess import TOPIC_STATION, ReprocessError, reprocess

    if args.compare:
        return cmd_compare(args)
    if args.coeffs is None and not args.calibrate:
        raise UserError("give --coeffs FILE (or 'none' for uncorrected figures), or --calibrate to calibrate "
                        "from the bag's twelve poses as the live graph does")
    load_plugins(args.plugin, run=bool(args.calibrate and args.effects))   # fitting plug-in effects: run them
    cal = load_calibration(args.coeffs)
    tol = tolerances_from_args(args)
    if args.site:
        site = site_for(args, cal, tol, args.bag)
    else:
        site = None   # the record's (and with --calibrate, the stand's measured one until a record exists)
        if cal is None and not args.calibrate:
            warn(f"{args.bag}: {NO_SITE} (give --site SITE.yaml)")
    det = detector_from_args(args)
    if args.coeffs_out:
        check_output(args.coeffs_out)
    try:
        with output_path(args.output) as tmp, progress_bar(None, "msg", "reprocess") as bar:   # whole or not at all
            def advance(done, total):
                bar.total = total
                bar.update(done - bar.n)

            rep = reprocess(args.bag, tmp, cal, site, tol, det, compression=args.compression,
                            warn=warn, calibrate=args.calibrate, probe_id=args.probe_id, effects=args.effects,
                            monitor=field_monitor(args), force_probe=args.force_probe, north=args.north,
                            progress=advance)
    except ValueError as exc:   # ReprocessError, a bad --effects
        raise UserError(str(exc)) from None
    except FileExistsError as exc:
        raise UserError(str(exc)) from None
    except FileNotFoundError as exc:
        raise UserError(str(exc)) from None
    except (BagError, ReprocessError) as exc:
        raise UserError(str(exc)) from None
    except OutputError:
        raise                   # "cannot write OUT: CAUSE", one line (cli.main)
    except OSError as exc:      # the input refused by the OS (output_path passes those on as they are)
        raise UserError(f"cannot read {exc.filename or args.bag}: {refused_write_words(exc)[1]}") from None
    for w in rep.warnings():
        if not w.startswith("skipped topic"):  # those were warned as they were met
            warn(f"{args.bag}: {w}")
    if rep.graph_outputs:
        print(f"not read (a recorded run's own outputs, made anew here or not needed): {', '.join(rep.graph_outputs)}")
    n = len(rep.stations)
    speed = rep.log_span_s / rep.seconds if rep.seconds > 0 else float("inf")
    used = rep.calibrations[-1].id if rep.calibrations else (cal.id if cal else "")
    by_id = {}
    for st in rep.stations:
        by_id[st["coefficients_id"]] = by_id.get(st["coefficients_id"], 0) + 1
    parts = [f"{k} with {cid}" + (" (the last)" if cid == used and len(by_id) > 1 else "") if cid else
             f"{k} uncorrected (before any coefficients)" for cid, k in by_id.items()]
    final = [s for s in rep.stations if s["coefficients_id"] == used]
    flagged = {k: sum(bool(s[k]) for s in final)
               for k in ("azimuth_undefined", "interference_suspected", "gravity_out_of_tolerance",
                         "moved_during_capture")}
    print(f"probe {rep.probe_serial or '(the bag names none)'}: {rep.messages_read} messages read, {rep.pairs} "
          f"imu/mag pairs, {n} stations: " + ", ".join(parts))
    print(f"flagged among the {len(final)} stations with {used or 'no coefficients'}: "
          + ", ".join(f"{k} {v}" for k, v in flagged.items()))
    if rep.noise is not None:
        print(f"detector: {rep.noise.describe()}")
    rc = 0
    if args.calibrate:
        if rep.calibrations:
            print(f"calibration: {len(rep.calibrations)} solve(s), last {rep.calibrations[-1].id}: "
                  f"{rep.calibration_message}")
            if args.coeffs_out:
                rep.calibrations[-1].save(args.coeffs_out)
                print(f"wrote {args.coeffs_out}")
        else:
            print(f"error: calibration did not solve: {rep.calibration_message or 'no twelve-pose captures'}",
                  file=sys.stderr)
            rc = 1
        captures, stand = first_record(rep.calibrations[0] if rep.calibrations else None)
        late = survey_raw(rep.stamped_stations(), len(rep.calibrations), captures, stand)
        if late:        # the live graph's summary says the same (io/accounting.py): not a clean run
            print(f"error: {late}", file=sys.stderr)
            rc = 1
        elif stand is None:     # a record that does not say where the stand's poses lie: said only
            before = raw_before_calibration(rep.stations)
            note = beyond_captures(before, captures)
            if note:
                print(f"note: {before} stations uncorrected before the calibration: {note}")
    print(f"wrote {args.output} ({n} {TOPIC_STATION} messages, "
          f"{sum(rep.copied.values())} input messages copied); {rep.log_span_s:.1f} s of data in "
          f"{rep.seconds:.2f} s ({speed:.0f}× real time)")
    if rep.bag_errors:
        for e in rep.bag_errors:
            print(f"error: {e}", file=sys.stderr)
        print(f"error: {args.bag} is damaged; the {rep.messages_read} readable messages before/around "
              f"the damage were processed and written to {args.output}", file=sys.stderr)
        return 1
    return rc


def cmd_compare(args):
    """``reprocess BAG --compare A.yaml B.yaml ... -o DIR``: the field effect ladder (:mod:`compare`)."""
    from ...lab import compare
    from ...io.bag import BagError
    from ...core.deps import require
    from ...correct.reprocess import ReprocessError

    if args.coeffs or args.calibrate:
        raise UserError("--compare replays the bag through each record given: not with --coeffs or --calibrate")
    require("matplotlib", "report", "reprocess --compare")   # the HTML's plots, before minutes of replay
    load_plugins(args.plugin, run=False)
    models, names = [], set()
    for spec in args.compare:
        cal = load_calibration(spec)
        name = "uncorrected" if cal is None else os.path.splitext(os.path.basename(spec))[0]
        base, k = name, 2
        while name in names:
            name, k = f"{base}-{k}", k + 1
        names.add(name)
        models.append((name, cal))
    tol = tolerances_from_args(args)
    site = load_site(args.site) if args.site else None
    if site is None and all(c is None for _, c in models):
        warn(f"{args.bag}: {NO_SITE} (give --site SITE.yaml)")
    for name, cal in models:
        note = site_override_note(cal, site)
        if note:
            warn(f"{args.bag}: {name}: {note}")
    try:
        runs = compare.compare(args.bag, models, args.output, site=site, tolerances=tol,
                               make_detector=lambda: detector_from_args(args), warn=warn,
                               monitor_window=args.monitor_window)
    except (FileExistsError, FileNotFoundError, BagError, ReprocessError) as exc:
        raise UserError(str(exc)) from None
    for line in compare.describe(runs, args.bag):
        print(line)
    md = os.path.join(args.output, "compare.md")
    page = os.path.join(args.output, "compare.html")
    atomic_write_text(md, compare.to_markdown(runs, args.bag))
    atomic_write_text(page, compare.to_html(runs, args.bag))
    print(f"wrote {md}, {page} and one bag per record in {args.output}/")
    return 0


def cmd_bag_recover(args):
    """Rewrite the readable part of a damaged bag (a recorder killed mid-run) as a finalized one."""
    from ...io.bag import BagError, recover

    try:
        rep = recover(args.bag, args.output)
    except FileExistsError as exc:
        raise UserError(str(exc)) from None
    except (FileNotFoundError, BagError) as exc:
        raise UserError(str(exc)) from None
    print(rep)
    return 0


def cmd_bag_from_csv(args):
    """Write probe-log CSVs as one rosbag2 MCAP, as the probe node would have recorded them."""
    from ...io.probelog import ProbeLog
    from ...correct.reprocess import write_probe_bag

    logs = []
    for path in args.logs:
        try:
            log, rejections = read_csv(path, Limits(), mag_unit=args.mag_unit)
        except OSError as exc:
            raise UserError(f"{path}: {exc.strerror}") from None
        except ValueError as exc:
            raise UserError(str(exc)) from None
        report(path, rejections, [], warn)
        if logs and len(log) and log.t_s[0] <= logs[-1].t_s[-1]:
            # logs that each start at 0: the next one follows the previous after a pause
            shift = logs[-1].t_s[-1] - log.t_s[0] + args.gap
            warn(f"{path}: its time starts at {log.t_s[0]:g} s, before the previous log ends: shifted by "
                  f"{shift:g} s to follow it after {args.gap:g} s")
            log.t_s = log.t_s + shift
        logs.append(log)
    log = ProbeLog.concatenate(logs)
    try:
        with output_path(args.output) as tmp, progress_bar(len(log), "sample", "bag") as bar:   # whole or not at all
            counts = write_probe_bag(log, tmp, compression=args.compression, serial=args.probe_serial,
                                     progress=lambda k: bar.update(k - bar.n))
    except FileExistsError as exc:
        raise UserError(str(exc)) from None
    print(f"wrote {args.output}: " + ", ".join(f"{n} {t}" for t, n in counts.items()))
    return 0


def cmd_replay_test(args):
    """``replay-test``: a bag through the live graph, compared with an expected set (:mod:`replaytest`)."""
    from ..replaytest import run

    return run(args)


def register(sub):
    """``reprocess``, ``replay-test``, ``bag recover``, ``bag from-csv``."""
    r = sub.add_parser("reprocess", help="re-run station detection, calibration and correction on a recorded bag (MCAP)")
    r.add_argument("bag", help="recorded bag: .mcap file or bag directory (/probe/imu, /probe/mag, ...)")
    r.add_argument("--coeffs", help="coefficient YAML, or 'none' for uncorrected figures")
    r.add_argument("--compare", nargs="+", metavar="RECORD", help="replay the bag through each record (YAML, or "
                   "'none') into -o DIR and write the field effect ladder: compare.md, compare.html (plots), one bag "
                   "per record")
    r.add_argument("--calibrate", action="store_true",
                   help="calibrate from the bag's twelve poses as the live calibration node does (the coefficients "
                        "are written into the output bag and applied to the stations after them)")
    r.add_argument("--coeffs-out", help="with --calibrate: also write the last solve's coefficient YAML here")
    r.add_argument("--probe-id", default="probe", help="with --calibrate: the probe's id in the record (a bag's "
                   "/probe/serial wins)")
    r.add_argument("--force-probe", action="store_true",
                   help="apply a record of another probe than the bag's /probe/serial (refused otherwise); every "
                        "station and this output then say so")
    r.add_argument("--effects", default="", metavar="NAME[:sensor[:axes]][@scope],...",
                   help="with --calibrate: effects to fit beyond the paper's model on the captured poses")
    r.add_argument("--plugin", action="append", help="Python file (or module) defining effects: run for --calibrate "
                   "--effects; a record's plug-in is loaded only from these, after its SHA-256 matches (repeatable)")
    r.add_argument("--monitor-window", type=int, default=30, metavar="N",
                   help="the field monitor's window: the model check over the last N stations (0: off)")
    r.add_argument("-o", "--output", required=True, help="bag to write (.mcap file or directory; must not exist); "
                   "with --compare the directory of the comparison")
    r.add_argument("--site", help="site reference YAML overriding the calibration record's (which owns one)")
    north_option(r)
    r.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd", help="chunk compression of the output bag (default zstd)")
    tolerance_options(r)
    detector_options(r, mag_unit=False)
    r.set_defaults(func=cmd_reprocess)
    rt = sub.add_parser("replay-test", help="replay a recorded bag through the live ROS 2 graph and compare its "
                        "stations with an expected set (reprocess's, or another bag's): a regression test for CI")
    rt.add_argument("bag", help="the recorded bag (MCAP) to replay")
    rt.add_argument("--expect", required=True, metavar="reprocess|FILE.mcap",
                    help="the expected stations: 'reprocess' (what reprocess makes of the same bag with the same "
                         "options) or a bag holding /survey/station (an earlier run, a golden reprocessed bag)")
    rt.add_argument("--calibrate", action="store_true", help="calibrate from the bag's twelve poses (the calibration "
                    "node; reprocess --calibrate), else correct with --coeffs")
    rt.add_argument("--coeffs", help="a calibration record to correct with (with --calibrate: for the stations before "
                    "the first solve)")
    rt.add_argument("--site", help="site reference YAML (overrides the record's; with --calibrate, the record's)")
    rt.add_argument("--effects", default="", help="with --calibrate: the model to fit beyond the paper's")
    north_option(rt)
    rt.add_argument("--plugin", action="append", help="Python file (or module) defining effects the records use")
    rt.add_argument("--param", action="append", metavar="NODE:NAME:=VALUE", help="extra node parameter (launcher)")
    rt.add_argument("--speed", type=float, default=50.0, help="the replay's speed ceiling (it is paced: never "
                    "faster than its slowest reader; default 50)")
    rt.add_argument("--tolerance", type=float, default=1e-6, help="angles in degrees (default 1e-6); |G| 1e-2, |B| "
                    "and positions 1e2 times it in their units")
    rt.add_argument("--out", help="the run's directory (default: BAG without .mcap + .replay)")
    rt.add_argument("--overwrite", action="store_true", help="replace a run in --out")
    rt.add_argument("--junit", metavar="FILE.xml", help="also write a JUnit report (one test case per station)")
    rt.add_argument("--timeout", type=float, default=0.0, help="stop the replay after this many seconds (0: none)")
    rt.set_defaults(func=cmd_replay_test)
    b = sub.add_parser("bag", help="bag tools: recover a damaged recording, write probe-log CSVs as a bag")
    bsub = b.add_subparsers(dest="bag_command", required=True)
    br = bsub.add_parser("recover", help="rewrite the readable part of a damaged bag (e.g. a killed recorder's) "
                                         "as a finalized bag that any reader opens")
    br.add_argument("bag", help="the damaged .mcap file or bag directory")
    br.add_argument("-o", "--output", required=True, help="bag to write (must not exist)")
    br.set_defaults(func=cmd_bag_recover)
    bc = bsub.add_parser("from-csv", help="write probe-log CSVs (one after the other) as one rosbag2 MCAP of "
                                          "/probe/imu, /probe/mag, /probe/temperature, /probe/reference")
    bc.add_argument("logs", nargs="+", help="probe-log CSV file(s), in time order")
    bc.add_argument("-o", "--output", required=True, help="bag to write (.mcap file or directory; must not exist)")
    bc.add_argument("--mag-unit", choices=list(MAG_UNITS), default="nT", help="unit of the logs' magnetometer columns")
    bc.add_argument("--gap", type=float, default=2.0, help="pause inserted between logs whose times overlap, s")
    bc.add_argument("--probe-serial", default="", help="the probe's serial number, written as /probe/serial")
    bc.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd", help="chunk compression of the bag (default zstd)")
    bc.set_defaults(func=cmd_bag_from_csv)
