"""The calibration result: a typed, versioned coefficient record with a YAML round trip.

The *calibrators* (``twelve_position``, the lab's fit, the calibration node) produce a
:class:`Calibration`: the probe model (:class:`model.ProbeModel`, the paper's base model plus any
lab effects, plug-ins included) and the site reference it owns; the record is what travels to the
correction node, ``correct``, ``reprocess`` and files.  Format version 2 carries any model
(``model.effects``: name, sensor, axes, scope, parameters with units, and for a plug-in effect
its file or module and SHA-256 — loading never executes it: the user names plug-ins, see
:mod:`plugins`); version 1 files (the base model only) still load.  Loading checks the version,
shapes, units and the consistency of the correction matrix with the parameters, so a hand-edited
file that no longer makes sense is refused with a message that says which field is wrong.

Units and conventions written into every record:

* accelerometer parameters and offsets are in the seed paper's **gravity-vector** convention
  (down positive, m/s²): ``g = -f`` with ``f`` the REP-145 specific force of ``sensor_msgs/Imu``;
* magnetometer parameters and offsets in nT;
* correction of a triad: ``v = C·(h - bias) = C·h + D`` with ``C = (K·E)⁻¹``, ``D = -C·bias``,
  followed, when the model has effects beyond the paper's, by Newton steps on the whole model
  (:meth:`model.ProbeModel.correct`);
* temperature effects relative to 25 °C; time effects in s since the data's first sample.

The record's ``id`` is a hash of the model, the probe and the site: a record means one set of
numbers, and a station's ``coefficients_id`` says which.
"""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os

import numpy as np
from . import yamltext

from . import effects as fx
from .errormodel import E_TERMS, TriadModel
from .frames import Site, specific_force_from_gravity
from .geomag import site_from_config
from .model import CorrectionPlan, ProbeModel
from .plugins import PluginError
from .output import atomic_write_text

FORMAT = "inclinometer_calib/coefficients"
FORMAT_VERSION = 2
#: Versions this code reads: 1 (the paper's base model only), 2 (any lab model).
READABLE_VERSIONS = (1, 2)
UNITS = {"acc": "m/s^2", "mag": "nT"}
#: The 1σ a record may carry per triad (``uncertainty``): bias in the triad's unit, scale (1).
UNCERTAINTY_KEYS = ("bias", "scale")
TRIAD_KEYS = {"acc": "accelerometer", "mag": "magnetometer"}
CONVENTIONS = {
    "tool_frame": "right-handed; Z along the tool axis pointing down-hole; X to the high side at toolface 0",
    "earth_frame": "NED",
    "orientation": "R = Rz(azimuth)·Ry(drift)·Rz(toolface) maps tool to NED",
    "accelerometer": "gravity vector, down positive, m/s^2 (= minus REP-145 specific force)",
    "magnetometer": "nT",
    "correction": "v = C·(h - bias) = C·h + D, C = (K·E)^-1, D = -C·bias; with model.effects, Newton steps "
                  "v <- v + C·(h - forward(v)) on the whole model from there",
    "temperature": "degC; temperature effects relative to model.temperature_reference_c",
    "time": "s since the first sample of the data being corrected (the probe's power-on)",
}


class CoefficientError(ValueError):
    """A coefficient record is malformed, inconsistent or of an unknown version."""


class Calibration:
    """A calibration record: the probe model (:class:`model.ProbeModel`: the paper's base model of
    both triads plus any lab effects), the site reference it belongs to, and metadata.

    ``Calibration(model, ...)``, or ``Calibration(acc=TriadModel, mag=TriadModel, ...)`` for the
    paper's model alone.  ``site``: the site reference (the record owns it: QC and azimuths of
    whatever the record corrects use it unless a user overrides it, loudly); ``site_source``
    says where it came from: "given" (a site file, node parameters), "measured" (the stand's field
    measured by the twelve poses, its total field in the scale of an assumed vertical component:
    the magnetometer's scale is then relative), "unknown" (an older record).
    ``not_identifiable``: parameters the data could not determine, with the reason (a lab fit).
    ``uncertainty``: the calibrator's 1σ of the corrected sensors, per triad (``acc``, ``mag``):
    ``bias`` (3, in m/s² or nT of the corrected output) and ``scale`` (3, dimensionless), with the
    ``basis`` they were computed on; the sensor terms of the position uncertainty
    (:func:`iscwsa.terms_from_calibration`).  Not part of the id: it describes the numbers."""

    def __init__(self, model: ProbeModel | None = None, *, acc: TriadModel | None = None,
                 mag: TriadModel | None = None, probe_id: str = "probe", method: str = "twelve_position",
                 created: str = "", site: Site | None = None, diagnostics: dict | None = None,
                 site_source: str = "given", not_identifiable=(), uncertainty: dict | None = None):
        if model is None:
            model = ProbeModel.base(acc, mag)
        elif acc is not None or mag is not None:
            raise TypeError("give either a model or acc/mag triads, not both")
        self.model = model
        self.probe_id = probe_id
        self.method = method
        self.created = created or _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()
        self.site = site if site is not None else Site()
        self.diagnostics = dict(diagnostics or {})
        self.site_source = site_source
        self.not_identifiable = [dict(x) for x in not_identifiable]
        self.uncertainty = {k: dict(v) for k, v in (uncertainty or {}).items()}
        self._plan = None

    def __repr__(self):
        return f"Calibration(id={self.id}, probe={self.probe_id!r}, model={self.model.describe()})"

    @property
    def acc(self) -> TriadModel:
        return self.model.acc

    @property
    def mag(self) -> TriadModel:
        return self.model.mag

    def triad(self, sensor: str) -> TriadModel:
        return self.model.triad(sensor)

    @property
    def effects(self) -> list:
        """Labels of every term of the model (base terms by name, others as NAME:sensor:axes[@scope])."""
        return list(fx.BASE) + self.model.labels()

    def _id_blob(self, version: int) -> dict:
        blob = {"acc": self.acc.parameters(), "mag": self.mag.parameters(), "probe": self.probe_id}
        if version >= 2:   # the model's effects and the site reference are part of what the record means
            blob["effects"] = self.model.terms_record()
            blob["site"] = self.site.to_dict()
        return blob

    @property
    def id(self) -> str:
        """Content hash of the model, the probe and the site (same content → same id)."""
        return self._hash(FORMAT_VERSION)

    def _hash(self, version: int) -> str:
        return _blob_hash(self._id_blob(version))

    @property
    def plan(self) -> CorrectionPlan:
        """The correction of survey data with everything data-independent worked out once."""
        if self._plan is None:
            self._plan = CorrectionPlan(self.model, "val")
        return self._plan

    def correct(self, g_raw, b_raw, temperature_c=None, time_s=None, history=None):
        """Corrected gravity vector (m/s²) and field (nT) from raw outputs in the same conventions,
        on survey data (:meth:`model.ProbeModel.correct`, the one correction path); ``history``
        (:class:`effects.History`) for effects that depend on the sequence of holds."""
        return self.plan.correct(g_raw, b_raw, temperature_c, time_s, history=history)

    @property
    def needs(self) -> tuple:
        """What the correction needs besides the vectors: ``temperature``, ``time``."""
        return self.model.needs("val")

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
            "model": {"base": list(fx.BASE), "effects": self.model.terms_record(),
                      "temperature_reference_c": fx.T_REF_C},
        }
        if self.not_identifiable:
            rec["model"]["not_identifiable"] = [dict(x) for x in self.not_identifiable]
        for sensor, key in TRIAD_KEYS.items():
            t = self.triad(sensor)
            rec[key] = {
                "units": {"input": UNITS[sensor], "bias": UNITS[sensor], "offset": UNITS[sensor],
                          "scale": "1", "nonorthogonality": "1"},
                "parameters": {k: float(v) for k, v in t.parameters().items()},
                "correction_matrix": [[float(x) for x in row] for row in t.correction_matrix],
                "offset": [float(x) for x in t.correction_offset],
            }
            if self.uncertainty.get(sensor):
                unc = self.uncertainty[sensor]
                rec[key]["uncertainty"] = {k: ([float(x) for x in unc[k]] if k in UNCERTAINTY_KEYS else unc[k])
                                           for k in unc}
            diag = self.diagnostics.get(sensor)
            if diag:
                rec[key]["diagnostics"] = diag
        if "implied_site" in self.diagnostics:
            rec["implied_site"] = self.diagnostics["implied_site"]
        if self.diagnostics.get("notes"):
            rec["notes"] = list(self.diagnostics["notes"])   # what the solve left out or warned about
        if self.diagnostics.get("fit"):
            rec["fit"] = self.diagnostics["fit"]             # a lab fit's statistics
        if self.diagnostics.get("turntable"):
            rec["turntable"] = self.diagnostics["turntable"]  # the turntable's α/β, sinusoids, residual
        if self.diagnostics.get("stand"):
            rec["stand"] = self.diagnostics["stand"]         # where the stand's poses lie in the data's time
        return rec

    def to_yaml(self) -> str:
        head = ("# inclinometer_calib coefficient record — see README 'Coefficient files'.\n"
                "# Accelerometer values are in the gravity-vector convention (down +, m/s^2 = -REP-145).\n")
        return head + yamltext.dump(self.to_record(), sort_keys=False, width=120)

    def save(self, path) -> None:
        atomic_write_text(path, self.to_yaml())

    @classmethod
    def from_record(cls, rec, source: str = "<record>", base_dir: str = ".") -> "Calibration":
        """Check and load a record of any readable version.  A plug-in effect is accepted only from
        a source the user named whose SHA-256 is the record's (:func:`plugins.require_plugin`);
        ``base_dir`` (the record's folder) resolves a plug-in file the record names by a relative
        path, only to say whether a named file is that one."""
        def fail(msg):
            raise CoefficientError(f"{source}: {msg}")

        if not isinstance(rec, dict):
            fail("not a mapping (expected a coefficient record)")
        if rec.get("format") != FORMAT:
            fail(f"format is {rec.get('format')!r}, expected {FORMAT!r}")
        version = rec.get("format_version")
        if version not in READABLE_VERSIONS:
            fail(f"format_version {version!r} is not supported (this version reads "
                 f"{', '.join(map(str, READABLE_VERSIONS))})")
        triads = {}
        uncertainty = {}
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
            if "uncertainty" in sec:
                unc = sec["uncertainty"]
                if not isinstance(unc, dict):
                    fail(f"{key}.uncertainty must be a mapping")
                for k in UNCERTAINTY_KEYS:
                    try:
                        v = np.asarray(unc.get(k), dtype=float)
                    except (TypeError, ValueError):
                        fail(f"{key}.uncertainty.{k} must be three numbers")
                    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.any(v < 0):
                        fail(f"{key}.uncertainty.{k} must be three finite non-negative numbers, got {unc.get(k)!r}")
                uncertainty[sensor] = dict(unc)
        try:
            site = site_from_config(rec.get("site", {}))
        except (TypeError, ValueError) as exc:
            fail(str(exc))
        mod = rec.get("model") or {}
        if not isinstance(mod, dict):
            fail("model must be a mapping")
        items = mod.get("effects", ()) if version >= 2 else ()
        if version == 1:    # v1: a list of the base model's effect names, nothing else
            extra = [e for e in mod.get("effects", ()) if e not in fx.BASE]
            if extra:
                fail(f"a version 1 record cannot carry effects beyond the base model, got {extra}")
        elif not isinstance(items, list):
            fail("model.effects must be a list")
        t_ref = mod.get("temperature_reference_c", fx.T_REF_C)
        if t_ref != fx.T_REF_C:
            fail(f"model.temperature_reference_c is {t_ref!r}; this version's effects are relative to {fx.T_REF_C}")
        try:
            probe = ProbeModel.from_record(triads["acc"][0], triads["mag"][0], items, base_dir, source)
        except PluginError as exc:
            raise CoefficientError(str(exc)) from None
        except ValueError as exc:
            fail(str(exc).removeprefix(f"{source}: "))
        diags = {s: d for s, (_, d) in triads.items() if d}
        if "implied_site" in rec:
            diags["implied_site"] = rec["implied_site"]
        if rec.get("notes"):
            diags["notes"] = [str(x) for x in rec["notes"]]
        if rec.get("fit"):
            diags["fit"] = rec["fit"]
        if rec.get("turntable"):
            diags["turntable"] = rec["turntable"]
        if "stand" in rec:
            span = rec["stand"]
            try:
                t0, t1 = float(span["t_start"]), float(span["t_end"])
            except (KeyError, TypeError, ValueError):
                fail(f"stand must be a mapping of t_start and t_end (data time, s), got {span!r}")
            if not (np.isfinite(t0) and np.isfinite(t1) and t0 <= t1):
                fail(f"stand: t_start {t0!r} .. t_end {t1!r} is not a span of data time")
            diags["stand"] = {"t_start": t0, "t_end": t1}
        cal = cls(probe, probe_id=str(rec.get("probe_id", "probe")), method=str(rec.get("method", "")),
                  created=str(rec.get("created", "")), site=site, diagnostics=diags,
                  site_source=str(rec.get("site_source", "unknown")),
                  not_identifiable=mod.get("not_identifiable", ()) if version >= 2 else (),
                  uncertainty=uncertainty)
        if "id" in rec and rec["id"] != cal._hash(version):
            moved = _plugin_named_elsewhere(cal, version, items, rec["id"])
            if moved:
                name, theirs, ours = moved
                fail(f"id {rec['id']!r} was issued with the plug-in of effect {name!r} at {theirs}, but that plug-in "
                     f"is named here at {ours} (the same content): the id includes the plug-in's path as the record "
                     f"names it, so name it at {theirs} (--plugin {theirs}, or the plugins parameter on a node)")
            fail(f"id {rec['id']!r} does not match the content (expected {cal._hash(version)!r}): edited without "
                 "re-issuing")
        return cal

    @classmethod
    def load(cls, path) -> "Calibration":
        try:
            with open(path, encoding="utf-8") as fh:
                rec = yamltext.load(fh)
        except yamltext.YAMLError as exc:
            raise CoefficientError(f"{path}: not valid YAML: {exc}") from None
        except UnicodeDecodeError:      # a bag, a binary file given for the record
            raise CoefficientError(f"{path}: not a calibration record (not UTF-8 text)") from None
        return cls.from_record(rec, source=str(path), base_dir=os.path.dirname(os.path.abspath(path)))

    @classmethod
    def from_yaml(cls, text: str, source: str = "<yaml>") -> "Calibration":
        try:
            rec = yamltext.load(text)
        except yamltext.YAMLError as exc:
            raise CoefficientError(f"{source}: not valid YAML: {exc}") from None
        return cls.from_record(rec, source=source)


def _plugin_named_elsewhere(cal: Calibration, version: int, items, rec_id):
    """When a record's id mismatches only because a plug-in of the same content (the same SHA-256:
    :func:`plugins.require_plugin` checked it) was named at another path than the record's — the
    id includes the path as the record names it — ``(effect, the record's path, the path named)``
    of the first such plug-in; else None.  Says why, decides nothing: the record is refused as any
    whose id mismatches."""
    if version < 2 or not isinstance(items, list):
        return None
    blob = cal._id_blob(version)
    moved = None
    for have, item in zip(blob["effects"], items):
        theirs = item.get("plugin") if isinstance(item, dict) else None
        ours = have.get("plugin")
        if isinstance(theirs, dict) and isinstance(ours, dict) and theirs != ours:
            have["plugin"] = theirs
            if moved is None:
                moved = (have["name"], theirs.get("file") or theirs.get("module"),
                         ours.get("file") or ours.get("module"))
    if moved is None:
        return None
    try:
        same = _blob_hash(blob) == rec_id
    except (TypeError, ValueError):     # the record's plug-in entry holds what JSON cannot say
        return None
    return moved if same else None


def _blob_hash(blob: dict) -> str:
    """A record's id: the SHA-256 of its id blob as sorted JSON, 12 hex digits."""
    return hashlib.sha256(json.dumps(blob, sort_keys=True).encode()).hexdigest()[:12]


# --------------------------------------------------------------------------------------------
# The CalibrationCoefficients message's fields (ROS-free: the nodes set them on an rclpy message,
# offline reprocessing serializes them with rosbags)
# --------------------------------------------------------------------------------------------
_PARAM_UNITS = {"acc": {"bias": "m/s^2", "scale": "1", "e": "1"}, "mag": {"bias": "nT", "scale": "1", "e": "1"}}


def _param_unit(sensor, name):
    kind = "bias" if name.startswith("bias") else "scale" if name.startswith("scale") else "e"
    return _PARAM_UNITS[sensor][kind]


def _residuals(cal: Calibration, sensor: str, conv):
    """Poses with residuals (Table 1 numbering) and their residuals (``conv``: into the message's
    convention), flattened x, y, z per pose."""
    per_pose = (cal.diagnostics.get(sensor) or {}).get("per_pose") or {}
    poses, res = [], []
    for p in sorted(int(k) for k in per_pose):
        r = per_pose.get(p, per_pose.get(str(p)))["residual"]
        if any(x is None or not math.isfinite(float(x)) for x in r):
            continue   # a pose the solve had no capture of
        poses.append(p)
        res.extend(float(x) for x in conv(np.asarray(r, dtype=float)))
    return poses, res


def message_fields(cal: Calibration) -> dict:
    """The fields of a ``CalibrationCoefficients`` message (all but the header), plain Python.

    The message's base model is ``corrected = matrix·(raw - offset)``: matrix = ``C = (K·E)^-1``
    and offset = the bias ``B``.  Its accelerometer fields are REP-145 (specific force): the matrix
    is the same as in the core's gravity-vector convention, the offset and the bias parameters are
    converted with :func:`frames.specific_force_from_gravity` (they change sign), as are the
    residuals.  Effects beyond the base model are named in ``*_model_effects``; their values, and
    everything else, are in ``coefficients_yaml``, the core record unchanged (gravity-vector
    convention, stated in the record) — the authoritative form a node applies.  ``poses_used``:
    the poses with residuals (a least-squares solve may lack some), Table 1 numbering.
    """
    out = {"id": cal.id, "probe_id": cal.probe_id, "created": cal.created}
    for sensor, prefix in (("acc", "accel"), ("mag", "mag")):
        conv = specific_force_from_gravity if sensor == "acc" else (lambda v: v)
        t = cal.triad(sensor)
        out[f"{prefix}_correction_matrix"] = [float(x) for x in t.correction_matrix.reshape(9)]
        out[f"{prefix}_offset"] = [float(x) for x in conv(t.bias)]   # corrected = matrix·(raw - offset)
        params = t.parameters()
        names = list(params)
        out[f"{prefix}_parameter_names"] = names
        out[f"{prefix}_parameter_values"] = [float(conv(params[n])) if n.startswith("bias") else float(params[n])
                                             for n in names]
        out[f"{prefix}_parameter_units"] = [_param_unit(sensor, n) for n in names]
        poses, res = _residuals(cal, sensor, conv)
        out[f"{prefix}_residuals"] = res
        out[f"{prefix}_residual_units"] = UNITS[sensor]
        out[f"{prefix}_rms_residual"] = float(math.sqrt(sum(r * r for r in res) / len(res))) if res else math.nan
        out[f"{prefix}_model_effects"] = list(fx.BASE) + [t.label for t in cal.model.extra_terms
                                                          if t.effect.sensor == sensor]
        if sensor == "acc":
            out["poses_used"] = list(poses)
    out["not_identifiable"] = [f"{x.get('parameter', '')}: {x.get('reason', '')}" for x in cal.not_identifiable]
    out["site_total_field_nt"] = float(cal.site.total_field_nt)
    out["site_dip_deg"] = float(cal.site.dip_deg)
    out["site_declination_deg"] = float(cal.site.declination_deg)
    out["site_gravity_mps2"] = float(cal.site.gravity_mps2)
    out["site_source"] = cal.site_source
    out["coefficients_yaml"] = cal.to_yaml()
    return out
