"""Survey evaluation: corrected angles, quality control against the site, errors against a reference.

Works on static stations (see :mod:`probelog`).  Gravity vectors are in the seed paper's
convention (down positive, m/s²), fields in nT.  Azimuths are reported from the NED frame's north:
magnetic azimuth plus the site declination (true azimuth when the declination is given; magnetic
when it is 0).

Quality control follows drilling practice: total field within 300 nT and dip within 0.25° of the
site reference (ISCWSA survey-QC e-book); the gravity tolerance is configurable (no industry-wide
fixed value; default 0.0981 m/s² = 10 mg).  Azimuth is flagged undefined below a minimum drift.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import frames
from .frames import Site, wrap180, wrap360


@dataclass(frozen=True)
class Tolerances:
    """QC tolerances: |ΔB| nT, |Δdip| deg, |ΔG| m/s²; azimuth undefined below ``min_drift_deg``.

    ``gravity_toolface_min_drift_deg``: above this drift the reported toolface is the gravity
    toolface, below it the magnetic toolface (the usual switch-over, ~3–5°).
    """

    field_nt: float = 300.0
    dip_deg: float = 0.25
    gravity_mps2: float = 0.0981
    min_drift_deg: float = 0.5
    gravity_toolface_min_drift_deg: float = 3.0


def evaluate(g, b, site: Site, tol: Tolerances = Tolerances(), ref=None) -> dict:
    """Angles, QC and (if ``ref`` (N, 3) deg is given) errors for corrected vectors ``g``, ``b``.

    Returns a dict of (N,) arrays.  Flags are booleans; ``status`` is 0 ok, 1 warn, 2 error.
    """
    g = np.atleast_2d(np.asarray(g, dtype=float))
    b = np.atleast_2d(np.asarray(b, dtype=float))
    out = frames.angles_from_vectors(g, b)
    out["azimuth_deg"] = wrap360(out["azimuth_deg"] + site.declination_deg)
    gtf_ok = out["drift_deg"] >= tol.gravity_toolface_min_drift_deg
    out["toolface_deg"] = np.where(gtf_ok, out["gravity_toolface_deg"], out["magnetic_toolface_deg"])
    out["toolface_is_gravity"] = gtf_ok
    out["delta_g"] = out["total_gravity"] - site.gravity_mps2
    out["delta_b"] = out["total_field"] - site.total_field_nt
    out["delta_dip"] = out["dip_deg"] - site.dip_deg
    out["azimuth_undefined"] = out["drift_deg"] < tol.min_drift_deg
    out["interference_suspected"] = (np.abs(out["delta_b"]) > tol.field_nt) | (np.abs(out["delta_dip"]) > tol.dip_deg)
    out["gravity_out_of_tolerance"] = np.abs(out["delta_g"]) > tol.gravity_mps2
    warn = out["azimuth_undefined"] | out["interference_suspected"]
    err = out["gravity_out_of_tolerance"] | ~np.all(np.isfinite(np.c_[g, b]), axis=1)
    out["status"] = np.where(err, 2, np.where(warn, 1, 0))
    if ref is not None:
        ref = np.atleast_2d(np.asarray(ref, dtype=float))
        out["drift_err"] = out["drift_deg"] - ref[:, 0]
        az_err = wrap180(out["azimuth_deg"] - ref[:, 1])
        out["azimuth_err"] = np.where(out["azimuth_undefined"], np.nan, az_err)
        out["toolface_err"] = wrap180(out["gravity_toolface_deg"] - ref[:, 2])
    return out


def summarize(result: dict) -> dict:
    """Overall error statistics over stations with a reference (azimuth only where defined)."""
    d = result.get("drift_err")
    if d is None:
        return {"stations": int(len(result["drift_deg"]))}
    known = np.isfinite(d)
    a = result["azimuth_err"][known]
    a = a[np.isfinite(a)]
    d = d[known]

    def rms(x):
        return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")

    def mx(x):
        return float(np.max(np.abs(x))) if len(x) else float("nan")

    return {"stations": int(known.sum()), "drift_rms_deg": rms(d), "drift_max_abs_deg": mx(d),
            "azimuth_rms_deg": rms(a), "azimuth_max_abs_deg": mx(a), "azimuth_stations": int(len(a))}


def table4(result: dict, ref) -> dict:
    """Paper Table 4 layout: drift error per set drift (mean over azimuth/toolface) and RMS.

    Returns ``{"drifts": [...], "mean_err": [...], "rms_err": [...], "overall_rms": x}``.
    """
    ref = np.asarray(ref, dtype=float)
    drifts = sorted({float(x) for x in ref[:, 0] if np.isfinite(x)})
    err = result["drift_err"]
    mean = [float(np.mean(err[ref[:, 0] == i])) for i in drifts]
    rms = [float(np.sqrt(np.mean(err[ref[:, 0] == i] ** 2))) for i in drifts]
    ok = np.isfinite(err)
    return {"drifts": drifts, "mean_err": mean, "rms_err": rms,
            "overall_rms": float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else float("nan")}


def table5(result: dict, ref, toolface_deg: float | None = None) -> dict:
    """Paper Table 5 layout: azimuth error by set drift (rows) × set azimuth (columns) at one set
    toolface (default: the grid's first), with the RMS of each drift row over *all* its stations."""
    ref = np.asarray(ref, dtype=float)
    drifts = sorted({float(x) for x in ref[:, 0] if np.isfinite(x)})
    azis = sorted({float(x) for x in ref[:, 1] if np.isfinite(x)})
    if toolface_deg is None:
        tfs = ref[np.isfinite(ref[:, 2]), 2]
        toolface_deg = float(tfs[0]) if len(tfs) else float("nan")
    err = result["azimuth_err"]
    cells = np.full((len(drifts), len(azis)), np.nan)
    rms = []
    for r, i in enumerate(drifts):
        row = ref[:, 0] == i
        for c, a in enumerate(azis):
            sel = row & (ref[:, 1] == a) & (ref[:, 2] == toolface_deg) & np.isfinite(err)
            if sel.any():
                cells[r, c] = float(np.mean(err[sel]))
        e = err[row & np.isfinite(err)]
        rms.append(float(np.sqrt(np.mean(e ** 2))) if len(e) else float("nan"))
    return {"drifts": drifts, "azimuths": azis, "toolface_deg": toolface_deg, "cells": cells.tolist(),
            "rms_err": rms}


def format_table4(before: dict | None, after: dict) -> str:
    cols = after["drifts"]
    w = 7
    lines = ["Table 4 — drift error (deg) by set drift: mean over azimuths/toolfaces",
             "state      " + "".join(f"{c:>{w}g}" for c in cols) + f"{'RMS':>{w + 1}}"]
    for name, t in (("before", before), ("after", after)):
        if t is None:
            continue
        lines.append(f"{name:<11}" + "".join(f"{v:>{w}.3f}" for v in t["mean_err"]) + f"{t['overall_rms']:>{w + 1}.3f}")
    return "\n".join(lines)


def format_table5(before: dict | None, after: dict) -> str:
    azis = after["azimuths"]
    w = 8
    lines = [f"Table 5 — azimuth error (deg) by set drift × set azimuth at toolface {after['toolface_deg']:g}; "
             "RMS per drift row over all toolfaces",
             "drift state  " + "".join(f"{a:>{w}g}" for a in azis) + f"{'RMS':>{w + 1}}"]
    for r, i in enumerate(after["drifts"]):
        for name, t in (("before", before), ("after", after)):
            if t is None:
                continue
            cells = "".join(f"{v:>{w}.2f}" if np.isfinite(v) else f"{'-':>{w}}" for v in t["cells"][r])
            lines.append(f"{i:>5g} {name:<7}" + cells + f"{t['rms_err'][r]:>{w + 1}.2f}")
    return "\n".join(lines)
