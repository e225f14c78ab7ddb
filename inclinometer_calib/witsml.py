"""WITSML 2.1 ``Trajectory`` out: the corrected survey stations as an Energistics document — ROS-free.

One document per run (well, wellbore, run): :func:`trajectory_document` builds it from station
dicts — those of :func:`launcher.read_bag` or :func:`launcher.station_dict`, so a recorded run
(``inclinometer-calib witsml RUN.mcap``) and the live ``wits`` node (``witsml_file``) give the same
document for the same stations; :func:`validate` checks it against the Energistics schema
(``Trajectory.xsd`` of WITSML 2.1 and energyML common 2.3, vendored in ``schemas/witsml21/``, see its
README); :func:`read_trajectory` parses one back.

Which stations.  A trajectory station is a part indexed by measured depth, so a station without
``measured_depth_m`` is left out (``Md`` is required); a station without ``coefficients_id`` is raw
(before any calibration: the stand poses, not a survey) and is left out, as from WITS0.  The rest
are exported in receive order with ``StatusTrajStation`` (``witsml:TrajStationStatus``, whose values
are ``open``, ``rejected``, ``position``):

=============  ===================  ===============================================================
``status``     StatusTrajStation    why
=============  ===================  ===============================================================
0 ok, 1 warn   ``position``         validated by the station QC and used for the positions below it
                                    (the survey's minimum curvature places warn stations too)
2 error        ``rejected``         the QC refused it (probe moved, |G| out of tolerance): not to
                                    be used
=============  ===================  ===============================================================

A station whose probe moved has no position (no ``Tvd``/``DispNs``/``DispEw``/``Dls``).  One
rejected for |G| alone keeps the position the survey gave it (it was placed in the path).

What goes where (tool frame Z down-hole; units are the Energistics uom symbols):

* ``Md``, ``Tvd`` (``eml:DatumVerticalDepth``), ``DispNs``, ``DispEw``: m.  ``Incl`` = drift,
  ``Azi``, ``Mtf``, ``Gtf``: ``dega``.  ``Dls``: ``1/30 dega/m`` (degree per 30 m).
* ``Azi`` and the displacements are along one north, the trajectory's ``AziRef``: the stations'
  ``azimuth_reference``, the one north of their ``azimuth_deg`` and ``north_m``/``east_m``
  (a bag recorded before the stations had one north is put along its positions' north by
  :func:`launcher.station_dict`).
* ``RawData``: the station's raw means before calibration — ``GravAxialRaw``, ``GravTran1Raw``,
  ``GravTran2Raw`` = g_z, g_x, g_y of the gravity vector (down positive, m/s²), ``MagAxialRaw``,
  ``MagTran1Raw``, ``MagTran2Raw`` = b_z, b_x, b_y (nT); left out where not known (NaN, or a bag
  recorded before the fields existed).
* ``Valid``: the corrected |G| (``GravTotalFieldCalc``, m/s²), |B| (``MagTotalFieldCalc``, nT),
  dip (``MagDipAngleCalc``, dega); the site's reference values (total − delta) in
  ``GravTotalFieldReference``, ``MagTotalFieldReference``, ``MagDipAngleReference``.
* ``CorUsed``: ``StnMagDeclUsed`` = azimuth(true) − azimuth(magnetic) when the azimuths are
  true or grid, and ``StnGridConUsed`` = azimuth(true) − azimuth(grid) when they are grid, wrapped
  to ±180° (WITSML's signs: true = magnetic + declination, grid = true − convergence); with the
  short-collar azimuth ``MagAxialDrlstrCor`` = −(the axial interference field solved), nT, and
  ``AxialMagInterferenceCorUsed`` true.  ``GravAccelCorUsed``
  and ``MagXAxialCorUsed`` (alignment corrections) are true: the calibration record corrects both
  triads' misalignment.
* The calibration record's id.  The schema has no element for it; it offers ``ExtensionNameValue``
  (name, value, time: the energyML way to carry a typed datum it does not model) on the
  trajectory and on each station.  Each station carries the id it was corrected with
  (``coefficients_id``); the trajectory carries one entry per record used, with the time of the
  first station it corrected.  (``Aliases`` names the object itself, ``CustomData`` is untyped
  ``xs:any``: neither fits.)

Reproducible: the uuids are uuid5 of (well, wellbore, run id) — the run id is by default the time of
the first exported station — and every time in the document is a station's own stamp (ISO 8601
UTC); numbers are written with Python's shortest round-trip repr, so they parse back bit for bit.
"""
from __future__ import annotations

import datetime as _dt
import functools
import math
import os
import uuid
from dataclasses import dataclass, field

from lxml import etree

from . import __version__
from .output import atomic_write_text

NS_WITSML = "http://www.energistics.org/energyml/data/witsmlv2"
NS_EML = "http://www.energistics.org/energyml/data/commonv2"
NS_XSI = "http://www.w3.org/2001/XMLSchema-instance"
NSMAP = {None: NS_WITSML, "eml": NS_EML, "xsi": NS_XSI}
XP = {"w": NS_WITSML, "eml": NS_EML}

#: WITSML versions this module writes.
VERSIONS = ("2.1",)
SCHEMA_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "schemas", "witsml21")
TRAJECTORY_XSD = os.path.join(SCHEMA_DIR, "energyml", "data", "witsml", "v2.1", "xsd_schemas", "Trajectory.xsd")
#: Namespace of the documents' uuid5s (fixed: the same input gives the same uuids everywhere).
UUID_NAMESPACE = uuid.uuid5(uuid.NAMESPACE_URL, "urn:inclinometer_calib:witsml")
ORIGINATOR = "inclinometer_calib"
EXTENSION_COEFFICIENTS = "coefficients_id"

#: SurveyStation.status -> witsml:TrajStationStatus
STATION_STATUS = {0: "position", 1: "position", 2: "rejected"}
#: SurveyStation.azimuth_reference -> eml:NorthReferenceKind
NORTH_REFERENCE = {"magnetic": "magnetic north", "true": "true north", "grid": "grid north"}

# uom symbol -> factor to the unit the station dicts use (reading back accepts these)
_TO_M = {"m": 1.0, "ft": 0.3048, "km": 1000.0}
_TO_DEG = {"dega": 1.0, "rad": 180.0 / math.pi}
_TO_DEG_PER_30M = {"1/30 dega/m": 1.0, "dega/m": 30.0, "0.01 dega/ft": 0.3 / 0.3048, "1/30 dega/ft": 1 / 0.3048,
                   "dega/ft": 30.0 / 0.3048}
_TO_MPS2 = {"m/s2": 1.0, "gn": 9.80665, "mgn": 9.80665e-3, "Gal": 0.01, "mGal": 1e-5, "ft/s2": 0.3048}
_TO_NT = {"nT": 1.0, "uT": 1e3, "mT": 1e6, "T": 1e9, "gauss": 1e5, "mgauss": 100.0, "ngauss": 1e-4}


class WitsmlError(ValueError):
    """A document that is not a valid WITSML 2.1 Trajectory (the message lists the first problems)."""


@dataclass
class TrajectoryExport:
    """A built document and what went into it."""

    xml: bytes
    exported: int
    #: stations left out, by reason ("raw (no calibration)", "no measured depth")
    skipped: dict = field(default_factory=dict)
    uuid: str = ""

    def skipped_text(self) -> str:
        return ", ".join(f"{n} {why}" for why, n in self.skipped.items()) or "none"


def _finite(x) -> bool:
    try:
        return x is not None and math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


def _num(x) -> str:
    return repr(float(x))


def _wrap180(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


def iso_time(stamp: float) -> str:
    """Unix seconds -> ISO 8601 UTC with microseconds and ``Z`` (an ``eml:TimeStamp``)."""
    t = _dt.datetime.fromtimestamp(float(stamp), _dt.timezone.utc)
    return t.isoformat(timespec="microseconds").replace("+00:00", "Z")


def _stamp(text: str) -> float:
    return _dt.datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def select_stations(stations) -> tuple[list, dict]:
    """(stations exported, {reason: count} of those left out) — see the module docstring."""
    kept, skipped = [], {}
    for s in stations:
        if not s.get("coefficients_id"):
            why = "raw (no calibration)"
        elif not _finite(s.get("measured_depth_m")):
            why = "no measured depth"
        else:
            kept.append(s)
            continue
        skipped[why] = skipped.get(why, 0) + 1
    return kept, skipped


def _azimuth_reference(s: dict) -> str:
    ref = s.get("azimuth_reference") or ""
    if ref in NORTH_REFERENCE:
        return ref
    # a bag recorded before the field existed: a declination was applied if the azimuths differ
    a, m = s.get("azimuth_deg"), s.get("azimuth_magnetic_deg")
    return "true" if _finite(a) and _finite(m) and abs(_wrap180(float(a) - float(m))) > 1e-9 else "magnetic"


def _north(stations) -> str:
    """The one north of the document's azimuths and displacements (module docstring)."""
    refs = ({_azimuth_reference(s) for s in stations if _finite(s.get("azimuth_deg"))}
            or {_azimuth_reference(s) for s in stations if s.get("azimuth_reference")})
    if len(refs) > 1:
        raise WitsmlError(f"the stations' azimuths are against different norths ({', '.join(sorted(refs))}): one "
                          "trajectory has one azimuth reference")
    return refs.pop() if refs else "magnetic"


def _azimuth_from(s: dict, north: str) -> float:
    """A station's azimuth from ``north``: its ``azimuth_deg`` when that is the north it declares,
    else its ``azimuth_<north>_deg``; NaN when not known."""
    a = s.get("azimuth_deg") if _azimuth_reference(s) == north else s.get(f"azimuth_{north}_deg")
    return float(a) if _finite(a) else math.nan


def _declination(s: dict, north: str) -> float:
    """The declination applied to the azimuths (none when they are magnetic)."""
    return math.nan if north == "magnetic" else _wrap180(_azimuth_from(s, "true") - _azimuth_from(s, "magnetic"))


def _convergence(s: dict, north: str) -> float:
    """The grid convergence applied to the azimuths (only when they are grid)."""
    return _wrap180(_azimuth_from(s, "true") - _azimuth_from(s, "grid")) if north == "grid" else math.nan


def _uuid(*parts) -> str:
    return str(uuid.uuid5(UUID_NAMESPACE, "\x1f".join(str(p) for p in parts)))


def trajectory_document(stations, well: str = "WELL", wellbore: str = "WELLBORE", run_id: str | None = None,
                        active: bool = False, version: str = "2.1") -> TrajectoryExport:
    """The WITSML ``Trajectory`` of ``stations`` (station dicts, receive order).

    ``well``/``wellbore`` name the well and wellbore (the wellbore reference's title and, with
    ``run_id``, the uuids: uuid5 of the names; ``run_id`` defaults to the ISO time of the first
    exported station).  ``active``: the survey is still growing (``ActiveStatus`` ``active``, the
    live node) or finished (``inactive``).  Not validated here: see :func:`validate`.
    """
    if version not in VERSIONS:
        raise WitsmlError(f"WITSML {version}: only {', '.join(VERSIONS)} is written")
    kept, skipped = select_stations(stations)
    north = _north(kept)
    run = run_id if run_id is not None else (iso_time(kept[0]["stamp"]) if kept else "empty")
    traj_uuid = _uuid("trajectory", well, wellbore, run)

    W = functools.partial(_el, NS_WITSML)
    E = functools.partial(_el, NS_EML)
    root = etree.Element(f"{{{NS_WITSML}}}Trajectory", nsmap=NSMAP, uuid=traj_uuid, schemaVersion=version)
    cit = E(root, "Citation")
    E(cit, "Title", f"{well} {wellbore}: inclinometer survey {run}")
    E(cit, "Originator", ORIGINATOR)
    E(cit, "Creation", iso_time(kept[0]["stamp"]) if kept else iso_time(0.0))
    E(cit, "Format", f"inclinometer_calib {__version__}")
    if kept:
        E(cit, "LastUpdate", iso_time(kept[-1]["stamp"]))
    left_out = "; left out: " + ", ".join(f"{n} {why}" for why, n in skipped.items()) if skipped else ""
    E(cit, "Description", f"{len(kept)} corrected survey stations of {well} {wellbore}{left_out}")
    first_use = {}
    for s in kept:
        first_use.setdefault(s["coefficients_id"], s["stamp"])
    for cid, t in first_use.items():
        ext = E(root, "ExtensionNameValue")
        E(ext, "Name", EXTENSION_COEFFICIENTS)
        E(ext, "Value", cid)
        E(ext, "DTim", iso_time(t))
        E(ext, "Description", "id of the inclinometer_calib calibration record applied to the stations from DTim on")
    E(root, "ActiveStatus", "active" if active else "inactive")
    idx = E(root, "Index")
    E(idx, "IndexKind", "measured depth")
    E(idx, "Uom", "m")
    E(idx, "Direction", "increasing")
    mds = [float(s["measured_depth_m"]) for s in kept]
    if kept:
        iv = E(root, "MdInterval")
        E(iv, "MdMin", _num(min(mds)))
        E(iv, "MdMax", _num(max(mds)))
        E(iv, "Uom", "m")
        W(root, "DTimTrajEnd", iso_time(kept[-1]["stamp"]))
        W(root, "DTimTrajStart", iso_time(kept[0]["stamp"]))
    uids = {}
    for s in kept:
        _station(W, E, root, s, north, uids)
    wb = W(root, "Wellbore")
    E(wb, "Uuid", _uuid("wellbore", well, wellbore))
    E(wb, "QualifiedType", "witsml21.Wellbore")
    E(wb, "Title", wellbore)
    # TrajectoryMetadata
    decl = next((d for d in (_declination(s, north) for s in kept) if _finite(d)), math.nan)
    conv = next((c for c in (_convergence(s, north) for s in kept) if _finite(c)), math.nan)
    if _finite(decl):
        W(root, "MagDeclUsed", _num(decl), uom="dega")
    if kept:
        md_max = W(root, "MdMaxMeasured")
        E(md_max, "MeasuredDepth", _num(max(mds)), uom="m")
    W(root, "NominalCalcAlgorithm", "minimum curvature")
    W(root, "NominalTypeSurveyTool", "magnetic multiple-shot")
    W(root, "NominalTypeTrajStation", "MD INCL and AZI")
    if _finite(conv):
        W(root, "GridConUsed", _num(conv), uom="dega")
    W(root, "AziRef", NORTH_REFERENCE[north])
    xml = etree.tostring(root, xml_declaration=True, encoding="utf-8", pretty_print=True)
    return TrajectoryExport(xml=xml, exported=len(kept), skipped=skipped, uuid=traj_uuid)


def _el(ns, parent, tag, text=None, **attrib):
    e = etree.SubElement(parent, f"{{{ns}}}{tag}", **attrib)
    if text is not None:
        e.text = str(text)
    return e


def _station(W, E, root, s: dict, north: str, uids: dict) -> None:
    uid = f"station-{int(s['station_id'])}"
    uids[uid] = uids.get(uid, 0) + 1
    if uids[uid] > 1:                      # a correction node restarted without its state file
        uid = f"{uid}-{uids[uid]}"
    st = W(root, "TrajectoryStation", uid=uid)
    when = iso_time(s["stamp"])
    E(st, "Creation", when)
    E(st, "LastUpdate", when)
    ext = E(st, "ExtensionNameValue")
    E(ext, "Name", EXTENSION_COEFFICIENTS)
    E(ext, "Value", s["coefficients_id"])
    md = E(st, "Md")
    E(md, "MeasuredDepth", _num(s["measured_depth_m"]), uom="m")
    W(st, "DTimStn", when)
    W(st, "TypeTrajStation", "MD INCL and AZI")
    W(st, "TypeSurveyTool", "magnetic multiple-shot")
    W(st, "CalcAlgorithm", "minimum curvature")
    if _finite(s.get("tvd_m")):
        tvd = W(st, "Tvd", **{f"{{{NS_XSI}}}type": "eml:DatumVerticalDepth"})
        E(tvd, "VerticalDepth", _num(s["tvd_m"]), uom="m")
    azi = _azimuth_from(s, north)

    def measure(tag, value, uom):
        if _finite(value):
            W(st, tag, _num(value), uom=uom)

    measure("Incl", s.get("drift_deg"), "dega")
    measure("Azi", azi, "dega")
    measure("Mtf", s.get("magnetic_toolface_deg"), "dega")
    measure("Gtf", s.get("gravity_toolface_deg"), "dega")
    measure("DispNs", s.get("north_m"), "m")
    measure("DispEw", s.get("east_m"), "m")
    measure("Dls", s.get("dls_deg_per_30m"), "1/30 dega/m")
    short_collar = s.get("azimuth_method") == "short_collar"
    W(st, "GravAccelCorUsed", "true")
    W(st, "MagXAxialCorUsed", "true")
    W(st, "AxialMagInterferenceCorUsed", "true" if short_collar else "false")
    for tag, total, delta, uom in (("GravTotalFieldReference", "total_gravity_mps2", "delta_g_mps2", "m/s2"),
                                   ("MagTotalFieldReference", "total_field_nt", "delta_b_nt", "nT"),
                                   ("MagDipAngleReference", "dip_deg", "delta_dip_deg", "dega")):
        if _finite(s.get(total)) and _finite(s.get(delta)):
            W(st, tag, _num(float(s[total]) - float(s[delta])), uom=uom)
    W(st, "StatusTrajStation", STATION_STATUS.get(int(s.get("status", 0)), "rejected"))
    g, b = _vector(s.get("raw_gravity_mps2")), _vector(s.get("raw_field_nt"))
    if g is not None or b is not None:
        raw = W(st, "RawData")
        for tag, v, k, uom in (("GravAxialRaw", g, 2, "m/s2"), ("GravTran1Raw", g, 0, "m/s2"),
                               ("GravTran2Raw", g, 1, "m/s2"), ("MagAxialRaw", b, 2, "nT"),
                               ("MagTran1Raw", b, 0, "nT"), ("MagTran2Raw", b, 1, "nT")):
            if v is not None:
                W(raw, tag, _num(v[k]), uom=uom)
    decl, conv = _declination(s, north), _convergence(s, north)
    axial = s.get("axial_field_nt")
    if _finite(decl) or _finite(conv) or (short_collar and _finite(axial)):
        cor = W(st, "CorUsed")
        if short_collar and _finite(axial):
            W(cor, "MagAxialDrlstrCor", _num(-float(axial)), uom="nT")
        if _finite(decl):
            W(cor, "StnMagDeclUsed", _num(decl), uom="dega")
        if _finite(conv):
            W(cor, "StnGridConUsed", _num(conv), uom="dega")
    valid = [(tag, s.get(k), uom) for tag, k, uom in (("MagTotalFieldCalc", "total_field_nt", "nT"),
                                                       ("MagDipAngleCalc", "dip_deg", "dega"),
                                                       ("GravTotalFieldCalc", "total_gravity_mps2", "m/s2"))]
    if any(_finite(v) for _, v, _ in valid):
        val = W(st, "Valid")
        for tag, v, uom in valid:
            if _finite(v):
                W(val, tag, _num(v), uom=uom)


def _vector(v):
    """Three finite floats, else None (missing, or NaN: not known)."""
    if v is None:
        return None
    v = [float(x) for x in v]
    return v if len(v) == 3 and all(math.isfinite(x) for x in v) else None


# ---------------------------------------------------------------------------------------------
# validation and reading back

@functools.lru_cache(maxsize=1)
def schema():
    """The WITSML 2.1 Trajectory schema (``xmlschema``; loaded once, about a second)."""
    import xmlschema

    return xmlschema.XMLSchema(TRAJECTORY_XSD)


def validate(xml: bytes, max_problems: int = 5) -> None:
    """Raise :class:`WitsmlError` unless ``xml`` is a valid WITSML 2.1 ``Trajectory`` (the vendored
    ``Trajectory.xsd`` and its includes); the message lists the first ``max_problems`` problems,
    each with its path in the document."""
    try:
        tree = etree.fromstring(xml)
    except (etree.XMLSyntaxError, ValueError) as exc:
        raise WitsmlError(f"not well-formed XML: {exc}") from None
    if tree.tag != f"{{{NS_WITSML}}}Trajectory":
        raise WitsmlError(f"root element is {tree.tag}, not a WITSML 2.1 Trajectory ({{{NS_WITSML}}}Trajectory)")
    problems = []
    for err in schema().iter_errors(etree.ElementTree(tree)):
        problems.append(f"{_where(err)}: {err.reason or err.message}")
        if len(problems) > max_problems:
            break
    if problems:
        more = " (and more)" if len(problems) > max_problems else ""
        raise WitsmlError("not a valid WITSML 2.1 Trajectory (Trajectory.xsd):\n  "
                          + "\n  ".join(problems[:max_problems]) + more)


def _where(err) -> str:
    """``line N, <path> (station <uid>)`` of a schema error."""
    el, uid = getattr(err, "elem", None), None
    line = getattr(el, "sourceline", None)
    while el is not None and hasattr(el, "getparent") and uid is None:
        uid = el.get("uid")
        el = el.getparent()
    return (f"line {line}, " if line else "") + str(err.path) + (f" (station {uid})" if uid else "")


def _measure(el, table: dict, what: str) -> float:
    if el is None:
        return math.nan
    uom = el.get("uom")
    if uom not in table:
        raise WitsmlError(f"{what}: unit {uom!r} not understood (expected one of {', '.join(table)})")
    return float(el.text) * table[uom]


def read_trajectory(xml: bytes) -> list:
    """The stations of a WITSML 2.1 ``Trajectory`` as dicts with the station dicts' keys where they
    exist (``measured_depth_m``, ``tvd_m``, ``drift_deg``, ``azimuth_deg``, ``azimuth_reference``
    ('magnetic', 'true', 'grid' from ``AziRef``), toolfaces, ``north_m``, ``east_m``,
    ``dls_deg_per_30m``, ``total_gravity_mps2``, ``total_field_nt``, ``dip_deg``,
    ``raw_gravity_mps2``/``raw_field_nt`` (x, y, z; NaN where absent), ``coefficients_id``,
    ``stamp`` (unix s)) plus ``uid``, ``station_status`` (the TrajStationStatus),
    ``declination_deg``, ``grid_convergence_deg``.  Units are converted from the uoms given (a
    unit it does not know is an error naming the element).  Parsed with lxml, not validated."""
    try:
        root = etree.fromstring(xml)
    except etree.XMLSyntaxError as exc:
        raise WitsmlError(f"not well-formed XML: {exc}") from None
    if root.tag != f"{{{NS_WITSML}}}Trajectory":
        raise WitsmlError(f"root element is {root.tag}, not a WITSML 2.1 Trajectory")
    azi_ref = root.findtext("w:AziRef", namespaces=XP)
    reference = {v: k for k, v in NORTH_REFERENCE.items()}.get(azi_ref, "")
    out = []
    for st in root.findall("w:TrajectoryStation", XP):
        uid = st.get("uid")

        def m(path, table, st=st, uid=uid):
            return _measure(st.find(path, XP), table, f"station {uid}: {path.split(':')[-1]}")

        ext = {e.findtext("eml:Name", namespaces=XP): e.findtext("eml:Value", namespaces=XP)
               for e in st.findall("eml:ExtensionNameValue", XP)}
        raw = {k: m(f"w:RawData/w:{k}", _TO_MPS2 if k.startswith("Grav") else _TO_NT)
               for k in ("GravTran1Raw", "GravTran2Raw", "GravAxialRaw", "MagTran1Raw", "MagTran2Raw", "MagAxialRaw")}
        when = st.findtext("w:DTimStn", namespaces=XP) or st.findtext("eml:Creation", namespaces=XP)
        out.append(dict(
            uid=uid,
            measured_depth_m=m("eml:Md/eml:MeasuredDepth", _TO_M),
            tvd_m=m("w:Tvd/eml:VerticalDepth", _TO_M),
            drift_deg=m("w:Incl", _TO_DEG),
            azimuth_deg=m("w:Azi", _TO_DEG),
            azimuth_reference=reference,
            magnetic_toolface_deg=m("w:Mtf", _TO_DEG),
            gravity_toolface_deg=m("w:Gtf", _TO_DEG),
            north_m=m("w:DispNs", _TO_M),
            east_m=m("w:DispEw", _TO_M),
            dls_deg_per_30m=m("w:Dls", _TO_DEG_PER_30M),
            total_gravity_mps2=m("w:Valid/w:GravTotalFieldCalc", _TO_MPS2),
            total_field_nt=m("w:Valid/w:MagTotalFieldCalc", _TO_NT),
            dip_deg=m("w:Valid/w:MagDipAngleCalc", _TO_DEG),
            raw_gravity_mps2=[raw["GravTran1Raw"], raw["GravTran2Raw"], raw["GravAxialRaw"]],
            raw_field_nt=[raw["MagTran1Raw"], raw["MagTran2Raw"], raw["MagAxialRaw"]],
            declination_deg=m("w:CorUsed/w:StnMagDeclUsed", _TO_DEG),
            grid_convergence_deg=m("w:CorUsed/w:StnGridConUsed", _TO_DEG),
            coefficients_id=ext.get(EXTENSION_COEFFICIENTS, ""),
            station_status=st.findtext("w:StatusTrajStation", namespaces=XP) or "",
            stamp=_stamp(when) if when else math.nan,
        ))
    return out


def write_trajectory(path, stations, **kwargs) -> TrajectoryExport:
    """Build (:func:`trajectory_document`), validate, and write atomically (temp file + rename: a
    document that does not validate, or a write that fails, leaves the file as it was)."""
    export = trajectory_document(stations, **kwargs)
    validate(export.xml)
    atomic_write_text(path, export.xml.decode("utf-8"))
    return export
