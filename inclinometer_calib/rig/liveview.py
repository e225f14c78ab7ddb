"""The live view of a survey in Foxglove: what the ``live`` node (:mod:`.nodes.live`) sends — ROS-free.

The node turns each ``SurveyStation`` into the station dict every other path uses
(:func:`surveystation.from_msg`: the same for a recorded bag's messages and live ones; every
field, the header as ``stamp`` in float seconds, arrays as lists), keeps the stations in a
:class:`LiveView` and sends, over the Foxglove SDK's WebSocket server, the channels of
:data:`CHANNELS`.  Diagnostics and the calibration status are passed on as they are
(:func:`message_dict`, a generic message -> plain dict conversion):

========================  ===============  ====================================================
topic                     encoding/schema  content
========================  ===============  ====================================================
``/live/station``         JSON             the latest ``SurveyStation``, every field (its
                                           station dict; NaN -> null, :func:`jsonable`):
                                           ``azimuth_deg``, ``north_m``/``east_m`` along the
                                           north ``azimuth_reference`` names, the azimuth from
                                           each north in ``azimuth_true_deg``,
                                           ``azimuth_magnetic_deg``, ``azimuth_grid_deg``
``/live/residuals``       JSON             the QC residual series of the corrected stations so
                                           far, one array per quantity (:meth:`LiveView.residuals`)
``/live/stations``        JSON             the station table, ``{"rows": [...]}`` (Table panel)
``/live/trajectory``      foxglove.        the well path as a line through the stations and a
                          SceneUpdate      sphere at each, coloured by status (:func:`scene_update`)
``/live/tf``              foxglove.        the frame of the trajectory (:func:`frame_transforms`)
                          FrameTransforms
``/live/diagnostics``     JSON             ``/diagnostics`` as is (schema name
                                           ``diagnostic_msgs/msg/DiagnosticArray``, which
                                           Foxglove's Diagnostics panels read)
``/live/calibration_status``  JSON         ``/calibration/status`` as is
``/live/log``             foxglove.Log     the stations' warnings and model diagnosis
========================  ===============  ====================================================

Frames of the trajectory.  The stations' positions are the correction node's minimum-curvature
``north_m``, ``east_m``, ``tvd_m`` (m, from the tie-in at the surface; north along the stations'
one north, their ``azimuth_reference``, which the trajectory entity names in its metadata
``north``).  They are drawn as they are, in NED, in the frame ``survey_ned`` (x north,
y east, z down = TVD).  A 3D view needs z up, so :func:`frame_transforms` places ``survey_ned`` in
``survey_enu`` (x east, y north, z up; the same origin), the frame the layout's 3D panel displays:
the rotation of 180° about (x + y)/√2, quaternion (x, y, z, w) = (√½, √½, 0, 0), which maps
(n, e, d) to (e, n, −d).

The series, the table and the scene hold every station so far (up to ``max_stations``), so a
client that connects late sees the whole survey with the next update (the node also re-sends
them periodically).  A re-survey at a measured depth already passed replaces the trajectory
below it, as the correction node's trajectory does.
"""
from __future__ import annotations

import dataclasses
import math
import re
from typing import Callable, Mapping

TOPIC_STATION = "/live/station"
TOPIC_RESIDUALS = "/live/residuals"
TOPIC_TABLE = "/live/stations"
TOPIC_TRAJECTORY = "/live/trajectory"
TOPIC_FRAMES = "/live/tf"
TOPIC_DIAGNOSTICS = "/live/diagnostics"
TOPIC_CALIBRATION_STATUS = "/live/calibration_status"
TOPIC_LOG = "/live/log"

#: Every channel the live node advertises: topic -> schema name.
CHANNELS = {
    TOPIC_STATION: "inclinometer_calib/msg/SurveyStation",
    TOPIC_RESIDUALS: "inclinometer_calib.live.Residuals",
    TOPIC_TABLE: "inclinometer_calib.live.StationTable",
    TOPIC_TRAJECTORY: "foxglove.SceneUpdate",
    TOPIC_FRAMES: "foxglove.FrameTransforms",
    TOPIC_DIAGNOSTICS: "diagnostic_msgs/msg/DiagnosticArray",
    TOPIC_CALIBRATION_STATUS: "inclinometer_calib/msg/CalibrationStatus",
    TOPIC_LOG: "foxglove.Log",
}

FRAME_NED = "survey_ned"      # x north, y east, z down (TVD), m; origin: the tie-in at the surface
FRAME_DISPLAY = "survey_enu"  # x east, y north, z up, m; same origin: the 3D panel's display frame
#: Rotation of survey_ned in survey_enu, (x, y, z, w): 180° about (x + y)/√2, (n, e, d) -> (e, n, -d).
NED_IN_ENU = (math.sqrt(0.5), math.sqrt(0.5), 0.0, 0.0)

#: Status colours (r, g, b, a) of the trajectory: SurveyStation.STATUS_OK/WARN/ERROR, and a
#: station computed before any calibration (empty coefficients_id).
STATUS_COLORS = {0: (0.15, 0.75, 0.25, 1.0), 1: (1.0, 0.65, 0.0, 1.0), 2: (0.9, 0.1, 0.1, 1.0)}
UNCORRECTED_COLOR = (0.6, 0.6, 0.6, 1.0)
SERIES = ("delta_g_mps2", "delta_b_nt", "delta_dip_deg")


# --------------------------------------------------------------------------------------------
# ROS message -> plain values -> JSON
# --------------------------------------------------------------------------------------------
def _field_names(msg) -> list:
    fields = getattr(msg, "get_fields_and_field_types", None)
    if fields is not None:                                  # rclpy (rosidl-generated) message
        return list(fields())
    if dataclasses.is_dataclass(msg):                       # rosbags message
        return [f.name for f in dataclasses.fields(msg)]
    raise TypeError(f"{type(msg).__name__} is not a ROS message")


def _plain(value):
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    if isinstance(value, (bytes, bytearray)):               # a ROS 2 byte/octet field reads as bytes
        return value[0] if len(value) == 1 else list(value)
    if hasattr(value, "tolist"):                            # numpy arrays and scalars (fixed arrays)
        return _plain(value.tolist())
    if isinstance(value, (list, tuple)) or type(value).__name__ == "array":   # sequences, array.array
        return [_plain(v) for v in value]
    return message_dict(value)


def message_dict(msg) -> dict:
    """Every field of a ROS message as plain Python values: nested messages as dicts (a header as
    ``{"stamp": {"sec", "nanosec"}, "frame_id"}``), arrays as lists, a ``byte`` as an int; floats
    unchanged (NaN stays NaN — :func:`jsonable` makes it null).  Works for rclpy messages and
    ``rosbags`` dataclasses.  (A ``SurveyStation`` becomes :func:`surveystation.from_msg` instead:
    the one station dict of every path.)"""
    return {name: _plain(getattr(msg, name)) for name in _field_names(msg)}


def station_fields(message_fields: Mapping[str, str]) -> dict:
    """Field name -> ROS 2 type of a station dict, from the message's (``SurveyStation``'s
    ``get_fields_and_field_types()``): the header replaced by ``stamp`` (double, s)."""
    return {"stamp": "double", **{k: t for k, t in message_fields.items() if k != "header"}}


def jsonable(value):
    """``value`` with every non-finite float replaced by None (JSON has no NaN: ``null``)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    return value


_INTEGER = {"int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "octet", "byte", "char"}


def json_schema(fields: Mapping[str, str], resolve: Callable[[str], Mapping[str, str]], title: str = "") -> dict:
    """The JSON Schema of a message whose fields (name -> ROS 2 IDL type, as rclpy's
    ``get_fields_and_field_types()`` gives them) are ``fields``; ``resolve(type_name)`` gives the
    fields of a nested message type (e.g. ``"std_msgs/Header"``).  Floats are ``number`` or
    ``null`` (NaN is sent as null); fixed arrays ``T[n]`` have exactly n items."""
    def of(t: str) -> dict:
        m = re.fullmatch(r"sequence<(.+?)(?:,\s*\d+)?>", t)
        if m:
            return {"type": "array", "items": of(m.group(1))}
        m = re.fullmatch(r"(.+)\[(\d+)\]", t)
        if m:
            n = int(m.group(2))
            return {"type": "array", "items": of(m.group(1)), "minItems": n, "maxItems": n}
        base = re.sub(r"<=\d+$", "", t)                      # bounded strings
        if base in ("double", "float"):
            return {"type": ["number", "null"]}
        if base in _INTEGER:
            return {"type": "integer"}
        if base == "boolean":
            return {"type": "boolean"}
        if base in ("string", "wstring"):
            return {"type": "string"}
        return json_schema(resolve(t), resolve)
    schema = {"type": "object", "properties": {k: of(t) for k, t in fields.items()}, "required": list(fields)}
    if title:
        schema["title"] = title
    return schema


# --------------------------------------------------------------------------------------------
# The survey so far
# --------------------------------------------------------------------------------------------
def _finite(*xs) -> bool:
    return all(isinstance(x, (int, float)) and math.isfinite(x) for x in xs)


def status_text(s: Mapping) -> str:
    """The table's status of a station (:func:`station_label`: the run report's words)."""
    return station_label(s)


def station_label(s) -> str:
    """The report's status of a station: QC verdict and flags for a corrected one; a station
    published before the calibration solved (empty ``coefficients_id``: raw sensor values, e.g. the
    stand poses themselves) is labelled uncorrected, without QC flags — its |B| and dip are off
    the reference because it is uncorrected, not because of interference."""
    if not s["coefficients_id"]:
        return f"uncorrected ({(s.get('uncorrected_reason') or 'before calibration').split(':')[0]})"
    flags = [n for n in ("azimuth_undefined", "interference_suspected") if s.get(n)]
    return ["ok", "warn", "error"][min(int(s["status"]), 2)] + (f" ({', '.join(flags)})" if flags else "")


def station_color(s: Mapping) -> tuple:
    """(r, g, b, a) of a station in the 3D view: by status; grey before any calibration."""
    return STATUS_COLORS.get(int(s["status"]), STATUS_COLORS[2]) if s["coefficients_id"] else UNCORRECTED_COLOR


class LiveView:
    """The stations received so far (station dicts, :func:`surveystation.from_msg`), oldest first, at
    most ``max_stations`` (the oldest dropped), and the trajectory through them."""

    def __init__(self, max_stations: int = 2000):
        if max_stations < 1:
            raise ValueError(f"max_stations must be at least 1, got {max_stations}")
        self.max_stations = int(max_stations)
        self.stations: list = []
        self.path: list = []   # stations with a position, in measured depth order

    def add(self, station: dict) -> None:
        """Take a station.  One with a finite measured depth and position joins the trajectory; a
        re-survey at a depth already passed replaces the stations at and below it."""
        self.stations.append(station)
        del self.stations[:-self.max_stations]
        s = station
        if _finite(s.get("measured_depth_m"), s.get("north_m"), s.get("east_m"), s.get("tvd_m")):
            self.path = [p for p in self.path if p["measured_depth_m"] < s["measured_depth_m"]] + [s]
            del self.path[:-self.max_stations]

    def residuals(self) -> dict:
        """The residual series of the corrected stations (before a calibration the residuals of the
        raw values say nothing about the survey): one list per key, the same length, in arrival
        order — ``station_id``, ``stamp_s``, ``measured_depth_m``, ``status``, ``delta_g_mps2``
        (m/s²), ``delta_b_nt`` (nT), ``delta_dip_deg`` (deg); NaN where unknown.  A Plot panel
        plots e.g. ``/live/residuals.delta_b_nt[:]`` against ``/live/residuals.station_id[:]``."""
        rows = [s for s in self.stations if s["coefficients_id"]]
        out = {"station_id": [int(s["station_id"]) for s in rows],
               "stamp_s": [float(s["stamp"]) for s in rows],
               "measured_depth_m": [float(s.get("measured_depth_m", math.nan)) for s in rows],
               "status": [int(s["status"]) for s in rows]}
        for k in SERIES:
            out[k] = [float(s[k]) for s in rows]
        return out

    def table(self) -> dict:
        """The station table: ``{"rows": [...]}``, newest first, one row per station with its
        id, measured depth (m), drift/azimuth/toolface (deg), the QC residuals, the temperature
        (°C), the status in the run report's words and the number of warnings."""
        rows = []
        for s in reversed(self.stations):
            rows.append({"station": int(s["station_id"]), "md_m": s.get("measured_depth_m", math.nan),
                         "drift_deg": s["drift_deg"], "azimuth_deg": s["azimuth_deg"],
                         "azimuth_reference": s.get("azimuth_reference", ""), "toolface_deg": s["toolface_deg"],
                         "toolface_type": s.get("toolface_type", ""),
                         "dG_mps2": s["delta_g_mps2"], "dB_nT": s["delta_b_nt"], "ddip_deg": s["delta_dip_deg"],
                         "tvd_m": s.get("tvd_m", math.nan), "north_m": s.get("north_m", math.nan),
                         "east_m": s.get("east_m", math.nan), "temperature_c": s["temperature_c"],
                         "status": status_text(s), "warnings": len(s.get("warnings", ())),
                         "model_misfit": bool(s.get("model_misfit", False))})
        return {"rows": rows}

    def trajectory(self) -> list:
        """The trajectory's points: ``{"station_id", "measured_depth_m", "ned": (north, east, tvd) m,
        "north": the north of ``ned`` (the station's ``azimuth_reference``), "color": (r, g, b, a)}``
        in measured depth order (frame :data:`FRAME_NED`)."""
        return [{"station_id": int(s["station_id"]), "measured_depth_m": float(s["measured_depth_m"]),
                 "ned": (float(s["north_m"]), float(s["east_m"]), float(s["tvd_m"])),
                 "north": s.get("azimuth_reference", ""), "color": station_color(s)}
                for s in self.path]


def log_entries(s: Mapping) -> list:
    """(level, text) of what a station says to the operator: ``"error"`` for a station not to be
    used, ``"warning"`` for each of its warnings and for a model misfit (with the diagnosis)."""
    out = []
    sid = s["station_id"]
    if s["coefficients_id"] and int(s["status"]) == 2:
        out.append(("error", f"station {sid}: status error (probe moved or gravity out of tolerance): not a survey"))
    out += [("warning", f"station {sid}: {w}") for w in s.get("warnings", ())]
    if s.get("model_misfit"):
        out.append(("warning", f"station {sid}: model misfit: {s.get('model_diagnosis', '')}"))
    return out


# --------------------------------------------------------------------------------------------
# Foxglove messages (the SDK's well-known schemas; imported where used)
# --------------------------------------------------------------------------------------------
def _fm():
    import foxglove.messages
    return foxglove.messages


def _timestamp(fm, stamp_s: float):
    if not math.isfinite(stamp_s):
        return None
    sec = math.floor(stamp_s)
    return fm.Timestamp(sec=int(sec), nsec=min(int(round((stamp_s - sec) * 1e9)), 999_999_999))


def scene_update(points: list, stamp_s: float = math.nan, sphere_m: float = 5.0):
    """``foxglove.SceneUpdate`` of the trajectory (:meth:`LiveView.trajectory`): one entity
    ``trajectory`` in :data:`FRAME_NED` with a line strip through the stations (per-point status
    colours, 3 px wide) and a sphere of ``sphere_m`` metres at each; the points are (north, east,
    tvd) in m as they are, and the entity's metadata ``north`` says which north (grid, true or
    magnetic; several, comma-separated, if the stations differ).  No points: the entity is deleted."""
    fm = _fm()
    ts = _timestamp(fm, stamp_s)
    if not points:
        return fm.SceneUpdate(deletions=[fm.SceneEntityDeletion(timestamp=ts, id="trajectory")])
    pts = [fm.Point3(x=p["ned"][0], y=p["ned"][1], z=p["ned"][2]) for p in points]
    colors = [fm.Color(r=c[0], g=c[1], b=c[2], a=c[3]) for c in (p["color"] for p in points)]
    line = fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, thickness=3.0, scale_invariant=True,
                            points=pts, colors=colors)
    spheres = [fm.SpherePrimitive(pose=fm.Pose(position=fm.Vector3(x=p["ned"][0], y=p["ned"][1], z=p["ned"][2]),
                                               orientation=fm.Quaternion(w=1.0)),
                                  size=fm.Vector3(x=sphere_m, y=sphere_m, z=sphere_m), color=c)
               for p, c in zip(points, colors)]
    north = ",".join(sorted({p.get("north") or "" for p in points}))
    return fm.SceneUpdate(entities=[fm.SceneEntity(timestamp=ts, frame_id=FRAME_NED, id="trajectory",
                                                   lines=[line], spheres=spheres,
                                                   metadata=[fm.KeyValuePair(key="north", value=north)])])


def frame_transforms(stamp_s: float = math.nan):
    """``foxglove.FrameTransforms``: :data:`FRAME_NED` in :data:`FRAME_DISPLAY` (:data:`NED_IN_ENU`)."""
    fm = _fm()
    x, y, z, w = NED_IN_ENU
    return fm.FrameTransforms(transforms=[fm.FrameTransform(
        timestamp=_timestamp(fm, stamp_s), parent_frame_id=FRAME_DISPLAY, child_frame_id=FRAME_NED,
        translation=fm.Vector3(), rotation=fm.Quaternion(x=x, y=y, z=z, w=w))])


def log_message(level: str, text: str, stamp_s: float = math.nan):
    """``foxglove.Log`` of one :func:`log_entries` entry (name ``inclinometer_calib``)."""
    fm = _fm()
    lv = {"error": fm.LogLevel.Error, "warning": fm.LogLevel.Warning}.get(level, fm.LogLevel.Info)
    return fm.Log(timestamp=_timestamp(fm, stamp_s), level=lv, message=text, name="inclinometer_calib")
