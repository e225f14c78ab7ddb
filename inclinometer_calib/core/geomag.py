"""The site's reference field from a geomagnetic model, gravity from the location, grid convergence — ROS-free.

A rig's reference is not typed in: it comes from a main-field model at the well's latitude,
longitude, altitude and date, unless the site has measured values (an in-field referencing survey,
IFR), which win, value by value.  Models, through maintained libraries:

* ``WMM2025`` — the World Magnetic Model 2025 (NOAA/BGS; ``pygeomag``), valid 2025.0–2030.0;
* ``IGRF-14`` — the International Geomagnetic Reference Field, 14th generation (IAGA; ``ppigrf``),
  1900–2030.

Both give the field's north, east and down components (nT) at a geodetic (WGS84) position; from
them the total field ``F``, the dip ``I = atan2(Z, H)`` and the declination ``D = atan2(Y, X)``
(east positive).  Gravity, when not measured, is WGS84 normal gravity (Somigliana) with the
free-air gradient.  Grid convergence (the angle from true north to grid north, for a projected
CRS named by EPSG code or PROJ string) comes from ``pyproj``'s meridian convergence: a grid
azimuth is the true azimuth minus it.

Azimuths then exist in three references: magnetic (what the magnetometers give), true
(magnetic + declination) and grid (true − convergence); :func:`azimuths` gives all three.  A run
reports every azimuth and every position along **one** of them (:func:`resolve_north`: the one
asked for, by default grid on a site with a grid, else true on a site with a declination, else
magnetic) and carries the others as separately named fields.
"""
from __future__ import annotations

import datetime as _dt
import math

import numpy as np

from .frames import wrap360

MODELS = ("WMM2025", "IGRF-14")
#: Validity of each model (decimal years); outside it a lookup is refused.
VALID = {"WMM2025": (2025.0, 2030.0), "IGRF-14": (1900.0, 2030.0)}
#: Keys of a site given by its location (the rest of a site's keys are measured values).
LOCATION_KEYS = ("latitude_deg", "longitude_deg", "altitude_m", "date", "model", "crs")


def decimal_year(date) -> float:
    """A date (``datetime.date``, ``datetime.datetime`` or ISO text) as a decimal year."""
    if isinstance(date, str):
        date = _dt.date.fromisoformat(date)
    if isinstance(date, _dt.datetime):
        start = _dt.datetime(date.year, 1, 1, tzinfo=date.tzinfo)
        end = _dt.datetime(date.year + 1, 1, 1, tzinfo=date.tzinfo)
        return date.year + (date - start) / (end - start)
    start, end = _dt.date(date.year, 1, 1), _dt.date(date.year + 1, 1, 1)
    return date.year + (date - start).days / (end - start).days


def model_field(lat_deg: float, lon_deg: float, alt_m: float, date, model: str = "WMM2025") -> dict:
    """The main field at a geodetic position: ``x`` (north), ``y`` (east), ``z`` (down), ``h``,
    ``f`` in nT, ``dip_deg``, ``declination_deg``, with the model and decimal year."""
    if model not in MODELS:
        raise ValueError(f"geomagnetic model {model!r} unknown (one of {', '.join(MODELS)})")
    if not (-90.0 <= lat_deg <= 90.0 and -180.0 <= lon_deg <= 360.0):
        raise ValueError(f"position {lat_deg}, {lon_deg}: latitude must be within ±90°, longitude ±180° (or 0–360°)")
    year = decimal_year(date)
    lo, hi = VALID[model]
    if not lo <= year < hi:
        raise ValueError(f"{model} is valid {lo:g}–{hi:g}; the date {year:.3f} is outside it")
    if model == "WMM2025":
        from pygeomag import GeoMag

        r = GeoMag().calculate(glat=float(lat_deg), glon=float(lon_deg), alt=float(alt_m) / 1000.0, time=year)
        x, y, z = float(r.x), float(r.y), float(r.z)
    else:
        import ppigrf

        d = date if isinstance(date, (_dt.date, _dt.datetime)) else _dt.date.fromisoformat(str(date))
        when = d if isinstance(d, _dt.datetime) else _dt.datetime(d.year, d.month, d.day)
        be, bn, bu = ppigrf.igrf(float(lon_deg), float(lat_deg), float(alt_m) / 1000.0, when)
        x, y, z = float(np.ravel(bn)[0]), float(np.ravel(be)[0]), -float(np.ravel(bu)[0])
    h = math.hypot(x, y)
    return {"model": model, "decimal_year": year, "x": x, "y": y, "z": z, "h": h, "f": math.hypot(h, z),
            "dip_deg": math.degrees(math.atan2(z, h)), "declination_deg": math.degrees(math.atan2(y, x))}


def normal_gravity(lat_deg: float, alt_m: float = 0.0) -> float:
    """WGS84 normal gravity (m/s²): Somigliana's formula on the ellipsoid, then the free-air
    gradient to first and second order in height (NIMA TR8350.2, eqs. 4-1 and 4-3)."""
    a, b = 6378137.0, 6356752.3142
    ge, gp = 9.7803253359, 9.8321849378
    s2 = math.sin(math.radians(lat_deg)) ** 2
    g0 = (a * ge * (1 - s2) + b * gp * s2) / math.sqrt(a * a * (1 - s2) + b * b * s2)
    f, m = 1 / 298.257223563, 0.00344978650684
    return g0 * (1 - 2 / a * (1 + f + m - 2 * f * s2) * alt_m + 3 / a ** 2 * alt_m ** 2)


def grid_convergence(lat_deg: float, lon_deg: float, crs) -> float:
    """Grid convergence (deg) at a position for a projected CRS (EPSG code, ``EPSG:…`` or PROJ
    text): the angle from true north to grid north, east positive — ``grid = true − γ``."""
    from pyproj import CRS, Proj

    c = CRS.from_user_input(int(crs) if isinstance(crs, (int, np.integer)) or str(crs).isdigit() else crs)
    if not c.is_projected:
        raise ValueError(f"CRS {crs!r} is not a projected CRS: it has no grid north")
    # pyproj's meridian convergence: east of the central meridian (north) true north lies east of
    # grid north by it, so a line to true north has grid azimuth −γ
    return float(Proj(c).get_factors(lon_deg, lat_deg).meridian_convergence)


def azimuths(azimuth_true_deg, declination_deg: float, convergence_deg: float = float("nan")) -> dict:
    """The three azimuth references of true azimuths: ``magnetic = true − D``, ``true``,
    ``grid = true − γ`` (NaN without a grid)."""
    t = np.asarray(azimuth_true_deg, dtype=float)
    return {"magnetic": wrap360(t - declination_deg), "true": wrap360(t),
            "grid": wrap360(t - convergence_deg) if np.isfinite(convergence_deg) else np.full_like(t, np.nan)}


#: The norths an azimuth and a position can be measured from (``SurveyStation.AZIMUTH_REFERENCE_*``).
NORTHS = ("grid", "true", "magnetic")
#: What a run may ask for: one of :data:`NORTHS`, or ``auto`` (:func:`default_north`).
NORTH_CHOICES = ("auto",) + NORTHS


def _has_declination(site) -> bool:
    # a declination typed in as 0 with nothing else says "magnetic"; one from a model or IFR is a value
    return bool(site.declination_deg) or bool(site.reference)


def default_north(site) -> str:
    """The north of a run that asks for none: grid on a site with a grid (a projected CRS, its
    convergence known), else true on a site with a declination, else magnetic (no site)."""
    if site is None:
        return "magnetic"
    if np.isfinite(site.grid_convergence_deg):
        return "grid"
    return "true" if _has_declination(site) else "magnetic"


def resolve_north(site, north: str = "auto") -> tuple:
    """``(north, note)``: the north a run's azimuths and positions are along on ``site`` (None: no
    site) when ``north`` (:data:`NORTH_CHOICES`) is asked for.  ``auto``: :func:`default_north`.
    A north the site cannot give falls back to the default and ``note`` says why: grid on a site
    without a grid; true or grid without a site (magnetic, no note: the stations say there is no site).
    Raises ``ValueError`` for a name not in :data:`NORTH_CHOICES`."""
    north = str(north or "auto")
    if north not in NORTH_CHOICES:
        raise ValueError(f"north {north!r}: one of {', '.join(NORTH_CHOICES)}")
    if north == "auto" or site is None:
        return default_north(site), ""
    if north == "grid" and not np.isfinite(site.grid_convergence_deg):
        return default_north(site), "grid north asked for, but the site has no grid (no projected CRS: give its crs)"
    return north, ""


def azimuth_reference(site, north: str = "auto") -> str:
    """What a site's stations' ``azimuth_deg`` and north/east are measured from, in words, with
    the corrections that take magnetic azimuths there (``north`` as for :func:`resolve_north`)."""
    n, _ = resolve_north(site, north)
    if site is None:
        return "magnetic north (no site)"
    ref = site.reference or {}
    decl = f"declination {site.declination_deg:+.3f}°, {ref.get('sources', {}).get('declination_deg', 'given')}"
    if n == "magnetic":
        return "magnetic north" + ("" if _has_declination(site) else " (the site gives no declination)")
    if n == "true":
        return f"true north ({decl})"
    return f"grid north of {ref.get('crs', 'the site')} (convergence {site.grid_convergence_deg:+.3f}°; {decl})"


#: A site's values (the reference field and gravity; measured, or a model's at the location).
SITE_VALUES = ("total_field_nt", "dip_deg", "declination_deg", "gravity_mps2")


def site_parameters(d: dict) -> dict:
    """The node parameters (names after ``site.``) of a site section (:func:`site_from_config`'s
    keys): the values as they are, a location's keys, and with a location the measured values'
    names in ``measured`` (they win over the model's in the node as here).  The node reads them
    back with :func:`site_from_parameters`."""
    measured = [k for k in SITE_VALUES if k in d]
    out = {k: float(d[k]) for k in measured}
    loc = {k: d[k] for k in LOCATION_KEYS if k in d}
    if loc:
        for k, v in loc.items():
            out[k] = float(v) if k in ("latitude_deg", "longitude_deg", "altitude_m") else str(v)
        out["measured"] = ",".join(measured)
    return out


def site_parameter_defaults(site=None) -> dict:
    """The node site parameters' defaults (names after ``site.``; ``nodes.common.declare_site``
    declares them): ``site``'s values (None: :class:`frames.Site`'s defaults) and no location."""
    from .frames import Site

    site = Site() if site is None else site
    return {**{k: float(getattr(site, k)) for k in SITE_VALUES}, "latitude_deg": math.nan,
            "longitude_deg": math.nan, "altitude_m": 0.0, "date": "", "model": MODELS[0], "crs": "", "measured": ""}


def site_from_parameters(values: dict, prefix: str = "site"):
    """A :class:`frames.Site` from a node's site parameters (``values``: names after ``prefix.``,
    as :func:`site_parameters` writes them and ``nodes.common.declare_site`` declares them): the
    four values, and a location unless ``latitude_deg`` and ``longitude_deg`` are NaN, with which
    only the values named in ``measured`` (IFR) are kept.  Parsed by :func:`site_from_config`;
    errors name the parameter (``prefix.key``)."""
    lat, lon = float(values.get("latitude_deg", math.nan)), float(values.get("longitude_deg", math.nan))
    if not (math.isfinite(lat) or math.isfinite(lon)):
        return site_from_config({k: values[k] for k in SITE_VALUES if k in values}, where=prefix)
    names = [x.strip() for x in str(values.get("measured", "")).split(",") if x.strip()]
    unknown = [n for n in names if n not in SITE_VALUES]
    if unknown:
        raise ValueError(f"{prefix}.measured names {unknown}; the site values are {', '.join(SITE_VALUES)}")
    missing = [n for n in names if n not in values]
    if missing:
        raise ValueError(f"{prefix}.measured names {missing}, which have no value")
    if not values.get("date"):
        raise ValueError(f"{prefix}.latitude_deg/longitude_deg given without {prefix}.date: the geomagnetic model "
                         "needs the survey date")
    d = {"latitude_deg": lat, "longitude_deg": lon}
    d.update({k: values[k] for k in ("altitude_m", "date", "model") if k in values})
    if values.get("crs"):
        d["crs"] = values["crs"]
    return site_from_config({**d, **{n: values[n] for n in names}}, where=prefix)


def _number(d: dict, key: str, where: str) -> float:
    v = d[key]
    if isinstance(v, bool):
        raise ValueError(f"{where}.{key}: expected a number, got {v!r}")
    try:
        return float(v)
    except (TypeError, ValueError):
        raise ValueError(f"{where}.{key}: expected a number, got {v!r}") from None


def _plausible(site, where: str):
    bad = [f"{where}.total_field_nt {site.total_field_nt!r} (must be > 0)"] if not site.total_field_nt > 0 else []
    if not site.gravity_mps2 > 0:
        bad.append(f"{where}.gravity_mps2 {site.gravity_mps2!r} (must be > 0)")
    if not -90 <= site.dip_deg <= 90:
        bad.append(f"{where}.dip_deg {site.dip_deg!r} (must be within ±90°)")
    if bad:
        raise ValueError(f"{where}: implausible reference: {'; '.join(bad)}")
    return site


def site_from_config(d, where: str = "site"):
    """The one reader of a site: a :class:`frames.Site` from a site section (a site file's, a
    record's, the launcher's; the nodes' parameters come through :func:`site_from_parameters`):
    measured values (``total_field_nt``, ``dip_deg``, ``declination_deg``, ``gravity_mps2``) and/or
    a location (``latitude_deg``, ``longitude_deg``, ``altitude_m``, ``date``, ``model``; optional
    ``crs`` for grid azimuths), and a record's ``reference`` (kept as it is, values only).
    Measured values win, value by value; the site's ``reference`` says where each came from.
    ``where`` names the section in the one-line ``ValueError`` of a bad site (``site.dip_deg: …``)."""
    from .frames import Site

    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected a mapping of {', '.join(SITE_VALUES)} and/or a location "
                         f"({', '.join(LOCATION_KEYS)}), got {type(d).__name__}")
    measured = {k: _number(d, k, where) for k in SITE_VALUES if k in d}
    loc = {k: d[k] for k in LOCATION_KEYS if k in d}
    unknown = set(d) - set(measured) - set(LOCATION_KEYS) - {"reference"}
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {sorted(unknown)}; expected measured values (total_field_nt, "
                         f"dip_deg, declination_deg, gravity_mps2) and/or a location ({', '.join(LOCATION_KEYS)})")
    if not loc:
        ref = d.get("reference") or {}
        if not isinstance(ref, dict):
            raise ValueError(f"{where}.reference: expected a mapping, got {type(ref).__name__}")
        return _plausible(Site(**measured, reference=dict(ref)), where)
    missing = [k for k in ("latitude_deg", "longitude_deg", "date") if k not in loc]
    if missing:
        raise ValueError(f"{where}: a location needs {', '.join(missing)} as well")
    lat, lon = _number(loc, "latitude_deg", where), _number(loc, "longitude_deg", where)
    alt = _number(loc, "altitude_m", where) if "altitude_m" in loc else 0.0
    model = str(loc.get("model", "WMM2025"))
    date = loc["date"] if isinstance(loc["date"], (_dt.date, _dt.datetime)) else str(loc["date"])
    try:
        m = model_field(lat, lon, alt, date, model)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    values = {"total_field_nt": m["f"], "dip_deg": m["dip_deg"], "declination_deg": m["declination_deg"],
              "gravity_mps2": normal_gravity(lat, alt)}
    source = {k: (f"{model} at {lat:g}, {lon:g}, {alt:g} m, {m['decimal_year']:.3f}" if k != "gravity_mps2"
                  else "WGS84 normal gravity") for k in values}
    for k, v in measured.items():
        values[k] = v
        source[k] = "measured (IFR)"
    ref = {"latitude_deg": lat, "longitude_deg": lon, "altitude_m": alt, "date": str(date), "model": model,
           "sources": source}
    if "crs" in loc:
        ref["crs"] = str(loc["crs"])
        from pyproj.exceptions import CRSError

        try:
            ref["grid_convergence_deg"] = grid_convergence(lat, lon, loc["crs"])
        except (ValueError, CRSError) as exc:     # CRSError: a CRS pyproj does not know
            raise ValueError(f"{where}.crs: {exc}") from None
    return _plausible(Site(**{k: float(v) for k, v in values.items()}, reference=ref), where)


def read_site_section(path) -> dict:
    """The site section of a site file (YAML: the keys of :func:`site_from_config`, at the top or
    under ``site:``), as it is; ``ValueError`` (one line, naming the file) when it cannot be read."""
    from . import yamltext

    try:
        with open(path, encoding="utf-8") as fh:
            d = yamltext.load(fh)
    except OSError as exc:
        raise ValueError(f"{path}: cannot read site reference: {exc.strerror}") from None
    except yamltext.YAMLError as exc:
        raise ValueError(f"{path}: cannot read site reference: not YAML ({' '.join(str(exc).split())})") from None
    return d.get("site", d) if isinstance(d, dict) else d


def load_site_file(path):
    """The :class:`frames.Site` of a site file (:func:`read_site_section`, :func:`site_from_config`);
    a bad site is one ``ValueError`` line naming the file and the key."""
    d = read_site_section(path)
    try:
        return site_from_config(d)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read site reference: {exc}") from None
