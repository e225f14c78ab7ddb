"""The calibration commands: ``simulate`` (a probe's logs), ``twelve-position`` (both triads from
the twelve poses), ``turntable`` (the magnetometer by the patent's method) and the offline ``demo``
(simulate, calibrate, correct)."""
from __future__ import annotations

import argparse
import json
import os

import numpy as np
from ...core import yamltext

from ...calibrate import simulate as sim
from ...calibrate.capture import CaptureSession
from ...calibrate.twelve_position import format_table2, format_table3
from ...core.coeffs import Calibration
from ...core.frames import Site
from ...core.output import atomic_write_text, check_output, output_folder
from ...core.survey import Tolerances, format_table4, format_table5, table4, table5
from ...io.probelog import MAG_UNITS, read_csv, report, write_csv
from ..common import UserError, load_site
from .shared import detector_from_args, detector_options, load_plugins, load_stations, warn
from .survey import correct_log, format_station_csv, summary_line


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
    atomic_write_text(os.path.join(out, "site.yaml"), yamltext.dump({"site": site.to_dict()}))
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
    from ...calibrate import turntable as tt

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
        report(args.log, rejections, [], warn)
        steps, messages = tt.steps_from_log(log, args.log, detector_from_args(args))
        for m in messages:
            warn(m)
        field = site.total_field_nt if site else (acc_rec.site.total_field_nt if acc_rec and
                                                  acc_rec.site_source == "given" else None)
        res = tt.solve(steps, field)
        res.step_offsets = tt.check_angles(steps, field)
    except OSError as exc:
        raise UserError(f"{exc.filename}: {exc.strerror}") from None
    except ValueError as exc:
        raise UserError(str(exc)) from None
    cal = tt.record(res, acc_rec, site, args.probe_id, warn=lambda m: warn(f"{args.log}: {m}"))
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
        warn(f"{where}: the data put this step {d:+.3f}° ± {sd:.3f}° off its set angle (the table was not where "
              "the log says)")
    for m in res.messages:
        print(f"note: {m}")
    print(f"wrote {args.output}")
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
            warn(f"{cal_path}: {w}")
    if session.calibration is None:
        raise UserError(f"{cal_path}: {session.message or 'calibration did not solve'}")
    cal = session.calibration
    if cal.site_source == "measured":
        site = cal.site
        if not quiet:
            warn(f"{cal_path}: no --site given: site reference taken from the calibration data — dip "
                  f"{site.dip_deg:.3f}°, horizontal field {site.declination_deg:+.3f}° from the stand's north "
                  f"(azimuths will be reported from the stand's north), total field {site.total_field_nt:.0f} nT "
                  f"in the scale of an assumed vertical component, gravity {site.gravity_mps2:g} m/s² assumed "
                  "(the scale factors are relative to them; angles are not affected); give --site for a survey "
                  "elsewhere")
    return session, cal


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


def cmd_demo(args):
    """Offline demo: simulate → twelve-position → correct; before/after tables."""
    out = args.out
    parser = argparse.ArgumentParser(prog="inclinometer-calib")
    _simulate_parser(parser.add_subparsers(dest="command", required=True))
    sim_args = parser.parse_args(["simulate", "--out", out, "--seed", str(args.seed)])
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
    print("before: " + summary_line(s_b))
    print("after:  " + summary_line(s_a))
    atomic_write_text(os.path.join(out, "stations.csv"), format_station_csv(st_a, res_a))
    print(f"outputs in {out}/ (cal.csv, val.csv, coeffs.yaml, stations.csv, truth.json)")
    return 0


def _simulate_parser(sub):
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
    return s


def register(sub):
    """``simulate``, ``twelve-position``, ``turntable``."""
    _simulate_parser(sub)

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
    detector_options(t)
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
    detector_options(tt)
    tt.set_defaults(func=cmd_turntable)


def register_demo(sub):
    """``demo``."""
    d = sub.add_parser("demo", help="offline demo: simulate, calibrate, correct, before/after tables")
    d.add_argument("--out", default="demo_offline",
                   help="output directory (default: ./demo_offline; scripts/demo.sh's live demo uses ./demo_out)")
    d.add_argument("--seed", type=int, default=1, help="random seed of the simulated probe (default 1)")
    d.set_defaults(func=cmd_demo)
