"""Command-line interface ``inclinometer-calib`` (works without ROS installed).

Sub-commands: ``simulate``, ``twelve-position``, ``correct``, ``demo``.
Errors in the input are reported as ``error: ...`` on stderr with exit status 2; rejected rows and
dropped stations are listed as warnings and the good data is used.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys

import numpy as np
import yaml

from ..calibrate import simulate as sim
from ..core.coeffs import Calibration
from .common import UserError, load_calibration, load_site
from .. import __version__
from ..core.deps import MissingDependency, require
from ..core.frames import Site
from ..core.geomag import NORTH_CHOICES, resolve_north
from ..calibrate.capture import CaptureSession
from ..detect.gates import SettlingTally, apply_gates
from ..core.output import OutputError, atomic_write_bytes, atomic_write_text, check_output, output_folder, output_path
from ..io.probelog import MAG_UNITS, Limits, read_csv, report, segment_stations, write_csv
from ..core.station import correct_stations
from ..io.progress import progress_bar
from ..core.model import ModelContextError
from ..correct.pipeline import (NO_SITE, along_north, context_warnings, evaluate_stations,
                       reference_along_north, site_override_note, station_status, usable)
from ..core.survey import Tolerances, format_table4, format_table5, summarize, table4, table5
from ..calibrate.twelve_position import format_table2, format_table3


def _warn(msg):
    print(f"warning: {msg}", file=sys.stderr)


# --------------------------------------------------------------------------------------------
def detector_from_args(args):
    """A :class:`streaming.StaticDetector` from the common detector options (defaults: noise from
    the data)."""
    from ..detect.streaming import StaticDetector

    try:
        return StaticDetector(noise_acc=getattr(args, "noise_acc_override", 0.0) or 0.0,
                              noise_mag=getattr(args, "noise_mag_override", 0.0) or 0.0,
                              k_sigma=getattr(args, "k_sigma", 6.0), min_duration_s=getattr(args, "min_static_s", 0.5))
    except ValueError as exc:
        raise UserError(str(exc)) from None


def load_stations(path, quiet=False, mag_unit="nT", detector=None, labels=True):
    """Read a log and find its stations (the live nodes' detector); print rejections and
    problems as warnings.  Returns ``(log, stations, rejections, problems)``."""
    try:
        log, rejections = read_csv(path, Limits(), mag_unit=mag_unit)
    except OSError as exc:
        raise UserError(f"{path}: {exc.strerror}") from None
    except ValueError as exc:
        raise UserError(str(exc)) from None
    stations, problems = segment_stations(log, detector=detector, use_labels=labels)
    if not quiet:
        report(path, rejections, problems, _warn)
    if rejections:
        _warn(f"{path}: {len(rejections)} of {len(rejections) + len(log)} rows rejected; "
              f"{len(log)} rows kept")
    return log, stations, rejections, problems


# --------------------------------------------------------------------------------------------
def load_plugins(specs, quiet=True, run=True):
    """The ``--plugin`` files/modules the user named (:mod:`plugins`: only these are ever executed).

    ``run``: the command needs their effects (simulate, fit, diagnose): executed now, their effects
    can then be named anywhere.  Otherwise (a command that reads records): named only, each executed
    when a record needs an effect from it and its SHA-256 is the record's."""
    from ..core.plugins import PluginError, load_plugin, name_plugin

    for plug in specs or ():
        try:
            names = load_plugin(plug) if run else ()
            if not run:
                name_plugin(plug)
        except PluginError as exc:
            raise UserError(str(exc)) from None
        if names and not quiet:
            print(f"plug-in {plug}: {', '.join(names)}", file=sys.stderr)


def cmd_simulate(args):
    load_plugins(args.plugin)
    try:
        probe = sim.build_probe(args.seed, args.effect, severity=args.severity,
                                noise_acc=args.noise_acc, noise_mag=args.noise_mag)
    except ValueError as exc:
        raise UserError(f"--effect: {exc}") from None
    site = Site(args.total_field, args.dip, args.declination, args.gravity)
    rng = np.random.default_rng(args.seed + 1)
    temps = [float(t) for t in args.cal_temps.split(",")]
    cal_session = sim.twelve_pose_session(temps, duration_s=args.pose_seconds, azimuth_deg=args.stand_azimuth,
                                          refs=args.pose_refs)
    if not args.rate > 0 or args.move_seconds < 0:
        raise UserError("--rate must be > 0 and --move-seconds >= 0")
    cal = sim.run_session(probe, site, cal_session, rng, rate_hz=args.rate, survey=False, move_s=args.move_seconds)
    try:
        val_temps = [float(x) for x in args.val_temp.split(":")]
    except ValueError:
        raise UserError(f"--val-temp {args.val_temp!r}: expected temperatures separated by ':'") from None
    val_session = sim.stand_grid_session(duration_s=args.station_seconds, temp_profile_c=val_temps)
    val = sim.run_session(probe, site, val_session, rng, rate_hz=args.rate, t0=cal.t_s[-1] + 10.0,
                          survey=not args.no_survey_effects, move_s=args.move_seconds)
    if args.no_labels:  # a log as a probe without a stand system writes it: no pose, no reference
        cal.pose[:] = 0
        cal.ref[:] = np.nan
    with output_folder(args.out) as out:       # all the files or none
        said = _write_simulation(args, out, probe, site, rng, temps, val_temps, cal, val, cal_session, val_session)
    print("\n".join(said))
    return 0


def _write_simulation(args, out, probe, site, rng, temps, val_temps, cal, val, cal_session, val_session) -> list:
    """The simulated session's files written into ``out``; returns what to say of them."""
    write_csv(os.path.join(out, "cal.csv"), cal, mag_unit=args.mag_unit)
    write_csv(os.path.join(out, "val.csv"), val, mag_unit=args.mag_unit)
    truth = {"seed": args.seed, "site": site.to_dict(), "probe": probe.to_dict(),
             "cal": {"stations": len(cal_session), "rows": len(cal), "temperatures_c": temps},
             "val": {"stations": len(val_session), "rows": len(val), "temperature_profile_c": val_temps,
                     "survey_effects": not args.no_survey_effects}}
    written = ["cal.csv", "val.csv"]
    if args.turntable:
        if args.turntable < 3:
            raise UserError("--turntable: give the number of table steps per mount (e.g. 12)")
        plan = sim.turntable_session(args.turntable, args.pose_seconds, tilt_deg=args.table_tilt,
                                     temp_c=temps[0])
        tt = sim.run_turntable(probe, site, plan, rng, rate_hz=args.rate, move_s=max(args.move_seconds, 0.5),
                               t0=val.t_s[-1] + 10.0)
        if args.no_table_angles:
            tt.table_deg[:] = np.nan
        write_csv(os.path.join(out, "turntable.csv"), tt, mag_unit=args.mag_unit)
        truth["turntable"] = {"steps_per_mount": args.turntable, "rows": len(tt), "tilt_deg": args.table_tilt,
                              "table_angles_written": not args.no_table_angles}
        written.append("turntable.csv")
    atomic_write_text(os.path.join(out, "truth.json"), json.dumps(truth, indent=2) + "\n")
    atomic_write_text(os.path.join(out, "site.yaml"), yaml.safe_dump({"site": site.to_dict()}))
    true_cal = Calibration(probe.model, probe_id=f"sim-{args.seed}", method="simulator truth", site=site)
    true_cal.save(os.path.join(out, "truth_coeffs.yaml"))
    return ([f"wrote {args.out}/cal.csv ({len(cal)} rows, {len(cal_session)} stations), "
             f"val.csv ({len(val)} rows, {len(val_session)} stations), "
             + (f"turntable.csv ({truth['turntable']['rows']} rows, 3 mounts × {args.turntable} steps), "
                if args.turntable else "") + "truth.json, truth_coeffs.yaml, site.yaml"]
            + [f"  hidden effect: {e.describe()}" for e in probe.effects])


def cmd_turntable(args):
    """The patent's turntable calibration of the magnetometer (:mod:`turntable`)."""
    if args.output:
        check_output(args.output)        # said before the work, not after it
    from ..calibrate import turntable as tt

    load_plugins(args.plugin, run=False)
    site = load_site(args.site) if args.site else None
    acc_rec = None
    if args.acc:
        try:
            acc_rec = Calibration.load(args.acc)
        except (OSError, ValueError) as exc:
            raise UserError(f"--acc {args.acc}: {exc}") from None
    try:
        log, rejections = read_csv(args.log, mag_unit=args.mag_unit)
        report(args.log, rejections, [], _warn)
        steps, messages = tt.steps_from_log(log, args.log, detector_from_args(args))
        for m in messages:
            _warn(m)
        field = site.total_field_nt if site else (acc_rec.site.total_field_nt if acc_rec and
                                                  acc_rec.site_source == "given" else None)
        res = tt.solve(steps, field)
        res.step_offsets = tt.check_angles(steps, field)
    except OSError as exc:
        raise UserError(f"{exc.filename}: {exc.strerror}") from None
    except ValueError as exc:
        raise UserError(str(exc)) from None
    cal = tt.record(res, acc_rec, site, args.probe_id, warn=lambda m: _warn(f"{args.log}: {m}"))
    doc = cal.diagnostics["turntable"]
    cal.save(args.output)
    if args.json:
        print(json.dumps(doc, indent=2, default=float))
        return 0
    p = res.parameters()
    print(f"Turntable calibration of the magnetometer: {len(steps)} steps in 3 mounts, residual RMS "
          f"{res.residual_rms_nt:.2f} nT ({doc['scale']})")
    print(f"{'axis':<5}{'k':>12}{'±':>10}{'bias nT':>11}{'±':>7}{'alpha deg':>11}{'±':>8}{'beta deg':>10}{'±':>8}")
    for i, a in enumerate("xyz"):
        beta = (f"{p['beta_deg'][i]:>10.3f}{p['beta_std'][i]:>8.3f}" if p["beta_defined"][i]
                else f"{'undefined':>18}")
        print(f"{a:<5}{p['k'][i]:>12.6f}{p['k_std'][i]:>10.2g}{p['bias_nT'][i]:>11.2f}{p['bias_std'][i]:>7.2f}"
              f"{p['alpha_deg'][i]:>11.4f}{p['alpha_std'][i]:>8.4f}{beta}")
    if not all(p["beta_defined"]):
        print("beta undefined: alpha is within 3σ of 0 there, so the direction of the tilt means nothing")
    print("Real axes against the marked ones (U − I, rad; row = real axis, column = marked axis):")
    for i, a in enumerate("xyz"):
        print(f"  {a}_m " + " ".join(f"{v:+.6f}±{sd:.1g}" for v, sd in zip(p['misalignment_rad'][i],
                                                                          p['misalignment_std'][i])))
    print("Sinusoids o = A·sin(θ + b) + C:")
    for sn in res.sinusoids:
        print(f"  {sn.mount} {sn.axis}: A {sn.A:10.2f}  b {sn.b_deg:8.3f}°  C {sn.C:10.2f}  rms {sn.rms:.2f} nT")
    for where, d, sd in res.step_offsets:
        _warn(f"{where}: the data put this step {d:+.3f}° ± {sd:.3f}° off its set angle (the table was not where "
              "the log says)")
    for m in res.messages:
        print(f"note: {m}")
    print(f"wrote {args.output}")
    return 0


def cmd_wits(args):
    """Export the corrected stations of a recorded run as WITS0 record 07 (:mod:`wits`)."""
    if args.output:
        check_output(args.output)        # said before the work, not after it
    import datetime as dt

    from .launcher import read_bag
    from ..rig.wits import describe, encode

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
    from .launcher import read_bag
    from ..rig.witsml import (OPTION_HELP, Options, WitsmlError, mag_models, parent_path, trajectory_document,
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
            records.append({"id": str((yaml.safe_load(text) or {})["id"]), "coefficients_yaml": text})
        except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
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


def run_twelve_position(cal_path, site, probe_id, quiet=False, mag_unit="nT", detector=None, effects=""):
    """Solve a twelve-pose log with the live calibration node's session (:class:`capture.CaptureSession`):
    the same detector, gates, pose identification, sequence and solve (and, with ``effects``, the
    same lab fit of a named model).  Pose labels, when the log has them, are checked against the
    poses gravity shows.  ``site`` None: the site reference is taken from the data (dip and the
    horizontal field's direction on the stand; the total field in the scale M_d sets).  Returns
    ``(session, calibration)``."""
    _, stations, _, _ = load_stations(cal_path, quiet=quiet, mag_unit=mag_unit, detector=detector)
    try:
        session = CaptureSession(site=site, probe_id=probe_id, effects=effects or "")
    except ValueError as exc:
        raise UserError(f"--effects: {exc}") from None
    for st in stations:
        session.offer(st)
    session.finish()
    if not quiet:   # what the captures met, and what the last solve said (earlier ones were provisional)
        for w in session.capture_warnings + session.solve_notes:
            if session.calibration is None and w == session.message:
                continue   # the error itself, said once below
            _warn(f"{cal_path}: {w}")
    if session.calibration is None:
        raise UserError(f"{cal_path}: {session.message or 'calibration did not solve'}")
    cal = session.calibration
    if cal.site_source == "measured":
        site = cal.site
        if not quiet:
            _warn(f"{cal_path}: no --site given: site reference taken from the calibration data — dip "
                  f"{site.dip_deg:.3f}°, horizontal field {site.declination_deg:+.3f}° from the stand's north "
                  f"(azimuths will be reported from the stand's north), total field {site.total_field_nt:.0f} nT "
                  f"in the scale of an assumed vertical component, gravity {site.gravity_mps2:g} m/s² assumed "
                  "(the scale factors are relative to them; angles are not affected); give --site for a survey "
                  "elsewhere")
    return session, cal


def check_site_against_record(site, cal, tol, where):
    """Warn when a site given now contradicts a record solved without one: its magnetometer scale
    is that of the assumed vertical field, so every station's |B| would be off by the difference."""
    if cal is None or cal.site_source != "measured":
        return
    diff = site.total_field_nt - cal.site.total_field_nt
    if abs(diff) > tol.field_nt:
        _warn(f"{where}: the coefficients were solved without a site (their magnetometer scale is that of an assumed "
              f"field of {cal.site.total_field_nt:.0f} nT) and this site's total field is {site.total_field_nt:.0f} nT: "
              f"every station's |B| will be {-diff:+.0f} nT off and flagged — calibrate with --site for a survey "
              "with another site")


def cmd_twelve_position(args):
    if args.output:
        check_output(args.output)        # said before the work, not after it
    load_plugins(args.plugin)
    session, cal = run_twelve_position(args.cal, load_site(args.site) if args.site else None, args.probe_id,
                                       mag_unit=args.mag_unit, detector=detector_from_args(args), effects=args.effects)
    result = session.result
    site = cal.site
    cal.save(args.output)
    print(format_table2(cal.acc, cal.mag))
    print()
    print(format_table3(cal.acc, cal.mag))
    print()
    print(f"Solved by: accelerometer {result.acc.method}; magnetometer {result.mag.method}")
    print("Per-pose residuals (output minus model; acc m/s^2, mag nT) and round-to-round spread")
    print(f"{'pose':>4} {'rounds':>6} {'acc x':>9} {'acc y':>9} {'acc z':>9} {'mag x':>8} {'mag y':>8} "
          f"{'mag z':>8} {'spread acc':>11} {'spread mag':>11}")

    def fmt(v, w, p):
        return f"{v:>{w}.{p}f}" if np.isfinite(v) else f"{'-':>{w}}"

    for i in range(12):
        ra, rm = result.acc.residuals[i], result.mag.residuals[i]
        sa, sm = (float(np.max(sol.round_spread[i])) if sol.rounds[i] > 1 else float("nan")
                  for sol in (result.acc, result.mag))
        print(f"{i + 1:>4} {result.acc.rounds[i]:>6} " + " ".join(fmt(v, 9, 5) for v in ra) + " " +
              " ".join(fmt(v, 8, 2) for v in rm) + " " + fmt(sa, 11, 5) + " " + fmt(sm, 11, 2))
    imp = result.implied_site()
    print(f"RMS residual: acc {result.acc.rms_residual:.5f} m/s^2 ({result.acc.z_rms:.1f}× the noise), "
          f"mag {result.mag.rms_residual:.2f} nT ({result.mag.z_rms:.1f}× the noise)")
    if cal.site_source == "measured":
        print(f"Measured on the stand (the site reference of this record): |B| {imp['total_field']:.1f} nT (in the "
              f"scale of the assumed vertical field), dip {imp['dip_deg']:.3f} deg, stand tilt "
              f"{imp['stand_tilt_deg']:.3f} deg")
    else:
        print(f"Implied by the corrected data: |B| {imp['total_field']:.1f} nT (site {site.total_field_nt:g}), "
              f"dip {imp['dip_deg']:.3f} deg (site {site.dip_deg:g}), stand tilt {imp['stand_tilt_deg']:.3f} deg")
    if session.fit is not None:
        poses = session.fit.model.fit_poses
        with_poses = " with the stand's pose errors" if poses else ""
        print(f"Model {cal.model.describe()}{with_poses} fitted to the captures: noise-normalised residual RMS "
              f"{session.fit.z_rms:.2f}")
        for r in session.fit.parameter_table(extras_only=True):
            if poses and r["name"].startswith("stand_pose_error.") and r["std"] == 0 and r["value"] == 0:
                continue   # a pose that is right: held at zero (it defines the frame)
            print(f"  {r['name']:<44}{r['value']:>14.6g} ± {r['std']:.2g} {r['unit']}")
        for n in cal.not_identifiable:
            print(f"  not identifiable: {n['parameter']}: {n['reason']}")
    print(f"wrote {args.output} (id {cal.id})")
    return 0


def correct_log(log_path, cal, site, tol, quiet=False, axial=False, mag_unit="nT", detector=None, msa=None,
                north="auto"):
    """Evaluate every static station of a log; returns (stations, result, summary).

    Azimuths (and the reference azimuths, in the result's ``reference_azimuth_deg``) are along
    ``north`` on ``site`` (:func:`pipeline.along_north`; the result's ``azimuth_reference`` names
    it): a north the site cannot give is refused (:class:`UserError`).

    Stations are found by the live nodes' detector and checked by the gates (in-hold motion,
    flat axes): a station that fails is kept in the output, flagged and left out of the error
    statistics.  ``axial``: azimuths from the short-collar correction of axial drill-string
    interference.  ``msa``: an :class:`msa.MSASettings` — azimuths from the multi-station analysis
    of the log's stations (:func:`msa.evaluate_with_msa`; stations that moved or have an unusable
    sensor stay out of the fit); the summary's ``msa`` is then the :class:`msa.MSAResult`.
    """
    north, note = resolve_north(site, north)
    if note:
        raise UserError(f"--north: {note}")
    _, stations, _, _ = load_stations(log_path, quiet=quiet, mag_unit=mag_unit, detector=detector)
    if not stations:
        raise UserError(f"{log_path}: no static stations found")
    tally = SettlingTally()
    for st in stations:
        for msg in tally.add(apply_gates(st)):   # corrected |G| is checked by the QC; the raw |g| gate is for captures
            if not quiet:
                _warn(f"{log_path}: {msg}")
    settled = tally.summary(len(stations), str(log_path))
    if settled and not quiet:
        _warn(settled)
    try:
        g, b = correct_stations(stations, cal, strict=True)   # the one correction path, with each station's temperature
    except ModelContextError as exc:
        raise UserError(f"{log_path}: {exc}") from None
    missing = [st for st in stations if context_warnings(st, cal)]
    if missing and not quiet:
        _warn(f"{log_path}: {len(missing)} station(s) without a temperature: {context_warnings(missing[0], cal)[0]}")
    ref = np.array([s.ref for s in stations])
    ref_used = np.where(np.array([s.moved for s in stations])[:, None], np.nan, ref)  # moved: no error figures
    has_ref = np.any(np.isfinite(ref_used), axis=1)
    if msa is not None:
        from ..correct.msa import evaluate_with_msa
        if site is None:
            raise UserError(f"{log_path}: multi-station analysis needs a site reference "
                            "(a record, or --site SITE.yaml)")
        use = np.array([not s.moved and not s.unusable for s in stations])
        try:
            res, fit = evaluate_with_msa(g, b, site, tol, ref_used if has_ref.any() else None, msa, use=use)
        except ValueError as exc:
            raise UserError(f"{log_path}: {exc}") from None
        _along(res, ref, site, north)
        return stations, res, {**_finish(stations, res), "msa": fit}
    res = evaluate_stations(g, b, site, tol, ref_used if has_ref.any() else None, axial)
    _along(res, ref, site, north)
    return stations, res, _finish(stations, res)


def _along(res, ref, site, north):
    """The result's azimuths and the log's reference azimuths along ``north`` (the errors, against
    the true reference, are unchanged)."""
    along_north(res, site, north)
    res["azimuth_reference"] = north
    res["reference_azimuth_deg"] = reference_along_north(ref[:, 1], site, north)


def _finish(stations, res) -> dict:
    """The one status rule on every station (:func:`pipeline.station_status`), and the summary of
    the usable ones only: a station that is not to be used has no error figures."""
    res["status"] = np.array([station_status(st, q) for st, q in zip(stations, res["status"])], dtype=int)
    bad = ~usable(res["status"])
    for k in ("drift_err", "azimuth_err", "toolface_err"):
        if k in res:
            res[k] = np.where(bad, np.nan, res[k])
    return summarize(res)


from ..io.surveystation import CSV_COLUMNS as STATION_COLUMNS  # noqa: E402  (the one field table)


def format_station_csv(stations, res) -> str:
    lines = [",".join(STATION_COLUMNS)]

    def f(v, p=4):
        return "" if v is None or not np.isfinite(v) else f"{v:.{p}f}"

    for k, st in enumerate(stations):
        flags = [n for n in ("azimuth_undefined", "interference_suspected", "gravity_out_of_tolerance",
                             "axial_degenerate", "msa_rejected", "msa_unobservable") if n in res and res[n][k]]
        flags += ["moved_during_capture"] if st.moved else []
        flags += [f"{s}_unusable" for s in st.unusable]
        err = (lambda n: res[n][k] if n in res else None)
        ref = list(st.ref)
        if "reference_azimuth_deg" in res:       # along the azimuths' north (correct_log)
            ref[1] = res["reference_azimuth_deg"][k]
        undefined = bool(res["azimuth_undefined"][k])
        row = [str(st.index), str(st.pose or ""), f(st.t_start, 3), f(st.t_end, 3), str(st.n), f(st.temp_c, 2),
               f(res["drift_deg"][k]), "" if res["azimuth_undefined"][k] else f(res["azimuth_deg"][k]),
               f(res["toolface_deg"][k]),
               "gravity" if res["toolface_is_gravity"][k] else "magnetic",
               f(res["gravity_toolface_deg"][k]), f(res["magnetic_toolface_deg"][k]),
               f(res["total_gravity"][k], 5), f(res["total_field"][k], 1), f(res["dip_deg"][k]),
               f(res["delta_g"][k], 5), f(res["delta_b"][k], 1), f(res["delta_dip"][k]),
               ["ok", "warn", "error"][int(res["status"][k])], "|".join(flags),
               *(f(v) for v in ref), f(err("drift_err")), f(err("azimuth_err")), f(err("toolface_err")),
               str(res.get("azimuth_reference", "")),
               *("" if undefined or n not in res else f(res[n][k])
                 for n in ("azimuth_true_deg", "azimuth_magnetic_deg", "azimuth_grid_deg"))]
        lines.append(",".join(row))
    return "\n".join(lines) + "\n"


def site_for(args, cal, tol, where):
    """The site reference of a run: the record's (it owns one), a ``--site`` overriding it (said
    aloud), or none at all (said too: no QC against a reference, azimuths magnetic)."""
    if args.site:
        site = load_site(args.site)
        note = site_override_note(cal, site)
        if note:
            _warn(f"{where}: {note}")
        check_site_against_record(site, cal, tol, where)
        return site
    if cal is not None:
        return cal.site
    _warn(f"{where}: {NO_SITE} (give --site SITE.yaml)")
    return None


def cmd_correct(args):
    if args.output:
        check_output(args.output)        # said before the work, not after it
    load_plugins(args.plugin, run=False)
    cal = load_calibration(args.coeffs)
    tol = Tolerances(field_nt=args.field_tol, dip_deg=args.dip_tol, gravity_mps2=args.gravity_tol)
    site = site_for(args, cal, tol, args.log)
    msa = _msa_settings(args, site)
    stations, res, summ = correct_log(args.log, cal, site, tol, axial=args.axial_correction, mag_unit=args.mag_unit,
                                      detector=detector_from_args(args), msa=msa, north=args.north)
    fit = summ.pop("msa", None)
    if args.output:
        atomic_write_text(args.output, format_station_csv(stations, res))
    summ["coefficients"] = cal.id if cal else "none"
    flags = ("azimuth_undefined", "interference_suspected", "gravity_out_of_tolerance") + \
        (("axial_degenerate",) if args.axial_correction or fit else ()) + \
        (("msa_rejected", "msa_unobservable") if fit else ())
    summ["flagged"] = {n: int(np.sum(res[n])) for n in flags}
    summ["azimuth_method"] = ("short_collar" if args.axial_correction else
                              ("msa" if fit.observable else "standard (MSA unobservable)") if fit else "standard")
    if fit is not None:
        summ["msa"] = fit.to_dict()
        summ["msa"]["stations"] = [st.index for st in stations]
    if site is not None:
        from ..core.geomag import azimuth_reference
        summ["azimuth_reference"] = azimuth_reference(site, args.north)
    status = np.asarray(res["status"], dtype=int)
    summ["qc"] = {name: int(np.sum(status == k)) for k, name in enumerate(("ok", "warn", "error"))}
    # the site checks themselves: |B|, dip, |G| against the site within the tolerances
    with np.errstate(invalid="ignore"):
        off = {"|B|": np.abs(res["delta_b"]) > tol.field_nt, "dip": np.abs(res["delta_dip"]) > tol.dip_deg,
               "|G|": np.abs(res["delta_g"]) > tol.gravity_mps2}
    out_of_tol = off["|B|"] | off["dip"] | off["|G|"]
    summ["qc"]["out_of_tolerance"] = {k: int(np.sum(v)) for k, v in off.items()}
    # most stations out of tolerance against the record's own site (no --site): another probe's
    # record, or interference — said, and not a clean exit (against a site given, the counts say it)
    n_fail = int(np.sum(out_of_tol))
    failed = cal is not None and not args.site and n_fail > len(stations) / 2
    qc_text = (f"QC against the site (|B| {tol.field_nt:g} nT, dip {tol.dip_deg:g}°, |G| {tol.gravity_mps2:g} m/s²): "
               f"{len(stations) - n_fail} of {len(stations)} stations within, "
               + ", ".join(f"{k} off at {v}" for k, v in summ["qc"]["out_of_tolerance"].items())
               + f"; status {summ['qc']['ok']} ok, {summ['qc']['warn']} warn, {summ['qc']['error']} error"
               + (" (the error stations are left out of the figures)" if summ["qc"]["error"] else ""))
    fail_text = (f"error: {n_fail} of the {len(stations)} stations are out of tolerance against the site of record "
                 f"{cal.id if cal else ''}: another probe's record, or magnetic interference (the flags in the "
                 "station table say which stations)?")
    if args.json:
        print(json.dumps(summ, indent=2))
        if failed:
            print(fail_text, file=sys.stderr)
        return 1 if failed else 0
    ref = np.array([s.ref for s in stations])
    if "drift_err" in res:
        label = "after" if cal else "uncorrected"
        print(format_table4(None, table4(res, ref)).replace("after ", f"{label[:6]:<6}"))
        print()
        print(format_table5(None, table5(res, ref)).replace(" after ", f" {label[:6]:<6}"))
        print()
    if fit is not None:
        from ..correct.msa import format_result
        print(format_result(fit, [st.index for st in stations], res["drift_deg"]))
        print()
    print(_summary_line(summ))
    print(qc_text)
    if "azimuth_reference" in summ:
        print(f"azimuths from {summ['azimuth_reference']}")
    if args.output:
        print(f"wrote {args.output} ({len(stations)} stations)")
    if failed:
        print(fail_text, file=sys.stderr)
        return 1
    return 0


def _msa_settings(args, site):
    """The multi-station analysis' settings from ``--msa`` and ``--reference-sigma`` (default:
    from where the site's values came from, :func:`msa.reference_sigma`), or None without
    ``--msa``."""
    if args.msa is None:
        if args.reference_sigma:
            raise UserError("--reference-sigma is a setting of --msa")
        return None
    if args.axial_correction:
        raise UserError("--axial-correction and --msa are two ways to correct axial interference: give one")
    from ..correct.msa import MSASettings, reference_sigma
    if args.reference_sigma:
        try:
            sb, sd = (float(x) for x in args.reference_sigma.split(","))
        except ValueError:
            raise UserError(f"--reference-sigma {args.reference_sigma!r}: expected FIELD_NT,DIP_DEG "
                            "(e.g. 50,0.1 for IFR, 152,0.22 for WMM)") from None
    else:
        sb, sd, _ = reference_sigma(site) if site is not None else (50.0, 0.1, "")
    try:
        return MSASettings(sigma_field_nt=sb, sigma_dip_deg=sd, parameters=args.msa)
    except ValueError as exc:
        raise UserError(f"--msa / --reference-sigma: {exc}") from None


def _summary_line(s):
    if "drift_rms_deg" not in s:
        return f"{s['stations']} stations (no reference angles in the log)"
    return (f"{s['stations']} stations: drift RMS {s['drift_rms_deg']:.3f} deg (max {s['drift_max_abs_deg']:.3f}), "
            f"azimuth RMS {s['azimuth_rms_deg']:.3f} deg (max {s['azimuth_max_abs_deg']:.3f}) "
            f"over {s['azimuth_stations']} stations with defined azimuth")


def cmd_demo(args):
    """Offline demo: simulate → twelve-position → correct; before/after tables."""
    out = args.out
    sim_args = build_parser().parse_args(["simulate", "--out", out, "--seed", str(args.seed)])
    cmd_simulate(sim_args)
    site = load_site(os.path.join(out, "site.yaml"))
    _, cal = run_twelve_position(os.path.join(out, "cal.csv"), site, f"sim-{args.seed}")
    cal.save(os.path.join(out, "coeffs.yaml"))
    print()
    print(format_table2(cal.acc, cal.mag))
    print()
    print(format_table3(cal.acc, cal.mag))
    print()
    val = os.path.join(out, "val.csv")
    tol = Tolerances()
    st_b, res_b, s_b = correct_log(val, None, site, tol, quiet=True)
    st_a, res_a, s_a = correct_log(val, cal, site, tol, quiet=True)
    ref = np.array([s.ref for s in st_a])
    print(format_table4(table4(res_b, ref), table4(res_a, ref)))
    print()
    print(format_table5(table5(res_b, ref), table5(res_a, ref)))
    print()
    print("before: " + _summary_line(s_b))
    print("after:  " + _summary_line(s_a))
    atomic_write_text(os.path.join(out, "stations.csv"), format_station_csv(st_a, res_a))
    print(f"outputs in {out}/ (cal.csv, val.csv, coeffs.yaml, stations.csv, truth.json)")
    return 0


def field_monitor(args):
    """The correction node's model check (:class:`lab.field.FieldMonitor`) over ``--monitor-window``
    stations, or None when it is 0."""
    if not getattr(args, "monitor_window", 0):
        return None
    from ..lab.field import FieldMonitor

    return FieldMonitor(window=args.monitor_window)


def cmd_reprocess(args):
    """Offline reprocessing of a recorded bag (see :mod:`inclinometer_calib.correct.reprocess`).

    Exit status 0; 1 when the input bag is damaged (everything readable was processed and
    written, the damage is reported as ``error:``) or ``--calibrate`` did not solve; 2 when
    nothing could be done.
    """
    from ..io.bag import BagError
    from ..correct.reprocess import TOPIC_STATION, ReprocessError, reprocess

    if args.compare:
        return cmd_compare(args)
    if args.coeffs is None and not args.calibrate:
        raise UserError("give --coeffs FILE (or 'none' for uncorrected figures), or --calibrate to calibrate "
                        "from the bag's twelve poses as the live graph does")
    load_plugins(args.plugin, run=bool(args.calibrate and args.effects))   # fitting plug-in effects: run them
    cal = load_calibration(args.coeffs)
    tol = Tolerances(field_nt=args.field_tol, dip_deg=args.dip_tol, gravity_mps2=args.gravity_tol)
    if args.site:
        site = site_for(args, cal, tol, args.bag)
    else:
        site = None   # the record's (and with --calibrate, the stand's measured one until a record exists)
        if cal is None and not args.calibrate:
            _warn(f"{args.bag}: {NO_SITE} (give --site SITE.yaml)")
    det = detector_from_args(args)
    if args.coeffs_out:
        check_output(args.coeffs_out)
    try:
        with output_path(args.output) as tmp, progress_bar(None, "msg", "reprocess") as bar:   # whole or not at all
            def advance(done, total):
                bar.total = total
                bar.update(done - bar.n)

            rep = reprocess(args.bag, tmp, cal, site, tol, det, compression=args.compression,
                            warn=_warn, calibrate=args.calibrate, probe_id=args.probe_id, effects=args.effects,
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
    for w in rep.warnings():
        if not w.startswith("skipped topic"):  # those were warned as they were met
            _warn(f"{args.bag}: {w}")
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
    from ..lab import compare
    from ..io.bag import BagError
    from ..core.deps import require
    from ..correct.reprocess import ReprocessError

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
    tol = Tolerances(field_nt=args.field_tol, dip_deg=args.dip_tol, gravity_mps2=args.gravity_tol)
    site = load_site(args.site) if args.site else None
    if site is None and all(c is None for _, c in models):
        _warn(f"{args.bag}: {NO_SITE} (give --site SITE.yaml)")
    for name, cal in models:
        note = site_override_note(cal, site)
        if note:
            _warn(f"{args.bag}: {name}: {note}")
    try:
        runs = compare.compare(args.bag, models, args.output, site=site, tolerances=tol,
                               make_detector=lambda: detector_from_args(args), warn=_warn,
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
    from ..io.bag import BagError, recover

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
    from ..io.probelog import ProbeLog
    from ..correct.reprocess import write_probe_bag

    logs = []
    for path in args.logs:
        try:
            log, rejections = read_csv(path, Limits(), mag_unit=args.mag_unit)
        except OSError as exc:
            raise UserError(f"{path}: {exc.strerror}") from None
        except ValueError as exc:
            raise UserError(str(exc)) from None
        report(path, rejections, [], _warn)
        if logs and len(log) and log.t_s[0] <= logs[-1].t_s[-1]:
            # logs that each start at 0: the next one follows the previous after a pause
            shift = logs[-1].t_s[-1] - log.t_s[0] + args.gap
            _warn(f"{path}: its time starts at {log.t_s[0]:g} s, before the previous log ends: shifted by "
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


# --------------------------------------------------------------------------------------------
# Model lab
# --------------------------------------------------------------------------------------------
def _lab_setup(args):
    from .. import lab
    from ..lab.spec import build_model

    load_plugins(args.plugin, quiet=args.json)
    if bool(args.bag) == bool(args.cal):
        raise UserError("give the calibration log (--cal, with --val and --free) or a recorded run (--bag)")
    try:
        if args.bag:
            from ..io.bag import BagError
            try:
                data, cal = lab.load_bag(args.bag, warn=_warn)
            except BagError as exc:
                raise UserError(str(exc)) from None
            if args.site:
                site = load_site(args.site)
            elif cal is not None:
                site = cal.site
                _warn(f"{args.bag}: no --site given: using the site reference of the run's own calibration "
                      f"({cal.site_source}): total field {site.total_field_nt:.0f} nT, dip {site.dip_deg:.3f}°")
            else:
                raise UserError(f"{args.bag}: no --site given and the run's captures do not solve: give --site")
            args.site_source = "given" if args.site else cal.site_source
        else:
            site = load_site(args.site) if args.site else _site_from_calibration(args.cal[0])
            args.site_source = "given" if args.site else "measured"
            data = lab.load_logs(args.cal, args.val, warn=_warn, free_paths=args.free or ())
        model = build_model(site, args.effects, fit_heading=args.fit_heading)
    except OSError as exc:
        raise UserError(f"{exc.filename}: {exc.strerror}") from None
    except ValueError as exc:
        raise UserError(str(exc)) from None
    return lab, site, data, model


def _site_from_calibration(cal_path):
    """Site reference measured by a twelve-pose log (see :func:`run_twelve_position`); a log that
    cannot give one is an error (never a default site)."""
    try:
        _, cal = run_twelve_position(cal_path, None, "probe", quiet=True)
    except UserError as exc:
        raise UserError(f"no --site given, and {cal_path} cannot measure one (no twelve-pose solve: {exc}): give "
                        "--site SITE.yaml") from None
    _warn(f"{cal_path}: no --site given: using the site reference the twelve poses measure (dip "
          f"{cal.site.dip_deg:.3f}°, horizontal field {cal.site.declination_deg:+.3f}° from the stand's north)")
    return cal.site


def _progress(args):
    if args.json or args.quiet:
        return None
    return lambda msg: print(f"  … {msg}", file=sys.stderr, flush=True)


def cmd_lab_fit(args):
    if args.output:
        check_output(args.output)        # said before the work, not after it
    from ..lab.diagnose import blocked_folds, field_fit, losses_text, validation

    lab, site, data, model = _lab_setup(args)
    figures = []          # (label, metrics): the headline first
    if args.fit_on in ("field", "cal"):     # never the validation references
        inv = args.fit_on == "field"
        result = field_fit(model, data, progress=_progress(args), survey_invariants=inv)
        v = validation(model, data, survey_invariants=inv)
        if v.get("stations"):
            figures.append(v)
        fitted_on = "cal logs" + (" and the survey's |g|, |B|, dip" if inv and (data.role == "val").any() else "")
    else:
        result = lab.fit(model, data, progress=_progress(args))
        folds = blocked_folds(data, args.folds)
        cv = lab.cross_validate(model, data, folds) if folds else {}
        if cv:
            figures.append(cv)
        v = validation(model, data)
        if v.get("stations"):
            v["kind"] = "in-sample"
            v["label"] = "in-sample: errors on stations the model was fitted on (they understate the field error)"
            figures.append(v)
        fitted_on = "cal + val logs"
    headline = figures[0] if figures else {}
    val = data.subset(data.role == "val")
    if args.output:   # the fitted model as the record that correct, reprocess and the nodes apply
        rec = model.record(probe_id=args.probe_id, site_source=args.site_source,
                           not_identifiable=result.not_identifiable,
                           fit_stats={"chi2": result.chi2, "dof": result.dof, "z_rms": result.z_rms,
                                      "stations": len(data), "data": data.describe(),
                                      "validation": {k: v for k, v in headline.items() if k != "stations"}},
                           method=f"lab fit ({fitted_on}) of {model.describe()}")
        rec.save(args.output)
    out = {"model": model.describe(), "effects": model.labels(), "data": data.describe(), "fitted_on": fitted_on,
           "fit": {"chi2": result.chi2, "dof": result.dof, "z_rms": result.z_rms, "success": result.success,
                   "seconds": result.seconds},
           "parameters": result.parameter_table(),
           "not_identifiable": [{"parameter": n.parameter, "reason": n.reason} for n in result.not_identifiable],
           "strong_correlations": [{"a": a, "b": b, "r": r} for a, b, r in result.strong_correlations(0.98)],
           "validation": figures, "val": headline,
           "losses": [x.to_json() for x in data.losses],
           "uncorrected": lab.uncorrected_metrics(val, site) if len(val) else {}}
    if args.output:
        out["record"] = {"path": args.output, "id": rec.id}
    if args.json:
        print(json.dumps(out, indent=2, default=float))
        return 0
    print(f"model: {out['model']}")
    print(f"data:  {out['data']}")
    lost = losses_text(data.losses)
    if lost:
        print(lost)
    print(f"fit:   on the {fitted_on}: χ²/dof {result.reduced_chi2:.2f}, noise-normalised residual RMS "
          f"{result.z_rms:.2f} ({result.seconds:.2f} s)")
    print(f"{'parameter':<44}{'value':>14}{'±1σ':>12}  unit")
    for r in result.parameter_table():
        print(f"{r['name']:<44}{r['value']:>14.6g}{r['std']:>12.2g}  {r['unit']}")
    for n in result.not_identifiable:
        print(f"not identifiable: {n.parameter}: {n.reason}")
    for a, b, r in result.strong_correlations(0.98):
        print(f"strongly correlated: {a} ~ {b} (r = {r:+.3f})")
    for f in figures:
        print(f"{f['label']}: drift RMS {f['drift_rms_deg']:.4f} deg, azimuth RMS "
              f"{f['azimuth_rms_deg']:.4f} deg over {f['stations']} stations")
    if args.output:
        print(f"wrote {args.output} (id {rec.id}): the calibration record of this model, for correct, reprocess "
              "and the correction node")
    return 0


def cmd_lab_diagnose(args):
    if args.plugin_out and os.path.exists(args.plugin_out):
        raise UserError(f"{args.plugin_out}: exists; name a new file for the plug-in (nothing is overwritten)")
    lab, site, data, model = _lab_setup(args)
    dg = lab.diagnose(data, model, progress=_progress(args))
    if args.plugin_out:
        _write_plugin(args.plugin_out, dg, " and ".join(str(x) for x in (args.cal or []) + [args.val] if x))
    if args.json:
        print(json.dumps(dg.to_json(), indent=2, default=float))
        return 0
    print(dg.verdict)
    print()
    print(f"errors: {dg.base_val.get('label', 'no station with a reference')}")
    print(f"{'candidate':<40}{'drift RMS':>10}{'az RMS':>10}{'pointing':>10}{'Wald p':>10}{'ΔBIC':>9}  note")
    b = dg.base_val
    print(f"{'(current model)':<40}{b.get('drift_rms_deg', float('nan')):>10.4f}"
          f"{b.get('azimuth_rms_deg', float('nan')):>10.4f}{dg.base_score:>10.4f}")
    for c in dg.ranked:
        print(f"{c.label:<40}{c.val.get('drift_rms_deg', float('nan')):>10.4f}{c.val.get('azimuth_rms_deg', float('nan')):>10.4f}"
              f"{c.score:>10.4f}{c.p:>10.1e}{c.delta_bic:>9.0f}  {'* ' if c.significant else ''}{c.note}")
    for u in dg.untestable:
        print(f"not testable here: {u['effect']}: {u['reason']}")
    return 0


def _write_plugin(path, dg, where) -> None:
    """Write the diagnosis' first term outside the catalogue as a plug-in module at ``path``
    (:func:`lab.discover.plugin_source`), whole or not at all; say what was written, or that
    nothing was found outside the catalogue."""
    from ..lab.discover import plugin_name, plugin_source

    outside = [p for p in dg.discovered if p.outside]
    if not outside:
        _warn(f"{path}: not written: nothing outside the catalogue was found")
        return
    import tempfile

    text = plugin_source(outside[0], where)
    fd, tmp = tempfile.mkstemp(prefix=os.path.basename(path) + ".", suffix=".part",
                               dir=os.path.dirname(os.path.abspath(path)))
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except OSError as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise UserError(f"{path}: not written: {exc.strerror}") from None
    _warn(f"wrote {path}: {outside[0].formula()} as the effect {plugin_name(outside[0])} — fit it: "
          f"inclinometer-calib lab fit ... --plugin {path} --effects {plugin_name(outside[0])}")


def cmd_lab_report(args):
    lab, site, data, model = _lab_setup(args)
    methods = None
    if args.turntable:
        from ..lab.methods import compare
        if not args.cal or not args.val:
            raise UserError("--turntable compares the methods on --cal (the twelve poses) and --val logs: give both")
        truth = load_calibration(args.truth) if args.truth else None
        try:
            methods = compare(args.cal[0], args.turntable, args.val, site, truth)
        except OSError as exc:
            raise UserError(f"{exc.filename}: {exc.strerror}") from None
        except ValueError as exc:
            raise UserError(f"--turntable: {exc}") from None
    steps = lab.write_report(args.output, data, site, args.effects, max_steps=args.max_steps,
                             progress=_progress(args), methods=methods)
    for k, s in enumerate(steps):
        v = s.base_val
        print(f"rung {k}: {s.model.describe()}: drift RMS {v.get('drift_rms_deg', float('nan')):.4f} deg, "
              f"azimuth RMS {v.get('azimuth_rms_deg', float('nan')):.4f} deg ({v.get('kind', '')})")
        for n in s.notes:
            print(f"  {n}")
    print(f"wrote {args.output}")
    return 0


def cmd_lab_noise(args):
    """The noise model of static logs: Allan deviation per axis of every hold, IEEE figures."""
    from .. import lab
    from ..detect.allan import format_noise, sensor_noise
    from ..lab.noise import COLUMNS, holds

    try:
        data = lab.load_logs(free_paths=args.logs, warn=_warn)
    except OSError as exc:
        raise UserError(f"{exc.filename}: {exc.strerror}") from None
    except ValueError as exc:
        raise UserError(str(exc)) from None
    segs = holds(data)
    noise = {s: sensor_noise(s, [x[:, COLUMNS[s]] for x in segs]) for s in ("acc", "mag")}
    if args.json:
        print(json.dumps({s: m.to_json() for s, m in noise.items()}, indent=2, default=float))
        return 0
    longest = max(float(np.ptp(x[:, 0])) for x in segs)
    print(f"{len(segs)} holds (longest {longest:.0f} s), Allan deviation up to τ = "
          f"{noise['mag'].curve.tau[-1] if len(noise['mag'].curve.tau) else float('nan'):.3g} s")
    print(format_noise(noise.values()))
    print("N: white noise density (σ at τ = 1 s); B: bias instability (flat part / 0.664); K: bias random walk "
          "(σ at τ = 3 s). '<': not resolved, one-sided 95 % bound. A walk the holds are too short to see is "
          "measured across the stations by 'lab diagnose'.")
    return 0


def parse_date(text: str, what: str):
    """A date or date-time given on the command line (ISO 8601: ``2026-03-01``,
    ``2026-03-01T14:30``, ``2026-03-01T14:30+02:00``) as an aware datetime; without a zone it is UTC."""
    import datetime as dt

    try:
        t = dt.datetime.fromisoformat(text)
    except ValueError:
        raise UserError(f"{what}: {text!r} is not an ISO 8601 date (e.g. 2026-03-01 or 2026-03-01T14:30Z)") from None
    return t.replace(tzinfo=dt.timezone.utc) if t.tzinfo is None else t


#: What the fleet's commands import (the ``fleet`` extra), checked before any work starts.
FLEET_REGISTRY = ("sqlalchemy", "alembic")
FLEET_REPROCESS = FLEET_REGISTRY + ("dask", "distributed", "pyarrow")


def _fleet_needs(purpose: str, modules) -> None:
    """One line, exit status 2, when the ``fleet`` extra is not installed (:func:`deps.require`)."""
    for module in modules:
        require(module, "fleet", purpose)


def _registry(args, create: bool = True):
    """The registry ``--db`` names; ``create=False`` for a command that only reads it."""
    from ..fleet.registry import DEFAULT_URL, Registry, RegistryError

    try:
        return Registry(args.db or DEFAULT_URL, create=create)
    except RegistryError as exc:
        raise UserError(str(exc)) from None


def cmd_fleet_register(args):
    """``fleet register SERIAL``: add a probe to the registry (or, with --update, change its details)."""
    _fleet_needs("fleet register", FLEET_REGISTRY)
    from ..fleet.registry import RegistryError

    with _registry(args) as reg:
        try:
            if args.update:
                p = reg.update_probe(args.serial, model=args.model, note=args.note,
                                     calibration_interval_days=args.interval)
            else:
                p = reg.add_probe(args.serial, model=args.model or "", note=args.note or "",
                                  calibration_interval_days=args.interval if args.interval is not None else 90.0)
        except RegistryError as exc:
            raise UserError(str(exc)) from None
        print(f"probe {p.serial}: model {p.model or '-'}, calibration interval {p.calibration_interval_days:g} days"
              + (f", note: {p.note}" if p.note else "") + f" (registry {reg.url.render_as_string(hide_password=True)})")
    return 0


def cmd_fleet_add(args):
    """``fleet add RECORD.yaml --date DATE``: store a calibration record of a registered probe, with
    the date of the calibration, the operator's note and the SHA-256 of the raw log."""
    _fleet_needs("fleet add", FLEET_REGISTRY)
    import hashlib

    from ..fleet.registry import RegistryError

    load_plugins(args.plugin, run=False)
    cal = load_calibration(args.record)
    if cal is None:
        raise UserError("fleet add: give a calibration record file")
    when = parse_date(args.date, "--date")
    raw = ""
    if args.raw_log:
        h = hashlib.sha256()
        try:
            with open(args.raw_log, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    h.update(chunk)
        except OSError as exc:
            raise UserError(f"--raw-log {args.raw_log}: {exc.strerror}") from None
        raw = h.hexdigest()
    with _registry(args) as reg:
        try:
            rid = reg.add_calibration(cal, calibrated_at=when, operator_note=args.note or "", raw_log_sha256=raw)
        except RegistryError as exc:
            raise UserError(f"{args.record}: {exc}") from None
    print(f"calibration {rid} of probe {cal.probe_id} at {when.astimezone().isoformat()} stored"
          + (f" (raw log sha256 {raw})" if raw else ""))
    return 0


def cmd_fleet_history(args):
    """``fleet history SERIAL``: each parameter over time with its 1σ, the calibrations that moved
    beyond their combined uncertainty, and whether the probe is overdue (text; --html with plots)."""
    _fleet_needs("fleet history", FLEET_REGISTRY)
    from ..fleet import history as fh
    from ..fleet.registry import RegistryError

    at = parse_date(args.at, "--at") if args.at else None
    if not (args.k > 0):
        raise UserError(f"--k must be positive, got {args.k}")
    with _registry(args, create=False) as reg:
        try:
            h = fh.analyse(reg.probe(args.serial), reg.history(args.serial), at=at, k=args.k)
        except RegistryError as exc:
            raise UserError(str(exc)) from None
    if args.json:
        print(json.dumps(fh.to_json(h), indent=2))
    else:
        print(fh.format_history(h))
    if args.html:
        try:
            atomic_write_text(args.html, fh.to_html(h))
        except OSError as exc:
            raise UserError(f"--html {args.html}: {exc.strerror}") from None
        if not args.json:
            print(f"wrote {args.html}")
    return 0


def _fleet_registry_parser(fsub):
    """``fleet register``, ``fleet add``, ``fleet history`` (the registry, docs/fleet.md)."""
    def db(p):
        p.add_argument("--db", help="registry: SQLAlchemy URL (e.g. postgresql+psycopg://user@host/fleet) or SQLite "
                                    "file (default sqlite:///fleet.db in the working folder)")

    r = fsub.add_parser("register", help="register a probe by its serial number")
    r.add_argument("serial", help="the probe's serial number (letters, digits, -_.:/)")
    r.add_argument("--model", help="the probe's model")
    r.add_argument("--note", help="a note on the probe")
    r.add_argument("--interval", type=float, metavar="DAYS", help="calibration interval, days (default 90): a "
                   "calibration older than this is not valid for a survey")
    r.add_argument("--update", action="store_true", help="change the details of a registered probe")
    db(r)
    r.set_defaults(func=cmd_fleet_register)
    a = fsub.add_parser("add", help="store a calibration record of a registered probe (its probe_id is the serial)")
    a.add_argument("record", help="calibration record YAML (twelve-position, turntable, lab fit ...)")
    a.add_argument("--date", required=True, help="when the probe was calibrated, ISO 8601 (UTC unless a zone is given)")
    a.add_argument("--note", help="the operator's note")
    a.add_argument("--raw-log", metavar="FILE", help="the raw calibration log (its SHA-256 is stored)")
    a.add_argument("--plugin", action="append", help="Python file (or module) defining plug-in effects the record "
                   "uses: loaded only from these, after its SHA-256 matches (repeatable)")
    db(a)
    a.set_defaults(func=cmd_fleet_add)
    h = fsub.add_parser("history", help="a probe's parameters over time with 1σ; flags calibrations that moved beyond "
                                        "their combined uncertainty and an overdue probe")
    h.add_argument("serial", help="the probe's serial number")
    h.add_argument("--html", metavar="FILE", help="also write the history with plots as one HTML file")
    h.add_argument("--at", metavar="DATE", help="check the calibration interval at this date (default now)")
    h.add_argument("--k", type=float, default=3.0, help="flag a parameter that moved by more than k·sqrt(σ1²+σ2²) "
                                                        "(default 3)")
    h.add_argument("--json", action="store_true", help="the history as JSON")
    db(h)
    h.set_defaults(func=cmd_fleet_history)


def cmd_fleet_reprocess(args):
    """``fleet reprocess BAGS... | --manifest FILE -o OUT``: many bags on Dask into one Parquet
    dataset (:mod:`inclinometer_calib.fleet.reprocess`). Exit status 0 when every bag is done
    (now or before), 1 when some failed (each with its reason in the summary), 2 when nothing
    could be done."""
    _fleet_needs("fleet reprocess", FLEET_REPROCESS)
    from ..fleet.manifest import ManifestError, entries_from_paths, read_manifest
    from ..fleet.registry import DEFAULT_URL
    from ..fleet.reprocess import Settings, reprocess_fleet

    if bool(args.bags) == bool(args.manifest):
        raise UserError("give the bags either as arguments or with --manifest FILE (one of the two)")
    try:
        entries = read_manifest(args.manifest) if args.manifest else entries_from_paths(args.bags)
    except ManifestError as exc:
        raise UserError(str(exc)) from None
    settings = Settings(field_nt=args.field_tol, dip_deg=args.dip_tol, gravity_mps2=args.gravity_tol,
                        monitor_window=args.monitor_window, force_probe=args.force_probe)
    with _registry(args, create=False):     # the records come from it: an existing one, before any cluster
        pass
    try:
        summary = reprocess_fleet(entries, out_dir=args.output, registry_url=args.db or DEFAULT_URL,
                                  scheduler=args.scheduler, n_workers=args.workers, progress=not args.no_progress,
                                  bags_per_task=args.bags_per_task, settings=settings)
    except OutputError:             # the output folder refused: "cannot write PATH: CAUSE"
        raise
    except OSError as exc:          # the scheduler cannot be reached
        raise UserError(f"{args.scheduler or args.output}: {exc}") from None
    except ValueError as exc:       # RegistryError (the registry cannot be opened), a run already there, bad options
        raise UserError(str(exc)) from None
    for line in summary.lines():
        print(line)
    print(f"wrote {summary.paths['dataset']}/ (Parquet, by probe and survey date: every run's), "
          f"{summary.paths['summary']} (this run's bags only: it replaces the last run's), {summary.paths['index']} "
          "(every bag done, and under what)")
    return 1 if summary.failed else 0


def _fleet_reprocess_parser(fsub):
    r = fsub.add_parser("reprocess", help="reprocess many bags on Dask (each with its probe's valid record from the "
                                          "registry) into one Parquet dataset partitioned by probe and survey date")
    r.add_argument("bags", nargs="*", help="bags (.mcap files or bag folders)")
    r.add_argument("--manifest", help="text file of bag paths, one a line, or CSV with columns bag[,serial]; relative "
                                      "paths are relative to the manifest's folder")
    r.add_argument("-o", "--output", required=True, help="output folder: stations/ (the dataset), summary.csv, "
                                                          "done-index.json (a rerun skips the bags done there)")
    r.add_argument("--db", help="registry: SQLAlchemy URL or SQLite file (default sqlite:///fleet.db)")
    r.add_argument("--scheduler", metavar="tcp://HOST:PORT", help="run on this Dask scheduler's cluster (default: a "
                   "local cluster on this machine)")
    r.add_argument("--workers", type=int, metavar="N", help="worker processes of the local cluster (default: the "
                   "cores; 0: no Dask, one bag after the other in this process)")
    r.add_argument("--bags-per-task", type=int, metavar="N", help="bags per Dask task (default: up to 10, at least 4 "
                   "tasks per worker; see docs/fleet.md)")
    r.add_argument("--force-probe", action="store_true", help="apply the record of the serial the manifest gives to a "
                   "bag that records another serial (refused otherwise); every station and the summary say so")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.add_argument("--monitor-window", type=int, default=30, metavar="N",
                   help="the field monitor's window, as reprocess (0: off)")
    r.add_argument("--field-tol", type=float, default=Tolerances.field_nt, help="QC |ΔB| tolerance, nT")
    r.add_argument("--dip-tol", type=float, default=Tolerances.dip_deg, help="QC |Δdip| tolerance, deg")
    r.add_argument("--gravity-tol", type=float, default=Tolerances.gravity_mps2, help="QC |ΔG| tolerance, m/s^2")
    r.set_defaults(func=cmd_fleet_reprocess)
    return r


def _fleet_parser(sub):
    """The ``fleet`` group: each part of the fleet adds its sub-commands to ``fsub`` here."""
    fleet = sub.add_parser("fleet", help="probe fleet: registry, calibration history, reprocessing many bags")
    fsub = fleet.add_subparsers(dest="fleet_command", required=True)
    _fleet_registry_parser(fsub)
    _fleet_reprocess_parser(fsub)
    return fsub


def _lab_parser(sub):
    lab = sub.add_parser("lab", help="model lab: fit any model, diagnose missing effects, report")
    lsub = lab.add_subparsers(dest="lab_command", required=True)

    def common(p, effects_help):
        p.add_argument("--cal", action="append", help="calibration log CSV (twelve poses and/or stand stations); "
                       "repeat for several runs (e.g. two heating rates)")
        p.add_argument("--bag", help="instead of logs: a recorded run (its captures are the calibration data, its "
                                     "stations with a reference the validation data)")
        p.add_argument("--val", help="validation / survey log CSV (reference angles)")
        p.add_argument("--free", action="append", help="log CSV without labels (probe turned by hand): its static "
                       "intervals constrain the model through |g|, |B| and dip only (repeatable)")
        p.add_argument("--effects", help=effects_help)
        p.add_argument("--plugin", action="append", help="Python file defining extra effects (repeatable)")
        p.add_argument("--site", help="site reference YAML")
        p.add_argument("--fit-heading", action="store_true", help="also fit the stand's heading offset")
        p.add_argument("--json", action="store_true", help="the result as JSON on standard output (no tables)")
        p.add_argument("--quiet", action="store_true", help="no progress lines")

    f = lsub.add_parser("fit", help="fit a model; parameters ± 1σ, identifiability, validation errors")
    common(f, "effects beyond the paper's base model: NAME[:sensor[:axes]][@scope],...")
    f.add_argument("--fit-on", choices=("field", "cal", "all"), default="field",
                   help="field (default): what a rig has — the calibration logs and the survey's |g|, |B|, dip, "
                        "never its reference angles; errors on the whole validation log. cal: the calibration "
                        "logs only. all: the validation references too (figures then cross-validated in blocks "
                        "of consecutive stations, and in-sample)")
    f.add_argument("-o", "--output", help="write the fitted model as a calibration record (YAML, format 2) that "
                   "correct, reprocess and the correction node apply")
    f.add_argument("--probe-id", default="probe", help="the probe's id in the record")
    f.add_argument("--folds", type=int, default=4, help="with --fit-on all: cross-validation folds (blocks of "
                   "consecutive validation stations)")
    f.set_defaults(func=cmd_lab_fit)
    d = lsub.add_parser("diagnose", help="rank candidate effects by significance against the noise and the field error; recommend the next")
    common(d, "effects already in the model (start of the diagnosis)")
    d.add_argument("--plugin-out", metavar="FILE.py",
                   help="when a term outside the catalogue is found, write it here as a plug-in effect to read, "
                        "edit and fit (lab fit --plugin FILE.py --effects discovered_<sensor>_<axis>)")
    d.set_defaults(func=cmd_lab_diagnose)
    r = lsub.add_parser("report", help="effect ladder + plots + tables as one self-contained HTML file")
    common(r, "effects to start from")
    r.add_argument("-o", "--output", required=True, help="HTML file to write")
    r.add_argument("--max-steps", type=int, default=4, help="most effects to add")
    r.add_argument("--turntable", help="a turntable log of the same probe: the report then compares the twelve "
                                       "positions, the turntable and the lab with both logs on the validation log")
    r.add_argument("--truth", help="with --turntable: the true record (a simulated probe's truth_coeffs.yaml) for "
                                   "the parameter errors")
    r.set_defaults(func=cmd_lab_report)
    n = lsub.add_parser("noise", help="the sensors' noise model from static logs: Allan deviation per axis, "
                                      "white noise, bias instability and random walk (IEEE Std 952 figures)")
    n.add_argument("logs", nargs="+", help="probe-log CSVs; every static hold counts (labels not needed)")
    n.add_argument("--json", action="store_true", help="the noise model as JSON")
    n.set_defaults(func=cmd_lab_noise)


# --------------------------------------------------------------------------------------------
def _detector_options(p, mag_unit=True):
    """Options of the static detector (all paths share it) and, for CSV inputs, the magnetometer unit."""
    g = p.add_argument_group("static detection (defaults: thresholds from the noise the data show)")
    g.add_argument("--noise-acc", dest="noise_acc_override", type=float, default=0.0, metavar="SIGMA",
                   help="accelerometer noise per sample, m/s^2 1σ, instead of measuring it (0: measure)")
    g.add_argument("--noise-mag", dest="noise_mag_override", type=float, default=0.0, metavar="SIGMA",
                   help="magnetometer noise per sample, nT 1σ, instead of measuring it (0: measure)")
    g.add_argument("--k-sigma", type=float, default=6.0,
                   help="a sample further than this many σ from the hold's mean is motion (default 6)")
    g.add_argument("--min-static-s", type=float, default=0.5, help="shortest hold reported as a station, s")
    if mag_unit:
        g.add_argument("--mag-unit", choices=list(MAG_UNITS), default="nT",
                       help="unit of the log's magnetometer columns (default nT)")


def _witsml_options(parser):
    """The WITSML options (:data:`witsml.OPTION_HELP`), checked by :meth:`witsml.Options.check` (one line, exit 2)."""
    from ..rig.witsml import OPTION_HELP, Options

    defaults = Options()
    for name, text in OPTION_HELP.items():
        default = getattr(defaults, name)
        shown = "" if default == "" or (isinstance(default, float) and math.isnan(default)) else f" (default {default})"
        parser.add_argument("--" + name.replace("_", "-"), default=default, type=type(default), help=text + shown,
                            metavar=name.split("_")[-1].upper())


def build_parser():
    p = argparse.ArgumentParser(prog="inclinometer-calib",
                                description="Calibrate magnetic borehole inclinometers and correct their surveys.")
    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="simulate a probe: twelve-pose calibration log and stand-grid validation log")
    s.add_argument("--out", required=True, help="output directory")
    s.add_argument("--effect", action="append", default=[], metavar="NAME[:sensor[:axes]]=V[,V..]",
                   help="add a physical effect (repeatable), e.g. axial_interference=300, "
                        "temperature_bias:mag=2, stand_pose_error=0.1")
    s.add_argument("--plugin", action="append", help="Python file defining extra effects (repeatable)")
    s.add_argument("--seed", type=int, default=1, help="random seed of the simulated probe and its noise (default 1)")
    s.add_argument("--severity", type=float, default=1.0, help="scale of the probe's base-model errors")
    s.add_argument("--noise-acc", type=float, default=0.002, help="accelerometer white noise, m/s^2 1σ")
    s.add_argument("--noise-mag", type=float, default=20.0, help="magnetometer white noise, nT 1σ")
    s.add_argument("--rate", type=float, default=100.0, help="sample rate, Hz")
    s.add_argument("--pose-seconds", type=float, default=3.0, help="time held in each calibration pose, s")
    s.add_argument("--station-seconds", type=float, default=1.0, help="time held at each validation station, s")
    s.add_argument("--cal-temps", default="25", help="temperature of each calibration round, °C (comma list)")
    s.add_argument("--val-temp", default="25:45:30",
                   help="validation temperature profile T1:T2[:T3..] (piecewise linear over the stations), °C")
    s.add_argument("--stand-azimuth", type=float, default=0.0, help="stand's rotation from (true) north, deg")
    s.add_argument("--total-field", type=float, default=Site.total_field_nt, help="site total field, nT")
    s.add_argument("--dip", type=float, default=Site.dip_deg, help="site dip, deg")
    s.add_argument("--declination", type=float, default=Site.declination_deg, help="site declination, deg")
    s.add_argument("--gravity", type=float, default=Site.gravity_mps2, help="site gravity, m/s^2")
    s.add_argument("--no-survey-effects", action="store_true",
                   help="leave survey-only effects (axial interference) out of the validation log")
    s.add_argument("--move-seconds", type=float, default=1.0, help="time of each move between stations, s")
    s.add_argument("--pose-refs", action="store_true",
                   help="give the calibration poses' set drift/azimuth/toolface too, as a stand's log does "
                        "(vertical poses without azimuth)")
    s.add_argument("--no-labels", action="store_true",
                   help="write the calibration log without pose labels or references")
    s.add_argument("--mag-unit", choices=list(MAG_UNITS), default="nT",
                   help="unit of the written magnetometer columns (reading them then needs --mag-unit)")
    s.add_argument("--turntable", type=int, default=0, metavar="STEPS",
                   help="also write turntable.csv: the patent's procedure, three mounts (xy, xz, yz) turned through "
                        "a full turn in STEPS equal steps, each held --pose-seconds")
    s.add_argument("--table-tilt", type=float, default=0.0, help="with --turntable: the table not level, deg")
    s.add_argument("--no-table-angles", action="store_true",
                   help="with --turntable: leave table_deg empty (the angles are then estimated)")
    s.set_defaults(func=cmd_simulate)

    t = sub.add_parser("twelve-position", help="fit both triads from a twelve-pose calibration log")
    t.add_argument("cal", help="calibration log CSV: the twelve poses, labelled or not (the poses are recognised "
                                "from gravity and field; labels are checked)")
    t.add_argument("-o", "--output", required=True, help="coefficient YAML to write")
    t.add_argument("--site", help="site reference YAML (total_field_nt, dip_deg, declination_deg, gravity_mps2)")
    t.add_argument("--probe-id", default="probe", help="the probe's id in the record")
    t.add_argument("--effects", default="", metavar="NAME[:sensor[:axes]][@scope],...",
                   help="effects to fit beyond the paper's model on the captured poses (the lab's fit, e.g. "
                        "temperature_bias:mag when the rounds span a temperature range)")
    t.add_argument("--plugin", action="append", help="Python file (or module) defining extra effects (repeatable)")
    _detector_options(t)
    t.set_defaults(func=cmd_twelve_position)

    tt = sub.add_parser("turntable", help="calibrate the magnetometer from a turntable log (the patent's method: "
                                          "three mounts, equal steps through a full turn)")
    tt.add_argument("log", help="turntable log CSV: the probe-log columns plus mount (xy, xz, yz) and table_deg")
    tt.add_argument("-o", "--output", required=True, help="calibration record YAML to write")
    tt.add_argument("--site", help="site reference YAML (its total field makes k absolute)")
    tt.add_argument("--acc", help="a record (e.g. the twelve positions') whose accelerometer calibration joins "
                                  "this one in the record written")
    tt.add_argument("--probe-id", default="probe", help="the probe's id in the record")
    tt.add_argument("--plugin", action="append", help="Python file (or module) defining plug-in effects the --acc "
                    "record uses: loaded only from these, after its SHA-256 matches (repeatable)")
    tt.add_argument("--json", action="store_true", help="the result as JSON")
    _detector_options(tt)
    tt.set_defaults(func=cmd_turntable)

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

    c = sub.add_parser("correct", help="correct a log's static stations; errors against ref_* if present")
    c.add_argument("log", help="probe log CSV")
    c.add_argument("--coeffs", required=True, help="coefficient YAML, or 'none' for uncorrected figures")
    c.add_argument("-o", "--output", help="station CSV to write")
    c.add_argument("--json", action="store_true", help="print the summary as JSON")
    c.add_argument("--site", help="site reference YAML overriding the calibration record's (which owns one)")
    c.add_argument("--north", choices=NORTH_CHOICES, default="auto", help="north of the azimuths and positions: grid, true or magnetic; auto (default): grid on a site with a grid "
                   "(crs), else true with a declination, else magnetic")
    c.add_argument("--plugin", action="append", help="Python file (or module) defining plug-in effects the record "
                   "uses: a record's plug-in is loaded only from these, after its SHA-256 matches (repeatable)")
    c.add_argument("--field-tol", type=float, default=Tolerances.field_nt, help="QC |ΔB| tolerance, nT")
    c.add_argument("--dip-tol", type=float, default=Tolerances.dip_deg, help="QC |Δdip| tolerance, deg")
    c.add_argument("--gravity-tol", type=float, default=Tolerances.gravity_mps2, help="QC |ΔG| tolerance, m/s^2")
    c.add_argument("--axial-correction", action="store_true",
                   help="short-collar correction of axial drill-string interference (azimuth from the site's "
                        "total field and dip; degenerate stations flagged and left uncorrected)")
    c.add_argument("--msa", nargs="?", const="auto", choices=("auto", "dz", "dz+msz", "dz+mbxy", "all"),
                   help="multi-station analysis of axial interference: the axial field (and, as the attitudes "
                        "support them, Z scale and X/Y biases) fitted over all stations with the reference's "
                        "uncertainty (default auto; docs/interference.md)")
    c.add_argument("--reference-sigma", metavar="FIELD_NT,DIP_DEG",
                   help="with --msa: 1-sigma of the site reference (default from its source: 50,0.1 measured/IFR; "
                        "152,0.22 a main-field model)")
    _detector_options(c)
    c.set_defaults(func=cmd_correct)

    d = sub.add_parser("demo", help="offline demo: simulate, calibrate, correct, before/after tables")
    d.add_argument("--out", default="demo_offline",
                   help="output directory (default: ./demo_offline; scripts/demo.sh's live demo uses ./demo_out)")
    d.add_argument("--seed", type=int, default=1, help="random seed of the simulated probe (default 1)")
    d.set_defaults(func=cmd_demo)
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
    r.add_argument("--north", choices=NORTH_CHOICES, default="auto", help="north of the azimuths and positions: grid, true or magnetic; auto (default): grid on a site with a grid "
                   "(crs), else true with a declination, else magnetic")
    r.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd", help="chunk compression of the output bag (default zstd)")
    r.add_argument("--field-tol", type=float, default=Tolerances.field_nt, help="QC |ΔB| tolerance, nT")
    r.add_argument("--dip-tol", type=float, default=Tolerances.dip_deg, help="QC |Δdip| tolerance, deg")
    r.add_argument("--gravity-tol", type=float, default=Tolerances.gravity_mps2, help="QC |ΔG| tolerance, m/s^2")
    _detector_options(r, mag_unit=False)
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
    rt.add_argument("--north", choices=NORTH_CHOICES, default="auto", help="north of the azimuths and positions: grid, true or magnetic; auto (default): grid on a site with a grid "
                   "(crs), else true with a declination, else magnetic")
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
    _lab_parser(sub)
    _fleet_parser(sub)
    return p


def cmd_replay_test(args):
    """``replay-test``: a bag through the live graph, compared with an expected set (:mod:`replaytest`)."""
    from .replaytest import run

    return run(args)


def main(argv=None):
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (UserError, MissingDependency, OutputError) as exc:  # an optional package (deps.py), an output refused
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
