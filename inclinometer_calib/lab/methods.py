"""The two seed methods side by side, and both together in the lab.

On one probe's logs: the twelve positions (the paper: both triads, from the stand's poses), the
turntable (the patent: the magnetometer, from three mounts turned through a full turn; its
accelerometer from the twelve positions) and the lab's fit of both logs together (the twelve poses
as oriented stations, the turntable's steps as free ones: their |g|, |B| and dip).  Each record
corrects the same validation log; with the truth (a simulated probe) the parameter errors too.
:data:`BLIND` says where each method is blind.
"""
from __future__ import annotations

import os

import numpy as np

#: What each method cannot see, in plain words.
BLIND = {
    "twelve-position": ("needs the site's dip (or assumes the stand's field is the site's); a stand that holds a pose "
                        "off biases the axes (the lab names it: stand_pose_error); without a site the magnetometer "
                        "scale is relative to an assumed vertical field"),
    "turntable": ("the magnetometer only (the accelerometer comes from elsewhere); a probe tilted in its jig is the "
                  "same as a misaligned sensor; the field must be uniform over the turn; without a site k is "
                  "relative (azimuths are not affected); needs no north, no dip, no level table"),
    "lab, both logs": ("the turntable's steps enter through |g|, |B| and dip only (their table angles are not "
                       "used); blind to whatever both logs are blind to — a rotation of both triads together "
                       "beyond what the poses define"),
}


def _stations(path, labels=True):
    from ..detect.gates import apply_gates
    from ..io.probelog import read_csv, segment_stations

    log, _ = read_csv(path)
    stations, _ = segment_stations(log, use_labels=labels)
    for st in stations:
        apply_gates(st)
    return log, [s for s in stations if not s.moved and not s.unusable]


def twelve_position_record(path, site):
    """The live node's twelve-position solve of a log (:class:`capture.CaptureSession`)."""
    from ..calibrate.capture import CaptureSession

    _, stations = _stations(path)
    session = CaptureSession(site=site)
    for st in stations:
        session.offer(st)
    session.finish()
    if session.calibration is None:
        raise ValueError(f"{path}: {session.message or 'the twelve positions did not solve'}")
    return session.calibration


def turntable_record(path, site, acc_cal=None):
    """The turntable's record (:func:`turntable.record`) and result."""
    from ..calibrate import turntable as tt
    from ..io.probelog import read_csv

    log, _ = read_csv(path)
    steps, _ = tt.steps_from_log(log, str(path))
    res = tt.solve(steps, site.total_field_nt if site is not None else None)
    return tt.record(res, acc_cal, site), res


def lab_record(cal_path, turntable_path, site):
    """The lab's base model fitted on the twelve-pose log with the turntable's steps as free stations."""
    from .data import load_logs
    from ..calibrate.fit import fit
    from ..calibrate.labmodel import LabModel

    data = load_logs(cal_path, free_paths=[turntable_path])
    model = LabModel.base(site)
    res = fit(model, data)
    return model.record(method="lab: twelve positions + turntable (invariants)", not_identifiable=res.not_identifiable)


def survey_errors(cal, val) -> dict:
    """Drift and azimuth RMS (deg) of ``cal`` on a validation log's stations with a reference
    (``val``: the log's path, or its stations from :func:`_stations` when several records are
    compared on it — read and segmented once)."""
    from ..core.station import correct_stations
    from ..core.survey import evaluate, summarize

    stations = _stations(val)[1] if isinstance(val, (str, bytes, os.PathLike)) else val
    ref = np.array([s.ref for s in stations], float)
    keep = np.isfinite(ref[:, 0])
    g, b = correct_stations([s for s, k in zip(stations, keep) if k], cal)
    return summarize(evaluate(g, b, cal.site, ref=ref[keep]))


def linear_triad(cal, sensor: str):
    """``(A, bias)`` of a record's whole model of one triad at 25 °C and t = 0 — the base model and
    any linear effects (a misalignment) together: its outputs for zero and for full-scale inputs
    along each axis."""
    from ..core.effects import FULL_SCALE

    fs = FULL_SCALE[sensor]
    v = np.vstack([np.zeros(3), fs * np.eye(3)])
    out = cal.model.forward_triad(sensor, v, 25.0, 0.0, role="cal")
    return (out[1:] - out[0]).T / fs, out[0]


def parameter_errors(cal, truth) -> dict:
    """Each triad's whole matrix and bias against the truth (:func:`linear_triad`): largest entry
    error of the matrix (ppm of its diagonal), largest bias error, and the largest error of the
    magnetometer's misalignment angles α (deg)."""
    from ..calibrate.turntable import angles_from_matrix

    out = {}
    for s in ("mag", "acc"):
        (a, ba), (t, bt) = linear_triad(cal, s), linear_triad(truth, s)
        out[f"{s}_matrix_ppm"] = float(np.max(np.abs(a - t) / np.abs(np.diag(t))[:, None]) * 1e6)
        out[f"{s}_bias"] = float(np.max(np.abs(ba - bt)))
        if s == "mag":
            out["mag_alpha_deg"] = float(np.max(np.abs(angles_from_matrix(a)["alpha_deg"]
                                                       - angles_from_matrix(t)["alpha_deg"])))
    return out


def compare(cal_path, turntable_path, val_path, site, truth=None) -> list:
    """Rows ``{method, drift_rms_deg, azimuth_rms_deg, [parameter errors], blind}`` for the twelve
    positions, the turntable (+ the twelve positions' accelerometer), the lab with both logs, and
    (given) the truth."""
    tp = twelve_position_record(cal_path, site)
    tt_cal, _ = turntable_record(turntable_path, site, tp)
    both = lab_record(cal_path, turntable_path, site)
    rows = []
    _, val = _stations(val_path)
    for name, cal in (("twelve-position", tp), ("turntable", tt_cal), ("lab, both logs", both)) + \
            ((("truth", truth),) if truth is not None else ()):
        s = survey_errors(cal, val)
        row = {"method": name, "drift_rms_deg": s["drift_rms_deg"], "azimuth_rms_deg": s["azimuth_rms_deg"],
               "blind": BLIND.get(name, "")}
        if truth is not None and name != "truth":
            row.update(parameter_errors(cal, truth))
        rows.append(row)
    return rows


def compare_html(rows) -> str:
    """The comparison as an HTML table (the lab report's section)."""
    import html

    params = any("mag_matrix_ppm" in r for r in rows)
    head = ["method", "drift RMS (deg)", "azimuth RMS (deg)"] + \
        (["mag K·E error (ppm)", "mag bias error (nT)", "mag α error (deg)", "acc K·E error (ppm)"] if params else []) \
        + ["blind to"]
    out = ["<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"]
    for r in rows:
        cells = [r["method"], f"{r['drift_rms_deg']:.4f}", f"{r['azimuth_rms_deg']:.4f}"]
        if params:
            cells += ([f"{r['mag_matrix_ppm']:.0f}", f"{r['mag_bias']:.2f}", f"{r['mag_alpha_deg']:.4f}",
                       f"{r['acc_matrix_ppm']:.0f}"] if "mag_matrix_ppm" in r else ["—"] * 4)
        cells.append(r["blind"])
        out.append("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>")
    return "\n".join(out) + "</table>"
