"""What several command groups share: the options they have in common and what turns them into
objects (the static detector's options, the QC tolerances, the north, ``--plugin``, ``--site``
against a record), the reading of a probe log into stations, and the one way a warning is said."""
from __future__ import annotations

import sys

from ...core.geomag import NORTH_CHOICES
from ...core.survey import Tolerances
from ...correct.pipeline import NO_SITE, site_override_note
from ...io.probelog import MAG_UNITS, Limits, read_csv, report, segment_stations
from ..common import UserError, load_site


def warn(msg):
    print(f"warning: {msg}", file=sys.stderr)


def detector_from_args(args):
    """A :class:`streaming.StaticDetector` from the common detector options (defaults: noise from
    the data)."""
    from ...detect.streaming import StaticDetector

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
        report(path, rejections, problems, warn)
    if rejections:
        warn(f"{path}: {len(rejections)} of {len(rejections) + len(log)} rows rejected; "
              f"{len(log)} rows kept")
    return log, stations, rejections, problems


def load_plugins(specs, quiet=True, run=True):
    """The ``--plugin`` files/modules the user named (:mod:`plugins`: only these are ever executed).

    ``run``: the command needs their effects (simulate, fit, diagnose): executed now, their effects
    can then be named anywhere.  Otherwise (a command that reads records): named only, each executed
    when a record needs an effect from it and its SHA-256 is the record's."""
    from ...core.plugins import PluginError, load_plugin, name_plugin

    for plug in specs or ():
        try:
            names = load_plugin(plug) if run else ()
            if not run:
                name_plugin(plug)
        except PluginError as exc:
            raise UserError(str(exc)) from None
        if names and not quiet:
            print(f"plug-in {plug}: {', '.join(names)}", file=sys.stderr)


def check_site_against_record(site, cal, tol, where):
    """Warn when a site given now contradicts a record solved without one: its magnetometer scale
    is that of the assumed vertical field, so every station's |B| would be off by the difference."""
    if cal is None or cal.site_source != "measured":
        return
    diff = site.total_field_nt - cal.site.total_field_nt
    if abs(diff) > tol.field_nt:
        warn(f"{where}: the coefficients were solved without a site (their magnetometer scale is that of an assumed "
              f"field of {cal.site.total_field_nt:.0f} nT) and this site's total field is {site.total_field_nt:.0f} nT: "
              f"every station's |B| will be {-diff:+.0f} nT off and flagged — calibrate with --site for a survey "
              "with another site")


def site_for(args, cal, tol, where):
    """The site reference of a run: the record's (it owns one), a ``--site`` overriding it (said
    aloud), or none at all (said too: no QC against a reference, azimuths magnetic)."""
    if args.site:
        site = load_site(args.site)
        note = site_override_note(cal, site)
        if note:
            warn(f"{where}: {note}")
        check_site_against_record(site, cal, tol, where)
        return site
    if cal is not None:
        return cal.site
    warn(f"{where}: {NO_SITE} (give --site SITE.yaml)")
    return None


def detector_options(p, mag_unit=True):
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


def tolerance_options(p):
    """The QC tolerances (``--field-tol``, ``--dip-tol``, ``--gravity-tol``; defaults :class:`survey.Tolerances`)."""
    p.add_argument("--field-tol", type=float, default=Tolerances.field_nt, help="QC |ΔB| tolerance, nT")
    p.add_argument("--dip-tol", type=float, default=Tolerances.dip_deg, help="QC |Δdip| tolerance, deg")
    p.add_argument("--gravity-tol", type=float, default=Tolerances.gravity_mps2, help="QC |ΔG| tolerance, m/s^2")


def tolerances_from_args(args) -> Tolerances:
    """The :class:`survey.Tolerances` of :func:`tolerance_options`."""
    return Tolerances(field_nt=args.field_tol, dip_deg=args.dip_tol, gravity_mps2=args.gravity_tol)


def north_option(p):
    """``--north``: the north of the azimuths and positions (:func:`geomag.resolve_north`)."""
    p.add_argument("--north", choices=NORTH_CHOICES, default="auto", help="north of the azimuths and positions: grid, true or magnetic; auto (default): grid on a site with a grid "
                   "(crs), else true with a declination, else magnetic")
