"""The survey pipeline, ROS-free: what happens to a closed station on every path.

The correction node, ``reprocess``, ``correct``, the launcher's run summary and the lab all go
through here, so that a station means the same numbers wherever it is computed:

1. the station (:class:`station.Station`, closed by :class:`streaming.StaticDetector` from a
   stream, a bag or a log) is gated (:func:`gates.apply_gates`);
2. it is corrected by the calibration record's model (:meth:`coeffs.Calibration.correct`, the one
   correction path: the paper's base model plus any lab effects, with the station's temperature
   and its time since the data's first sample);
3. it is evaluated against the **site reference, which the record owns**
   (:func:`survey.evaluate`: angles, |G|, |B|, dip and their QC); a site given by the user
   overrides the record's, and says so at every record it overrides (:func:`site_override_note`);
   without a record and without a site there is no reference: the station's QC fields are NaN and
   it says why — never a default site;
4. its azimuth, its reference azimuth and its position are put along the run's **one north**
   (:func:`along_north`, the north from :func:`geomag.resolve_north`: grid, true or magnetic),
   the azimuths from the other norths beside them, and it is placed in the trajectory by minimum
   curvature from that azimuth;
5. the field monitor (:class:`lab.field.FieldMonitor`), when there is one, tests the latest
   stations' residuals against the site for the trend a missing effect leaves, and says in words
   when the model stops explaining the data.

The result is the plain field dict of a ``SurveyStation`` message (:func:`station_fields`): the
node sets it on an rclpy message, ``reprocess`` serializes it with rosbags, the CLI prints it.
"""
from __future__ import annotations

import math

import numpy as np

from .axial import evaluate_with_axial
from ..detect.gates import SettlingTally, apply_gates
from ..core.geomag import azimuths, resolve_north
from .iscwsa import position_covariance, terms_from_calibration
from ..core.station import Station, StationSequence, correct_stations
from ..core.survey import Tolerances, evaluate, summarize
from .trajectory import minimum_curvature

NAN = float("nan")
#: The default tie-in of a trajectory: the surface (md, inclination, azimuth, tvd, north, east).
TIE_IN_SURFACE = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
NO_SITE = ("no site reference: no calibration record yet and no site given — |G|, |B| and dip are not "
           "checked, azimuths are magnetic")


#: A record's ``probe_id`` that names no probe (the default of older records and tools): applied
#: without the serial check, and said.
UNNAMED_PROBE = "probe"


class ProbeMismatch(ValueError):
    """A calibration record of one probe offered for another probe's data (not forced)."""


def probe_mismatch(cal, serial: str):
    """What is wrong with applying record ``cal`` to the data of probe ``serial`` — the record
    names another probe — or None (no record, data of no named probe, a record naming no probe,
    or the same probe)."""
    if cal is None or not serial:
        return None
    rec = str(getattr(cal, "probe_id", "") or "")
    if not rec or rec == UNNAMED_PROBE or rec == serial:
        return None
    return f"record {cal.id} is a calibration of probe {rec}, the data are of probe {serial}"


def site_override_note(cal, site) -> str:
    """What a user's site changes against the record's (said loudly wherever it happens), or ""."""
    if cal is None or site is None:
        return ""
    own = cal.site
    diffs = [f"{name} {getattr(site, attr):g} instead of {getattr(own, attr):g}"
             for name, attr in (("total field", "total_field_nt"), ("dip", "dip_deg"),
                                ("declination", "declination_deg"), ("gravity", "gravity_mps2"))
             if getattr(site, attr) != getattr(own, attr)]
    if not diffs:
        return ""
    return (f"the site reference given overrides the one of record {cal.id} ({cal.site_source}): "
            + ", ".join(diffs) + " — QC and azimuths use the given one")


def evaluate_stations(g, b, site, tol: Tolerances = Tolerances(), ref=None, axial: bool = False) -> dict:
    """:func:`survey.evaluate` (or the short-collar :func:`axial.evaluate_with_axial`) of corrected
    vectors; ``site`` None: no reference — angles only (azimuths magnetic), the QC fields NaN and
    not flagged, status at least warn."""
    if site is None:
        from ..core.frames import Site
        res = evaluate(g, b, Site(declination_deg=0.0), tol)   # angles only: its QC is voided below
        n = len(res["status"])
        for k in ("delta_g", "delta_b", "delta_dip"):
            res[k] = np.full(n, NAN)
        res["interference_suspected"] = np.zeros(n, bool)
        res["gravity_out_of_tolerance"] = np.zeros(n, bool)
        res["status"] = np.maximum(res["status"], 1)
        if ref is not None:
            from ..core.survey import reference_errors
            res.update(reference_errors(res, ref, Site(declination_deg=0.0), tol))
        return res
    if axial:
        return evaluate_with_axial(g, b, site, tol, ref=ref)
    return evaluate(g, b, site, tol, ref=ref)


def along_north(res: dict, site, north: str) -> dict:
    """Evaluated stations (:func:`evaluate_stations`' result, whose ``azimuth_deg`` is true:
    magnetic + the site's declination) with their azimuth from ``north`` (:data:`geomag.NORTHS`):
    ``azimuth_deg`` becomes it, and ``azimuth_true_deg``, ``azimuth_magnetic_deg`` and
    ``azimuth_grid_deg`` hold the azimuth from each north (true NaN without a site, grid NaN without
    a grid; :func:`geomag.azimuths`: magnetic = true − D, grid = true − γ).  The one place a
    station's azimuth is put along the run's north.  In place; returns ``res``."""
    decl = site.declination_deg if site is not None else 0.0
    refs = azimuths(res["azimuth_deg"], decl, site.grid_convergence_deg if site is not None else NAN)
    res["azimuth_true_deg"] = refs["true"] if site is not None else np.full_like(refs["true"], np.nan)
    res["azimuth_magnetic_deg"], res["azimuth_grid_deg"] = refs["magnetic"], refs["grid"]
    res["azimuth_deg"] = refs[north]
    return res


def reference_along_north(azimuth_true_deg, site, north: str):
    """A reference azimuth (deg, from the site's NED north: true) from ``north`` (:func:`along_north`'s
    conversion), so that it compares with the station's ``azimuth_deg``."""
    decl = site.declination_deg if site is not None else 0.0
    return azimuths(azimuth_true_deg, decl, site.grid_convergence_deg if site is not None else NAN)[north]


def station_status(st: Station, qc_status: int) -> int:
    """A station's status, the one rule for every path: 2 (error, not to be used) when the probe
    moved during the hold or a gate refused a sensor's data (a flat or clipped axis, an implausible
    |g|: :mod:`gates`), else the QC's verdict (0 ok, 1 warn, 2 error: :func:`survey.evaluate`).
    What is 2 never counts in a summary figure as good (:func:`usable`)."""
    return 2 if (st.moved or st.unusable) else int(qc_status)


def usable(status) -> np.ndarray:
    """The stations a summary figure (an RMS, a maximum) may count: status below 2."""
    return np.asarray(status) < 2


def context_warnings(st: Station, cal) -> list:
    """What the model needs of a station and does not get (said in the station's warnings)."""
    if cal is not None and "temperature" in cal.needs and not math.isfinite(st.temp_c):
        return [f"no temperature at this station: the model's temperature effect(s) cannot be applied "
                f"(record {cal.id}); its corrected values are NaN"]
    return []



def evaluate_log(stations, cal, site, tol: Tolerances, north: str, *, axial: bool = False, msa=None,
                 where: str = "", warn=None) -> tuple:
    """Every static station of a log in one batch, the steps of the module docstring for the
    ``correct`` command: returns ``(result, summary)`` (:func:`evaluate_stations`' dict, and
    :func:`survey.summarize` of the usable stations).

    Each station is gated (in-hold motion, flat axes: one that fails stays in the result, flagged,
    its status error and its error figures NaN), corrected by ``cal`` (None: uncorrected), and
    evaluated against ``site``; azimuths, and the log's reference azimuths in
    ``reference_azimuth_deg``, are along ``north`` (resolved: :func:`geomag.resolve_north`; the
    result's ``azimuth_reference`` names it).  ``axial``: azimuths from the short-collar correction
    of axial drill-string interference.  ``msa``: an :class:`msa.MSASettings` — azimuths from the
    multi-station analysis of the stations (:func:`msa.evaluate_with_msa`; stations that moved or
    have an unusable sensor stay out of the fit); the summary's ``msa`` is then the
    :class:`msa.MSAResult`.  ``warn`` (a callable, or None for silence) hears what the gates and
    the model met, each line starting with ``where``; a log that cannot be evaluated raises
    ``ValueError`` (``where: why``).
    """
    def say(msg):
        if warn is not None:
            warn(msg)

    tally = SettlingTally()
    for st in stations:
        for msg in tally.add(apply_gates(st)):   # corrected |G| is checked by the QC; the raw |g| gate is for captures
            say(f"{where}: {msg}")
    settled = tally.summary(len(stations), where)
    if settled:
        say(settled)
    try:
        g, b = correct_stations(stations, cal, strict=True)   # the one correction path, with each station's temperature
    except ValueError as exc:   # ModelContextError: a temperature or time the model needs and the log lacks
        raise ValueError(f"{where}: {exc}") from None
    missing = [st for st in stations if context_warnings(st, cal)]
    if missing:
        say(f"{where}: {len(missing)} station(s) without a temperature: {context_warnings(missing[0], cal)[0]}")
    ref = np.array([s.ref for s in stations])
    ref_used = np.where(np.array([s.moved for s in stations])[:, None], np.nan, ref)  # moved: no error figures
    has_ref = np.any(np.isfinite(ref_used), axis=1)
    if msa is not None:
        from .msa import evaluate_with_msa
        if site is None:
            raise ValueError(f"{where}: multi-station analysis needs a site reference "
                             "(a record, or --site SITE.yaml)")
        use = np.array([not s.moved and not s.unusable for s in stations])
        try:
            res, fit = evaluate_with_msa(g, b, site, tol, ref_used if has_ref.any() else None, msa, use=use)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        _log_along(res, ref, site, north)
        return res, {**_log_summary(stations, res), "msa": fit}
    res = evaluate_stations(g, b, site, tol, ref_used if has_ref.any() else None, axial)
    _log_along(res, ref, site, north)
    return res, _log_summary(stations, res)


def _log_along(res, ref, site, north):
    """The result's azimuths and the log's reference azimuths along ``north`` (the errors, against
    the true reference, are unchanged)."""
    along_north(res, site, north)
    res["azimuth_reference"] = north
    res["reference_azimuth_deg"] = reference_along_north(ref[:, 1], site, north)


def _log_summary(stations, res) -> dict:
    """The one status rule on every station (:func:`station_status`), and the summary of the
    usable ones only: a station that is not to be used has no error figures."""
    res["status"] = np.array([station_status(st, q) for st, q in zip(stations, res["status"])], dtype=int)
    bad = ~usable(res["status"])
    for k in ("drift_err", "azimuth_err", "toolface_err"):
        if k in res:
            res[k] = np.where(bad, np.nan, res[k])
    return summarize(res)

class SurveyProcessor:
    """Gates, corrects and evaluates closed stations (the steps of the module docstring).

    ``calibration``: the record to apply (:meth:`set_calibration` replaces it); ``site``: a user's
    site reference overriding the record's (None: the record's); ``axial``: azimuths from the
    short-collar correction of axial drill-string interference (:func:`axial.evaluate_with_axial`;
    QC stays on the measured field); ``monitor``: a :class:`lab.field.FieldMonitor` or None;
    ``north``: the north of the azimuths and positions (:data:`geomag.NORTH_CHOICES`, resolved on
    the site in force by :func:`geomag.resolve_north`: a north the site cannot give is said in every
    station's warnings; with a site given, a ``ValueError`` at once).
    """

    def __init__(self, tolerances: Tolerances = Tolerances(), calibration=None, *, site=None,
                 axial: bool = False, monitor=None, tie_in=TIE_IN_SURFACE, probe_serial: str = "",
                 force_probe: bool = False, north: str = "auto"):
        self.tolerances = tolerances
        self.north = str(north)
        _, note = resolve_north(site, self.north)     # ValueError: not a north
        if site is not None and note:
            raise ValueError(note)
        # the trajectory: (md, inclination, azimuth, tvd, north, east) of the stations with a depth,
        # in order of depth, from the tie-in (default: the surface, vertical)
        self.tie_in = tuple(float(x) for x in tie_in)
        self._path = [self.tie_in]
        self._mag_azimuths = [NAN]          # magnetic azimuth of each station of the path (ISCWSA weights)
        self._terms = None                  # the ISCWSA tool model for this record and site
        self.site_given = site
        self.axial = axial
        self.monitor = monitor
        self.calibration = None
        self.probe_serial = str(probe_serial or "")
        self.force_probe = bool(force_probe)
        self.forced = ""                    # what every station says when a mismatched record is forced
        self.refused = ""                   # why the record was dropped (the data's serial is another probe's)
        self._next_id = 0
        self._previous = StationSequence()   # the stations before the next (:class:`StationSequence`)
        self.notes: list = []
        if calibration is not None:
            self.set_calibration(calibration)

    @property
    def site(self):
        """The site reference in force: the user's, else the record's, else None."""
        if self.site_given is not None:
            return self.site_given
        return self.calibration.site if self.calibration is not None else None

    def set_calibration(self, calibration) -> list:
        """Apply a record from now on; returns what must be said about it (a site override, a
        forced record of another probe).  Raises :class:`ProbeMismatch` for a record of another
        probe than the data's (:func:`probe_mismatch`) unless ``force_probe``: the record in force
        stays."""
        forced = self._check_probe(calibration, self.probe_serial)
        self.calibration = calibration
        self._terms = None
        self.forced, self.refused = forced, ""
        note = site_override_note(calibration, self.site_given)
        self.notes = [n for n in (note, forced) if n]
        if self.monitor is not None:
            self.monitor.reset(calibration)
        return list(self.notes)

    def _check_probe(self, cal, serial) -> str:
        why = probe_mismatch(cal, serial)
        if why is None:
            return ""
        if not self.force_probe:
            raise ProbeMismatch(f"{why}: not applied (force it only if the record is known to fit these data)")
        return f"FORCED: {why}, applied by the user's order"

    def set_probe_serial(self, serial: str) -> list:
        """The data's probe from now on (``/probe/serial``).  Raises :class:`ProbeMismatch` when the
        record in force is another probe's (not forced): the record is then dropped (the stations
        go uncorrected, and say why)."""
        serial = str(serial or "")
        try:
            forced = self._check_probe(self.calibration, serial)
        except ProbeMismatch as exc:
            self.probe_serial = serial
            self.calibration, self._terms, self.forced, self.refused = None, None, "", f"uncorrected: {exc}"
            raise
        self.probe_serial = serial
        self.forced = forced
        return [forced] if forced else []

    def process(self, st: Station, ref=None, have_temperature: bool = True) -> dict:
        """The ``SurveyStation`` fields of one closed station (:func:`station_fields`).

        A station in which the probe moved is still evaluated, and flagged.  ``ref``: the
        reference attitude (drift, azimuth, toolface deg; NaN where not given), or None;
        ``have_temperature``: the stream has a temperature at all (else ``temperature_c`` is NaN)."""
        apply_gates(st)
        cal = self.calibration
        st.warnings.extend(w for w in context_warnings(st, cal) if w not in st.warnings)
        for said in (self.forced, self.refused if cal is None else ""):
            if said and said not in st.warnings:
                st.warnings.append(said)
        if ref is not None and not any(math.isfinite(x) for x in ref):
            ref = None
        g, b = correct_stations([st], cal, previous=self._previous)
        self._previous = self._previous.after(st, g[0], b[0])     # what the next station needs of this one
        site = self.site
        if site is None and NO_SITE not in st.warnings:
            st.warnings.append(NO_SITE)
        res = evaluate_stations(g, b, site, self.tolerances, None if ref is None else [ref], self.axial)
        north, note = resolve_north(site, self.north)
        note = f"{note}: azimuths and positions along {north} north" if note else ""
        if note and note not in st.warnings:
            st.warnings.append(note)
        along_north(res, site, north)       # the azimuth reported (true, or short-collar) along the run's north
        values = {k: (v[0].item() if hasattr(v[0], "item") else v[0]) for k, v in res.items()}
        values.update(self._trajectory(st, values))
        if ref is not None:                 # the reference attitude's azimuth (site NED: true) along it too
            ref = (ref[0], float(reference_along_north(ref[1], site, north)), ref[2])
        fields = station_fields(self._next_id, st, values, cal.id if cal is not None else "", ref, north,
                                have_temperature)
        fields["probe_serial"] = self.probe_serial
        self._next_id += 1
        if self.monitor is not None and cal is not None:
            verdict = self.monitor.add(st, fields, g[0], b[0])
            fields["model_misfit"] = verdict.misfit
            fields["model_diagnosis"] = verdict.text
        return fields

    def _trajectory(self, st: Station, values: dict) -> dict:
        """Depth and position of a station by minimum curvature from the station before it in depth
        (:mod:`trajectory`: from its measured depth, drift and ``azimuth_deg``, so north/east are
        along the north of its azimuth, :func:`along_north`).  A station at or above a depth already
        surveyed (a re-survey) replaces what lies below it.  Without a depth (or a drift, or when the probe moved) the fields are NaN."""
        out = {"measured_depth_m": NAN, "tvd_m": NAN, "north_m": NAN, "east_m": NAN, "dls_deg_per_30m": NAN,
               "position_covariance_ned_m2": [NAN] * 9}
        md, inc = float(st.md_m), float(values.get("drift_deg", NAN))
        if not (math.isfinite(md) and math.isfinite(inc)) or st.moved:
            out["measured_depth_m"] = md if math.isfinite(md) else NAN
            return out
        azi = float(values["azimuth_deg"])
        azi = azi if math.isfinite(azi) and not values.get("azimuth_undefined") else 0.0
        while len(self._path) > 1 and self._path[-1][0] >= md:      # a re-survey replaces what it overlaps
            self._path.pop()
            self._mag_azimuths.pop()
        prev = self._path[-1]
        if md <= prev[0]:      # at or above the tie-in: nothing to place it from
            out["measured_depth_m"] = md
            return out
        t = minimum_curvature([prev[0], md], [prev[1], inc], [prev[2], azi], tie_in=(prev[3], prev[4], prev[5]))
        self._path.append((md, inc, azi, float(t.tvd[-1]), float(t.north[-1]), float(t.east[-1])))
        azi_mag = values.get("azimuth_magnetic_deg", NAN)
        self._mag_azimuths.append(float(azi_mag) if math.isfinite(float(azi_mag)) else azi)
        out.update(measured_depth_m=md, tvd_m=float(t.tvd[-1]), north_m=float(t.north[-1]),
                   east_m=float(t.east[-1]), dls_deg_per_30m=float(t.dls[-1]),
                   position_covariance_ned_m2=self._covariance(self.site))
        return out

    def _covariance(self, site) -> list:
        """The ISCWSA MWD covariance (NEV m², row-major 3×3, along the positions' north) of the
        station just placed, from the tie-in through every station of the path (:mod:`iscwsa`;
        the sensor terms from the record's uncertainty, the declination's from the site's source).
        NaN without a site (no field to weigh the magnetic terms by)."""
        if site is None:
            return [NAN] * 9
        if self._terms is None:
            self._terms = terms_from_calibration(self.calibration, site)
        path = np.array(self._path)
        unc = position_covariance(path[:, 0], path[:, 1], path[:, 2], total_gravity_mps2=site.gravity_mps2,
                                  total_field_nt=site.total_field_nt, dip_deg=site.dip_deg, tvd=path[:, 3],
                                  terms=self._terms, azi_magnetic_deg=np.array(self._mag_azimuths))
        return [float(x) for x in unc.cov[-1].ravel()]


def _finite_or_nan(x) -> float:
    x = float(x)
    return x if math.isfinite(x) else NAN


def station_fields(station_id: int, seg: Station, v: dict, coefficients_id: str, ref, azimuth_reference: str,
                   have_temperature: bool) -> dict:
    """The fields of a ``SurveyStation`` message (all but the header) for an evaluated station.

    Plain Python values, shared by the correction node (rclpy message) and offline reprocessing
    (rosbags type store), so both publish the same thing.  Undefined values are NaN, never 0."""
    ref = (NAN, NAN, NAN) if ref is None else tuple(float(x) for x in ref)  # NaN: not given (partial is fine)
    axial = "azimuth_method" in v
    return dict(
        station_id=int(station_id),
        drift_deg=_finite_or_nan(v["drift_deg"]),
        azimuth_deg=NAN if v["azimuth_undefined"] else _finite_or_nan(v["azimuth_deg"]),
        azimuth_reference=azimuth_reference,
        azimuth_method=str(v["azimuth_method"]) if axial else "standard",
        axial_field_nt=_finite_or_nan(v["axial_field_nt"]) if axial else NAN,
        azimuth_sigma_deg=_finite_or_nan(v["azimuth_sigma_deg"]) if axial else NAN,
        axial_degenerate=bool(v["axial_degenerate"]) if axial else False,
        toolface_deg=_finite_or_nan(v["toolface_deg"]),
        toolface_type="gravity" if v["toolface_is_gravity"] else "magnetic",
        # defined down to the azimuth threshold; it is *reported* (toolface_deg) above the switch-over
        gravity_toolface_deg=NAN if v["azimuth_undefined"] else _finite_or_nan(v["gravity_toolface_deg"]),
        magnetic_toolface_deg=_finite_or_nan(v["magnetic_toolface_deg"]),
        total_gravity_mps2=_finite_or_nan(v["total_gravity"]),
        total_field_nt=_finite_or_nan(v["total_field"]),
        dip_deg=_finite_or_nan(v["dip_deg"]),
        delta_g_mps2=_finite_or_nan(v["delta_g"]),
        delta_b_nt=_finite_or_nan(v["delta_b"]),
        delta_dip_deg=_finite_or_nan(v["delta_dip"]),
        status=station_status(seg, v["status"]),
        is_static=not seg.short,
        interference_suspected=bool(v["interference_suspected"]),
        azimuth_undefined=bool(v["azimuth_undefined"]),
        gravity_out_of_tolerance=bool(v["gravity_out_of_tolerance"]),
        moved_during_capture=bool(seg.moved),
        warnings=[str(w) for w in seg.warnings],
        model_misfit=False,
        model_diagnosis="",
        samples_averaged=int(seg.n),
        duration_s=float(seg.duration_s),
        temperature_c=float(seg.temp_c) if have_temperature else NAN,
        coefficients_id=coefficients_id,
        uncorrected_reason="",
        reference_drift_deg=ref[0],
        reference_azimuth_deg=ref[1],
        reference_toolface_deg=ref[2],
        measured_depth_m=_finite_or_nan(v.get("measured_depth_m", NAN)),
        tvd_m=_finite_or_nan(v.get("tvd_m", NAN)),
        north_m=_finite_or_nan(v.get("north_m", NAN)),
        east_m=_finite_or_nan(v.get("east_m", NAN)),
        dls_deg_per_30m=_finite_or_nan(v.get("dls_deg_per_30m", NAN)),
        azimuth_magnetic_deg=NAN if v["azimuth_undefined"] else _finite_or_nan(v.get("azimuth_magnetic_deg", NAN)),
        azimuth_grid_deg=NAN if v["azimuth_undefined"] else _finite_or_nan(v.get("azimuth_grid_deg", NAN)),
        azimuth_true_deg=NAN if v["azimuth_undefined"] else _finite_or_nan(v.get("azimuth_true_deg", NAN)),
        raw_gravity_mps2=[_finite_or_nan(x) for x in np.asarray(seg.g, float).reshape(3)],
        raw_field_nt=[_finite_or_nan(x) for x in np.asarray(seg.b, float).reshape(3)],
        position_covariance_ned_m2=[_finite_or_nan(x) for x in v.get("position_covariance_ned_m2", [NAN] * 9)],
    )
