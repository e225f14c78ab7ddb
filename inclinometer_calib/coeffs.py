"""The calibration result: a typed, versioned coefficient record with a YAML round trip.

The *calibrator* (``twelve_position``, later the general fit) produces a :class:`Calibration`;
the record is what travels to the correction node and to files.  Loading checks the version,
shapes, units and the consistency of the correction matrix with the parameters, so a hand-edited
file that no longer makes sense is refused with a message that says which field is wrong.

Units and conventions written into every record:

* accelerometer parameters and offsets are in the seed paper's **gravity-vector** convention
  (down positive, m/s²): ``g = -f`` with ``f`` the REP-145 specific force of ``sensor_msgs/Imu``;
* magnetometer parameters and offsets in nT;
* correction of a triad: ``v = C·(h - bias) = C·h + D`` with ``C = (K·E)⁻¹``, ``D = -C·bias``.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
from dataclasses import dataclass, field

import numpy as np
import yaml

from .errormodel import E_TERMS, TriadModel
from .frames import Site
from .probelog import atomic_write_text

FORMAT = "inclinometer_calib/coefficients"
FORMAT_VERSION = 1
UNITS = {"acc": "m/s^2", "mag": "nT"}
TRIAD_KEYS = {"acc": "accelerometer", "mag": "magnetometer"}
CONVENTIONS = {
    "tool_frame": "right-handed; Z along the tool axis pointing down-hole; X to the high side at toolface 0",
    "earth_frame": "NED",
    "orientation": "R = Rz(azimuth)·Ry(drift)·Rz(toolface) maps tool to NED",
    "accelerometer": "gravity vector, down positive, m/s^2 (= minus REP-145 specific force)",
    "magnetometer": "nT",
    "correction": "v = C·(h - bias) = C·h + D, C = (K·E)^-1, D = -C·bias",
}


class CoefficientError(ValueError):
    """A coefficient record is malformed, inconsistent or of an unknown version."""


@dataclass
class Calibration:
    """Calibration of both triads plus metadata and per-pose diagnostics."""

    acc: TriadModel
    mag: TriadModel
    probe_id: str = "probe"
    method: str = "twelve_position"
    created: str = ""
    site: Site = field(default_factory=Site)
    effects: tuple = ("bias", "scale", "nonorthogonality")
    diagnostics: dict = field(default_factory=dict)
    #: where ``site`` came from: "given" (a site file, node parameters), "measured" (the stand's
    #: field measured by the twelve poses, its total field in the scale of an assumed vertical
    #: component: the magnetometer's scale is then relative), "unknown" (an older record)
    site_source: str = "given"

    def __post_init__(self):
        if not self.created:
            self.created = _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()

    @property
    def id(self) -> str:
        """Content hash of the coefficients (same coefficients → same id)."""
        blob = json.dumps({"acc": self.acc.parameters(), "mag": self.mag.parameters(),
                           "probe": self.probe_id}, sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:12]

    def triad(self, sensor: str) -> TriadModel:
        return self.acc if sensor == "acc" else self.mag

    def correct(self, g_raw, b_raw):
        """Corrected (gravity vector m/s², field nT) from raw outputs in the same conventions."""
        return self.acc.inverse(g_raw), self.mag.inverse(b_raw)

    # ---- record ----------------------------------------------------------------------------
    def to_record(self) -> dict:
        rec = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "id": self.id,
            "probe_id": self.probe_id,
            "created": self.created,
            "method": self.method,
            "conventions": dict(CONVENTIONS),
            "site": self.site.to_dict(),
            "site_source": self.site_source,
            "model": {"effects": list(self.effects)},
        }
        for sensor, key in TRIAD_KEYS.items():
            t = self.triad(sensor)
            rec[key] = {
                "units": {"input": UNITS[sensor], "bias": UNITS[sensor], "offset": UNITS[sensor],
                          "scale": "1", "nonorthogonality": "1"},
                "parameters": {k: float(v) for k, v in t.parameters().items()},
                "correction_matrix": [[float(x) for x in row] for row in t.correction_matrix],
                "offset": [float(x) for x in t.correction_offset],
            }
            diag = self.diagnostics.get(sensor)
            if diag:
                rec[key]["diagnostics"] = diag
        if "implied_site" in self.diagnostics:
            rec["implied_site"] = self.diagnostics["implied_site"]
        if self.diagnostics.get("notes"):
            rec["notes"] = list(self.diagnostics["notes"])   # what the solve left out or warned about
        return rec

    def to_yaml(self) -> str:
        head = ("# inclinometer_calib coefficient record — see README 'Coefficient files'.\n"
                "# Accelerometer values are in the gravity-vector convention (down +, m/s^2 = -REP-145).\n")
        return head + yaml.safe_dump(self.to_record(), sort_keys=False, width=120)

    def save(self, path) -> None:
        atomic_write_text(path, self.to_yaml())

    @classmethod
    def from_record(cls, rec, source: str = "<record>") -> "Calibration":
        def fail(msg):
            raise CoefficientError(f"{source}: {msg}")

        if not isinstance(rec, dict):
            fail("not a mapping (expected a coefficient record)")
        if rec.get("format") != FORMAT:
            fail(f"format is {rec.get('format')!r}, expected {FORMAT!r}")
        if rec.get("format_version") != FORMAT_VERSION:
            fail(f"format_version {rec.get('format_version')!r} is not supported (this version reads {FORMAT_VERSION})")
        triads = {}
        for sensor, key in TRIAD_KEYS.items():
            sec = rec.get(key)
            if not isinstance(sec, dict):
                fail(f"missing section {key!r}")
            units = sec.get("units", {})
            for u in ("input", "bias", "offset"):
                if units.get(u) != UNITS[sensor]:
                    fail(f"{key}.units.{u} is {units.get(u)!r}, expected {UNITS[sensor]!r} "
                         f"(convert the values, do not just relabel them)")
            params = sec.get("parameters")
            need = [f"{p}_{a}" for p in ("bias", "scale") for a in "xyz"] + list(E_TERMS)
            if not isinstance(params, dict):
                fail(f"{key}.parameters missing")
            missing = [k for k in need if k not in params]
            if missing:
                fail(f"{key}.parameters lacks {missing}")
            try:
                vals = {k: float(params[k]) for k in need}
            except (TypeError, ValueError):
                fail(f"{key}.parameters must all be numbers")
            if not all(np.isfinite(list(vals.values()))):
                fail(f"{key}.parameters contain NaN/inf")
            model = TriadModel.from_parameters(vals)
            try:
                cmat = np.asarray(sec.get("correction_matrix"), dtype=float)
                off = np.asarray(sec.get("offset"), dtype=float)
            except (TypeError, ValueError):
                fail(f"{key}.correction_matrix/offset must be numbers")
            if cmat.shape != (3, 3):
                fail(f"{key}.correction_matrix has shape {cmat.shape}, expected 3×3")
            if off.shape != (3,):
                fail(f"{key}.offset has shape {off.shape}, expected 3")
            if np.linalg.cond(model.A) > 1e6:
                fail(f"{key}: the sensitivity matrix K·E is singular or ill-conditioned")
            if not np.allclose(cmat, model.correction_matrix, rtol=1e-6, atol=1e-9) or \
                    not np.allclose(off, model.correction_offset, rtol=1e-6, atol=1e-6 * max(1.0, np.abs(off).max())):
                fail(f"{key}: correction_matrix/offset disagree with the parameters (hand-edited?)")
            triads[sensor] = (model, sec.get("diagnostics", {}))
        try:
            site = Site.from_dict(rec.get("site", {}))
        except (TypeError, ValueError) as exc:
            fail(str(exc))
        diags = {s: d for s, (_, d) in triads.items() if d}
        if "implied_site" in rec:
            diags["implied_site"] = rec["implied_site"]
        if rec.get("notes"):
            diags["notes"] = [str(x) for x in rec["notes"]]
        cal = cls(acc=triads["acc"][0], mag=triads["mag"][0], probe_id=str(rec.get("probe_id", "probe")),
                  method=str(rec.get("method", "")), created=str(rec.get("created", "")), site=site,
                  effects=tuple(rec.get("model", {}).get("effects", ())), diagnostics=diags,
                  site_source=str(rec.get("site_source", "unknown")))
        if "id" in rec and rec["id"] != cal.id:
            fail(f"id {rec['id']!r} does not match the coefficients (expected {cal.id!r}): edited without re-issuing")
        return cal

    @classmethod
    def load(cls, path) -> "Calibration":
        try:
            with open(path, encoding="utf-8") as fh:
                rec = yaml.safe_load(fh)
        except yaml.YAMLError as exc:
            raise CoefficientError(f"{path}: not valid YAML: {exc}") from None
        return cls.from_record(rec, source=str(path))

    @classmethod
    def from_yaml(cls, text: str, source: str = "<yaml>") -> "Calibration":
        try:
            rec = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise CoefficientError(f"{source}: not valid YAML: {exc}") from None
        return cls.from_record(rec, source=source)


# --------------------------------------------------------------------------------------------
# The CalibrationCoefficients message's fields (ROS-free: the nodes set them on an rclpy message,
# offline reprocessing serializes them with rosbags)
# --------------------------------------------------------------------------------------------
_PARAM_UNITS = {"acc": {"bias": "m/s^2", "scale": "1", "e": "1"}, "mag": {"bias": "nT", "scale": "1", "e": "1"}}


def _param_unit(sensor, name):
    kind = "bias" if name.startswith("bias") else "scale" if name.startswith("scale") else "e"
    return _PARAM_UNITS[sensor][kind]


def _residuals(cal: Calibration, sensor: str, sign: float):
    """Poses with residuals (Table 1 numbering) and their residuals, flattened x, y, z per pose."""
    per_pose = (cal.diagnostics.get(sensor) or {}).get("per_pose") or {}
    poses, res = [], []
    for p in sorted(int(k) for k in per_pose):
        r = per_pose.get(p, per_pose.get(str(p)))["residual"]
        if any(x is None or not math.isfinite(float(x)) for x in r):
            continue   # a pose the solve had no capture of
        poses.append(p)
        res.extend(sign * float(x) for x in r)
    return poses, res


def message_fields(cal: Calibration) -> dict:
    """The fields of a ``CalibrationCoefficients`` message (all but the header), plain Python.

    The message's model is ``corrected = matrix·(raw - offset)``: matrix = ``C = (K·E)^-1`` and
    offset = the bias ``B``.  Its accelerometer fields are REP-145 (specific force): the matrix is
    the same as in the core's gravity-vector convention, the offset and the bias parameters change
    sign (``f = -g``), as do the residuals.  ``coefficients_yaml`` carries the core record
    unchanged (gravity-vector convention, stated in the record).  ``poses_used``: the poses with
    residuals (a least-squares solve may lack some), Table 1 numbering.
    """
    out = {"id": cal.id, "probe_id": cal.probe_id, "created": cal.created}
    for sensor, prefix, sign in (("acc", "accel", -1.0), ("mag", "mag", 1.0)):
        t = cal.triad(sensor)
        out[f"{prefix}_correction_matrix"] = [float(x) for x in t.correction_matrix.reshape(9)]
        out[f"{prefix}_offset"] = [sign * float(x) for x in t.bias]   # corrected = matrix·(raw - offset)
        params = t.parameters()
        names = list(params)
        out[f"{prefix}_parameter_names"] = names
        out[f"{prefix}_parameter_values"] = [(sign if n.startswith("bias") else 1.0) * float(params[n]) for n in names]
        out[f"{prefix}_parameter_units"] = [_param_unit(sensor, n) for n in names]
        poses, res = _residuals(cal, sensor, sign)
        out[f"{prefix}_residuals"] = res
        out[f"{prefix}_residual_units"] = UNITS[sensor]
        out[f"{prefix}_rms_residual"] = float(math.sqrt(sum(r * r for r in res) / len(res))) if res else math.nan
        out[f"{prefix}_model_effects"] = list(cal.effects)
        if sensor == "acc":
            out["poses_used"] = list(poses)
    out["coefficients_yaml"] = cal.to_yaml()
    return out
