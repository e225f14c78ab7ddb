"""``correct``: a probe log's static stations corrected, checked against the site and (with
reference angles) their errors; and what the offline demo shares with it (:func:`correct_log`, the
station table)."""
from __future__ import annotations

import json
import sys

import numpy as np

from ...core.geomag import resolve_north
from ...core.output import atomic_write_text, check_output
from ...core.survey import format_table4, format_table5, table4, table5
from ...correct.pipeline import evaluate_log
from ...io.surveystation import CSV_COLUMNS as STATION_COLUMNS   # the one field table
from ..common import UserError, load_calibration
from .shared import (detector_from_args, detector_options, load_plugins, load_stations, north_option, site_for,
                     tolerance_options, tolerances_from_args, warn)


def correct_log(log_path, cal, site, tol, quiet=False, axial=False, mag_unit="nT", detector=None, msa=None,
                north="auto"):
    """Read a log, find its static stations (the live nodes' detector) and evaluate every one
    (:func:`pipeline.evaluate_log`: gates, correction, QC, status; ``axial``, ``msa`` and the
    result's fields there); returns (stations, result, summary).  A north the site cannot give,
    a log without stations or one the model cannot correct is refused (:class:`UserError`);
    ``quiet``: no warnings."""
    north, note = resolve_north(site, north)
    if note:
        raise UserError(f"--north: {note}")
    _, stations, _, _ = load_stations(log_path, quiet=quiet, mag_unit=mag_unit, detector=detector)
    if not stations:
        raise UserError(f"{log_path}: no static stations found")
    try:
        res, summary = evaluate_log(stations, cal, site, tol, north, axial=axial, msa=msa, where=str(log_path),
                                    warn=None if quiet else warn)
    except ValueError as exc:
        raise UserError(str(exc)) from None
    return stations, res, summary


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


def cmd_correct(args):
    if args.output:
        check_output(args.output)        # said before the work, not after it
    load_plugins(args.plugin, run=False)
    cal = load_calibration(args.coeffs)
    tol = tolerances_from_args(args)
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
        from ...core.geomag import azimuth_reference
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
        from ...correct.msa import format_result
        print(format_result(fit, [st.index for st in stations], res["drift_deg"]))
        print()
    print(summary_line(summ))
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
    from ...correct.msa import MSASettings, reference_sigma
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


def summary_line(s):
    if "drift_rms_deg" not in s:
        return f"{s['stations']} stations (no reference angles in the log)"
    return (f"{s['stations']} stations: drift RMS {s['drift_rms_deg']:.3f} deg (max {s['drift_max_abs_deg']:.3f}), "
            f"azimuth RMS {s['azimuth_rms_deg']:.3f} deg (max {s['azimuth_max_abs_deg']:.3f}) "
            f"over {s['azimuth_stations']} stations with defined azimuth")


def register(sub):
    """``correct``."""
    c = sub.add_parser("correct", help="correct a log's static stations; errors against ref_* if present")
    c.add_argument("log", help="probe log CSV")
    c.add_argument("--coeffs", required=True, help="coefficient YAML, or 'none' for uncorrected figures")
    c.add_argument("-o", "--output", help="station CSV to write")
    c.add_argument("--json", action="store_true", help="print the summary as JSON")
    c.add_argument("--site", help="site reference YAML overriding the calibration record's (which owns one)")
    north_option(c)
    c.add_argument("--plugin", action="append", help="Python file (or module) defining plug-in effects the record "
                   "uses: a record's plug-in is loaded only from these, after its SHA-256 matches (repeatable)")
    tolerance_options(c)
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
    detector_options(c)
    c.set_defaults(func=cmd_correct)
