"""WITSML out: the corrected survey stations as an Energistics trajectory, 2.1 or 1.4.1.1 — ROS-free.

One trajectory per run (well, wellbore, run): :func:`trajectory_document` builds it from station
dicts — those of :func:`bag.read_bag` or :func:`surveystation.from_msg`, so a recorded run
(``inclinometer-calib witsml RUN.mcap``) and the live ``wits`` node (``witsml_file``) give the same
document for the same stations — in one of two versions:

* **2.1** (the current release): a ``Trajectory`` (``Trajectory.xsd`` of WITSML 2.1 and energyML
  common 2.3, vendored in ``schemas/witsml21/``);
* **1.4.1.1** (what many stores still speak): a ``trajectorys`` document of one ``trajectory``
  (``obj_trajectory.xsd`` of the WITSML 1.4.1.1 data schema, vendored in ``schemas/witsml1411/``).

:func:`validate` checks any document this module writes against its version's schema (the version
from the root element); :func:`read_document` / :func:`read_trajectory` parse either version back.

Where the trajectory hangs (:class:`Options`).  A store takes a trajectory only under a wellbore it
already has, and depths only against a datum.  Either the well, wellbore and datum are ours — their
documents are built beside the trajectory (``TrajectoryExport.parents``, in load order: 2.1 ``Well``,
the datum as an ``eml:ReferencePointInACrs`` of kind ``datum`` (with ``datum_elevation``, an
``eml:VerticalCrs`` EPSG:5714 "MSL height" it is measured in, loaded before it), ``Wellbore``;
1.4.1.1 ``wells`` (the datum a ``wellDatum`` in it, and mean sea level as a second one when the
elevation is given), ``wellbores``), with uuids/uids from the names — or they exist in the store:
``well_uid`` and ``wellbore_uid`` (2.1: uuids; 1.4.1.1: uids) name them, no parent document is
built, and ``datum_uid`` names the store's datum (without it the wellbore's default datum
applies, as both versions define).  MD and TVD are from the datum: 2.1 ``DefaultMdDatum`` and
``DefaultTvdDatum`` (and the wellbore's); 1.4.1.1 ``commonData/defaultDatum`` and the ``datum``
attribute of every ``md``/``tvd``/``mdMn``/``mdMx``.

Which stations.  A trajectory station is indexed by measured depth, so a station without
``measured_depth_m`` is left out (``Md`` is required); a station without ``coefficients_id`` is raw
(before any calibration: the stand poses, not a survey) and is left out, as from WITS0.  The rest
are exported in receive order with ``StatusTrajStation`` (``TrajStationStatus``: ``open``,
``rejected``, ``position``):

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

What goes where (:data:`MEASURES` is the one table of station key ↔ element ↔ quantity, used by
both writers and the reader; 1.4.1.1 names are the 2.1 names with a lower-case first letter; units
are the Energistics uom symbols, the foot the dictionary's international foot, 0.3048 m exactly):

* ``Md``, ``Tvd``, ``DispNs``, ``DispEw``: ``units`` (``m`` or ``ft``).  ``Dls``: degree per 30 m
  (2.1 ``1/30 dega/m``, 1.4.1.1 ``dega/30m``) or per 100 ft (``0.01 dega/ft``, ``dega/100ft``).
  ``Incl`` = drift, ``Azi``, ``Mtf``, ``Gtf``: ``dega``.
* ``Azi`` and the displacements are along one north, the trajectory's ``AziRef`` (:func:`_north`):
  the stations' ``azimuth_reference``, the one north of their ``azimuth_deg`` and
  ``north_m``/``east_m`` (a bag recorded before the stations had one north is put along its
  positions' north by :func:`surveystation.from_msg`).
* ``MatrixCov``: the station's ``position_covariance_ned_m2`` (ISCWSA, :mod:`iscwsa`, 1σ, along the
  positions' north): ``VarianceNN`` … ``VarianceVertVert`` in m² or ft², ``BiasN/E/Vert`` 0 (rev 4
  has no bias terms), 2.1 ``Sigma`` 1.  Left out where the station has none (NaN).
* ``ToolErrorModel`` (1.4.1.1 ``iscwsaToolErrorModel``): :data:`iscwsa.MODEL_NAME`, with the
  stations' covariance.  2.1 references it by title and a uuid5 of the name; the object itself is
  not written (its required ``MisalignmentMode``, one of SPE-90408's three modes, has no value for
  rev 4's four XYM terms together).
* ``MagModelUsed``, ``MagModelValid``, ``InfieldRefCorUsed``: the geomagnetic model of the site the
  station was evaluated against (:func:`mag_models`: the calibration record's site, when its
  reference field is the station's — a site overridden in the correction node is not the
  record's), or the one ``mag_model`` names; left out when not known (a site typed in).
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
  ``AxialMagInterferenceCorUsed`` true.  ``GravAccelCorUsed`` and ``MagXAxialCorUsed`` (alignment
  corrections) are true: the calibration record corrects both
  triads' misalignment.
* The calibration record's id.  Neither schema has an element for it; both offer an extension
  name/value (2.1 ``ExtensionNameValue``, 1.4.1.1 ``extensionNameValue``) on the trajectory (1.4.1.1:
  its ``commonData``) and on each station.  Each station carries the id it was corrected with
  (``coefficients_id``); the trajectory carries one entry per record used, with the time of the
  first station it corrected.

Times.  Every time in the documents is a station's own stamp (ISO 8601 UTC), shifted by
``start_time`` when one is given: a log replayed with its own clock starts at 1970, and
``start_time`` (ISO 8601) puts the first exported station there and every other time by the same
shift.  Times before 1980 are said (:attr:`TrajectoryExport.notes`).

Reproducible: the uuids are uuid5 of (well, wellbore, run id) — the run id is by default the time of
the first exported station — the same for both versions and both units; numbers are written with
Python's shortest round-trip repr, so in metres they parse back bit for bit.
"""
from __future__ import annotations

import datetime as _dt
import functools
import math
import os
import re
import uuid
from dataclasses import dataclass, field, fields

from lxml import etree

from .. import __version__
from ..core.output import atomic_write_text

NS_WITSML = "http://www.energistics.org/energyml/data/witsmlv2"
NS_EML = "http://www.energistics.org/energyml/data/commonv2"
NS_WITSML14 = "http://www.witsml.org/schemas/1series"
NS_XSI = "http://www.w3.org/2001/XMLSchema-instance"
NSMAP = {None: NS_WITSML, "eml": NS_EML, "xsi": NS_XSI}
XP = {"w": NS_WITSML, "eml": NS_EML}
XP14 = {"w": NS_WITSML14}

#: WITSML versions this module writes.
VERSIONS = ("2.1", "1.4.1.1")
#: Units of depths and displacements (and of DLS's length, and of the covariance).
UNITS = ("m", "ft")
_SCHEMAS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "schemas")
SCHEMA_DIR = os.path.join(_SCHEMAS, "witsml21")
TRAJECTORY_XSD = os.path.join(SCHEMA_DIR, "energyml", "data", "witsml", "v2.1", "xsd_schemas", "Trajectory.xsd")
SCHEMA_DIR_1411 = os.path.join(_SCHEMAS, "witsml1411")
_XSD_1411 = os.path.join(SCHEMA_DIR_1411, "witsml_v1.4.1.1_data", "xsd_schemas")
#: The 1.4.1.1 objects written: trajectory, and the well and wellbore it hangs on.
XSD_1411 = tuple(os.path.join(_XSD_1411, f"obj_{o}.xsd") for o in ("trajectory", "well", "wellbore"))
#: Namespace of the documents' uuid5s (fixed: the same input gives the same uuids everywhere).
UUID_NAMESPACE = uuid.uuid5(uuid.NAMESPACE_URL, "urn:inclinometer_calib:witsml")
ORIGINATOR = "inclinometer_calib"
EXTENSION_COEFFICIENTS = "coefficients_id"
#: Stamps before this (1980-01-01T00:00:00Z, unix s) are a replayed log's clock, not a survey's time.
EARLIEST_SURVEY_TIME = 315532800.0

#: SurveyStation.status -> TrajStationStatus
STATION_STATUS = {0: "position", 1: "position", 2: "rejected"}
#: SurveyStation.azimuth_reference -> AziRef (2.1 eml:NorthReferenceKind, 1.4.1.1 AziRef: the same words)
NORTH_REFERENCE = {"magnetic": "magnetic north", "true": "true north", "grid": "grid north"}
#: The datum kinds both versions name: 2.1 eml:ReferencePointKind -> 1.4.1.1 ElevCodeEnum.
DATUM_KINDS = {"rotary table": "RT", "kelly bushing": "KB", "derrick floor": "DF", "rotary bushing": "RB",
               "ground level": "GL", "casing flange": "CF", "crown valve": "CV", "seafloor": "SF",
               "mean sea level": "SL", "lowest astronomical tide": "LAT"}
#: The vertical CRS of a datum's elevation: EPSG:5714, "MSL height" (up, metres or feet as written).
MSL_EPSG = 5714

FOOT_M = 0.3048                     # the international foot: the Energistics UOM dictionary's "ft", exact
US_SURVEY_FOOT_M = 1200.0 / 3937.0  # "ftUS"


# ---------------------------------------------------------------------------------------------
# units and the station table

@dataclass(frozen=True)
class Quantity:
    """A quantity's uom written (``written``: by (version, units), by units, or for all (None)) and
    the factors of the uoms read back to the station dicts' unit (``to_si``)."""

    name: str
    written: dict
    to_si: dict

    def uom(self, version: str, units: str) -> str:
        w = self.written
        return w.get((version, units)) or w.get(units) or w[None]


LENGTH = Quantity("length", {"m": "m", "ft": "ft"},
                  {"m": 1.0, "ft": FOOT_M, "ftUS": US_SURVEY_FOOT_M, "km": 1000.0})
AREA = Quantity("area", {"m": "m2", "ft": "ft2"}, {"m2": 1.0, "ft2": FOOT_M ** 2})
#: Dogleg severity, in the station dicts degree per 30 m.
DLS = Quantity("dogleg severity",
               {("2.1", "m"): "1/30 dega/m", ("2.1", "ft"): "0.01 dega/ft",
                ("1.4.1.1", "m"): "dega/30m", ("1.4.1.1", "ft"): "dega/100ft"},
               {"1/30 dega/m": 1.0, "dega/30m": 1.0, "dega/m": 30.0, "0.01 dega/ft": 30.0 / (100 * FOOT_M),
                "dega/100ft": 30.0 / (100 * FOOT_M), "1/30 dega/ft": 1 / FOOT_M, "dega/30ft": 1 / FOOT_M,
                "dega/ft": 30.0 / FOOT_M})
ANGLE = Quantity("angle", {None: "dega"}, {"dega": 1.0, "rad": 180.0 / math.pi})
ACCELERATION = Quantity("acceleration", {None: "m/s2"},
                        {"m/s2": 1.0, "gn": 9.80665, "mgn": 9.80665e-3, "Gal": 0.01, "mGal": 1e-5, "ft/s2": FOOT_M})
FIELD = Quantity("magnetic flux density", {None: "nT"},
                 {"nT": 1.0, "uT": 1e3, "mT": 1e6, "T": 1e9, "gauss": 1e5, "mgauss": 100.0, "ngauss": 1e-4})

#: The station's measures: row key (the station dict's key where one exists), the element's path
#: under the station in 2.1 (1.4.1.1: each step with a lower-case first letter), its quantity.  In
#: schema order within each group.  ``Md`` and ``Tvd`` (:data:`DEPTHS`) are built per version.
MEASURES = (
    ("drift_deg", "Incl", ANGLE),
    ("azimuth_deg", "Azi", ANGLE),
    ("magnetic_toolface_deg", "Mtf", ANGLE),
    ("gravity_toolface_deg", "Gtf", ANGLE),
    ("north_m", "DispNs", LENGTH),
    ("east_m", "DispEw", LENGTH),
    ("dls_deg_per_30m", "Dls", DLS),
    ("reference_gravity_mps2", "GravTotalFieldReference", ACCELERATION),
    ("reference_field_nt", "MagTotalFieldReference", FIELD),
    ("reference_dip_deg", "MagDipAngleReference", ANGLE),
    ("raw_gz", "RawData/GravAxialRaw", ACCELERATION),
    ("raw_gx", "RawData/GravTran1Raw", ACCELERATION),
    ("raw_gy", "RawData/GravTran2Raw", ACCELERATION),
    ("raw_bz", "RawData/MagAxialRaw", FIELD),
    ("raw_bx", "RawData/MagTran1Raw", FIELD),
    ("raw_by", "RawData/MagTran2Raw", FIELD),
    ("axial_correction_nt", "CorUsed/MagAxialDrlstrCor", FIELD),
    ("declination_deg", "CorUsed/StnMagDeclUsed", ANGLE),
    ("grid_convergence_deg", "CorUsed/StnGridConUsed", ANGLE),
    ("total_field_nt", "Valid/MagTotalFieldCalc", FIELD),
    ("dip_deg", "Valid/MagDipAngleCalc", ANGLE),
    ("total_gravity_mps2", "Valid/GravTotalFieldCalc", ACCELERATION),
    ("cov_nn", "MatrixCov/VarianceNN", AREA),
    ("cov_ne", "MatrixCov/VarianceNE", AREA),
    ("cov_nv", "MatrixCov/VarianceNVert", AREA),
    ("cov_ee", "MatrixCov/VarianceEE", AREA),
    ("cov_ev", "MatrixCov/VarianceEVert", AREA),
    ("cov_vv", "MatrixCov/VarianceVertVert", AREA),
    ("bias_n", "MatrixCov/BiasN", LENGTH),
    ("bias_e", "MatrixCov/BiasE", LENGTH),
    ("bias_v", "MatrixCov/BiasVert", LENGTH),
)
#: Md and Tvd: row key, the value's path under the station per version, quantity.
DEPTHS = (("measured_depth_m", {"2.1": "eml:Md/eml:MeasuredDepth", "1.4.1.1": "w:md"}, LENGTH),
          ("tvd_m", {"2.1": "w:Tvd/eml:VerticalDepth", "1.4.1.1": "w:tvd"}, LENGTH))
#: (row, column) of the NED covariance (row-major 3×3) behind each MatrixCov key.
COVARIANCE = {"cov_nn": 0, "cov_ne": 1, "cov_nv": 2, "cov_ee": 4, "cov_ev": 5, "cov_vv": 8}
_COV_FROM = (0, 1, 2, 1, 4, 5, 2, 5, 8)      # the full 3×3 from its upper triangle (row-major indexes)
_COV_KEY = {v: k for k, v in COVARIANCE.items()}
_RAW = (("raw_gravity_mps2", ("raw_gx", "raw_gy", "raw_gz")), ("raw_field_nt", ("raw_bx", "raw_by", "raw_bz")))

#: The station's elements in schema order, per version (names as in 2.1; a group name stands for
#: its MEASURES in table order).
LAYOUT = {
    "2.1": ("Md", "DTimStn", "TypeTrajStation", "TypeSurveyTool", "CalcAlgorithm", "Tvd", "Incl", "Azi", "Mtf",
            "Gtf", "DispNs", "DispEw", "Dls", "GravAccelCorUsed", "MagXAxialCorUsed", "InfieldRefCorUsed",
            "AxialMagInterferenceCorUsed", "GravTotalFieldReference", "MagTotalFieldReference",
            "MagDipAngleReference", "MagModelUsed", "MagModelValid", "StatusTrajStation", "RawData", "CorUsed",
            "Valid", "MatrixCov", "ToolErrorModel"),
    "1.4.1.1": ("DTimStn", "TypeTrajStation", "TypeSurveyTool", "CalcAlgorithm", "Md", "Tvd", "Incl", "Azi", "Mtf",
                "Gtf", "DispNs", "DispEw", "Dls", "ToolErrorModel", "GravAccelCorUsed", "MagXAxialCorUsed",
                "InfieldRefCorUsed", "AxialMagInterferenceCorUsed", "GravTotalFieldReference",
                "MagTotalFieldReference", "MagDipAngleReference", "MagModelUsed", "MagModelValid",
                "StatusTrajStation", "RawData", "CorUsed", "Valid", "MatrixCov"),
}
#: The station type: 2.1 and 1.4.1.1 name it differently.
TRAJ_STATION_TYPE = {"2.1": "MD INCL and AZI", "1.4.1.1": "magnetic multi-shot"}
_NAME_1411 = {"ToolErrorModel": "iscwsaToolErrorModel"}


def element_name(name: str, version: str) -> str:
    """The element ``name`` (2.1) in ``version``: 1.4.1.1 lower-cases the first letter."""
    if version == "2.1":
        return name
    return _NAME_1411.get(name) or name[0].lower() + name[1:]


def _path(path: str, version: str) -> str:
    return "/".join("w:" + element_name(step, version) for step in path.split("/"))


class WitsmlError(ValueError):
    """A document that is not valid WITSML, or options that cannot make one (the message says which)."""


# ---------------------------------------------------------------------------------------------
# options

@dataclass(frozen=True)
class Options:
    """What a trajectory document is made of besides its stations (module docstring).  The CLI's
    ``--name-with-dashes`` and the wits node's ``witsml.<name>`` parameters are these fields
    (:data:`OPTION_HELP`); ``well``/``wellbore`` are the CLI's ``--well``/``--wellbore`` and the
    node's ``well_id``/``wellbore``."""

    well: str = "WELL"
    wellbore: str = "WELLBORE"
    version: str = "2.1"
    units: str = "m"
    start_time: str = ""
    datum: str = "rotary table"
    datum_elevation: float = math.nan
    well_uid: str = ""
    wellbore_uid: str = ""
    datum_uid: str = ""
    mag_model: str = ""

    def check(self) -> None:
        """Raise :class:`WitsmlError` (one line) for the first option that cannot make a document."""
        for f in fields(self):
            why = option_problem(f.name, getattr(self, f.name), self.version)
            if why:
                raise WitsmlError(why)
        if bool(self.well_uid) != bool(self.wellbore_uid):
            raise WitsmlError("well_uid and wellbore_uid name an existing well and wellbore together: give both "
                              "or neither")
        if self.datum_uid and not self.well_uid:
            raise WitsmlError("datum_uid names a datum of an existing well: it needs well_uid and wellbore_uid")
        if self.well_uid and math.isfinite(self.datum_elevation):
            raise WitsmlError("datum_elevation describes a datum this export writes; with well_uid the well and "
                              "its datums are the store's")

    @property
    def existing(self) -> bool:
        """The well and wellbore exist in the store (no parent documents)."""
        return bool(self.well_uid)

    def shift(self, first_stamp: float) -> float:
        """Seconds added to every stamp: ``start_time`` − the first exported station's stamp (0 without one)."""
        return parse_time(self.start_time) - first_stamp if self.start_time else 0.0


#: What each option is (CLI help, node parameter description).
OPTION_HELP = {
    "well": "well name",
    "wellbore": "wellbore name",
    "version": f"WITSML version: {' or '.join(VERSIONS)}",
    "units": "depths and displacements in m or ft (DLS per 30 m or per 100 ft, the covariance in m2 or ft2)",
    "start_time": "ISO 8601 time of the first exported station (a replayed log's stamps begin in 1970): every "
                  "time is shifted by the same amount (empty: the stamps as recorded)",
    "datum": f"the MD/TVD datum's kind: {', '.join(DATUM_KINDS)}",
    "datum_elevation": "the datum's elevation above mean sea level, in the document's units (NaN: not given)",
    "well_uid": "an existing well's uid in the store (2.1: a uuid), with its wellbore's: the trajectory references "
                "them and no well/wellbore documents are written (empty: ours, written beside the trajectory)",
    "wellbore_uid": "an existing wellbore's uid in the store (2.1: a uuid), with its well's",
    "datum_uid": "an existing datum's uid (1.4.1.1: the well's wellDatum uid; 2.1: the reference point's uuid); "
                 "without it the wellbore's default datum applies",
    "mag_model": "the geomagnetic model the site came from, when the calibration record does not say it (a site "
                 "given to the correction node); empty: the record's",
}
_UUID = re.compile(r"[a-fA-F0-9]{8}-[a-fA-F0-9]{4}-[1-5][a-fA-F0-9]{3}-[a-fA-F0-9]{4}-[a-fA-F0-9]{12}")


def option_problem(name: str, value, version: str = "2.1") -> str | None:
    """Why ``value`` is not a valid option ``name`` (one line), or None; the node checks its
    parameters with it, :meth:`Options.check` the whole set."""
    if name in ("well", "wellbore"):
        if not str(value).strip():
            return f"{name}: a name is needed"
        if version == "1.4.1.1" and len(value) > 64:
            return f"{name} {value!r}: WITSML 1.4.1.1 names are at most 64 characters"
    elif name == "version" and value not in VERSIONS:
        return f"version {value!r}: {' or '.join(VERSIONS)} is written"
    elif name == "units" and value not in UNITS:
        return f"units {value!r}: {' or '.join(UNITS)}"
    elif name == "datum" and value not in DATUM_KINDS:
        return f"datum {value!r}: one of {', '.join(DATUM_KINDS)}"
    elif name == "start_time" and value:
        try:
            parse_time(value)
        except ValueError:
            return f"start_time {value!r}: not an ISO 8601 time (e.g. 2026-03-01T06:30:00Z)"
    elif name == "datum_elevation" and math.isinf(float(value)):
        return "datum_elevation: not a number"
    elif name in ("well_uid", "wellbore_uid", "datum_uid") and value:
        if version == "2.1" and not _UUID.fullmatch(value):
            return f"{name} {value!r}: WITSML 2.1 objects are named by uuid (8-4-4-4-12 hex digits)"
        if len(value) > 64 or " " in value:
            return f"{name} {value!r}: a uid is at most 64 characters without spaces"
    elif name == "mag_model" and len(value) > 64:
        return f"mag_model {value!r}: at most 64 characters"
    return None


def parse_time(text: str) -> float:
    """ISO 8601 time -> unix seconds (UTC when no zone is given)."""
    t = _dt.datetime.fromisoformat(str(text).strip().replace("Z", "+00:00"))
    if t.tzinfo is None:
        t = t.replace(tzinfo=_dt.timezone.utc)
    return t.timestamp()


# ---------------------------------------------------------------------------------------------
# geomagnetic models

@dataclass(frozen=True)
class MagModel:
    """The geomagnetic model behind a site: ``name`` (``WMM2025``; ``+IFR`` when a value was
    measured in field), its validity (decimal years, ``""`` if unknown), and the reference field the
    site gives (to recognise the stations evaluated against it)."""

    name: str
    valid: str = ""
    total_field_nt: float = math.nan
    dip_deg: float = math.nan
    ifr: bool | None = None


def mag_models(records) -> dict:
    """``{record id: MagModel}`` of calibration records (dicts with ``id`` and ``coefficients_yaml``,
    as :func:`bag.read_bag` gives them) whose site came from a geomagnetic model
    (``site.reference.model``, :func:`geomag.site_from_config`); a record without one is left out."""
    from ..core import yamltext

    from ..core.geomag import VALID

    out = {}
    for rec in records:
        try:
            site = (yamltext.load(rec["coefficients_yaml"]) or {}).get("site") or {}
        except yamltext.YAMLError:
            continue
        ref = site.get("reference") or {}
        name = str(ref.get("model") or "")
        if not name:
            continue
        sources = ref.get("sources") or {}
        ifr = any("IFR" in str(sources.get(k, "")) for k in ("total_field_nt", "dip_deg", "declination_deg"))
        lo_hi = VALID.get(name)
        out[rec["id"]] = MagModel(name + ("+IFR" if ifr else ""), f"{lo_hi[0]:.1f}-{lo_hi[1]:.1f}" if lo_hi else "",
                                  float(site.get("total_field_nt", math.nan)), float(site.get("dip_deg", math.nan)),
                                  ifr)
    return out


def _station_model(s: dict, models: dict, opts: Options) -> MagModel | None:
    """The model of the site ``s`` was evaluated against: ``mag_model`` if given, else its record's
    when the station's reference field (total − delta) is that site's."""
    if opts.mag_model:
        from ..core.geomag import VALID

        lo_hi = VALID.get(opts.mag_model)
        return MagModel(opts.mag_model, f"{lo_hi[0]:.1f}-{lo_hi[1]:.1f}" if lo_hi else "")
    m = models.get(s.get("coefficients_id"))
    if m is None:
        return None
    ref_b = _f(s.get("total_field_nt")) - _f(s.get("delta_b_nt"))
    ref_dip = _f(s.get("dip_deg")) - _f(s.get("delta_dip_deg"))
    if abs(ref_b - m.total_field_nt) <= 1e-3 and abs(ref_dip - m.dip_deg) <= 1e-6:
        return m
    return None        # evaluated against another site (an override): the record's model is not its


# ---------------------------------------------------------------------------------------------
# building

@dataclass
class TrajectoryExport:
    """A built trajectory document and what went into it."""

    xml: bytes
    exported: int
    #: stations left out, by reason ("raw (no calibration)", "no measured depth")
    skipped: dict = field(default_factory=dict)
    uuid: str = ""
    version: str = "2.1"
    #: the documents the trajectory hangs on, in load order: (kind, xml); empty when they exist in the store
    parents: list = field(default_factory=list)
    #: one-line remarks on the content (times before 1980)
    notes: list = field(default_factory=list)

    def skipped_text(self) -> str:
        return ", ".join(f"{n} {why}" for why, n in self.skipped.items()) or "none"


def _f(x) -> float:
    try:
        return float(x) if x is not None else math.nan
    except (TypeError, ValueError):
        return math.nan


def _finite(x) -> bool:
    return math.isfinite(_f(x))


def _num(x) -> str:
    return repr(float(x))


def _wrap180(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


def iso_time(stamp: float) -> str:
    """Unix seconds -> ISO 8601 UTC with microseconds and ``Z`` (an ``eml:TimeStamp``, a 1.4.1.1 ``timestamp``)."""
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


def _oriented(s: dict, north: str) -> tuple:
    """The station's azimuth (deg), north and east (m) and NED covariance (9, m²) along ``north``
    (:func:`_north`): the one place that puts a station's directions on the document's north.  The
    stations' positions and covariance are along the north they declare (:func:`_north` refuses a
    mix), so only the azimuth is chosen."""
    cov = [_f(x) for x in (s.get("position_covariance_ned_m2") or [math.nan] * 9)]
    return _azimuth_from(s, north), _f(s.get("north_m")), _f(s.get("east_m")), cov


def _declination(s: dict, north: str) -> float:
    """The declination applied to the azimuths (none when they are magnetic)."""
    return math.nan if north == "magnetic" else _wrap180(_azimuth_from(s, "true") - _azimuth_from(s, "magnetic"))


def _convergence(s: dict, north: str) -> float:
    """The grid convergence applied to the azimuths (only when they are grid)."""
    return _wrap180(_azimuth_from(s, "true") - _azimuth_from(s, "grid")) if north == "grid" else math.nan


def _vector(v):
    """Three finite floats, else None (missing, or NaN: not known)."""
    if v is None:
        return None
    v = [float(x) for x in v]
    return v if len(v) == 3 and all(math.isfinite(x) for x in v) else None


def _row(s: dict, north: str, model: MagModel | None) -> dict:
    """The station's values by :data:`MEASURES`/:data:`DEPTHS` key, in the station dicts' units
    (NaN: not written), and its texts by element name (None: not written)."""
    azi, n, e, cov = _oriented(s, north)
    short_collar = s.get("azimuth_method") == "short_collar"
    row = {"measured_depth_m": _f(s["measured_depth_m"]), "tvd_m": _f(s.get("tvd_m")),
           "drift_deg": _f(s.get("drift_deg")), "azimuth_deg": azi,
           "magnetic_toolface_deg": _f(s.get("magnetic_toolface_deg")),
           "gravity_toolface_deg": _f(s.get("gravity_toolface_deg")), "north_m": n, "east_m": e,
           "dls_deg_per_30m": _f(s.get("dls_deg_per_30m")),
           "reference_gravity_mps2": _f(s.get("total_gravity_mps2")) - _f(s.get("delta_g_mps2")),
           "reference_field_nt": _f(s.get("total_field_nt")) - _f(s.get("delta_b_nt")),
           "reference_dip_deg": _f(s.get("dip_deg")) - _f(s.get("delta_dip_deg")),
           "axial_correction_nt": -_f(s.get("axial_field_nt")) if short_collar else math.nan,
           "declination_deg": _declination(s, north), "grid_convergence_deg": _convergence(s, north),
           "total_field_nt": _f(s.get("total_field_nt")), "dip_deg": _f(s.get("dip_deg")),
           "total_gravity_mps2": _f(s.get("total_gravity_mps2"))}
    for key, parts in _RAW:
        v = _vector(s.get(key))
        row.update(zip(parts, v if v is not None else [math.nan] * 3))
    have_cov = all(math.isfinite(x) for x in cov)
    for key, k in COVARIANCE.items():
        row[key] = cov[k] if have_cov else math.nan
    for key in ("bias_n", "bias_e", "bias_v"):
        row[key] = 0.0 if have_cov else math.nan           # rev 4 has no bias terms
    row.update(MagModelUsed=model.name if model else None, MagModelValid=(model.valid or None) if model else None,
               InfieldRefCorUsed=None if model is None or model.ifr is None else ("true" if model.ifr else "false"),
               GravAccelCorUsed="true", MagXAxialCorUsed="true",
               AxialMagInterferenceCorUsed="true" if short_collar else "false",
               StatusTrajStation=STATION_STATUS.get(int(s.get("status", 0)), "rejected"),
               TypeSurveyTool="magnetic multiple-shot", CalcAlgorithm="minimum curvature")
    return row


def _uuid(*parts) -> str:
    return str(uuid.uuid5(UUID_NAMESPACE, "\x1f".join(str(p) for p in parts)))


@dataclass(frozen=True)
class _Ids:
    """The uids of the trajectory and what it references (2.1: uuids)."""

    trajectory: str
    well: str
    wellbore: str
    datum: str            # "" when the store's wellbore default applies
    vertical_crs: str     # "" without a datum elevation
    tool_error_model: str


def _ids(opts: Options, run: str) -> _Ids:
    traj = _uuid("trajectory", opts.well, opts.wellbore, run)
    tem = _uuid("tool error model", _model_name())
    if opts.existing:
        return _Ids(traj, opts.well_uid, opts.wellbore_uid, opts.datum_uid, "", tem)
    datum = _uuid("datum", opts.well, opts.datum) if opts.version == "2.1" else DATUM_KINDS[opts.datum]
    crs = ""
    if math.isfinite(opts.datum_elevation):
        crs = _uuid("vertical crs", MSL_EPSG, opts.units) if opts.version == "2.1" else DATUM_KINDS["mean sea level"]
    well = _uuid("well", opts.well)
    return _Ids(traj, well, _uuid("wellbore", opts.well, opts.wellbore), datum, crs, tem)


def _model_name() -> str:
    from ..correct.iscwsa import MODEL_NAME

    return MODEL_NAME


class _Writer:
    """Measures in one version and units: ``measure(parent, tag, value_si, quantity)``."""

    def __init__(self, version: str, units: str, ns: str):
        self.version, self.units, self.ns = version, units, ns

    def el(self, parent, tag, text=None, ns=None, **attrib):
        e = etree.SubElement(parent, f"{{{ns or self.ns}}}{tag}", **attrib)
        if text is not None:
            e.text = str(text)
        return e

    def value(self, value: float, q: Quantity) -> tuple[str, str]:
        uom = q.uom(self.version, self.units)
        return _num(value / q.to_si[uom]), uom

    def measure(self, parent, tag, value, q: Quantity, ns=None, **attrib):
        if math.isfinite(value):
            text, uom = self.value(value, q)
            return self.el(parent, tag, text, ns=ns, uom=uom, **attrib)
        return None

    def station_body(self, st, row: dict, special: dict) -> None:
        """The station's LAYOUT elements after what ``special`` (name -> callable(st)) builds itself."""
        groups: dict = {}
        for key, path, q in MEASURES:
            head, _, tail = path.partition("/")
            groups.setdefault(head, []).append((key, tail, q))
        for name in LAYOUT[self.version]:
            if name in special:
                special[name](st)
            elif name in groups:
                items = groups[name]
                if items[0][1]:                    # a group of measures
                    present = [(key, tail, q) for key, tail, q in items if math.isfinite(row[key])]
                    if present:
                        g = self.el(st, element_name(name, self.version))
                        for key, tail, q in present:
                            self.measure(g, element_name(tail, self.version), row[key], q)
                        if name == "MatrixCov" and self.version == "2.1":
                            self.el(g, "Sigma", "1.0")      # the covariance is 1σ
                else:
                    key, _, q = items[0]
                    self.measure(st, element_name(name, self.version), row[key], q)
            elif row.get(name) is not None:
                self.el(st, element_name(name, self.version), row[name])


def trajectory_document(stations, run_id: str | None = None, active: bool = False, models: dict | None = None,
                        **options) -> TrajectoryExport:
    """The WITSML trajectory of ``stations`` (station dicts, receive order) with :class:`Options`
    ``options`` (``well``, ``wellbore``, ``version``, ``units``, ``start_time``, ``datum``, …).

    ``run_id`` (with the well and wellbore names) makes the uuids; it defaults to the ISO time of the
    first exported station.  ``active``: the survey is still growing (2.1 ``ActiveStatus`` ``active``,
    the live node) or finished (``inactive``).  ``models``: :func:`mag_models` of the run's
    calibration records.  Not validated here: see :func:`validate`."""
    opts = Options(**options)
    opts.check()
    kept, skipped = select_stations(stations)
    north = _north(kept)
    shift = opts.shift(kept[0]["stamp"]) if kept else 0.0

    def when(stamp):
        return iso_time(float(stamp) + shift)

    run = run_id if run_id is not None else (when(kept[0]["stamp"]) if kept else "empty")
    ids = _ids(opts, run)
    rows = [_row(s, north, _station_model(s, models or {}, opts)) for s in kept]
    first = when(kept[0]["stamp"]) if kept else iso_time(0.0)
    left_out = "; left out: " + ", ".join(f"{n} {why}" for why, n in skipped.items()) if skipped else ""
    info = {"kept": kept, "rows": rows, "north": north, "when": when, "first": first, "ids": ids, "run": run,
            "active": active,
            "description": f"{len(kept)} corrected survey stations of {opts.well} {opts.wellbore}{left_out}"}
    if opts.version == "2.1":
        root, parents = _trajectory_21(opts, info), ([] if opts.existing else _parents_21(opts, ids, first))
    else:
        root, parents = _trajectory_1411(opts, info), ([] if opts.existing else _parents_1411(opts, ids, first))
    notes = []
    if kept and float(kept[0]["stamp"]) + shift < EARLIEST_SURVEY_TIME:
        notes.append(f"the stations' times begin {first}, before 1980: a replayed log's clock, not the survey's; "
                     "give the survey's start (start_time) to date them")
    return TrajectoryExport(xml=_bytes(root), exported=len(kept), skipped=skipped, uuid=ids.trajectory,
                            version=opts.version, parents=[(k, _bytes(r)) for k, r in parents], notes=notes)


def _bytes(root) -> bytes:
    return etree.tostring(root, xml_declaration=True, encoding="utf-8", pretty_print=True)


def _first_use(kept) -> dict:
    first = {}
    for s in kept:
        first.setdefault(s["coefficients_id"], s["stamp"])
    return first


def _citation(w: _Writer, root, title: str, created: str, description: str = "", updated: str = ""):
    cit = w.el(root, "Citation", ns=NS_EML)
    w.el(cit, "Title", title, ns=NS_EML)
    w.el(cit, "Originator", ORIGINATOR, ns=NS_EML)
    w.el(cit, "Creation", created, ns=NS_EML)
    w.el(cit, "Format", f"inclinometer_calib {__version__}", ns=NS_EML)
    if updated:
        w.el(cit, "LastUpdate", updated, ns=NS_EML)
    if description:
        w.el(cit, "Description", description, ns=NS_EML)


def _reference(w: _Writer, parent, tag: str, uid: str, qualified_type: str, title: str, ns=None):
    """A 2.1 ``eml:DataObjectReference``."""
    ref = w.el(parent, tag, ns=ns)
    w.el(ref, "Uuid", uid, ns=NS_EML)
    w.el(ref, "QualifiedType", qualified_type, ns=NS_EML)
    w.el(ref, "Title", title, ns=NS_EML)
    return ref


def _datum_title(opts: Options) -> str:
    return f"{opts.datum} of {opts.well}"


def _trajectory_21(opts: Options, info: dict):
    kept, rows, when, ids = info["kept"], info["rows"], info["when"], info["ids"]
    w = _Writer("2.1", opts.units, NS_WITSML)
    E = functools.partial(w.el, ns=NS_EML)
    root = etree.Element(f"{{{NS_WITSML}}}Trajectory", nsmap=NSMAP, uuid=ids.trajectory, schemaVersion="2.1")
    _citation(w, root, f"{opts.well} {opts.wellbore}: inclinometer survey {info['run']}", info["first"],
              info["description"], when(kept[-1]["stamp"]) if kept else "")
    for cid, t in _first_use(kept).items():
        ext = E(root, "ExtensionNameValue")
        E(ext, "Name", EXTENSION_COEFFICIENTS)
        E(ext, "Value", cid)
        E(ext, "DTim", when(t))
        E(ext, "Description", "id of the inclinometer_calib calibration record applied to the stations from DTim on")
    E(root, "ActiveStatus", "active" if info["active"] else "inactive")
    idx = E(root, "Index")
    E(idx, "IndexKind", "measured depth")
    E(idx, "Uom", opts.units)
    E(idx, "Direction", "increasing")
    mds = [r["measured_depth_m"] for r in rows]
    if kept:
        iv = E(root, "MdInterval")
        E(iv, "MdMin", w.value(min(mds), LENGTH)[0])
        E(iv, "MdMax", w.value(max(mds), LENGTH)[0])
        E(iv, "Uom", opts.units)
        w.el(root, "DTimTrajEnd", when(kept[-1]["stamp"]))
        w.el(root, "DTimTrajStart", when(kept[0]["stamp"]))
    if ids.datum:
        for tag in ("DefaultMdDatum", "DefaultTvdDatum"):
            _reference(w, root, tag, ids.datum, "eml23.ReferencePointInACrs", _datum_title(opts))
    uids: dict = {}
    tem = (ids.tool_error_model, _model_name())
    for s, row in zip(kept, rows):
        uid = _station_uid(s, uids)
        st = w.el(root, "TrajectoryStation", uid=uid)
        t = when(s["stamp"])
        E(st, "Creation", t)
        E(st, "LastUpdate", t)
        ext = E(st, "ExtensionNameValue")
        E(ext, "Name", EXTENSION_COEFFICIENTS)
        E(ext, "Value", s["coefficients_id"])

        def md(st, row=row):
            w.measure(E(st, "Md"), "MeasuredDepth", row["measured_depth_m"], LENGTH, ns=NS_EML)

        def tvd(st, row=row):
            if math.isfinite(row["tvd_m"]):
                el = w.el(st, "Tvd", **{f"{{{NS_XSI}}}type": "eml:DatumVerticalDepth"})
                w.measure(el, "VerticalDepth", row["tvd_m"], LENGTH, ns=NS_EML)

        def tool_error_model(st, row=row):
            if math.isfinite(row["cov_nn"]):
                _reference(w, st, "ToolErrorModel", tem[0], "witsml21.ToolErrorModel", tem[1])

        w.station_body(st, {**row, "DTimStn": t, "TypeTrajStation": TRAJ_STATION_TYPE["2.1"]},
                       {"Md": md, "Tvd": tvd, "ToolErrorModel": tool_error_model})
    _reference(w, root, "Wellbore", ids.wellbore, "witsml21.Wellbore", opts.wellbore)
    # TrajectoryMetadata
    decl = next((r["declination_deg"] for r in rows if math.isfinite(r["declination_deg"])), math.nan)
    conv = next((r["grid_convergence_deg"] for r in rows if math.isfinite(r["grid_convergence_deg"])), math.nan)
    w.measure(root, "MagDeclUsed", decl, ANGLE)
    if kept:
        w.measure(w.el(root, "MdMaxMeasured"), "MeasuredDepth", max(mds), LENGTH, ns=NS_EML)
    w.el(root, "NominalCalcAlgorithm", "minimum curvature")
    w.el(root, "NominalTypeSurveyTool", "magnetic multiple-shot")
    w.el(root, "NominalTypeTrajStation", TRAJ_STATION_TYPE["2.1"])
    w.measure(root, "GridConUsed", conv, ANGLE)
    w.el(root, "AziRef", NORTH_REFERENCE[info["north"]])
    return root


def _station_uid(s: dict, uids: dict) -> str:
    uid = f"station-{int(s['station_id'])}"
    uids[uid] = uids.get(uid, 0) + 1
    if uids[uid] > 1:                      # a correction node restarted without its state file
        uid = f"{uid}-{uids[uid]}"
    return uid


def _parents_21(opts: Options, ids: _Ids, created: str) -> list:
    """The 2.1 Well, (VerticalCrs,) datum and Wellbore documents, in load order."""
    w = _Writer("2.1", opts.units, NS_WITSML)
    E = functools.partial(w.el, ns=NS_EML)
    out = []
    well = etree.Element(f"{{{NS_WITSML}}}Well", nsmap=NSMAP, uuid=ids.well, schemaVersion="2.1")
    _citation(w, well, opts.well, created)
    E(well, "ActiveStatus", "active")
    out.append(("well", well))
    eml_map = {"eml": NS_EML, "xsi": NS_XSI}
    if ids.vertical_crs:
        crs = etree.Element(f"{{{NS_EML}}}VerticalCrs", nsmap=eml_map, uuid=ids.vertical_crs, schemaVersion="2.3",
                            uom=opts.units)
        _citation(w, crs, f"MSL height (EPSG:{MSL_EPSG}), {opts.units}", created)
        E(crs, "Direction", "up")
        E(E(crs, "AbstractVerticalCrs", **{f"{{{NS_XSI}}}type": "eml:VerticalEpsgCrs"}), "EpsgCode", MSL_EPSG)
        out.append(("vertical_crs", crs))
    datum = etree.Element(f"{{{NS_EML}}}ReferencePointInACrs", nsmap=eml_map, uuid=ids.datum, schemaVersion="2.3")
    _citation(w, datum, _datum_title(opts), created,
              f"the MD and TVD datum of {opts.well}"
              + (f", {_num(opts.datum_elevation)} {opts.units} above mean sea level"
                 if ids.vertical_crs else ""))
    E(datum, "Kind", opts.datum)
    if ids.vertical_crs:
        _reference(w, datum, "VerticalCrs", ids.vertical_crs, "eml23.VerticalCrs", f"MSL height (EPSG:{MSL_EPSG})",
                   ns=NS_EML)
        E(datum, "VerticalCoordinate", _num(opts.datum_elevation))
    out.append(("datum", datum))
    wb = etree.Element(f"{{{NS_WITSML}}}Wellbore", nsmap=NSMAP, uuid=ids.wellbore, schemaVersion="2.1")
    _citation(w, wb, opts.wellbore, created)
    E(wb, "ActiveStatus", "active")
    for tag in ("DefaultMdDatum", "DefaultTvdDatum"):
        _reference(w, wb, tag, ids.datum, "eml23.ReferencePointInACrs", _datum_title(opts))
    _reference(w, wb, "Well", ids.well, "witsml21.Well", opts.well)
    out.append(("wellbore", wb))
    return out


def _trajectory_1411(opts: Options, info: dict):
    kept, rows, when, ids = info["kept"], info["rows"], info["when"], info["ids"]
    w = _Writer("1.4.1.1", opts.units, NS_WITSML14)
    E = w.el
    datum = {"datum": ids.datum} if ids.datum else {}
    root = etree.Element(f"{{{NS_WITSML14}}}trajectorys", nsmap={None: NS_WITSML14}, version="1.4.1.1")
    tr = E(root, "trajectory", uidWell=ids.well, uidWellbore=ids.wellbore, uid=ids.trajectory)
    E(tr, "nameWell", opts.well)
    E(tr, "nameWellbore", opts.wellbore)
    E(tr, "name", f"inclinometer survey {info['run']}"[:64])
    mds = [r["measured_depth_m"] for r in rows]
    if kept:
        E(tr, "dTimTrajStart", when(kept[0]["stamp"]))
        E(tr, "dTimTrajEnd", when(kept[-1]["stamp"]))
        w.measure(tr, "mdMn", min(mds), LENGTH, **datum)
        w.measure(tr, "mdMx", max(mds), LENGTH, **datum)
    decl = next((r["declination_deg"] for r in rows if math.isfinite(r["declination_deg"])), math.nan)
    conv = next((r["grid_convergence_deg"] for r in rows if math.isfinite(r["grid_convergence_deg"])), math.nan)
    w.measure(tr, "magDeclUsed", decl, ANGLE)
    w.measure(tr, "gridConUsed", conv, ANGLE)
    E(tr, "aziRef", NORTH_REFERENCE[info["north"]])
    uids: dict = {}
    for s, row in zip(kept, rows):
        st = E(tr, "trajectoryStation", uid=_station_uid(s, uids))

        def tool_error_model(st, row=row):
            if math.isfinite(row["cov_nn"]):
                E(st, "iscwsaToolErrorModel", _model_name())

        w.station_body(st, {**row, "DTimStn": when(s["stamp"]), "TypeTrajStation": TRAJ_STATION_TYPE["1.4.1.1"]},
                       {"Md": lambda st, row=row: w.measure(st, "md", row["measured_depth_m"], LENGTH, **datum),
                        "Tvd": lambda st, row=row: w.measure(st, "tvd", row["tvd_m"], LENGTH, **datum),
                        "ToolErrorModel": tool_error_model})
        _extension_1411(w, st, s["coefficients_id"])
    cd = E(tr, "commonData")
    E(cd, "sourceName", f"inclinometer_calib {__version__}")
    E(cd, "dTimCreation", info["first"])
    if kept:
        E(cd, "dTimLastChange", when(kept[-1]["stamp"]))
    E(cd, "itemState", "actual")
    E(cd, "comments", info["description"])
    if ids.datum:
        E(cd, "defaultDatum", opts.datum, uidRef=ids.datum)
    for cid, t in _first_use(kept).items():
        _extension_1411(w, cd, cid, when(t), "id of the inclinometer_calib calibration record applied to the "
                                             "stations from dTim on")
    return root


def _extension_1411(w: _Writer, parent, value: str, dtim: str = "", description: str = ""):
    ext = w.el(parent, "extensionNameValue")
    w.el(ext, "name", EXTENSION_COEFFICIENTS)
    w.el(ext, "value", value)
    w.el(ext, "dataType", "string")
    if dtim:
        w.el(ext, "dTim", dtim)
    if description:
        w.el(ext, "description", description)


def _parents_1411(opts: Options, ids: _Ids, created: str) -> list:
    """The 1.4.1.1 ``wells`` (with the datum, and mean sea level under it when an elevation is
    given) and ``wellbores`` documents, in load order."""
    w = _Writer("1.4.1.1", opts.units, NS_WITSML14)
    E = w.el
    wells = etree.Element(f"{{{NS_WITSML14}}}wells", nsmap={None: NS_WITSML14}, version="1.4.1.1")
    well = E(wells, "well", uid=ids.well)
    E(well, "name", opts.well)
    E(well, "timeZone", "Z")                # the documents' times are UTC
    if ids.vertical_crs and ids.vertical_crs != ids.datum:
        msl = E(well, "wellDatum", uid=ids.vertical_crs)
        E(msl, "name", "mean sea level")
        E(msl, "code", DATUM_KINDS["mean sea level"])
    d = E(well, "wellDatum", uid=ids.datum)
    E(d, "name", opts.datum)
    E(d, "code", DATUM_KINDS[opts.datum])
    if ids.vertical_crs and ids.vertical_crs != ids.datum:
        w.measure(d, "elevation", opts.datum_elevation * LENGTH.to_si[opts.units], LENGTH, datum=ids.vertical_crs)
    cd = E(well, "commonData")
    E(cd, "sourceName", f"inclinometer_calib {__version__}")
    E(cd, "dTimCreation", created)
    wellbores = etree.Element(f"{{{NS_WITSML14}}}wellbores", nsmap={None: NS_WITSML14}, version="1.4.1.1")
    wb = E(wellbores, "wellbore", uidWell=ids.well, uid=ids.wellbore)
    E(wb, "nameWell", opts.well)
    E(wb, "name", opts.wellbore)
    cd = E(wb, "commonData")
    E(cd, "sourceName", f"inclinometer_calib {__version__}")
    E(cd, "dTimCreation", created)
    E(cd, "defaultDatum", opts.datum, uidRef=ids.datum)
    return [("well", wells), ("wellbore", wellbores)]


# ---------------------------------------------------------------------------------------------
# validation and reading back

#: Root elements this module writes -> (version, the schema file that declares it, its name in
#: messages).  2.1: ``Trajectory.xsd`` includes Well, Wellbore and energyML common 2.3's objects.
ROOTS = {
    f"{{{NS_WITSML}}}Trajectory": ("2.1", TRAJECTORY_XSD, "Trajectory.xsd"),
    f"{{{NS_WITSML}}}Well": ("2.1", TRAJECTORY_XSD, "Well.xsd"),
    f"{{{NS_WITSML}}}Wellbore": ("2.1", TRAJECTORY_XSD, "Wellbore.xsd"),
    f"{{{NS_EML}}}ReferencePointInACrs": ("2.1", TRAJECTORY_XSD, "eml Datum.xsd"),
    f"{{{NS_EML}}}VerticalCrs": ("2.1", TRAJECTORY_XSD, "eml CRS.xsd"),
    f"{{{NS_WITSML14}}}trajectorys": ("1.4.1.1", XSD_1411[0], "obj_trajectory.xsd"),
    f"{{{NS_WITSML14}}}wells": ("1.4.1.1", XSD_1411[1], "obj_well.xsd"),
    f"{{{NS_WITSML14}}}wellbores": ("1.4.1.1", XSD_1411[2], "obj_wellbore.xsd"),
}


@functools.lru_cache(maxsize=None)
def schema(xsd: str = TRAJECTORY_XSD) -> etree.XMLSchema:
    """The vendored schema ``xsd`` and everything it includes and imports, compiled by libxml2
    (lxml's ``XMLSchema``: about 20 ms for 2.1's, loaded once per process)."""
    return etree.XMLSchema(etree.parse(xsd))


def load_schemas(version: str) -> None:
    """Load ``version``'s schemas now (the live node: not at the first station)."""
    for v, xsd, _ in ROOTS.values():
        if v == version:
            schema(xsd)


def validate(xml: bytes, max_problems: int = 5) -> str:
    """Raise :class:`WitsmlError` unless ``xml`` is a valid document of one of :data:`ROOTS` (the
    version from its root element, checked against the vendored schema of that version); the
    message lists the first ``max_problems`` problems, each with its line and path in the document.
    Returns the version."""
    try:
        tree = etree.fromstring(xml)
    except (etree.XMLSyntaxError, ValueError) as exc:
        raise WitsmlError(f"not well-formed XML: {exc}") from None
    if tree.tag not in ROOTS:
        raise WitsmlError(f"root element is {tree.tag}, not a WITSML 2.1 Trajectory ({{{NS_WITSML}}}Trajectory) "
                          f"or 1.4.1.1 trajectorys ({{{NS_WITSML14}}}trajectorys), nor their well or wellbore")
    version, xsd_path, xsd = ROOTS[tree.tag]
    checker = schema(xsd_path)
    if checker.validate(tree):
        return version
    doc = tree.getroottree()
    problems = [f"{_where(doc, err)}: {_reason(err.message)}" for err in list(checker.error_log)[:max_problems + 1]]
    more = " (and more)" if len(problems) > max_problems else ""
    raise WitsmlError(f"not a valid WITSML {version} {etree.QName(tree).localname} ({xsd}):\n  "
                      + "\n  ".join(problems[:max_problems]) + more)


def _reason(message: str, most: int = 12) -> str:
    """libxml2's words for a schema error, its ``{namespace}`` prefixes left out and a set of
    allowed values longer than ``most`` cut to its first ones and its size (a unit's set has
    hundreds)."""
    message = re.sub(r"\{[^{}]*\}(?=\w)", "", message)

    def cut(m):
        values = m.group(1).split(", ")
        return m.group(0) if len(values) <= most else \
            "{" + ", ".join(values[:most]) + f", ... ({len(values)} values)" + "}"
    return re.sub(r"\{('[^{}]*')\}", cut, message)


def _where(doc, err) -> str:
    """``line N, /Trajectory/TrajectoryStation[2]/Incl (station <uid>)`` of a schema error: the
    element's path by local names (an index where siblings share the name) and the uid of the
    station it is in."""
    try:
        found = doc.xpath(err.path, namespaces={k: v for k, v in doc.getroot().nsmap.items() if k}) \
            if err.path else []
    except etree.XPathError:
        found = []
    el = found[0] if found and isinstance(found[0], etree._Element) else None
    if el is None:
        return f"line {err.line}" + (f", {err.path}" if err.path else "")
    steps, uid, node = [], None, el
    while node is not None:
        name = etree.QName(node).localname
        parent = node.getparent()
        same = [c for c in parent if c.tag == node.tag] if parent is not None else [node]
        steps.append(f"{name}[{same.index(node) + 1}]" if len(same) > 1 else name)
        if uid is None and name in ("TrajectoryStation", "trajectoryStation"):
            uid = node.get("uid")
        node = parent
    return f"line {err.line}, /" + "/".join(reversed(steps)) + (f" (station {uid})" if uid else "")


def _measure(el, q: Quantity, what: str) -> float:
    if el is None:
        return math.nan
    uom = el.get("uom")
    if uom not in q.to_si:
        raise WitsmlError(f"{what}: unit {uom!r} not understood (expected one of {', '.join(q.to_si)})")
    return float(el.text) * q.to_si[uom]


def read_document(xml: bytes) -> dict:
    """A WITSML 2.1 ``Trajectory`` or 1.4.1.1 ``trajectorys`` (one trajectory) parsed back: ``version``,
    ``uid``, ``wellbore`` and ``wellbore_uid`` (1.4.1.1 also ``well``, ``well_uid``), ``datum`` and
    ``datum_uid`` (the MD/TVD default datum's name and uid; ``""`` when not given),
    ``azimuth_reference`` ('magnetic', 'true', 'grid' from ``AziRef``), and ``stations``: dicts with
    the station dicts' keys where they exist (``measured_depth_m``, ``tvd_m``, ``drift_deg``,
    ``azimuth_deg``, ``azimuth_reference``, toolfaces, ``north_m``, ``east_m``, ``dls_deg_per_30m``,
    ``total_gravity_mps2``, ``total_field_nt``, ``dip_deg``, ``raw_gravity_mps2``/``raw_field_nt``
    (x, y, z; NaN where absent), ``position_covariance_ned_m2`` (9, m², NaN where absent),
    ``axial_field_nt``, ``coefficients_id``, ``stamp`` (unix s)) plus ``uid``, ``station_status``
    (the TrajStationStatus), ``declination_deg``, ``grid_convergence_deg``, the reference values
    (``reference_gravity_mps2``, ``reference_field_nt``, ``reference_dip_deg``), ``mag_model``,
    ``mag_model_valid``, ``tool_error_model``.  Units are converted from the uoms given (a unit it
    does not know is an error naming the element).  Parsed with lxml, not validated."""
    try:
        root = etree.fromstring(xml)
    except etree.XMLSyntaxError as exc:
        raise WitsmlError(f"not well-formed XML: {exc}") from None
    if root.tag == f"{{{NS_WITSML}}}Trajectory":
        version, traj, ns = "2.1", root, XP
        wb = traj.find("w:Wellbore", ns)
        doc = {"wellbore": wb.findtext("eml:Title", namespaces=ns) if wb is not None else "",
               "wellbore_uid": wb.findtext("eml:Uuid", namespaces=ns) if wb is not None else "",
               "datum": traj.findtext("w:DefaultMdDatum/eml:Title", "", ns),
               "datum_uid": traj.findtext("w:DefaultMdDatum/eml:Uuid", "", ns), "uid": traj.get("uuid")}
    elif root.tag == f"{{{NS_WITSML14}}}trajectorys":
        version, ns = "1.4.1.1", XP14
        trajs = root.findall("w:trajectory", ns)
        if len(trajs) != 1:
            raise WitsmlError(f"a trajectorys document of {len(trajs)} trajectories: one is read")
        traj = trajs[0]
        dd = traj.find("w:commonData/w:defaultDatum", ns)
        doc = {"well": traj.findtext("w:nameWell", "", ns), "well_uid": traj.get("uidWell", ""),
               "wellbore": traj.findtext("w:nameWellbore", "", ns), "wellbore_uid": traj.get("uidWellbore", ""),
               "datum": dd.text if dd is not None else "", "datum_uid": dd.get("uidRef", "") if dd is not None else "",
               "uid": traj.get("uid")}
    else:
        raise WitsmlError(f"root element is {root.tag}, not a WITSML 2.1 Trajectory or 1.4.1.1 trajectorys")
    n = functools.partial(element_name, version=version)
    reference = {v: k for k, v in NORTH_REFERENCE.items()}.get(traj.findtext(f"w:{n('AziRef')}", namespaces=ns), "")
    stations = []
    for st in traj.findall(f"w:{n('TrajectoryStation')}", ns):
        uid = st.get("uid")
        row = {key: _measure(st.find(_path(path, version), ns), q, f"station {uid}: {path.split('/')[-1]}")
               for key, path, q in MEASURES}
        for key, paths, q in DEPTHS:
            row[key] = _measure(st.find(paths[version], ns), q, f"station {uid}: {paths[version].split(':')[-1]}")
        ext_tag, name_tag, value_tag = (("eml:ExtensionNameValue", "eml:Name", "eml:Value") if version == "2.1" else
                                        ("w:extensionNameValue", "w:name", "w:value"))
        ext = {e.findtext(name_tag, namespaces=ns): e.findtext(value_tag, namespaces=ns)
               for e in st.findall(ext_tag, ns)}
        when = st.findtext(f"w:{n('DTimStn')}", namespaces=ns) or st.findtext("eml:Creation", namespaces=ns)
        tem = (st.findtext("w:ToolErrorModel/eml:Title", namespaces=ns) if version == "2.1"
               else st.findtext("w:iscwsaToolErrorModel", namespaces=ns))
        out = {k: v for k, v in row.items() if k not in COVARIANCE and not k.startswith(("raw_", "bias_"))}
        for key, parts in _RAW:
            out[key] = [row[p] for p in parts]
        out["position_covariance_ned_m2"] = [row[_COV_KEY[k]] for k in _COV_FROM]
        out["axial_field_nt"] = -row["axial_correction_nt"]
        del out["axial_correction_nt"]
        out.update(uid=uid, azimuth_reference=reference, coefficients_id=ext.get(EXTENSION_COEFFICIENTS, ""),
                   station_status=st.findtext(f"w:{n('StatusTrajStation')}", "", ns),
                   mag_model=st.findtext(f"w:{n('MagModelUsed')}", "", ns),
                   mag_model_valid=st.findtext(f"w:{n('MagModelValid')}", "", ns), tool_error_model=tem or "",
                   stamp=_stamp(when) if when else math.nan)
        stations.append(out)
    return {"version": version, "azimuth_reference": reference, **doc, "stations": stations}


def read_trajectory(xml: bytes) -> list:
    """The stations of a WITSML 2.1 or 1.4.1.1 trajectory document (:func:`read_document`)."""
    return read_document(xml)["stations"]


# ---------------------------------------------------------------------------------------------
# writing

def parent_path(path, kind: str) -> str:
    """Where the ``kind`` parent document of the trajectory at ``path`` is written: beside it,
    ``<stem>.<kind>.xml`` (``trajectory.xml`` -> ``trajectory.well.xml``)."""
    stem, ext = os.path.splitext(os.fspath(path))
    return f"{stem}.{kind}{ext or '.xml'}"


#: The parent documents' kinds (any version).
PARENT_KINDS = ("well", "vertical_crs", "datum", "wellbore")


def write_trajectory(path, stations, **kwargs) -> TrajectoryExport:
    """Build (:func:`trajectory_document`), validate every document, and write them atomically: the
    parents beside the trajectory (:func:`parent_path`) first, then the trajectory (temp file +
    rename: a document that does not validate, or a write that fails, leaves the files as they were)."""
    export = trajectory_document(stations, **kwargs)
    validate(export.xml)
    for _, xml in export.parents:
        validate(xml)
    for kind, xml in export.parents:
        atomic_write_text(parent_path(path, kind), xml.decode("utf-8"))
    atomic_write_text(path, export.xml.decode("utf-8"))
    return export
