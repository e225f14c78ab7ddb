"""The model lab's commands: ``lab fit``, ``lab diagnose``, ``lab report``, ``lab noise``."""
from __future__ import annotations

import json
import os
import sys

import numpy as np

from ...core.output import check_output
from ..common import UserError, load_calibration, load_site
from .calibrate import run_twelve_position
from .shared import load_plugins, warn


def _lab_setup(args):
    from ... import lab
    from ...lab.spec import build_model

    load_plugins(args.plugin, quiet=args.json)
    if bool(args.bag) == bool(args.cal):
        raise UserError("give the calibration log (--cal, with --val and --free) or a recorded run (--bag)")
    try:
        if args.bag:
            from ...io.bag import BagError
            try:
                data, cal = lab.load_bag(args.bag, warn=warn)
            except BagError as exc:
                raise UserError(str(exc)) from None
            if args.site:
                site = load_site(args.site)
            elif cal is not None:
                site = cal.site
                warn(f"{args.bag}: no --site given: using the site reference of the run's own calibration "
                      f"({cal.site_source}): total field {site.total_field_nt:.0f} nT, dip {site.dip_deg:.3f}°")
            else:
                raise UserError(f"{args.bag}: no --site given and the run's captures do not solve: give --site")
            args.site_source = "given" if args.site else cal.site_source
        else:
            site = load_site(args.site) if args.site else _site_from_calibration(args.cal[0])
            args.site_source = "given" if args.site else "measured"
            data = lab.load_logs(args.cal, args.val, warn=warn, free_paths=args.free or ())
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
    warn(f"{cal_path}: no --site given: using the site reference the twelve poses measure (dip "
          f"{cal.site.dip_deg:.3f}°, horizontal field {cal.site.declination_deg:+.3f}° from the stand's north)")
    return cal.site


def _progress(args):
    if args.json or args.quiet:
        return None
    return lambda msg: print(f"  … {msg}", file=sys.stderr, flush=True)


def cmd_lab_fit(args):
    if args.output:
        check_output(args.output)        # said before the work, not after it
    from ...lab.diagnose import blocked_folds, field_fit, losses_text, validation

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
    from ...lab.discover import plugin_name, plugin_source

    outside = [p for p in dg.discovered if p.outside]
    if not outside:
        warn(f"{path}: not written: nothing outside the catalogue was found")
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
    warn(f"wrote {path}: {outside[0].formula()} as the effect {plugin_name(outside[0])} — fit it: "
          f"inclinometer-calib lab fit ... --plugin {path} --effects {plugin_name(outside[0])}")


def cmd_lab_report(args):
    lab, site, data, model = _lab_setup(args)
    methods = None
    if args.turntable:
        from ...lab.methods import compare
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
    from ... import lab
    from ...detect.allan import format_noise, sensor_noise
    from ...lab.noise import COLUMNS, holds

    try:
        data = lab.load_logs(free_paths=args.logs, warn=warn)
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


def register(sub):
    """``lab fit``, ``lab diagnose``, ``lab report``, ``lab noise``."""
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
