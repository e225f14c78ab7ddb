"""The survey station as the graph outputs it — ``SurveyStation`` — one field table for every form.

:data:`FIELDS` lists the message's fields (all but the header) in the order of
``msg/SurveyStation.msg``, each with its ROS 2 type and the value a recording made before the
field existed reads as.  Every spelling of an output station comes from it:

* the message: :func:`to_msg` fills any object with the fields (an rclpy ``SurveyStation``, a
  ``rosbags`` dataclass), :func:`from_msg` reads one back;
* the station dict every path hands on (the WITS/WITSML writers, the live view, the run summary,
  ``replay-test``): the fields as plain Python values plus ``stamp`` (the header's, s) —
  :func:`from_msg`;
* the Parquet row of the fleet's dataset: :func:`to_row`, typed by :func:`arrow_types`;
* the offline CSV of ``correct-log`` (:data:`CSV_COLUMNS`): a column per reported field, under the
  name :data:`CSV_NAMES` gives, plus the columns of the log's own station (times, pose, errors).

``correct.pipeline.station_fields`` computes the values (the one evaluation of a station).  The
module is ROS-free: the message class is the caller's (``nodes/``) or ``rosbags``'.
"""
from __future__ import annotations

import math
from typing import NamedTuple

NAN = math.nan


class Field(NamedTuple):
    """One ``SurveyStation`` field: name, ROS 2 type as the ``.msg`` spells it, and the value of a
    recording made before the field existed (``None``: every recording has it)."""

    name: str
    ros_type: str
    missing: object = None


#: The message's fields but the header, in the ``.msg`` order (``test_surveystation`` holds it to the ``.msg``).
FIELDS = (
    Field("station_id", "uint32"),
    Field("drift_deg", "float64"),
    Field("azimuth_deg", "float64"),
    Field("azimuth_reference", "string", ""),
    Field("azimuth_method", "string", ""),
    Field("axial_field_nt", "float64", NAN),
    Field("azimuth_sigma_deg", "float64", NAN),
    Field("axial_degenerate", "bool", False),
    Field("toolface_deg", "float64"),
    Field("toolface_type", "string", ""),
    Field("gravity_toolface_deg", "float64"),
    Field("magnetic_toolface_deg", "float64"),
    Field("total_gravity_mps2", "float64"),
    Field("total_field_nt", "float64"),
    Field("dip_deg", "float64"),
    Field("delta_g_mps2", "float64"),
    Field("delta_b_nt", "float64"),
    Field("delta_dip_deg", "float64"),
    Field("status", "uint8"),
    Field("is_static", "bool", True),
    Field("interference_suspected", "bool"),
    Field("azimuth_undefined", "bool"),
    Field("gravity_out_of_tolerance", "bool", False),
    Field("moved_during_capture", "bool"),
    Field("warnings", "string[]"),
    Field("model_misfit", "bool"),
    Field("model_diagnosis", "string"),
    Field("samples_averaged", "uint32"),
    Field("duration_s", "float64"),
    Field("temperature_c", "float64"),
    Field("coefficients_id", "string"),
    Field("uncorrected_reason", "string", ""),
    Field("reference_drift_deg", "float64"),
    Field("reference_azimuth_deg", "float64"),
    Field("reference_toolface_deg", "float64"),
    Field("measured_depth_m", "float64", NAN),
    Field("tvd_m", "float64", NAN),
    Field("north_m", "float64", NAN),
    Field("east_m", "float64", NAN),
    Field("dls_deg_per_30m", "float64", NAN),
    Field("azimuth_magnetic_deg", "float64", NAN),
    Field("azimuth_grid_deg", "float64", NAN),
    Field("azimuth_true_deg", "float64", NAN),
    Field("raw_gravity_mps2", "float64[3]", (NAN,) * 3),
    Field("raw_field_nt", "float64[3]", (NAN,) * 3),
    Field("position_covariance_ned_m2", "float64[9]", (NAN,) * 9),
    Field("probe_serial", "string", ""),
)
#: The field names, in the message's order.
NAMES = tuple(f.name for f in FIELDS)
#: The station dict's keys: the fields and the header's stamp (s).
DICT_KEYS = NAMES + ("stamp",)

#: Message field -> its column in the ``correct-log`` CSV (the fields the offline CSV reports).
CSV_NAMES = {
    "samples_averaged": "samples", "temperature_c": "temp_c", "drift_deg": "drift_deg",
    "azimuth_deg": "azimuth_deg", "toolface_deg": "toolface_deg", "toolface_type": "toolface_type",
    "gravity_toolface_deg": "gravity_toolface_deg", "magnetic_toolface_deg": "magnetic_toolface_deg",
    "total_gravity_mps2": "total_gravity_mps2", "total_field_nt": "total_field_nt", "dip_deg": "dip_deg",
    "delta_g_mps2": "delta_g_mps2", "delta_b_nt": "delta_b_nt", "delta_dip_deg": "delta_dip_deg",
    "status": "status", "reference_drift_deg": "ref_drift_deg", "reference_azimuth_deg": "ref_azimuth_deg",
    "reference_toolface_deg": "ref_toolface_deg", "azimuth_reference": "azimuth_reference",
    "azimuth_true_deg": "azimuth_true_deg", "azimuth_magnetic_deg": "azimuth_magnetic_deg",
    "azimuth_grid_deg": "azimuth_grid_deg",
}


def _csv(*names) -> list:
    return [CSV_NAMES[n] for n in names]


#: The ``correct-log`` CSV's columns: the log's station (index, pose, times), the fields above, the
#: flags (the bool fields set, and the sensors a gate refused) and the errors against the reference.
CSV_COLUMNS = (["station", "pose", "t_start_s", "t_end_s"]
               + _csv("samples_averaged", "temperature_c", "drift_deg", "azimuth_deg", "toolface_deg",
                      "toolface_type", "gravity_toolface_deg", "magnetic_toolface_deg", "total_gravity_mps2",
                      "total_field_nt", "dip_deg", "delta_g_mps2", "delta_b_nt", "delta_dip_deg", "status")
               + ["flags"]
               + _csv("reference_drift_deg", "reference_azimuth_deg", "reference_toolface_deg")
               + ["drift_err_deg", "azimuth_err_deg", "toolface_err_deg"]
               + _csv("azimuth_reference", "azimuth_true_deg", "azimuth_magnetic_deg", "azimuth_grid_deg"))


def _plain(v, ros_type: str):
    if ros_type.endswith("]"):
        return [str(x) for x in v] if ros_type.startswith("string") else [float(x) for x in v]
    return v.item() if hasattr(v, "item") else v


def from_msg(msg) -> dict:
    """A ``SurveyStation`` (rclpy message, ``rosbags`` dataclass, any object with the fields) as the
    station dict: every field of :data:`FIELDS` as plain Python values (a field the recording
    predates as its ``missing`` value), and ``stamp`` (s).  A station recorded before the stations
    had one north (no ``azimuth_true_deg``) is put along its positions' north (:func:`_one_north`)."""
    d = {}
    for f in FIELDS:
        v = getattr(msg, f.name) if f.missing is None else getattr(msg, f.name, f.missing)
        d[f.name] = _plain(v, f.ros_type)
    d["stamp"] = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
    if not hasattr(msg, "azimuth_true_deg"):
        _one_north(d)
    return d


def to_msg(fields: dict, msg):
    """``msg`` (a ``SurveyStation``: rclpy's, ``rosbags``', any object with the fields) with every
    field of ``fields`` set (a station dict or ``pipeline.station_fields``; ``stamp`` is the
    caller's, into the header).  Raises ``KeyError`` for a name that is not a field.  Returns ``msg``."""
    for name, value in fields.items():
        if name == "stamp":
            continue
        if name not in _INDEX:
            raise KeyError(f"{name!r} is not a SurveyStation field")
        setattr(msg, name, value)
    return msg


def to_row(station: dict) -> dict:
    """The Parquet row of a station dict: ``stamp`` and the fields, in :data:`DICT_KEYS`' order
    (:func:`arrow_types` types them).  Raises ``ValueError`` for a key that is not a field."""
    extra = set(station) - set(DICT_KEYS)
    if extra:
        raise ValueError(f"station fields {sorted(extra)} are not SurveyStation fields")
    return {k: station[k] for k in DICT_KEYS if k in station}


def arrow_types(pa) -> list:
    """``[(name, pyarrow type)]`` of the fields (``pa`` the ``pyarrow`` module): float64, uint32,
    uint8, bool, string; ``string[]`` a list of strings, ``float64[N]`` a fixed-size list of N."""
    scalars = {"float64": pa.float64(), "uint32": pa.uint32(), "uint8": pa.uint8(), "bool": pa.bool_(),
               "string": pa.string()}
    out = []
    for f in FIELDS:
        base, _, n = f.ros_type.partition("[")
        t = scalars[base]
        if n:
            t = pa.list_(t, int(n[:-1])) if n[:-1] else pa.list_(t)
        out.append((f.name, t))
    return out


_INDEX = {f.name: f for f in FIELDS}


def _one_north(d: dict) -> None:
    """A station dict of a bag recorded before the stations had one north, put along it (in place).
    Then ``azimuth_deg`` and ``reference_azimuth_deg`` were true (``azimuth_reference`` "true", or
    empty in older bags) while ``north_m``/``east_m`` were along grid north when the site had a grid
    (``azimuth_grid_deg`` finite): such a station becomes a grid one (its true azimuth in
    ``azimuth_true_deg``, its reference azimuth minus the convergence) — what its positions are."""
    grid, az = d["azimuth_grid_deg"], d["azimuth_deg"]
    if not (math.isfinite(grid) and math.isfinite(az)):
        if d["azimuth_reference"] == "true":
            d["azimuth_true_deg"] = az
        return
    d["azimuth_true_deg"] = az
    convergence = az - grid
    d["azimuth_deg"], d["azimuth_reference"] = grid, "grid"
    if math.isfinite(d["reference_azimuth_deg"]):
        d["reference_azimuth_deg"] = (d["reference_azimuth_deg"] - convergence) % 360.0
